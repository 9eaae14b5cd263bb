"""The ``cdpr`` command line.

Each sub-command lives in its own module in :mod:`cdpr.pipelines.commands` and exposes
``register(subparsers)``, which adds its parser and sets ``func`` to a callable taking the parsed
arguments and returning an exit code.  Errors derived from
:class:`~cdpr.analysis.errors.CdprError` become one line on stderr and exit code 2; so does an
:class:`OSError` that no command turned into a clearer error (an output folder that cannot be
created, a full disk), rather than a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import warnings
from collections.abc import Sequence

from cdpr.analysis.errors import CdprError

from . import __version__, commands


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser, with every command module registered (sorted by name)."""
    parser = argparse.ArgumentParser(
        prog="cdpr",
        description="Cable-driven parallel robot force balance: acquisition and analysis.",
    )
    parser.add_argument("--version", action="version", version=f"cdpr {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cdpr`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("default")
            code = int(args.func(args) or 0)
        for w in caught:  # a library's warning (numpy, pandas): one line each, after the command
            text = " ".join(str(w.message).split())
            print(f"cdpr {args.command}: warning: {w.category.__name__}: {text}", file=sys.stderr)
        return code
    except CdprError as exc:  # one line, whatever the message holds
        print(f"cdpr {args.command}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except OSError as exc:  # an unwritable output folder, a full disk, ...: one line, no traceback
        where = f"{exc.filename}: " if exc.filename is not None else ""
        print(f"cdpr {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"cdpr {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
