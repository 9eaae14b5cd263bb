"""A frame-by-frame reference of the load-cell decoding rules (docs/daq_drivers.md, the module
docstring of ``cdpr.daq.can_decoder``), written separately for the tests from the shipped DBC's
layout by hand (``data_samples/loadcell.dbc``: four 8-byte frames 0x181, 0x281, 0x381, 0x481;
channels 2j+1 and 2j+2 as little-endian signed 24-bit counts in bytes 0-2 and 3-5; byte 6 their
status bits, 0-2 for the first channel and 4-6 for the second (saturated, slack, fault); byte 7 the
rolling counter).  No numpy, no cantools: one frame at a time, as the rules are written."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

IDS = (0x181, 0x281, 0x381, 0x481)
RAW_MISSING = -(1 << 31)
GAP, BAD_FRAME = 16, 8
CHANNEL_TO_SAMPLE = ((1, 1), (2, 2), (4, 32))  # saturated, slack, fault -> source status bits


def int24(b: bytes) -> int:
    v = b[0] | b[1] << 8 | b[2] << 16
    return v - (1 << 24) if v & 0x800000 else v


@dataclass
class Frame:
    t_ns: int
    t_bus_ns: int
    arbitration_id: int
    data: bytes
    extended: bool = False
    error: bool = False
    remote: bool = False
    t_s: float = 0.0  # the bus time as a log holds it (t_bus_ns is its round(t_s * 1e9))


@dataclass
class Reference:
    offsets: list[float]
    gains: list[float]
    rate_hz: float = 0.0
    samples: list[dict] = field(default_factory=list)
    lost: int = 0
    bad: int = 0
    partial: int = 0
    pauses: int = 0
    bad_frames: list[bool] = field(default_factory=list)
    _open: dict | None = None
    _mark: bool = False
    _last_counter: int | None = None
    _last_t: int = 0
    _seq: int = 0

    def feed(self, f: Frame) -> None:
        is_lc = f.arbitration_id in IDS and not (f.extended or f.error or f.remote)
        if is_lc and len(f.data) != 8:
            self.bad += 1
            self._mark = True
            self.bad_frames.append(True)
            return
        self.bad_frames.append(False)
        if not is_lc:
            return
        counter = f.data[7]
        if self._open is not None and counter != self._open["counter"]:
            self._close()
        if self._open is None:
            self._open = {"counter": counter, "t": f.t_ns, "tb": f.t_bus_ns, "frames": {}}
        if f.arbitration_id in self._open["frames"]:
            self.bad += 1
            self._mark = True
            return
        self._open["frames"][f.arbitration_id] = f.data
        if len(self._open["frames"]) == 4:
            self._close()

    def flush(self) -> None:
        if self._open is not None:
            self._close()

    def _close(self) -> None:
        s = self._open
        assert s is not None
        self._open = None
        c, t = s["counter"], s["t"]
        if self._last_counter is None:
            self._seq = c
        else:
            step = (c - self._last_counter) % 256 or 256
            if self.rate_hz > 0 and t - self._last_t > round(256e9 / self.rate_hz):
                self.pauses += 1
            self.lost += step - 1
            self._seq += step
        self._last_counter, self._last_t = c, t
        raw = [RAW_MISSING] * 8
        ch_status = [0] * 8
        for j, fid in enumerate(IDS):
            d = s["frames"].get(fid)
            if d is None:
                continue
            raw[2 * j], raw[2 * j + 1] = int24(d[0:3]), int24(d[3:6])
            ch_status[2 * j], ch_status[2 * j + 1] = d[6] & 7, (d[6] >> 4) & 7
        status = 0
        if len(s["frames"]) < 4:
            status |= GAP
            self.partial += 1
        if self._mark:
            status |= BAD_FRAME
            self._mark = False
        for bit, sbit in CHANNEL_TO_SAMPLE:
            if any(x & bit for x in ch_status):
                status |= sbit
        T = [
            math.nan if r == RAW_MISSING else (r - o) * g
            for r, o, g in zip(raw, self.offsets, self.gains, strict=True)
        ]
        self.samples.append(
            {"t_ns": t, "T": T, "raw": raw, "ch_status": ch_status, "counter": c,
             "seq": self._seq, "t_bus_ns": s["tb"], "status": status}
        )  # fmt: skip
