"""Log replay: candump .log, ASC and BLF files written by python-can's own writers, replayed as a
load-cell source at maximum and at recorded speed."""

from __future__ import annotations

import time
from pathlib import Path

import can
import pytest

import cdpr.daq.drivers  # noqa: F401
from cdpr.analysis.errors import ConfigError
from cdpr.daq.source import create_source

N_SAMPLES = 30
PERIOD_S = 0.01  # 100 Hz


def _messages(t0: float) -> list[can.Message]:
    """N_SAMPLES samples of 4 hand-built TPDOs; channel k of sample s holds 1000*s + k counts."""
    out = []
    for s in range(N_SAMPLES):
        if s == 12:
            continue  # a lost sample in the log
        for j, fid in enumerate((0x181, 0x281, 0x381, 0x481)):
            a, b = 1000 * s + 2 * j + 1, -(1000 * s + 2 * j + 2)
            data = (a & 0xFFFFFF).to_bytes(3, "little") + (b & 0xFFFFFF).to_bytes(3, "little")
            data += bytes([0, s & 0xFF])
            out.append(
                can.Message(
                    timestamp=t0 + s * PERIOD_S + j * 1e-4,
                    arbitration_id=fid,
                    data=data,
                    is_extended_id=False,
                    channel="can0",
                )
            )
    return out


def _write(path: Path, msgs: list[can.Message]) -> None:
    writer = {".log": can.CanutilsLogWriter, ".asc": can.ASCWriter, ".blf": can.BLFWriter}[
        path.suffix
    ]
    w = writer(str(path))
    for m in msgs:
        w.on_message_received(m)
    w.stop()


def _replay(path: Path, **kw) -> tuple[list, object]:
    src = create_source(
        "can_replay", "rp", {"path": str(path), "gain_N_per_count": 0.001, **kw}, "cfg.toml"
    )
    out = []
    with src:
        end = time.monotonic() + 5.0
        while not src.exhausted and time.monotonic() < end:
            out += src.read(0.05)
        out += src.read(0.01)
    return out, src


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_replay_max_speed_decodes_every_frame(tmp_path: Path, suffix: str) -> None:
    t0 = 1_700_000_000.0
    msgs = _messages(t0)
    path = tmp_path / f"run{suffix}"
    _write(path, msgs)
    rd, src = _replay(path, speed="max")
    raw = [r for r in rd if r.stream == "can_raw"]
    ten = [r for r in rd if r.stream == "tensions"]
    assert len(raw) == len(msgs) == 4 * (N_SAMPLES - 1)
    assert [r.values["data"] for r in raw] == [bytes(m.data) for m in msgs]
    assert [r.values["counter"] for r in ten] == [s for s in range(N_SAMPLES) if s != 12]
    assert src.stats.lost == 1
    s = ten[20].values["counter"]
    assert ten[20].values["T_c1_N"] == pytest.approx((1000 * s + 1) * 0.001)
    assert ten[20].values["T_c8_N"] == pytest.approx(-(1000 * s + 8) * 0.001)
    if suffix == ".log":  # candump keeps absolute times: t_ns is the recorded time
        assert raw[0].t_ns == pytest.approx(t0 * 1e9, abs=2e3)
    gaps = [(b.t_ns - a.t_ns) / 1e9 for a, b in zip(ten[:5], ten[1:6], strict=True)]
    assert gaps == pytest.approx([PERIOD_S] * 5, abs=2e-5)


def test_replay_recorded_speed_takes_recorded_time(tmp_path: Path) -> None:
    path = tmp_path / "run.log"
    _write(path, _messages(1_700_000_000.0))
    span = (N_SAMPLES - 1) * PERIOD_S + 3e-4
    t = time.monotonic()
    rd, _ = _replay(path, speed="recorded")
    took = time.monotonic() - t
    assert span * 0.9 < took < span + 0.25
    rd2, _ = _replay(path, speed="recorded", time_scale=4.0)
    assert len(rd2) == len(rd)


def test_replay_bad_settings(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as e:
        create_source("can_replay", "rp", {"path": str(tmp_path / "none.log")}, "cfg.toml")
    assert e.value.key == "sources.rp.path" and e.value.source == "cfg.toml"
    (tmp_path / "x.log").write_text("")
    with pytest.raises(ConfigError) as e:
        create_source("can_replay", "rp", {"path": str(tmp_path / "x.log"), "speed": "fast"})
    assert e.value.key == "sources.rp.speed"
