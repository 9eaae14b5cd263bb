"""ASCII line protocols of the serial load-cell amplifier and the tunnel data link.

Both are NMEA-like: one line per sample, fields separated by commas, an XOR checksum of every byte
between ``$`` and ``*`` written as two upper-case hex digits, and ``\\r\\n`` at the end::

    $LC,<seq>,<t_device_us>,<c1>,...,<cN>,<status>*<XX>\\r\\n
    $TUN,<seq>,<airspeed_mps>,<static_pressure_Pa>,<temperature_K>[,<relative_humidity>]*<XX>\\r\\n

- ``seq``: sample counter, decimal, wraps at 2**32; a jump counts as lost samples.
- ``t_device_us``: the amplifier's own clock, decimal microseconds (wraps at 2**32).
- ``c1..cN``: raw ADC counts, signed decimal (N = 1..32; 8 for the rig's amplifier).
- ``status``: hex bit field, 3 bits per channel, channel k (1-based) at bits ``3(k-1)``:
  +1 saturated, +2 slack/underrange, +4 sensor fault.
- tunnel values: decimal floats in SI units; the optional fifth value is the relative humidity as
  a fraction 0..1 (a line without it is the original four-value line, still valid: a reader
  accepts both, a tunnel without a hygrometer never sends it).

Example (checksum computed over ``LC,17,...,0``)::

    $LC,17,340000,120345,-2,0,0,0,0,0,0,0*0C\\r\\n
    $TUN,3,25.5100,101325.00,293.150*59\\r\\n
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

MAX_LINE_BYTES = 512


class LineError(ValueError):
    """A line that does not follow the protocol (the reason is the message)."""


def checksum(body: bytes) -> int:
    """XOR of all bytes of ``body`` (the text between ``$`` and ``*``)."""
    c = 0
    for b in body:
        c ^= b
    return c


def frame_line(body: str) -> bytes:
    """``$<body>*<XX>\\r\\n`` with the XOR checksum of ``body``."""
    raw = body.encode("ascii")
    return b"$" + raw + b"*%02X\r\n" % checksum(raw)


def format_loadcell_line(seq: int, t_device_us: int, counts: Sequence[int], status: int) -> bytes:
    """One ``$LC`` line (bytes, with ``\\r\\n``)."""
    cs = ",".join(str(int(c)) for c in counts)
    body = f"LC,{seq % (1 << 32)},{t_device_us % (1 << 32)},{cs},{status:X}"
    return frame_line(body)


def format_tunnel_line(
    seq: int,
    airspeed_mps: float,
    static_pressure_Pa: float,
    temperature_K: float,
    relative_humidity: float | None = None,
) -> bytes:
    """One ``$TUN`` line (bytes, with ``\\r\\n``); ``relative_humidity`` (0..1) adds the
    optional fifth value."""
    body = f"TUN,{seq % (1 << 32)},{airspeed_mps:.4f},{static_pressure_Pa:.2f},{temperature_K:.3f}"
    if relative_humidity is not None:
        body += f",{relative_humidity:.4f}"
    return frame_line(body)


def split_checked(line: bytes) -> list[str]:
    """Verify framing and checksum of one line (without the line end) and return its fields.

    Raises :class:`LineError` with the reason.
    """
    line = line.rstrip(b"\r\n")
    if not line.startswith(b"$"):
        raise LineError("no leading '$'")
    star = line.rfind(b"*")
    if star < 0 or len(line) - star != 3:
        raise LineError("no '*XX' checksum at the end (truncated?)")
    body = line[1:star]
    try:
        want = int(line[star + 1 :], 16)
    except ValueError:
        raise LineError("checksum is not hex") from None
    got = checksum(body)
    if got != want:
        raise LineError(f"checksum mismatch (line says {want:02X}, computed {got:02X})")
    try:
        return body.decode("ascii").split(",")
    except UnicodeDecodeError:
        raise LineError("non-ASCII bytes") from None


@dataclass(frozen=True)
class LoadCellLine:
    seq: int
    t_device_us: int
    counts: tuple[int, ...]
    status: int


@dataclass(frozen=True)
class TunnelLine:
    seq: int
    airspeed_mps: float
    static_pressure_Pa: float
    temperature_K: float
    relative_humidity: float | None = None


def parse_loadcell_line(line: bytes, n_channels: int) -> LoadCellLine:
    """Parse a ``$LC`` line with ``n_channels`` counts; :class:`LineError` if it is not one."""
    f = split_checked(line)
    if f[0] != "LC":
        raise LineError(f"unexpected sentence {f[0]!r} (expected 'LC')")
    if len(f) != n_channels + 4:
        raise LineError(f"expected {n_channels} channels, got {len(f) - 4}")
    try:
        return LoadCellLine(
            int(f[1]), int(f[2]), tuple(int(x) for x in f[3 : 3 + n_channels]), int(f[-1], 16)
        )
    except ValueError:
        raise LineError("a field is not an integer") from None


def parse_tunnel_line(line: bytes) -> TunnelLine:
    """Parse a ``$TUN`` line; :class:`LineError` if it is not one."""
    f = split_checked(line)
    if f[0] != "TUN":
        raise LineError(f"unexpected sentence {f[0]!r} (expected 'TUN')")
    if len(f) not in (5, 6):
        raise LineError(f"expected 4 or 5 fields after TUN, got {len(f) - 1}")
    try:
        rh = float(f[5]) if len(f) == 6 else None
        out = TunnelLine(int(f[1]), float(f[2]), float(f[3]), float(f[4]), rh)
    except ValueError:
        raise LineError("a field is not a number") from None
    if rh is not None and not 0.0 <= rh <= 1.0:  # NaN fails too
        raise LineError(f"relative humidity {f[5]!r} outside 0..1")
    return out


class LineSplitter:
    """Split a byte stream into lines at ``\\n`` (block reads, no per-byte work in Python).

    ``feed(data)`` returns the complete lines (without ``\\r\\n``) and the over-long fragments that
    were discarded (a line longer than ``max_line`` bytes without a line end is garbage).
    """

    def __init__(self, max_line: int = MAX_LINE_BYTES) -> None:
        self.max_line = max_line
        self._buf = b""

    def feed(self, data: bytes) -> tuple[list[bytes], list[bytes]]:
        buf = self._buf + data
        parts = buf.split(b"\n")
        self._buf = parts.pop()
        junk: list[bytes] = []
        if len(self._buf) > self.max_line:
            junk.append(self._buf)
            self._buf = b""
        lines = []
        for p in parts:
            p = p.rstrip(b"\r")
            if len(p) > self.max_line:
                junk.append(p)
            elif p:
                lines.append(p)
        return lines, junk

    def reset(self) -> bytes:
        """Drop and return the partial line (after the port went away)."""
        rest, self._buf = self._buf, b""
        return rest
