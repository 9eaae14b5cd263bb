"""The CAN decoder's counter gaps over a real python-can virtual bus: a sender that pauses for
0.7 s, 1.5 s and 3 s loses nothing (a pause longer than a counter wrap is reported as a pause with
its duration), and real gaps are counted modulo 256.  Expected counts are written by hand."""

from __future__ import annotations

import time
import uuid

import can

import cdpr.daq.drivers  # noqa: F401  (registers the drivers)
from cdpr.daq.health import HealthMonitor
from cdpr.daq.recorder import SourceCounters
from cdpr.daq.source import create_source

RATE_HZ = 200.0  # one wrap of the 8-bit counter: 256 / 200 Hz = 1.28 s
CABLES = [f"k{i}" for i in range(1, 9)]


def _frames(counter: int) -> list[can.Message]:
    """The four TPDOs of one sample, built by hand: counts = counter, status 0, counter byte."""
    out = []
    for fid in (0x181, 0x281, 0x381, 0x481):
        data = (counter & 0xFFFFFF).to_bytes(3, "little") * 2 + bytes([0, counter & 0xFF])
        out.append(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
    return out


def test_paused_sender_is_a_pause_and_gaps_are_counted_modulo_256() -> None:
    ch = f"test-{uuid.uuid4().hex}"
    settings = {
        "interface": "virtual",
        "channel": ch,
        "bitrate": 1_000_000,
        "rate_hz": RATE_HZ,
        "cables": CABLES,
        "offset_counts": [0.0] * 8,
        "gain_N_per_count": 1.0,
        "bus_options": {"receive_own_messages": False},
    }
    src = create_source("can_loadcell", "lc", settings, "test.toml")
    tx = can.Bus(interface="virtual", channel=ch, bitrate=1_000_000, receive_own_messages=False)
    got: list[int] = []
    recv_ns: list[int] = []

    def burst(first: int, n: int) -> None:
        # send a burst and read it all before going on: reception times then bound the pause
        for k in range(first, first + n):
            for m in _frames(k % 256):
                tx.send(m)
        end = time.monotonic() + 30.0
        want = len(got) + n
        while len(got) < want and time.monotonic() < end:
            for r in src.read(0.05):
                if r.stream == "tensions":
                    got.append(int(r.values["counter"]))
                    recv_ns.append(r.t_ns)
        assert len(got) == want

    try:
        src.open()
        burst(0, 20)  # counters 0..19
        time.sleep(0.7)  # shorter than a wrap: nothing to say
        burst(20, 20)  # 20..39
        time.sleep(1.5)  # longer than a wrap: a pause, nothing lost
        burst(40, 20)  # 40..59
        time.sleep(3.0)  # two wraps and more: still one pause, nothing lost
        burst(60, 20)  # 60..79
        assert src.stats.lost == 0
        burst(79 + 141, 20)  # an outage with the counter running: 80..219 missing = 140 lost
        assert src.stats.lost == 140
        burst(239 + 31, 20)  # 239 -> 270 % 256 = 14 across the wrap: 240..269 = 30 lost
        assert src.stats.lost == 170
    finally:
        src.close()
        tx.shutdown()
    assert got[:80] == list(range(80))
    assert got[80:100] == list(range(220, 240)) and got[100] == 14
    pauses = src.stats.extra["pauses"], src.stats.extra["pause_s"]
    assert pauses[0] == 2
    d15, d30 = pauses[1]
    # the host-time gap is the sleep plus at most the reading of one burst (a loaded machine)
    assert 1.5 <= d15 < 1.5 + 10.0 and 3.0 <= d30 < 3.0 + 10.0
    assert abs(d15 - (recv_ns[40] - recv_ns[39]) * 1e-9) < 1e-3
    gap_07 = (recv_ns[20] - recv_ns[19]) * 1e-9
    assert 0.7 <= gap_07 < 1.28  # the 0.7 s pause, not reported

    # the recorder's health check turns each pause into one fault event naming its duration
    events: list[tuple[str, dict]] = []
    hm = HealthMonitor(
        {"lc": [RATE_HZ]},
        lambda msg, level, **kw: events.append((msg, kw)),
        startup_timeout_s=5.0,
        stall_timeout_s=60.0,
    )
    hm.start()
    hm.delivered("lc")
    c = SourceCounters("lc", lost=src.stats.lost, extra=dict(src.stats.extra))
    hm.check({"lc": c}, stopping=False, others_running=True)
    kinds = {kw["fault"]: msg for msg, kw in events}
    assert kinds["lost"] == "source lc: 170 samples lost (counter gaps) (total 170)"
    assert kinds["pauses"].startswith("source lc: 2 pause(s) longer than a counter wrap (total 2)")
    assert f"{d15:.2f} s, {d30:.2f} s" in kinds["pauses"]


def test_sample_split_across_reads_is_whole_and_a_missing_frame_is_one_incomplete_sample() -> None:
    """Where the soak's incomplete samples could come from, tried on a real virtual bus: frames of
    one sample split across two reads give one complete sample; a frame missing on the bus (what
    the soak's slcan adapter did when its buffer was full) gives exactly one incomplete sample,
    NaN for its two channels, and no sample invented."""
    import math

    from cdpr.daq.source import STATUS_GAP

    ch = f"test-{uuid.uuid4().hex}"
    settings = {
        "interface": "virtual",
        "channel": ch,
        "bitrate": 1_000_000,
        "rate_hz": RATE_HZ,
        "cables": CABLES,
        "offset_counts": [0.0] * 8,
        "gain_N_per_count": 1.0,
        "bus_options": {"receive_own_messages": False},
    }
    src = create_source("can_loadcell", "lc", settings, "test.toml")
    tx = can.Bus(interface="virtual", channel=ch, bitrate=1_000_000, receive_own_messages=False)
    out = []
    try:
        src.open()
        f0 = _frames(7)
        for m in f0[:2]:
            tx.send(m)
        out += src.read(0.05)  # the first half of sample 7 alone
        for m in f0[2:] + _frames(8)[:2] + _frames(8)[3:] + _frames(9):  # 0x381 of 8 missing
            tx.send(m)
        end = time.monotonic() + 30.0
        while sum(r.stream == "tensions" for r in out) < 3 and time.monotonic() < end:
            out += src.read(0.05)
    finally:
        src.close()
        tx.shutdown()
    t = [r for r in out if r.stream == "tensions"]
    assert [r.values["counter"] for r in t] == [7, 8, 9]
    assert [bool(r.status & STATUS_GAP) for r in t] == [False, True, False]
    nan = [k for k in CABLES if math.isnan(t[1].values[f"T_{k}_N"])]
    assert nan == ["k5", "k6"]  # frame 0x381 carries channels 5 and 6
    assert t[0].values["T_k1_N"] == 7.0 and t[2].values["T_k8_N"] == 9.0
    assert src.stats.lost == 0 and src.stats.extra["partial_samples"] == 1
