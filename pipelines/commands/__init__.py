"""One module per ``cdpr`` sub-command; each exposes ``register(subparsers)``."""
