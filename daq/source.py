"""The source interface every driver implements, its readings, and the registry of drivers.

A source is opened, yields timestamped :class:`Reading` objects from :meth:`Source.read`, describes
its streams (names, units, shapes, rates) with :meth:`Source.describe`, and is closed; it is a
context manager.  Drivers register by name with :func:`register_source` as ``"module:Class"``
strings and are imported lazily by :func:`create_source`, so a config can name a driver whose
dependencies are only imported when it is used.
"""

from __future__ import annotations

import importlib
import time
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from cdpr.analysis.conventions import (  # noqa: F401  (the status bits, re-exported for drivers)
    STATUS_BAD_FRAME,
    STATUS_GAP,
    STATUS_OK,
    STATUS_SATURATED,
    STATUS_SENSOR_FAULT,
    STATUS_SLACK,
    STATUS_STALE,
)
from cdpr.analysis.errors import ConfigError


@dataclass(frozen=True, slots=True)
class Reading:
    """One sample of one stream.

    stream: stream name (``"tensions"``, ``"can_raw"``, ``"tunnel"``, ``"pose"``, ``"event"``, ...).
    t_ns: host time of reception, integer ns since the Unix epoch (``time.time_ns()``).
    values: field name -> value; numeric fields carry their unit in the name (``_N``, ``_m``, ...).
    status: 0 for a good sample, else a bit field of ``STATUS_*`` flags (defined once, in
        :mod:`cdpr.analysis.conventions`).
    """

    stream: str
    t_ns: int
    values: Mapping[str, Any]
    status: int = 0


@dataclass(frozen=True)
class FieldDescription:
    """A field of a stream: unit (SI, ``""`` if none), dtype (``"float64"``, ``"int64"``, ``"bytes"``,
    ``"str"``) and shape (``()`` for a scalar)."""

    unit: str
    dtype: str = "float64"
    shape: tuple[int, ...] = ()


@dataclass(frozen=True)
class StreamDescription:
    """What a stream carries: its fields and its nominal rate (Hz, 0 if event-driven)."""

    fields: Mapping[str, FieldDescription]
    rate_hz: float = 0.0
    doc: str = ""


@dataclass
class SourceStats:
    """Counters every source keeps: samples read, samples lost (counter gaps), bad frames or lines,
    bus or port errors and reopen attempts."""

    read: int = 0
    lost: int = 0
    bad: int = 0
    errors: int = 0
    reopened: int = 0
    extra: dict[str, int] = field(default_factory=dict)


class Source(ABC):
    """Base class of every driver: ``open`` / ``read`` / ``close`` and ``describe``.

    Subclasses implement :meth:`_open`, :meth:`_read` and :meth:`_close`; :meth:`read` wraps
    :meth:`_read` and counts what it returns.
    """

    kind: str = "source"

    def __init__(self, name: str) -> None:
        self.name = name
        self.stats = SourceStats()
        self._is_open = False

    # lifecycle -----------------------------------------------------------------------------
    def open(self) -> None:
        """Open the underlying device; idempotent."""
        if not self._is_open:
            self._open()
            self._is_open = True

    def close(self) -> None:
        """Close the underlying device; idempotent, never raises for an already closed source."""
        if self._is_open:
            self._is_open = False
            self._close()

    @property
    def is_open(self) -> bool:
        return self._is_open

    @property
    def exhausted(self) -> bool:
        """True when a finite source (a log replay) has delivered everything; live sources: False."""
        return False

    def __enter__(self) -> Source:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # data ----------------------------------------------------------------------------------
    def read(self, timeout_s: float = 0.1) -> list[Reading]:
        """Readings available within ``timeout_s`` (possibly none)."""
        if not self._is_open:
            self.open()
        out = self._read(timeout_s)
        self.stats.read += len(out)
        return out

    @abstractmethod
    def describe(self) -> dict[str, StreamDescription]:
        """Streams this source produces, by stream name."""

    def settings(self) -> dict[str, Any]:
        """The configuration this source was built with (for the run's config snapshot)."""
        return {}

    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _read(self, timeout_s: float) -> list[Reading]: ...

    @abstractmethod
    def _close(self) -> None: ...


class ReopenBackoff:
    """Exponential backoff between attempts to reopen a lost device (monotonic clock, s).

    ``delay_s`` starts at ``first_s``; each :meth:`failed` schedules the next attempt ``delay_s``
    from now and doubles ``delay_s`` (at most ``max_s``); :meth:`succeeded` resets it.
    """

    def __init__(self, first_s: float, max_s: float) -> None:
        self.first_s = float(first_s)
        self.max_s = float(max_s)
        self.delay_s = self.first_s
        self.next_open = 0.0

    def due(self, timeout_s: float) -> bool:
        """True when an attempt is due; otherwise sleep up to ``timeout_s`` towards it, False."""
        now = time.monotonic()
        if now < self.next_open:
            time.sleep(min(timeout_s, self.next_open - now))
            return False
        return True

    def failed(self) -> None:
        """Schedule the next attempt ``delay_s`` from now and double the delay (capped)."""
        self.next_open = time.monotonic() + self.delay_s
        self.delay_s = min(self.delay_s * 2, self.max_s)

    def succeeded(self) -> None:
        """An attempt worked: the next failure waits ``first_s`` again."""
        self.delay_s = self.first_s


def now_ns() -> int:
    """Host time in integer nanoseconds since the Unix epoch."""
    return time.time_ns()


_REGISTRY: dict[str, str] = {}


def register_source(kind: str, target: str) -> None:
    """Register a driver class under ``kind`` as ``"package.module:ClassName"`` (imported lazily)."""
    _REGISTRY[kind] = target


def source_kinds() -> list[str]:
    """Registered driver names."""
    return sorted(_REGISTRY)


def create_source(
    kind: str, name: str, settings: Mapping[str, Any], origin: str = "<config>"
) -> Source:
    """Build the driver registered as ``kind`` with ``settings`` (keyword arguments).

    ``settings`` are checked by the kind's schema (:mod:`cdpr.daq.source_schema`) first; an unknown
    kind or bad settings raise :class:`ConfigError` naming ``origin`` and ``sources.<name>.<key>``.
    """
    try:
        target = _REGISTRY[kind]
    except KeyError:
        raise ConfigError(
            origin, f"sources.{name}.kind", f"unknown driver {kind!r} (known: {source_kinds()})"
        ) from None
    from .source_schema import SOURCE_KINDS, check_source, driver_settings

    kwargs = dict(settings)
    if kind in SOURCE_KINDS:  # types, ranges and unknown keys: the driver's schema
        kwargs = driver_settings(check_source({**kwargs, "kind": kind}, name, origin))
    module_name, _, cls_name = target.partition(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    if getattr(cls, "accepts_origin", False):
        # drivers that validate their settings name the config file and key in their errors
        kwargs.setdefault("origin", origin)
    try:
        return cls(name=name, **kwargs)
    except TypeError as exc:
        raise ConfigError(origin, f"sources.{name}", f"bad settings: {exc}") from None
