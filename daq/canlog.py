"""CAN log files read fast, whatever their format: :func:`read_log` gives the frames of a log as
blocks of :class:`~cdpr.daq.can_frames.FrameColumns`, through one reader per format (one module
each, :data:`READERS`); any other format python-can reads goes through python-can's own
``LogReader``.  Every reader gives exactly what ``LogReader`` gives for each frame (every field,
the timestamp the same float), reads a bounded amount of the file at a time, and names the file
and the line (or the frame, or the byte) of what it cannot read in a
:class:`~cdpr.analysis.errors.ConfigError` instead of stopping or skipping silently.  A timestamp
whose integer ns would not fit an int64 (after 2262) is an error in every format.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import ConfigError

from .can_frames import T_MAX_S, T_PROBLEM, FrameColumns

#: suffix -> ``module:function`` of the reader of that format (``function(path, progress=...)``
#: yields FrameColumns): candump ``-L`` (can-utils), Vector ASC and BLF, PEAK TRC, python-can's CSV
READERS = {
    ".log": "canlog_candump:read_candump",
    ".asc": "canlog_asc:read_asc",
    ".blf": "canlog_blf:read_blf",
    ".trc": "canlog_trc:read_trc",
    ".csv": "canlog_csv:read_csv",
}

Progress = Callable[[int], None]


def read_log(
    path: str | os.PathLike[str],
    progress: Progress | None = None,
    block_frames: int = 100_000,
) -> Iterator[FrameColumns]:
    """The frames of any CAN log, a block at a time (``progress(bytes read)`` after each block of
    a format read here): by the format's reader (:data:`READERS`, from the suffix), else by
    python-can's ``LogReader`` (``block_frames`` at a time)."""
    p = Path(path)
    spec = READERS.get(p.suffix.lower())
    if spec is not None:
        module, func = spec.split(":")
        reader = getattr(importlib.import_module(f"{__package__}.{module}"), func)
        yield from reader(p, progress=progress)
        return
    yield from _read_python_can(p, block_frames)


def readable(path: str | os.PathLike[str]) -> bool:
    """Whether :func:`read_log` knows the format of ``path`` (from its suffix)."""
    import can.io.player

    suffix = Path(path).suffix.lower()
    return suffix in READERS or suffix in can.io.player.MESSAGE_READERS


def _read_python_can(p: Path, block_frames: int) -> Iterator[FrameColumns]:
    """python-can's ``LogReader`` for the formats not read here (SQLite ``.db``, MF4, ...)."""
    import can

    try:
        reader = can.LogReader(str(p))
    except (ValueError, OSError) as exc:  # an unknown suffix, an unreadable file
        raise ConfigError(str(p), "", f"cannot read the CAN log: {exc}") from None
    count = 0
    try:
        block: list[Any] = []
        it = iter(reader)
        while True:
            try:
                m = next(it)
            except StopIteration:
                break
            except (
                Exception
            ) as exc:  # python-can raises what its parsers raise: never a silent stop
                raise ConfigError(
                    str(p), f"frame {count + 1}", f"python-can cannot read it: {exc}"
                ) from None
            count += 1
            block.append(m)
            if len(block) >= block_frames:
                yield _checked(FrameColumns.from_messages(block), p, count - len(block))
                block = []
        if block:
            yield _checked(FrameColumns.from_messages(block), p, count - len(block))
    finally:
        stop = getattr(reader, "stop", None)
        if stop is not None:
            stop()


def _checked(cols: FrameColumns, path: Path, before: int) -> FrameColumns:
    """``cols`` (frames ``before + 1 ...`` of a log python-can read), or a ConfigError for a
    timestamp beyond :data:`T_MAX_S`."""
    late = np.flatnonzero(~(cols.t_s < T_MAX_S))
    if len(late):
        raise ConfigError(str(path), f"frame {before + int(late[0]) + 1}", T_PROBLEM)
    return cols
