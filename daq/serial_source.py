"""Serial load cells: pyserial on a real port, the ``$LC`` line protocol, block reads, reopen.

:class:`SerialLineSource` is the shared machinery of every line-protocol driver: it reads whatever
bytes are available in blocks (never byte by byte), splits lines, hands each to the subclass's
parser, turns a bad line into a ``serial_bad`` reading (the raw line and the reason, counted in
``stats.bad``; never an exception), counts sequence gaps as lost samples, and when the port vanishes
(an unplugged USB adapter) closes it and retries opening the same path with exponential backoff
(``stats.reopened``).

:class:`SerialLoadCellSource` decodes ``$LC`` lines (:mod:`cdpr.daq.serial_protocol`) into the same
``tensions`` stream as the CAN driver: ``T_<cable>_N``, ``raw_<cable>_counts``, ``status_<cable>``,
``seq``, ``t_device_us``.
"""

from __future__ import annotations

import logging
import time
from abc import abstractmethod
from collections.abc import Sequence
from typing import Any

import serial

from cdpr.analysis.conventions import status_from_channel_bits
from cdpr.analysis.errors import ConfigError

from .loadcell import calibration_from_settings
from .serial_protocol import LineError, LineSplitter, parse_loadcell_line
from .source import (
    STATUS_BAD_FRAME,
    FieldDescription,
    Reading,
    ReopenBackoff,
    Source,
    StreamDescription,
)

log = logging.getLogger(__name__)

SERIAL_BAD_DESCRIPTION = StreamDescription(
    {"line": FieldDescription("", "str"), "reason": FieldDescription("", "str")},
    0.0,
    "lines that failed framing, checksum or parsing, kept raw (latin-1) with the reason",
)
BITS_PER_BYTE = 10  # 8N1: start + 8 data + stop


def check_serial_budget(
    origin: str, prefix: str, baudrate: int, rate_hz: float, line_bytes: int
) -> None:
    """Refuse (ConfigError on ``rate_hz``) when ``line_bytes`` per sample at ``rate_hz`` exceed the
    port's capacity ``baudrate / 10`` bytes/s (8N1); both come checked (> 0) by the schema."""
    need = rate_hz * line_bytes * BITS_PER_BYTE
    if need > baudrate:
        raise ConfigError(
            origin,
            f"{prefix}.rate_hz",
            f"{rate_hz:g} lines/s of up to {line_bytes} bytes need {need:.0f} baud, more than "
            f"{baudrate} (at most {baudrate // (line_bytes * BITS_PER_BYTE)} Hz fits)",
        )


class SerialLineSource(Source):
    """Base of line-protocol drivers (see the module docstring).

    port: device path (``/dev/ttyUSB0``, a pty link, or any pyserial URL); baudrate: bit/s;
    reopen_backoff_s: (first, max) delay between reopen attempts, s.
    Subclasses implement :meth:`_parse` (bytes -> Reading, raising LineError) and ``describe``.
    """

    accepts_origin = True

    def __init__(
        self,
        name: str,
        port: str,
        baudrate: int = 115200,
        reopen_backoff_s: Sequence[float] = (0.05, 2.0),
        origin: str = "<config>",
    ) -> None:
        super().__init__(name)
        self.origin = origin
        self.prefix = f"sources.{name}"
        # types and ranges: checked by create_source (cdpr.daq.source_schema)
        self.baudrate = int(baudrate)
        self.port = port
        self.backoff = (float(reopen_backoff_s[0]), float(reopen_backoff_s[1]))
        self.ser: serial.Serial | None = None
        self.splitter = LineSplitter()
        self._reopen = ReopenBackoff(*self.backoff)
        self._last_seq: int | None = None
        self.seq_modulus = 1 << 32
        self.poll_s = 0.02  # pyserial read timeout: one blocking wait, then drain in_waiting

    # lifecycle ----------------------------------------------------------------------------
    def _make_port(self) -> serial.Serial:
        return serial.serial_for_url(
            self.port, baudrate=self.baudrate, timeout=self.poll_s, exclusive=True
        )

    def _open(self) -> None:
        try:
            self.ser = self._make_port()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ConfigError(
                self.origin, f"{self.prefix}.port", f"cannot open {self.port}: {exc}"
            ) from None

    def _close(self) -> None:
        self._drop_port()

    def _drop_port(self) -> None:
        ser, self.ser = self.ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception as exc:  # a vanished device may fail to close cleanly
                log.debug("%s: close failed: %s", self.name, exc)

    def _lost_port(self, why: str, out: list[Reading]) -> None:
        self.stats.errors += 1
        log.warning(
            "%s: port %s lost (%s); reopening in %.2f s",
            self.name,
            self.port,
            why,
            self._reopen.delay_s,
        )
        self._drop_port()
        rest = self.splitter.reset()
        if rest:
            out.append(self._bad(rest, "partial line when the port was lost", time.time_ns()))
        self._reopen.failed()

    def _try_reopen(self, timeout_s: float) -> bool:
        if not self._reopen.due(timeout_s):
            return False
        try:
            self.ser = self._make_port()
        except (serial.SerialException, OSError, ValueError):
            self._reopen.failed()
            time.sleep(min(timeout_s, self._reopen.delay_s))
            return False
        self.stats.reopened += 1
        self._reopen.succeeded()
        log.warning("%s: port %s reopened", self.name, self.port)
        return True

    # data ---------------------------------------------------------------------------------
    def _read(self, timeout_s: float) -> list[Reading]:
        out: list[Reading] = []
        if self.ser is None and not self._try_reopen(timeout_s):
            return out
        ser = self.ser
        assert ser is not None
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                data = ser.read(1)  # blocks until a byte arrives or poll_s passes
                if data:
                    waiting = ser.in_waiting
                    if waiting:
                        data += ser.read(waiting)
                    t_ns = time.time_ns()
                    lines, junk = self.splitter.feed(data)
                    for j in junk:
                        out.append(self._bad(j, "over-long line without a line end", t_ns))
                    for line in lines:
                        try:
                            r = self._parse(line, t_ns)
                            if isinstance(r, list):
                                out.extend(r)
                            else:
                                out.append(r)
                        except LineError as exc:
                            out.append(self._bad(line, str(exc), t_ns))
                if out or time.monotonic() >= deadline:
                    break
        except (serial.SerialException, OSError) as exc:
            self._lost_port(str(exc), out)
        return out

    def _bad(self, line: bytes, reason: str, t_ns: int) -> Reading:
        self.stats.bad += 1
        return Reading(
            "serial_bad", t_ns, {"line": line.decode("latin-1"), "reason": reason}, STATUS_BAD_FRAME
        )

    def _check_seq(self, seq: int) -> None:
        if self._last_seq is not None:
            step = (seq - self._last_seq) % self.seq_modulus
            if 1 < step < self.seq_modulus // 2:
                self.stats.lost += step - 1
        self._last_seq = seq

    @abstractmethod
    def _parse(self, line: bytes, t_ns: int) -> Reading | list[Reading]:
        """One good line as a reading, or several (a subclass's protocol); raise LineError for a
        bad one."""


class SerialLoadCellSource(SerialLineSource):
    """Load cells on a serial line speaking ``$LC`` (one line per sample, all channels).

    Settings: port, baudrate (default 115200), rate_hz (nominal, checked against the baud rate),
    cables (names in channel order, default c1..c8), offset_counts, gain_N_per_count.
    """

    kind = "serial_loadcell"

    def __init__(
        self,
        name: str,
        port: str,
        baudrate: int = 115200,
        rate_hz: float = 100.0,
        cables: Sequence[str] | None = None,
        offset_counts: Any = None,
        gain_N_per_count: Any = None,
        reopen_backoff_s: Sequence[float] = (0.05, 2.0),
        origin: str = "<config>",
    ) -> None:
        super().__init__(name, port, baudrate, reopen_backoff_s, origin)
        cables = [f"c{i + 1}" for i in range(8)] if cables is None else [str(c) for c in cables]
        if not cables or len(set(cables)) != len(cables):
            raise ConfigError(
                origin, f"{self.prefix}.cables", f"expected unique names, got {cables}"
            )
        self.cables = cables
        self.rate_hz = float(rate_hz)
        n = len(cables)
        # worst-case line: $LC, 10-digit seq and time, 8-char counts, status hex, *XX\r\n
        self.line_bytes = 4 + 11 + 11 + 9 * n + (3 * n + 3) // 4 + 5
        check_serial_budget(origin, self.prefix, self.baudrate, self.rate_hz, self.line_bytes)
        self.calibration = calibration_from_settings(
            origin, self.prefix, n, offset_counts, gain_N_per_count
        )

    def settings(self) -> dict[str, Any]:
        return {
            "port": self.port,
            "baudrate": self.baudrate,
            "rate_hz": self.rate_hz,
            "cables": list(self.cables),
            **self.calibration.to_mapping(),
        }

    def describe(self) -> dict[str, StreamDescription]:
        f: dict[str, FieldDescription] = {}
        for c in self.cables:
            f[f"T_{c}_N"] = FieldDescription("N")
        for c in self.cables:
            f[f"raw_{c}_counts"] = FieldDescription("counts", "int64")
        for c in self.cables:
            f[f"status_{c}"] = FieldDescription("", "int64")
        f["seq"] = FieldDescription("", "int64")
        f["t_device_us"] = FieldDescription("us", "int64")
        return {
            "tensions": StreamDescription(f, self.rate_hz, "cable tensions (N) and raw counts"),
            "serial_bad": SERIAL_BAD_DESCRIPTION,
        }

    def _parse(self, line: bytes, t_ns: int) -> Reading:
        n = len(self.cables)
        p = parse_loadcell_line(line, n)
        self._check_seq(p.seq)
        T = self.calibration.to_newtons(p.counts)
        values: dict[str, Any] = {}
        status = 0
        for i, c in enumerate(self.cables):
            values[f"T_{c}_N"] = float(T[i])
        for i, c in enumerate(self.cables):
            values[f"raw_{c}_counts"] = p.counts[i]
        for i, c in enumerate(self.cables):
            st = (p.status >> (3 * i)) & 7
            values[f"status_{c}"] = st
            status |= status_from_channel_bits(int(st))
        values["seq"] = p.seq
        values["t_device_us"] = p.t_device_us
        return Reading("tensions", t_ns, values, status)
