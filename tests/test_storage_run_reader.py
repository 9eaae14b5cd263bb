"""``open_run``: the columnar reader against the values written and against the ``mcap`` package's
own reader (``iter_decoded_messages`` + ``json.loads``) on the same file."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cdpr.analysis.errors import CdprError, ConfigError
from cdpr.daq.mcap_io import McapRunWriter
from cdpr.daq.run_reader import open_run
from cdpr.daq.source import FieldDescription, Reading, StreamDescription

T0 = 1_700_000_000_000_000_000
CABLES = ("c1", "c2", "c3")


def _write_run(p: Path, n: int = 3000, chunk_size: int = 4096) -> dict[str, np.ndarray]:
    """A run with tensions (n rows, many chunks), poses with covariance, tunnel and events; returns
    the values written (a separate record of the truth, not read back)."""
    rng = np.random.default_rng(7)
    T = rng.uniform(35.0, 300.0, (n, len(CABLES)))
    T[5, 1] = math.nan  # a lost frame
    raw = rng.integers(-(2**31), 2**31, (n, len(CABLES)))
    t = T0 + np.arange(n, dtype=np.int64) * 1_000_000 + rng.integers(0, 999, n)
    w = McapRunWriter(p, chunk_size=chunk_size)
    fields = {f"T_{c}_N": FieldDescription("N") for c in CABLES}
    fields |= {f"raw_{c}_counts": FieldDescription("counts", "int64") for c in CABLES}
    fields["t_bus_ns"] = FieldDescription("ns", "int64")
    w.add_stream("tensions", StreamDescription(fields, 1000.0, "tensions"))
    w.add_metadata("run", {"rig": "flat", "label": "reader"})
    w.add_attachment("rig/flat.toml", b"[rig]\nname='flat'\n", "application/toml")
    cov = np.arange(36, dtype=np.float64) * 1e-6
    for i in range(n):
        vals: dict[str, object] = {f"T_{c}_N": float(T[i, j]) for j, c in enumerate(CABLES)}
        vals |= {f"raw_{c}_counts": int(raw[i, j]) for j, c in enumerate(CABLES)}
        vals["t_bus_ns"] = int(t[i]) + 17
        w.write(Reading("tensions", int(t[i]), vals, 16 if i == 5 else 0))
        if i % 100 == 0:
            k = i // 100
            w.write(
                Reading(
                    "pose",
                    int(t[i]) + 1,
                    {
                        "position_O_m": [0.5 + k, 0.1, 0.3],
                        "quaternion_wxyz": [0.5, 0.5, -0.5, 0.5],
                        "reprojection_px": 0.25,
                        "covariance": (cov * (k + 1)).tolist(),
                        "flags": k,
                    },
                )
            )
            w.write(Reading("tunnel", int(t[i]) + 2, {"airspeed_mps": 20.0 + k}))
    w.write(Reading("event", int(t[10]), {"message": "wind on", "level": "warning", "point": 3}))
    w.finish()
    return {"t": t, "T": T, "raw": raw, "cov": cov}


def _mcap_messages(p: Path, topic: str) -> list[tuple[int, dict]]:
    """(time, values) of every sample of ``topic`` read with the ``mcap`` package's reader; column
    blocks decoded by the independent tests/_block_reader.py."""
    from _block_reader import block_rows, is_block_channel
    from mcap.reader import make_reader

    out: list[tuple[int, dict]] = []
    with p.open("rb") as fh:
        for _, ch, m in make_reader(fh).iter_messages(topics=[topic]):
            if is_block_channel(ch):
                out += [(r.pop("t_ns"), r) for r in block_rows(m.data)]
            else:
                out.append((m.log_time, json.loads(m.data)))
    return out


def test_tension_table_matches_values_written_and_the_mcap_reader(tmp_path: Path) -> None:
    p = tmp_path / "run.mcap"
    truth = _write_run(p)
    with open_run(p) as run:
        assert not run.recovered and run.warning is None
        df = run.table("/tensions")
        assert list(df.columns[:1]) == ["t_ns"] and df["t_ns"].dtype == np.int64
        assert np.array_equal(df["t_ns"].to_numpy(), truth["t"])
        for j, c in enumerate(CABLES):
            got = df[f"T_{c}_N"].to_numpy()
            assert np.array_equal(got, truth["T"][:, j], equal_nan=True)  # bit-exact floats
            assert df[f"raw_{c}_counts"].dtype == np.int64
            assert np.array_equal(df[f"raw_{c}_counts"].to_numpy(), truth["raw"][:, j])
        assert np.array_equal(df["t_bus_ns"].to_numpy(), truth["t"] + 17)  # int64 exact
        assert df["status"].to_numpy()[5] == 16 and df["status"].sum() == 16
        # the mcap package's reader on the same file: every value of every message
        ref = _mcap_messages(p, "/tensions")
        assert len(ref) == len(df)
        ref_df = pd.DataFrame.from_records([b for _, b in ref]).astype(np.float64)
        assert np.array_equal(
            df[ref_df.columns].to_numpy(np.float64), ref_df.to_numpy(), equal_nan=True
        )

        info = run.streams["/tensions"]
        assert info.count == 3000 and info.rate_hz == 1000.0
        assert (info.start_ns, info.stop_ns) == (int(truth["t"][0]), int(truth["t"][-1]))
        assert info.fields["T_c1_N"].unit == "N" and info.fields["raw_c2_counts"].type == "integer"
        assert run.metadata["run"]["label"] == "reader"
        assert run.attachments["rig/flat.toml"] == ("application/toml", b"[rig]\nname='flat'\n")


def test_columns_time_windows_and_iteration(tmp_path: Path) -> None:
    p = tmp_path / "run.mcap"
    truth = _write_run(p)
    t = truth["t"]
    with open_run(p) as run:
        a, b = int(t[700]), int(t[2100])
        df = run.table("/tensions", columns=["T_c2_N"], start_ns=a, stop_ns=b)
        assert list(df.columns) == ["t_ns", "T_c2_N"]
        assert np.array_equal(df["t_ns"].to_numpy(), t[700:2100])
        parts = list(run.iter_tables("/tensions", window_ns=123_456_789))
        assert len(parts) == math.ceil((t[-1] + 1 - t[0]) / 123_456_789)
        whole = pd.concat(parts, ignore_index=True)
        assert np.array_equal(whole["t_ns"].to_numpy(), t)
        assert np.array_equal(whole["T_c3_N"].to_numpy(), truth["T"][:, 2])
        with pytest.raises(CdprError, match="no column 'T_c9_N'"):
            run.table("/tensions", columns=["T_c9_N"])
        with pytest.raises(CdprError, match="no topic '/nope'"):
            run.table("/nope")


def test_pose_event_and_tunnel_columns(tmp_path: Path) -> None:
    p = tmp_path / "run.mcap"
    truth = _write_run(p)
    with open_run(p) as run:
        pose = run.table("/pose")
        assert list(pose.columns[:8]) == ["t_ns", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"]
        assert len(pose) == 30
        assert np.array_equal(pose["x_m"].to_numpy(), 0.5 + np.arange(30))
        assert pose[["qw", "qx", "qy", "qz"]].to_numpy()[0].tolist() == [0.5, 0.5, -0.5, 0.5]
        cov_cols = [f"cov_{i}{j}" for i in range(6) for j in range(6)]
        assert np.array_equal(pose[cov_cols].to_numpy()[2], truth["cov"] * 3)
        assert pose["reprojection_px"].tolist() == [0.25] * 30
        assert pose["flags"].tolist() == list(range(30)) and pose["status"].sum() == 0
        ev = run.table("/event")
        assert ev.loc[0, "message"] == "wind on" and ev.loc[0, "level"] == 3
        assert ev.loc[0, "name"] == "event" and ev.loc[0, "point"] == 3
        tun = run.table("/tunnel", columns=["airspeed_mps"])
        assert np.array_equal(tun["airspeed_mps"].to_numpy(), 20.0 + np.arange(30))


def test_truncated_run_reads_through_recovery_and_says_so(tmp_path: Path) -> None:
    p = tmp_path / "run.mcap"
    truth = _write_run(p)
    cut = tmp_path / "cut.mcap"
    data = p.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with open_run(cut) as run:
        assert run.recovered
        assert run.warning is not None and "recovery" in run.warning and str(cut) in run.warning
        df = run.table("/tensions")
        n = len(df)
        assert 0 < n < 3000
        # what was salvaged is exactly the first n samples written
        assert np.array_equal(df["t_ns"].to_numpy(), truth["t"][:n])
        assert np.array_equal(df["T_c1_N"].to_numpy(), truth["T"][:n, 0])
        assert run.metadata["run"]["rig"] == "flat"
    assert not list(tmp_path.glob("*.recovered.mcap"))  # the recovered copy is temporary


def test_bad_files_are_config_errors(tmp_path: Path) -> None:
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(ConfigError, match="not an MCAP file"):
        open_run(bad)
    with pytest.raises(ConfigError, match="file not found"):
        open_run(tmp_path / "missing.mcap")
    shutil.rmtree(tmp_path)


def test_irregular_flat_bodies_take_the_json_path_with_the_same_values(tmp_path: Path) -> None:
    """Rows whose keys differ (a field only in some readings, another order), a string and a
    boolean value: the vectorised decoder steps aside and the values are still the ones written."""
    p = tmp_path / "run.mcap"
    w = McapRunWriter(p)
    rows = [
        {"airspeed_mps": 20.0, "temperature_K": 293},
        {"temperature_K": 294, "airspeed_mps": 21.5},  # another order
        {"airspeed_mps": 22.0, "temperature_K": 295, "note": "gust"},  # a string, an extra key
        {"airspeed_mps": math.nan, "temperature_K": 296, "valve_open": True},
    ]
    for i, v in enumerate(rows):
        w.write(Reading("tunnel", T0 + i, v))
    w.finish()
    with open_run(p) as run:
        df = run.table("/tunnel")
    assert df["t_ns"].tolist() == [T0 + i for i in range(4)]
    assert np.array_equal(df["airspeed_mps"].to_numpy(), [20.0, 21.5, 22.0, np.nan], equal_nan=True)
    assert df["temperature_K"].tolist() == [293, 294, 295, 296]
    assert df["note"].tolist()[2] == "gust" and df["valve_open"].tolist()[3] is True


def test_pose_columns_at_once_equal_the_row_by_row_path(tmp_path: Path, monkeypatch) -> None:
    """The pose decoder's fast path (every row with the same keys: columns at once) gives the same
    frame as the row-by-row path, on rows with a covariance, a lost pose (null position), integer
    flags, a float, a list and a frame id; rows that differ take the row path."""
    from cdpr.daq import run_reader

    p = tmp_path / "run.mcap"
    w = McapRunWriter(p)
    for i in range(50):
        pos = [math.nan] * 3 if i == 7 else [0.5 + i, 0.1, 0.3]
        vals = {"position_O_m": pos, "quaternion_xyzw": [0.0, 0.0, 0.0, 1.0], "flags": i % 3}
        vals |= {"covariance": (np.arange(36) * (i + 1.0)).tolist(), "reprojection_px": 0.1 * i}
        vals |= {"euler_rad": [0.0, 0.01 * i, 0.0]}
        w.write(Reading("pose", T0 + i, vals, 4 if i == 7 else 0))
    w.finish()
    results: list[object] = []
    real = run_reader._pose_frame

    def spy(rows: list) -> object:
        results.append(real(rows))
        return results[-1]

    monkeypatch.setattr(run_reader, "_pose_frame", spy)
    with open_run(p) as run:
        fast = run.table("/pose")
    assert results and all(r is not None for r in results)  # the columns-at-once path
    monkeypatch.setattr(run_reader, "_pose_frame", lambda rows: None)
    with open_run(p) as run:
        slow = run.table("/pose")
    pd.testing.assert_frame_equal(fast, slow)
    assert np.isnan(fast["x_m"][7]) and fast["flags"].dtype == np.int64
    assert fast["cov_55"][1] == 70.0 and fast["euler_rad_1"][3] == pytest.approx(0.03)
