"""CLI, configuration loading, batch analysis and reports.  Nothing imports this package."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("cdpr")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0+unknown"
