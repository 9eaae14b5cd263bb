"""CAN load-cell driver: DBC byte layout, calibration, frame budget, counters, errors, slcan on a pty."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path

import can
import numpy as np
import pytest
import serial

import cdpr.daq.drivers  # noqa: F401  (registers the drivers)
from cdpr.analysis.errors import ConfigError
from cdpr.daq.loadcell import can_frame_bits, frame_budget
from cdpr.daq.slcan_emulator import SlcanEmulator
from cdpr.daq.source import (
    STATUS_BAD_FRAME,
    STATUS_GAP,
    STATUS_SATURATED,
    STATUS_SENSOR_FAULT,
    STATUS_SLACK,
    create_source,
)

ROOT = Path(__file__).resolve().parents[1]
CABLES = [f"k{i}" for i in range(1, 9)]


def _chan() -> str:
    return f"test-{uuid.uuid4().hex}"


def _source(channel: str, **kw):
    settings = {
        "interface": "virtual",
        "channel": channel,
        "bitrate": 1_000_000,
        "rate_hz": 100.0,
        "cables": CABLES,
        "offset_counts": [1000.0 * i for i in range(8)],
        "gain_N_per_count": 1e-4,
        "bus_options": {"receive_own_messages": False},
        **kw,
    }
    return create_source("can_loadcell", "lc", settings, "test.toml")


def _read_all(src, n_min: int, timeout_s: float = 2.0):
    out = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        out += src.read(0.05)
        if sum(r.stream == "tensions" for r in out) >= n_min:
            out += src.read(0.05)
            break
    return out


def _frames(counter: int, counts: list[int], status_byte: int = 0) -> list[can.Message]:
    """Four TPDOs built by hand (independent of cantools): int24 little-endian, status, counter."""
    msgs = []
    for j, fid in enumerate((0x181, 0x281, 0x381, 0x481)):
        a, b = counts[2 * j], counts[2 * j + 1]
        data = (a & 0xFFFFFF).to_bytes(3, "little") + (b & 0xFFFFFF).to_bytes(3, "little")
        data += bytes([status_byte if j == 0 else 0, counter & 0xFF])
        msgs.append(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
    return msgs


def test_frame_bits_hand_values() -> None:
    # standard 11-bit id, 8 data bytes: 44 + 64 + 3 IFS = 111 bits; + floor(97/4) = 24 stuff bits
    assert can_frame_bits(8, stuffing=False) == 111
    assert can_frame_bits(8) == 135
    assert can_frame_bits(0, stuffing=False) == 47
    assert can_frame_bits(8, extended=True, stuffing=False) == 131
    # 1 Mbit/s carries 1e6/135 = 7407 worst-case 8-byte frames/s: 8 one-frame cells at 1 kHz don't fit
    b = frame_budget(1_000_000, 1000.0, 8)
    assert b.frames_per_s == 8000 and b.bits_per_s == 1_080_000 and not b.fits


def test_dbc_decode_matches_hand_layout() -> None:
    ch = _chan()
    tx = can.Bus(interface="virtual", channel=ch, bitrate=1_000_000, receive_own_messages=False)
    with _source(ch) as src:
        counts = [-2, 0x123456, 0, 8388607, -8388608, 1, 12345, -12345]
        # status byte of TPDO1: bit0 ch1 saturated, bit5 ch2 slack, bit6 ch2 fault
        for m in _frames(7, counts, 0b0110_0001):
            tx.send(m)
        rd = _read_all(src, 1)
    tx.shutdown()
    raw = [r for r in rd if r.stream == "can_raw"]
    ten = [r for r in rd if r.stream == "tensions"]
    assert [r.values["arbitration_id"] for r in raw] == [0x181, 0x281, 0x381, 0x481]
    assert raw[0].values["data"] == bytes.fromhex("feffff5634126107")
    assert len(ten) == 1
    v = ten[0].values
    assert [v[f"raw_{c}_counts"] for c in CABLES] == counts
    # T = (counts - offset) * gain, offsets 0, 1000, ..., 7000 counts, gain 1e-4 N/count
    assert v["T_k1_N"] == pytest.approx(-2e-4)
    assert v["T_k2_N"] == pytest.approx((1193046 - 1000) * 1e-4)
    assert v["T_k4_N"] == pytest.approx((8388607 - 3000) * 1e-4)
    assert v["T_k5_N"] == pytest.approx((-8388608 - 4000) * 1e-4)
    assert v["T_k8_N"] == pytest.approx((-12345 - 7000) * 1e-4)
    assert v["status_k1"] == 1 and v["status_k2"] == 2 | 4 and v["status_k3"] == 0
    assert v["counter"] == 7
    assert ten[0].status == STATUS_SATURATED | STATUS_SLACK | STATUS_SENSOR_FAULT


def test_frame_budget_refused_names_key() -> None:
    # 4 frames/sample x 135 bits x 2 kHz = 1.08 Mbit/s > 0.9 x 1 Mbit/s
    with pytest.raises(ConfigError) as e:
        _source(_chan(), rate_hz=2000.0)
    assert e.value.source == "test.toml" and e.value.key == "sources.lc.rate_hz"
    assert "1666 Hz fits" in str(e.value)
    # 1 kHz fits at 1 Mbit/s (54 %) but not at 500 kbit/s (108 %)
    _source(_chan(), rate_hz=1000.0)
    with pytest.raises(ConfigError, match="rate_hz"):
        _source(_chan(), rate_hz=1000.0, bitrate=500_000)


def test_bad_settings_name_key() -> None:
    with pytest.raises(ConfigError) as e:
        _source(_chan(), gain_N_per_count=[1e-4] * 7)
    assert e.value.key == "sources.lc.gain_N_per_count"
    with pytest.raises(ConfigError) as e:
        _source(_chan(), dbc="no/such.dbc")
    assert e.value.key == "sources.lc.dbc"


def test_counter_gaps_and_partial_samples() -> None:
    ch = _chan()
    tx = can.Bus(interface="virtual", channel=ch, bitrate=1_000_000, receive_own_messages=False)
    counts = [100 * (i + 1) for i in range(8)]
    with _source(ch, offset_counts=0.0) as src:
        for c in (253, 254, 255, 0, 1, 4, 5):  # wrap without loss, then 2 and 3 lost
            for m in _frames(c, counts):
                tx.send(m)
        frames = _frames(6, counts)
        for m in frames[:2] + frames[3:]:  # TPDO3 of sample 6 lost: a partial sample
            tx.send(m)
        for m in _frames(7, counts):
            tx.send(m)
        rd = _read_all(src, 9)
        stats = src.stats
    tx.shutdown()
    ten = [r for r in rd if r.stream == "tensions"]
    assert [r.values["counter"] for r in ten] == [253, 254, 255, 0, 1, 4, 5, 6, 7]
    assert [r.values["seq"] for r in ten] == [253, 254, 255, 256, 257, 260, 261, 262, 263]
    assert stats.lost == 2
    assert stats.extra["partial_samples"] == 1
    part = ten[7]
    assert part.status & STATUS_GAP
    assert math.isnan(part.values["T_k5_N"]) and math.isnan(part.values["T_k6_N"])
    assert part.values["T_k7_N"] == pytest.approx(700 * 1e-4)  # counts x gain


def test_a_truncated_frame_is_bad_and_flags_its_sample() -> None:
    """TPDO3 of sample 6 arrives with 3 bytes (the DBC says 8): counted bad, sample 6 flagged
    gap + bad frame with channels 5 and 6 missing; the samples around it are clean."""
    ch = _chan()
    tx = can.Bus(interface="virtual", channel=ch, bitrate=1_000_000, receive_own_messages=False)
    counts = [100 * (i + 1) for i in range(8)]
    with _source(ch, offset_counts=0.0) as src:
        for c in (5, 6, 7):
            frames = _frames(c, counts)
            if c == 6:
                frames[2] = can.Message(
                    arbitration_id=0x381, data=bytes(frames[2].data)[:3], is_extended_id=False
                )
            for m in frames:
                tx.send(m)
        rd = _read_all(src, 3)
        stats = src.stats
    tx.shutdown()
    ten = [r for r in rd if r.stream == "tensions"]
    assert [r.values["counter"] for r in ten] == [5, 6, 7]
    assert [r.status for r in ten] == [0, STATUS_GAP | STATUS_BAD_FRAME, 0]
    assert math.isnan(ten[1].values["T_k5_N"]) and math.isnan(ten[1].values["T_k6_N"])
    assert stats.bad == 1 and stats.lost == 0


def test_error_frames_counted() -> None:
    ch = _chan()
    tx = can.Bus(interface="virtual", channel=ch, bitrate=1_000_000, receive_own_messages=False)
    with _source(ch) as src:
        tx.send(can.Message(arbitration_id=0x20000080, is_error_frame=True, data=b"\0" * 8))
        for m in _frames(1, [0] * 8):
            tx.send(m)
        rd = _read_all(src, 1)
        assert src.stats.errors == 1 and src.stats.extra["error_frames"] == 1
    tx.shutdown()
    assert sum(r.stream == "can_raw" and r.values["is_error_frame"] for r in rd) == 1


def test_slcan_emulator_answers_protocol(tmp_path: Path) -> None:
    with SlcanEmulator(tmp_path / "slcan0") as emu:
        with serial.Serial(str(tmp_path / "slcan0"), 115200, timeout=1.0) as port:

            def ask(cmd: bytes) -> bytes:
                port.write(cmd + b"\r")
                return port.read_until(b"\r")

            assert ask(b"V") == b"V1013\r"
            assert ask(b"N") == b"NCDPR\r"
            assert ask(b"F") == b"F00\r"
            assert ask(b"S6") == b"\r" and emu.bitrate == 500_000
            assert ask(b"O") == b"\r" and emu.is_open
            port.write(b"S8\r")
            assert port.read(1) == b"\a"  # bit rate changes only when closed
            assert ask(b"t12321122") == b"z\r"
            assert emu.received == [(0x123, b"\x11\x22", False)]
            assert emu.opened_event_wait(1.0)
            assert emu.send(0x181, bytes.fromhex("0102030405060708"))
            assert port.read_until(b"\r") == b"t18180102030405060708\r"
            assert ask(b"C") == b"\r" and not emu.is_open
            assert not emu.send(0x181, b"\x00")


_RIG = ROOT / "data_samples" / "flat_experiment2.toml"
_SCHEDULE = """
[schedule]
name = "slcan-test"
rate_hz = 50.0
tunnel_rate_hz = 10.0
method = "{method}"
seed = 3

[[segments]]
label = "tare"
tare = true
duration_s = 0.6

[[segments]]
label = "v41"
duration_s = 0.9
wind_mps = 41.42
euler_deg = [0.0, 4.0, 0.0]

[[faults]]
kind = "port_vanish"   # the USB adapter is pulled out for 0.2 s and plugged back
start_s = 1.0
duration_s = 0.2
"""


def test_slcan_across_processes_matches_truth(tmp_path: Path) -> None:
    """The virtual rig runs in a subprocess behind an emulated slcan adapter on a pty; python-can's
    slcan interface reads it here; decoded tensions match the truth the subprocess writes."""
    from cdpr.analysis.tension import METHODS

    sched = tmp_path / "s.toml"
    sched.write_text(_SCHEDULE.format(method="exact" if "exact" in METHODS else "closed-form"))
    link, tlink, truth = tmp_path / "can0", tmp_path / "tun0", tmp_path / "truth.npz"
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdpr.daq.virtual_rig", "--rig", str(_RIG), "--schedule", str(sched),
         "--transport", "slcan", "--pty-link", str(link), "--tunnel-link", str(tlink),
         "--truth", str(truth), "--wait-reader", "10"],
        stdout=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == f"READY {link}"
        import tomllib

        from cdpr.daq.schema import rig_from_mapping
        from cdpr.daq.virtual_rig import VirtualRig, load_schedule

        rig = rig_from_mapping(tomllib.loads(_RIG.read_text()), str(_RIG))
        vr = VirtualRig(rig, load_schedule(sched, rig))  # same seed: same calibration as the child
        srcs = []
        for name, (kind, st) in vr.source_settings(
            "slcan", link=str(link), tunnel_link=str(tlink)
        ).items():
            srcs.append(create_source(kind, name, {**st, "reopen_backoff_s": [0.05, 0.1]}, "t"))
        rd = []
        for s in srcs:
            s.open()
        while proc.poll() is None:
            for s in srcs:
                rd += s.read(0.02)
        # the last frames may still be in the pty on a loaded machine: read until the tensions
        # go quiet (nothing new for 0.5 s), within a bound far beyond any load
        deadline, quiet = time.monotonic() + 10.0, time.monotonic()
        while time.monotonic() < deadline and time.monotonic() - quiet < 0.5:
            for s in srcs:
                got = s.read(0.05)
                if got:
                    rd += got
                    quiet = time.monotonic()
        for s in srcs:
            s.close()
        out = proc.stdout.read()
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode in (0, -9), out
    tr = np.load(truth)
    ten = [r for r in rd if r.stream == "tensions"]
    tun = [r for r in rd if r.stream == "tunnel"]
    n = tr["t_rel_ns"].shape[0]
    lc = srcs[0].stats
    seq = np.array([r.values["seq"] for r in ten])
    assert n == 75 and (seq[:45] == np.arange(45)).all(), (len(ten), out, lc)
    # the adapter vanished for samples 50..59 (frames still in the pty when it was pulled out
    # are lost with it); the driver reopened the bus and went on to the end
    assert lc.errors >= 1 and lc.reopened >= 1
    assert not np.isin(np.arange(50, 60), seq).any() and seq[-1] == n - 1
    assert 10 <= lc.lost <= 25 and len(ten) + lc.lost == n, (lc, seq[40:])
    T = np.array([[r.values[f"T_{c}_N"] for c in rig.cable_names] for r in ten])
    # exact up to quantisation (gain 5e-5 N/count -> 2.5e-5 N)
    assert np.abs(T - tr["tensions_sensor_N"][seq]).max() <= 2.6e-5
    # and the true tensions within 6 sigma of noise plus drift
    assert np.abs(T - tr["tensions_true_N"][seq]).max() < 6 * 0.05 + 0.002 * 1.5
    # wind on changed the tensions by more than the noise
    assert np.abs(T[-1] - T[0]).max() > 1.0
    assert len(tun) >= 12
    assert tun[-1].values["airspeed_mps"] == pytest.approx(41.42, abs=0.3)
    lat_ms = (np.array([r.t_ns for r in ten]) - tr["t_ns"][seq]) / 1e6
    # after the frame was sent (causality, strict); the upper bound survives a load of 8 (a
    # broken time base would be seconds off)
    assert np.median(lat_ms) > 1.0 and np.median(lat_ms) < 1000.0


def test_slcan_bus_reopened_after_adapter_vanishes(tmp_path: Path) -> None:
    """The adapter disappears (pty closed, link removed) and comes back: the driver logs it, reopens
    the bus with backoff and decodes again."""
    link = tmp_path / "slcan0"
    emu = SlcanEmulator(link)
    counts = [10 * (i + 1) for i in range(8)]
    try:
        src = create_source(
            "can_loadcell",
            "lc",
            {"interface": "slcan", "channel": str(link), "bitrate": 500_000, "rate_hz": 50.0,
             "cables": CABLES, "bus_options": {"sleep_after_open": 0.0, "tty_baudrate": 115200},
             "reopen_backoff_s": [0.05, 0.2]},
            "t",
        )  # fmt: skip
        with src:
            assert emu.opened_event_wait(2.0) and emu.bitrate == 500_000

            def send(counter: int) -> None:
                for m in _frames(counter, counts):
                    assert emu.send(m.arbitration_id, bytes(m.data))

            send(1)
            first = _read_all(src, 1)
            emu.vanish()
            gone = []
            for _ in range(5):
                gone += src.read(0.05)
            assert src.stats.errors >= 1 and src.bus is None
            emu.restore()
            end = time.monotonic() + 3.0
            while not emu.opened_event_wait(0.01) and time.monotonic() < end:
                gone += src.read(0.05)  # the driver reopens the bus: C, S6, O again
            assert emu.is_open
            send(2)
            again = _read_all(src, 1)
            assert src.stats.reopened >= 1
    finally:
        emu.close()
    t1 = [r for r in first if r.stream == "tensions"]
    t2 = [r for r in again if r.stream == "tensions"]
    assert len(t1) == 1 and len(t2) == 1 and not gone
    assert t2[0].values["raw_k3_counts"] == 30 and t2[0].values["counter"] == 2


def test_long_gap_is_a_pause_not_invented_wraps() -> None:
    """A gap is what the 8-bit counter says modulo 256; more than one wrap of host time between two
    samples is a pause with its duration, never whole wraps guessed from the host clock."""
    from cdpr.daq.can_decoder import build_decoder
    from cdpr.daq.can_frames import FrameColumns

    t0 = 1_000_000_000_000
    msgs = [m for c in (10, 11, 21) for m in _frames(c, [0] * 8)]
    t = np.repeat([t0, t0 + 10_000_000, t0 + 3_010_000_000], 4).astype(np.int64)
    for m, tk in zip(msgs, t.tolist(), strict=True):
        m.timestamp = tk / 1e9
    # counter 11 -> 21: 9 samples missing by the counter; 3.0 s > one wrap (2.56 s at 100 Hz)
    for split in (12, 1, 5):  # the samples in one block, or frame by frame, or cut mid-sample
        dec, _ = build_decoder("t", "sources.lc", None, None, None, None, rate_hz=100.0)
        seq = []
        for a in range(0, 12, split):
            s = dec.decode_frames(FrameColumns.from_messages(msgs[a : a + split]), t[a : a + split])
            seq += s.columns["seq"].tolist()
        assert seq == [10, 11, 21] and dec.lost == 9
        assert dec.n_pauses == 1 and dec.pauses == [(t0 + 10_000_000, 3_000_000_000)]


def test_error_frame_flood_reopens_bus() -> None:
    ch = _chan()
    tx = can.Bus(interface="virtual", channel=ch, bitrate=1_000_000, receive_own_messages=False)
    with _source(ch, error_frame_limit=5, reopen_backoff_s=[0.01, 0.05]) as src:
        for _ in range(10):
            tx.send(can.Message(arbitration_id=0x20000004, is_error_frame=True, data=b"\0" * 8))
        for _ in range(5):
            src.read(0.02)
        assert src.stats.extra["error_frames"] == 6 and src.stats.reopened == 1
        for m in _frames(3, [7] * 8):
            tx.send(m)
        rd = _read_all(src, 1)
    tx.shutdown()
    assert [r.values["raw_k1_counts"] for r in rd if r.stream == "tensions"] == [7]


def _default_sigint() -> None:
    """In a child before exec: SIGINT back to its default, so that Python installs its
    KeyboardInterrupt handler even when this process runs with SIGINT ignored (no job control)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait_drained(link: Path, proc: subprocess.Popen, timeout_s: float) -> None:
    """Readiness, not a sleep: wait until the pty holds no unread byte for the reader ``proc``
    (FIONREAD on the slave side) and ``proc`` sleeps waiting for more (state ``S`` in
    /proc/<pid>/stat: python-can returns frames it has buffered before it blocks), three polls in
    a row."""
    import fcntl
    import struct
    import termios

    fd = os.open(os.path.realpath(link), os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        end = time.monotonic() + timeout_s
        quiet = 0
        while quiet < 3:
            assert time.monotonic() < end, "the logger did not drain the pty"
            assert proc.poll() is None, proc.communicate()
            pending = struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0" * 4))[0]
            state = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
            quiet = quiet + 1 if pending == 0 and state == "S" else 0
            time.sleep(0.02)
    finally:
        os.close(fd)


def test_python_can_logger_reads_the_emulated_adapter(tmp_path: Path) -> None:
    """An independent reader: python-can's own `can.logger` CLI, in another process, records the
    virtual rig's emulated slcan adapter to a candump log; the frames are exactly the rig's, and the
    replay driver decodes them to the truth."""
    import signal
    import tomllib

    from cdpr.analysis.tension import METHODS
    from cdpr.daq.schema import rig_from_mapping
    from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping

    rig = rig_from_mapping(tomllib.loads(_RIG.read_text()), str(_RIG))
    text = _SCHEDULE.format(method="exact" if "exact" in METHODS else "closed-form")
    data = tomllib.loads(text)
    data.pop("faults")
    data["segments"][1]["duration_s"] = 0.3
    vr = VirtualRig(rig, schedule_from_mapping(data, "s.toml", rig))
    link, log = tmp_path / "can0", tmp_path / "out.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}
    run = vr.start("slcan", link=link, wait_reader_s=120.0)
    logger = subprocess.Popen(
        [sys.executable, "-m", "can.logger", "-i", "slcan", "-c", str(link), "-b", "1000000",
         "--sleep-after-open=0", "-f", str(log)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, cwd=tmp_path,
        preexec_fn=_default_sigint,
    )  # fmt: skip
    try:
        assert run.wait(120.0)  # the rig waited for the logger's "O", then sent every frame
        _wait_drained(link, logger, timeout_s=120.0)
        logger.send_signal(signal.SIGINT)
        logger.wait(60)
    finally:
        run.stop()
        if logger.poll() is None:
            logger.kill()
    out, err = logger.communicate()
    assert logger.returncode == 0, err
    ids, frames = vr.can_frames()
    got = list(can.LogReader(str(log)))
    assert len(got) == 4 * vr.n_samples == 180
    assert [m.arbitration_id for m in got] == ids * vr.n_samples
    assert [bytes(m.data) for m in got] == [bytes(f) for f in frames.reshape(-1, 8)]
    kind, st = vr.source_settings("virtual")["loadcell"]
    cal = {k: st[k] for k in ("cables", "offset_counts", "gain_N_per_count")}
    src = create_source("can_replay", "rp", {"path": str(log), "speed": "max", **cal})
    rd = []
    with src:
        while not src.exhausted:
            rd += src.read(0.05)
    T = np.array(
        [[r.values[f"T_{c}_N"] for c in rig.cable_names] for r in rd if r.stream == "tensions"]
    )
    assert T.shape == (45, 8)
    assert np.abs(T - vr.tensions_sensor_N).max() <= 2.6e-5


def test_fast_unpack_agrees_with_cantools() -> None:
    """The decoder's vectorised integer unpacking gives what cantools decodes, on random
    payloads (the samples' raw counts and status bits against cantools' signals)."""
    import random

    from cdpr.daq.can_dbc import DEFAULT_DBC, load_dbc
    from cdpr.daq.can_decoder import LoadCellDecoder
    from cdpr.daq.can_frames import FrameColumns
    from cdpr.daq.loadcell import Calibration

    db = load_dbc(DEFAULT_DBC)
    dec = LoadCellDecoder(db, CABLES, Calibration(np.zeros(8), np.ones(8)))
    assert sorted(dec.dbc._fast) == [0x181, 0x281, 0x381, 0x481]  # the numpy unpacking
    rnd = random.Random(5)
    msgs = []
    for k in range(500):  # a complete sample of random payloads per counter value
        for fid in (0x181, 0x281, 0x381, 0x481):
            data = bytes(rnd.randrange(256) for _ in range(7)) + bytes([k % 256])
            msgs.append(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
    s = dec.decode_frames(FrameColumns.from_messages(msgs), np.arange(len(msgs)))
    assert len(s) == 500
    bits = {"Saturated": 1, "Slack": 2, "Fault": 4}
    for i, m in enumerate(msgs):
        ref = db.get_message_by_frame_id(m.arbitration_id).decode(
            bytes(m.data), decode_choices=False, scaling=False
        )
        for name, v in ref.items():
            if name == "Counter":
                assert s.columns["counter"][i // 4] == v
                continue
            ch, what = name.split("_")
            cable = CABLES[int(ch[2:]) - 1]
            if what == "Counts":
                assert s.columns[f"raw_{cable}_counts"][i // 4] == v, (i, name)
            else:
                assert bool(s.columns[f"status_{cable}"][i // 4] & bits[what]) == bool(v)
