"""HDF5 export: one table per stream, metadata attributes, attachments; read back by h5py and pandas."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest

from cdpr.analysis.errors import CdprError, InputError
from cdpr.daq.hdf5_io import export_hdf5
from cdpr.daq.mcap_io import McapRunWriter
from cdpr.daq.source import FieldDescription, Reading, StreamDescription

T0 = 1_700_000_000_000_000_000


def _run(path: Path) -> None:
    w = McapRunWriter(path)
    w.add_metadata("run", {"rig": "flat-optimum", "operator": "me"})
    w.add_attachment("rig/flat.toml", b"[rig]\n", "application/toml")
    w.add_stream(
        "tensions",
        StreamDescription(
            {"T_c1_N": FieldDescription("N"), "T_c2_N": FieldDescription("N")}, 200.0
        ),
    )
    for i in range(300):
        w.write(
            Reading(
                "tensions",
                T0 + i * 5_000_000,
                {"T_c1_N": 35.0 + 0.5 * i, "T_c2_N": float("nan") if i == 7 else 100.0, "seq": i},
                16 if i == 7 else 0,
            )
        )
    for i in range(3):
        w.write(Reading("can_raw", T0 + i, {"arbitration_id": 0x181 + i, "data": bytes([i, 2, 3])}))
    w.write(
        Reading("pose", T0, {"position_O_m": [0.5, 0.0, 0.335], "quaternion_xyzw": [0, 0, 0, 1]})
    )
    w.write(Reading("image_cam", T0, {"data": b"\x89PNG-bytes", "format": "png"}))
    w.write(Reading("event", T0 + 9, {"message": "wind on 17.27 m/s"}))
    w.finish()


def test_export_reads_back_with_h5py_and_pandas(tmp_path: Path) -> None:
    run = tmp_path / "run.mcap"
    _run(run)
    out = tmp_path / "run.h5"
    counts = export_hdf5(run, out).counts
    assert counts == {"tensions": 300, "can_raw": 3, "pose": 1, "image_cam": 1, "event": 1}
    with h5py.File(out, "r") as f:
        assert f.attrs["format"] == "cdpr-run-hdf5/2" and f.attrs["source_file"] == "run.mcap"
        ds = f["streams/tensions"]
        assert ds.attrs["schema"] == "cdpr.tensions" and ds.attrs["rate_hz"] == 200.0
        df = pd.DataFrame(ds[()])
        assert list(df.columns) == ["t_ns", "T_c1_N", "T_c2_N", "seq", "status"]
        assert df["t_ns"].dtype == np.int64 and df["seq"].dtype == np.int64
        np.testing.assert_array_equal(df["t_ns"], T0 + np.arange(300) * 5_000_000)
        np.testing.assert_allclose(df["T_c1_N"], 35.0 + 0.5 * np.arange(300))
        assert np.isnan(df["T_c2_N"][7]) and df["status"][7] == 16 and df["T_c2_N"][8] == 100.0
        raw = pd.DataFrame(f["streams/can_raw"][()])
        assert raw["arbitration_id"].tolist() == [0x181, 0x182, 0x183]
        assert bytes(f["blobs/can_raw/data"][2]) == bytes([2, 2, 3])
        pose = pd.DataFrame(f["streams/pose"][()])
        assert list(pose.columns[:8]) == ["t_ns", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"]
        assert pose["z_m"][0] == 0.335 and pose["qw"][0] == 1.0 and pose["qx"][0] == 0.0
        assert bytes(f["blobs/image_cam/data"][0]) == b"\x89PNG-bytes"
        ev = f["streams/event"][()]
        assert ev["message"][0].decode() == "wind on 17.27 m/s"
        assert f["metadata/run"].attrs["rig"] == "flat-optimum"
        att = f["attachments/rig_flat.toml"]
        assert bytes(att[()]) == b"[rig]\n" and att.attrs["media_type"] == "application/toml"
    with pytest.raises(InputError, match="never overwritten"):
        export_hdf5(run, out)


def test_export_of_a_bad_file_writes_nothing(tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"not mcap at all")
    with pytest.raises(CdprError, match="not an MCAP file"):
        export_hdf5(bad, tmp_path / "out.h5")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.mcap"]
