"""ASCII line protocols of the serial load-cell amplifier and the tunnel data link.

Both are NMEA-like: one line per sample, fields separated by commas, an XOR checksum of every byte
between ``$`` and ``*`` written as two upper-case hex digits, and ``\\r\\n`` at the end::

    $LC,<seq>,<t_device_us>,<c1>,...,<cN>,<status>*<XX>\\r\\n
    $TUN,<seq>,<airspeed_mps>,<static_pressure_Pa>,<temperature_K>[,<relative_humidity>]*<XX>\\r\\n
    $TPT,<seq>,<phase>,<label>[,<kind>,<target_aoa_deg>,<target_sideslip_deg>,<target_airspeed_mps>]*<XX>\\r\\n

- ``seq``: sample counter, decimal, wraps at 2**32; a jump counts as lost samples.
- ``t_device_us``: the amplifier's own clock, decimal microseconds (wraps at 2**32).
- ``c1..cN``: raw ADC counts, signed decimal (N = 1..32; 8 for the rig's amplifier).
- ``status``: hex bit field, 3 bits per channel, channel k (1-based) at bits ``3(k-1)``:
  +1 saturated, +2 slack/underrange, +4 sensor fault.
- tunnel values: decimal floats in SI units; the optional fifth value is the relative humidity as
  a fraction 0..1 (a line without it is the original four-value line, still valid: a reader
  accepts both, a tunnel without a hygrometer never sends it).
- ``$TPT`` (the tunnel controller announcing a test point, on the same link as ``$TUN``): its own
  ``seq`` counter; ``phase`` ``start`` or ``end``; ``label`` a non-empty token of printable ASCII
  without blanks, ``,``, ``*`` or ``$``; optionally the four targets together: ``kind`` (one of
  :data:`POINT_KINDS`), angle of attack and sideslip in degrees and airspeed in m/s (decimal,
  finite, airspeed >= 0).

Example (checksum computed over ``LC,17,...,0``)::

    $LC,17,340000,120345,-2,0,0,0,0,0,0,0*0C\\r\\n
    $TUN,3,25.5100,101325.00,293.150*59\\r\\n
    $TPT,0,start,alpha-a2-b0-v25.51,wind_on,2,0,25.51*4A\\r\\n
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from cdpr.analysis.conventions import STEADY_POINT_KINDS

MAX_LINE_BYTES = 512
POINT_KINDS = STEADY_POINT_KINDS
"""The kinds a ``$TPT`` line carries: the steady ones (an oscillation point's motion does not fit
the line)."""
TPT_PHASES = ("start", "end")


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


def format_test_point_line(
    seq: int,
    phase: str,
    label: str,
    kind: str | None = None,
    target_aoa_deg: float | None = None,
    target_sideslip_deg: float | None = None,
    target_airspeed_mps: float | None = None,
) -> bytes:
    """One ``$TPT`` line (bytes, with ``\\r\\n``); the targets are written when ``kind`` is given
    (all four together).  No checks: a test may write a bad line on purpose."""
    body = f"TPT,{seq % (1 << 32)},{phase},{label}"
    if kind is not None:
        body += f",{kind},{target_aoa_deg:g},{target_sideslip_deg:g},{target_airspeed_mps:g}"
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


@dataclass(frozen=True)
class TestPointLine:
    __test__ = False  # not a pytest class

    seq: int
    phase: str
    label: str
    kind: str | None = None
    target_aoa_deg: float | None = None
    target_sideslip_deg: float | None = None
    target_airspeed_mps: float | None = None


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


def is_test_point_line(line: bytes) -> bool:
    """Whether ``line`` claims to be a ``$TPT`` sentence (before any check)."""
    return line.startswith(b"$TPT,") or line.startswith(b"$TPT*")


def _label_ok(label: str) -> bool:
    return bool(label) and all(33 <= ord(c) <= 126 and c not in ",*$" for c in label)


def parse_test_point_line(line: bytes) -> TestPointLine:
    """Parse a ``$TPT`` line; :class:`LineError` (with the reason) if it is not a valid one."""
    f = split_checked(line)
    if f[0] != "TPT":
        raise LineError(f"unexpected sentence {f[0]!r} (expected 'TPT')")
    if len(f) not in (4, 8):
        raise LineError(f"expected 3 or 7 fields after TPT, got {len(f) - 1}")
    try:
        seq = int(f[1])
    except ValueError:
        raise LineError(f"test-point seq {f[1]!r} is not an integer") from None
    if f[2] not in TPT_PHASES:
        raise LineError(f"test-point phase {f[2]!r}: expected 'start' or 'end'")
    if not _label_ok(f[3]):
        raise LineError(
            f"test-point label {f[3]!r}: expected a non-empty token without blanks, ',', '*', '$'"
        )
    if len(f) == 4:
        return TestPointLine(seq, f[2], f[3])
    if f[4] not in POINT_KINDS:
        raise LineError(f"test-point kind {f[4]!r}: expected one of {list(POINT_KINDS)}")
    try:
        aoa, beta, v = (float(x) for x in f[5:8])
    except ValueError:
        raise LineError("a test-point target is not a number") from None
    if not all(math.isfinite(x) for x in (aoa, beta, v)) or v < 0:
        raise LineError(f"test-point targets {f[5:8]}: expected finite numbers, airspeed >= 0")
    return TestPointLine(seq, f[2], f[3], f[4], aoa, beta, v)


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
