"""Serial load cells and tunnel conditions over real pseudo-terminals: checksums, bad lines, seq gaps,
the port vanishing and coming back, and the manual tunnel source."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

import cdpr.daq.drivers  # noqa: F401
from cdpr.analysis.errors import ConfigError
from cdpr.daq.serial_protocol import (
    LineError,
    LineSplitter,
    checksum,
    format_loadcell_line,
    parse_loadcell_line,
    split_checked,
)
from cdpr.daq.slcan_emulator import PtyPort
from cdpr.daq.source import STATUS_SATURATED, STATUS_SLACK, create_source

CABLES = ["a", "b", "c", "d"]


def test_checksum_is_nmea_xor() -> None:
    # the textbook NMEA sentence and its published checksum
    body = b"GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"
    assert checksum(body) == 0x47
    assert split_checked(b"$" + body + b"*47")[0] == "GPGGA"
    with pytest.raises(LineError, match="checksum mismatch"):
        split_checked(b"$" + body + b"*48")


def test_loadcell_line_format_by_hand() -> None:
    line = format_loadcell_line(17, 340000, [120345, -2, 0, 7], 0b010_000_000_001)
    assert line.startswith(b"$LC,17,340000,120345,-2,0,7,401*") and line.endswith(b"\r\n")
    p = parse_loadcell_line(line, 4)
    assert p.seq == 17 and p.counts == (120345, -2, 0, 7) and p.status == 0x401
    with pytest.raises(LineError, match="expected 8 channels"):
        parse_loadcell_line(line, 8)


def test_splitter_blocks_and_garbage() -> None:
    sp = LineSplitter(max_line=40)
    lines, junk = sp.feed(b"$A*41\r\n$B")
    assert lines == [b"$A*41"] and junk == []
    lines, junk = sp.feed(b"*42\r\n" + b"x" * 50)
    assert lines == [b"$B*42"] and junk == [b"x" * 50]


def _lc_source(link: Path, **kw):
    settings = {
        "port": str(link),
        "baudrate": 115200,
        "rate_hz": 50.0,
        "cables": CABLES,
        "offset_counts": [0, 100, 200, 300],
        "gain_N_per_count": 0.01,
        "reopen_backoff_s": [0.02, 0.1],
        **kw,
    }
    return create_source("serial_loadcell", "lc", settings, "rig.toml")


def _drain(src, n: int, stream: str = "tensions", timeout_s: float = 2.0):
    out = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and sum(r.stream == stream for r in out) < n:
        out += src.read(0.05)
    return out


def test_serial_loadcell_bad_lines_counted_and_kept(tmp_path: Path) -> None:
    port = PtyPort(tmp_path / "ttyLC")
    try:
        with _lc_source(port.link) as src:
            good = [format_loadcell_line(k, 1000 * k, [k, 100 + k, 200, 300], 0) for k in range(6)]
            bad_sum = bytearray(good[1])
            bad_sum[5] = ord("9")  # corrupt a digit: checksum mismatch
            truncated = good[2][:12] + b"\r\n"  # line cut short
            assert port.write(good[0] + bytes(bad_sum) + truncated + b"\x00\xff garbage\r\n")
            # sample 4 with flags: ch1 saturated (1), ch2 slack (2 << 3); seq 3 lost
            flagged = format_loadcell_line(4, 4000, [50, 90, 200, 300], 1 | (2 << 3))
            assert port.write(flagged + good[5])
            rd = _drain(src, 3)
            # samples 1..3 never decoded (1 and 2 arrived as bad lines, 3 not at all)
            assert src.stats.bad == 3 and src.stats.lost == 3
    finally:
        port.close()
    ten = [r for r in rd if r.stream == "tensions"]
    bad = [r for r in rd if r.stream == "serial_bad"]
    assert [r.values["seq"] for r in ten] == [0, 4, 5]
    assert ten[0].values["T_a_N"] == 0.0 and ten[0].values["T_b_N"] == pytest.approx(0.0)
    assert ten[1].values["T_a_N"] == pytest.approx(0.5)  # 50 counts x 0.01
    assert ten[1].values["T_b_N"] == pytest.approx(-0.1)  # (90 - 100) x 0.01
    assert ten[1].status == STATUS_SATURATED | STATUS_SLACK
    assert ten[1].values["status_a"] == 1 and ten[1].values["status_b"] == 2
    reasons = [r.values["reason"] for r in bad]
    assert "checksum mismatch" in reasons[0]
    assert "truncated" in reasons[1]
    assert reasons[2] == "no leading '$'"
    assert bad[1].values["line"] == truncated[:-2].decode()


def test_serial_port_vanishes_and_returns(tmp_path: Path) -> None:
    port = PtyPort(tmp_path / "ttyLC")
    try:
        with _lc_source(port.link) as src:
            assert port.write(format_loadcell_line(0, 0, [1, 2, 3, 4], 0))
            before = _drain(src, 1)
            port.vanish()  # unplugged: pty closed, link removed
            during = []
            for _ in range(6):
                during += src.read(0.03)
            assert src.stats.errors >= 1 and src.ser is None
            assert not port.link.exists()
            port.restore()  # plugged back: a new pty at the same path
            end = time.monotonic() + 2.0
            while src.ser is None and time.monotonic() < end:
                during += src.read(0.03)
            assert src.stats.reopened == 1
            deadline = time.monotonic() + 1.0
            while not port.reader_attached() and time.monotonic() < deadline:
                time.sleep(0.01)
            assert port.write(format_loadcell_line(9, 9, [5, 6, 7, 8], 0))
            after = _drain(src, 1)
            assert src.stats.lost == 8  # seq 1..8 never arrived
    finally:
        port.close()
    assert [r.values["seq"] for r in before if r.stream == "tensions"] == [0]
    assert not [r for r in during if r.stream == "tensions"]
    assert [r.values["raw_d_counts"] for r in after if r.stream == "tensions"] == [8]


def test_serial_settings_errors_name_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as e:
        _lc_source(tmp_path / "none", cables=["a"] * 4)
    assert e.value.key == "sources.lc.cables"
    # 8 channels need ~120 bytes/line = 1200 bits: 115200 baud carries ~96 lines/s
    with pytest.raises(ConfigError) as e:
        _lc_source(tmp_path / "none", cables=[f"c{i}" for i in range(8)], rate_hz=200.0)
    assert e.value.key == "sources.lc.rate_hz" and e.value.source == "rig.toml"
    with pytest.raises(ConfigError) as e:
        _lc_source(tmp_path / "none").open()
    assert e.value.key == "sources.lc.port"


def test_serial_tunnel_and_density(tmp_path: Path) -> None:
    from cdpr.daq.serial_protocol import format_tunnel_line

    port = PtyPort(tmp_path / "ttyTUN")
    try:
        src = create_source("serial_tunnel", "tun", {"port": str(port.link), "rate_hz": 10.0})
        with src:
            assert port.write(format_tunnel_line(0, 17.27, 101325.0, 293.15) + b"$TUN,1,x*00\r\n")
            assert port.write(format_tunnel_line(1, 25.51, 100000.0, 300.0))
            rd = _drain(src, 2, "tunnel")
    finally:
        port.close()
    tun = [r for r in rd if r.stream == "tunnel"]
    assert [r.values["airspeed_mps"] for r in tun] == [17.27, 25.51]
    # rho = p / (R T) = 101325 / (287.05287 * 293.15) = 1.20410 kg/m^3
    assert tun[0].values["density_kgpm3"] == pytest.approx(1.20410, abs=1e-5)
    assert tun[1].values["density_kgpm3"] == pytest.approx(100000 / (287.05287 * 300.0))
    assert src.stats.bad == 1


def test_tunnel_line_optional_humidity_by_hand() -> None:
    """The fifth value is optional: the four-value line is unchanged (backwards compatible)."""
    from cdpr.daq.serial_protocol import format_tunnel_line, parse_tunnel_line

    old = format_tunnel_line(3, 25.51, 101325.0, 293.15)
    assert old == b"$TUN,3,25.5100,101325.00,293.150*59\r\n"  # the docstring's example
    assert parse_tunnel_line(old).relative_humidity is None
    body = b"TUN,4,25.5100,101325.00,293.150,0.4500"
    line = b"$" + body + b"*%02X\r\n" % checksum(body)
    assert format_tunnel_line(4, 25.51, 101325.0, 293.15, 0.45) == line
    assert parse_tunnel_line(line).relative_humidity == 0.45
    for bad in (b"TUN,4,25.5,101325.0,293.15,1.2", b"TUN,4,25.5,101325.0,293.15,nan"):
        with pytest.raises(LineError, match="outside 0..1"):
            parse_tunnel_line(b"$" + bad + b"*%02X" % checksum(bad))
    extra = b"TUN,4,25.5,101325.0,293.15,0.4,9"
    with pytest.raises(LineError, match="expected 4 or 5 fields"):
        parse_tunnel_line(b"$" + extra + b"*%02X" % checksum(extra))


def test_serial_tunnel_humidity_and_moist_density(tmp_path: Path) -> None:
    from cdpr.daq.serial_protocol import format_tunnel_line

    port = PtyPort(tmp_path / "ttyTUN")
    try:
        src = create_source("serial_tunnel", "tun", {"port": str(port.link), "rate_hz": 10.0})
        with src:
            assert port.write(format_tunnel_line(0, 25.0, 101325.0, 303.15, 0.8))
            assert port.write(format_tunnel_line(1, 25.0, 101325.0, 303.15))
            rd = _drain(src, 2, "tunnel")
    finally:
        port.close()
    wet, dry = (r.values for r in rd if r.stream == "tunnel")
    assert wet["relative_humidity"] == 0.8 and "relative_humidity" not in dry
    # by hand at 30 deg C: e_s = 4245 Pa (steam tables: 4.2455 kPa), e = 0.8 e_s = 3396 Pa,
    # rho = (p - e)/(287.05287 T) + e/(461.5 T) = 1.12537 + 0.02427 = 1.1496 kg/m^3
    assert wet["density_kgpm3"] == pytest.approx(1.1496, abs=3e-4)
    assert dry["density_kgpm3"] == pytest.approx(101325.0 / (287.05287 * 303.15))
    assert dry["density_kgpm3"] - wet["density_kgpm3"] > 0.01  # 1.3 % denser when dry


def test_manual_tunnel_per_test_point() -> None:
    src = create_source(
        "manual_tunnel", "tun", {"airspeed_mps": 41.42, "rate_hz": 20.0, "label": "tp3"}, "cfg.toml"
    )
    with src:
        r0 = src.read(0.01)
        assert r0[0].values["airspeed_mps"] == 41.42 and r0[0].values["label"] == "tp3"
        assert r0[0].values["static_pressure_Pa"] == 101325.0
        src.set_point(0.0, label="tare")
        r1 = src.read(0.01)
        assert r1[0].values["airspeed_mps"] == 0.0 and r1[0].values["label"] == "tare"
        r2 = src.read(0.2)  # repeats at rate_hz
        assert r2 and r2[0].values["seq"] == 2
    with pytest.raises(ConfigError) as e:
        create_source("manual_tunnel", "tun", {"airspeed_mps": -3.0}, "cfg.toml")
    assert e.value.key == "sources.tun.airspeed_mps" and e.value.source == "cfg.toml"
