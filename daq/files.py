"""Files read and written whole: TOML parsing with clear errors and atomic outputs.

Shared by the drivers' tools (:mod:`cdpr.daq.virtual_rig`) and every pipeline
(:mod:`cdpr.pipelines.config` re-exports both).  Errors are
:class:`~cdpr.analysis.errors.ConfigError` naming the file.
"""

from __future__ import annotations

import os
import tempfile
import tomllib
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import tomli_w

from cdpr.analysis.errors import ConfigError


def load_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Parse a TOML file; a missing file or a syntax error becomes a :class:`ConfigError`."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(str(p), "", "file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(p), "", f"invalid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(str(p), "", f"cannot read: {exc.strerror}") from None


@contextmanager
def atomic_output(path: str | os.PathLike[str], mode: str = "w") -> Iterator[Any]:
    """Write to a temporary file beside ``path`` and move it into place only on success.

    A failure (or an exception from the caller) leaves no partial file behind.
    """
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".part", dir=p.parent)
    except (FileExistsError, NotADirectoryError) as exc:
        raise ConfigError(
            str(p), "", f"cannot write: {exc.filename} is not a folder (a file is in the way)"
        ) from None
    except OSError as exc:
        raise ConfigError(str(p), "", f"cannot write: {exc.strerror or exc}") from None
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs get the usual permissions
        try:
            os.replace(tmp, p)
        except OSError as exc:
            raise ConfigError(str(p), "", f"cannot write: {exc.strerror or exc}") from None
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def toml_inline_arrays(data: Mapping[str, Any]) -> str:
    """TOML text with short arrays on one line (tomli_w writes one element per line)."""

    def value(v: Any) -> str:
        if isinstance(v, list | tuple):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return tomli_w.dumps({"v": v})[4:].strip()

    lines: list[str] = []
    for sec, body in data.items():
        if isinstance(body, list):
            for item in body:
                lines.append(f"\n[[{sec}]]")
                lines += [f"{k} = {value(v)}" for k, v in item.items()]
        else:
            lines.append(f"\n[{sec}]")
            lines += [f"{k} = {value(v)}" for k, v in body.items()]
    text = "\n".join(lines).lstrip("\n") + "\n"
    tomllib.loads(text)  # what we write must read back
    return text
