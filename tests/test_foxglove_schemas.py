"""Channels that claim a Foxglove schema keep it exactly; a camera frame without a pose is no
``foxglove.PoseInFrame`` message, its status goes on ``/pose_status``, and every reader still sees
every frame (issue 19, item 4).

Truth: Foxglove's own published JSON schemas (``tests/data/foxglove/``, copied from
github.com/foxglove/schemas), real recorded runs (the recorder over the virtual camera's rendered
frames and the real IR-mark detector, a third of the frames covered; ``cdpr simulate`` with a
camera), and a run in the layout written before the change, built here with the ``mcap``
package's own writer from the bodies the old writer produced.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from _camera_runs import COVER_EVERY, covered_camera_run, simulated_camera_run
from mcap.reader import make_reader

from cdpr.daq.mcap_writer import McapRunWriter
from cdpr.daq.run_reader import open_run
from cdpr.daq.source import Reading

PUBLISHED = Path(__file__).parent / "data" / "foxglove"
ROOT = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000
STATUS_BAD_FRAME = 8  # docs/recording.md: status bit 8, bad frame
FLAG_NO_POSE = 1  # docs/vision.md: flag bit 1, no pose


def _published(name: str) -> dict[str, Any]:
    """Foxglove's published schema of ``foxglove.<name>``."""
    return json.loads((PUBLISHED / f"{name.removeprefix('foxglove.')}.json").read_text())


def _messages(path: Path) -> list[tuple[str, str, dict[str, Any], int, Any]]:
    """(topic, schema name, schema, log time, body) of every message, by the mcap package."""
    out = []
    with path.open("rb") as fh:
        for schema, channel, msg in make_reader(fh).iter_messages():
            out.append(
                (channel.topic, schema.name, json.loads(schema.data), msg.log_time,
                 json.loads(msg.data))
            )  # fmt: skip
    return out


@pytest.fixture(scope="module")
def covered_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return covered_camera_run(tmp_path_factory.mktemp("covered") / "run.mcap")


@pytest.fixture(scope="module")
def simulated_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulated_camera_run(tmp_path_factory.mktemp("sim"))


@pytest.mark.parametrize("which", ["covered_run", "simulated_run"])
def test_every_foxglove_message_of_a_recorded_run_is_valid_against_the_published_schema(
    which: str, request: pytest.FixtureRequest
) -> None:
    """Every message of a channel that names a ``foxglove.*`` schema validates against Foxglove's
    published schema, and the schema the file embeds is that one; our own channels' messages
    validate against their own schemas."""
    run: Path = request.getfixturevalue(which)
    seen: dict[str, int] = {}
    for topic, name, schema, _, body in _messages(run):
        if name.startswith("foxglove."):
            assert schema == _published(name), topic
        jsonschema.Draft202012Validator(_published(name) if name.startswith("foxglove.") else
                                        schema).validate(body)  # fmt: skip
        seen[name] = seen.get(name, 0) + 1
    assert seen["foxglove.PoseInFrame"] > 0 and seen["foxglove.CompressedImage"] > 0
    assert seen["foxglove.Log"] > 0 and seen["cdpr.pose_status"] >= seen["foxglove.PoseInFrame"]


def test_a_frame_without_a_pose_has_its_status_only_and_every_reader_sees_every_frame(
    covered_run: Path, tmp_path: Path, capsys
) -> None:
    from cdpr.pipelines.cli import main

    msgs = _messages(covered_run)
    status = [(t, b) for topic, _, _, t, b in msgs if topic == "/pose_status"]
    poses = {t: b for topic, _, _, t, b in msgs if topic == "/pose"}
    covered = [b["frame_index"] % COVER_EVERY == COVER_EVERY - 1 for _, b in status]
    assert [b["frame_index"] for _, b in status] == list(range(len(status)))
    assert len(status) >= 15 and 0 < sum(covered) < len(status)
    for (t, b), cov in zip(status, covered, strict=True):
        if cov:  # no marks in the frame: no pose, no PoseInFrame message, its status says why
            assert b["has_pose"] == 0 and b["status"] == STATUS_BAD_FRAME
            assert b["flags"] & FLAG_NO_POSE and b["n_points"] == 0 and t not in poses
        else:
            assert b["has_pose"] == 1 and b["status"] == 0 and b["flags"] == 0
            p = poses[t]["pose"]["position"]
            assert abs(p["x"] - 0.5) < 1e-3 and abs(p["z"] - 0.335) < 1e-3  # flat_optimum's pose
    assert len(poses) == len(status) - sum(covered)

    # open_run: one row per frame, NaN where there is no pose; status, flags and covariance kept
    with open_run(covered_run) as run:
        assert run.streams["/pose"].count == len(status)
        df = run.table("/pose")
        assert df["t_ns"].tolist() == [t for t, _ in status]
        assert df["x_m"].isna().tolist() == covered
        assert df["status"].tolist() == [b["status"] for _, b in status]
        assert df["flags"].tolist() == [b["flags"] for _, b in status]
        assert np.isfinite(df.loc[~np.array(covered), "cov_00"]).all()
        assert list(df.columns[:8]) == ["t_ns", "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"]
        win = run.iter_tables("/pose", window_ns=150_000_000)
        assert sum(len(w) for w in win) == len(status)
        assert run.times("/pose").tolist() == [t for t, _ in status]

    # inspect: the frames under /pose, the covered ones as bad; /pose_status is not listed twice
    assert main(["inspect", str(covered_run)]) == 0
    out = capsys.readouterr().out
    (row,) = [x.split() for x in out.splitlines() if x.strip().startswith("/pose")]
    assert row[1] == "foxglove.PoseInFrame" and int(row[2]) == len(status)
    assert int(row[-1]) == sum(covered)

    # export: one table of every frame, no second copy of the status
    import h5py

    h5 = tmp_path / "run.h5"
    assert main(["export", str(covered_run), "--hdf5", str(h5)]) == 0
    with h5py.File(h5) as f:
        assert "pose_status" not in f["streams"]
        tab = f["streams/pose"][()]
        assert len(tab) == len(status) and np.isnan(tab["x_m"]).tolist() == covered


# -------------------------------------------------------------------------------------------------
# runs written before the change: /pose alone, foxglove.PoseInFrame with nulls and extra fields


def _camera_reading(k: int) -> Reading:
    """Frame ``k`` as the camera source gives it: a pose (3 in 7 frames: none; frame 5: a pose
    with numbers but flagged, status bad frame), covariance, flags, counts."""
    lost = k % 7 in (2, 3, 6)
    flagged = k == 5
    pos = [0.5 + 1e-4 * k, -2e-4 * k, 0.335] if not lost else [math.nan] * 3
    ang = 0.01 * k
    quat = [math.cos(ang / 2), 0.0, math.sin(ang / 2), 0.0] if not lost else [math.nan] * 4
    eul = [0.0, ang, 0.0] if not lost else [math.nan] * 3
    cov = (np.diag([1e-8, 2e-8, 3e-8, 1e-7, 2e-7, 3e-7]) * (1 + 0.1 * k)).reshape(-1).tolist()
    values = {
        "position_O_m": pos,
        "quaternion_wxyz": quat,
        "euler_rad": eul,
        "reprojection_px": 0.03 + 1e-3 * k if not lost else math.nan,
        "covariance": cov if not lost else [math.nan] * 36,
        "flags": (FLAG_NO_POSE | 2) if lost else (4 if flagged else 0),
        "n_points": 0 if lost else 6,
        "frame_index": k,
    }
    return Reading("pose", T0 + k * 33_000_000, values, STATUS_BAD_FRAME if lost or flagged else 0)


def _old_pose_body(r: Reading) -> bytes:
    """The ``/pose`` body the writer produced before the change (one channel): Foxglove's fields
    with nulls for a lost pose, then the reading's other values and ``status``."""
    v = dict(r.values)
    p = v.pop("position_O_m")
    w, x, y, z = v.pop("quaternion_wxyz")
    body = {
        "timestamp": {"sec": r.t_ns // 10**9, "nsec": r.t_ns % 10**9},
        "frame_id": "O",
        "pose": {
            "position": dict(zip("xyz", p, strict=True)),
            "orientation": {"x": x, "y": y, "z": z, "w": w},
        },
        **v,
        "status": r.status,
    }
    text = json.dumps(body, separators=(",", ":"), allow_nan=True)
    return text.replace("NaN", "null").encode()


def _tension_readings(cables: list[str], n: int = 60) -> list[Reading]:
    return [
        Reading(
            "tensions",
            T0 + i * 10_000_000,
            {**{f"T_{c}_N": 100.0 + j for j, c in enumerate(cables)}, "seq": i},
        )
        for i in range(n)
    ]


def _write_old_layout(path: Path, rig_text: str, tensions: list[Reading], poses: list[Reading]):
    """A run as the old writer laid it out, written by the ``mcap`` package's writer."""
    from mcap.writer import Writer

    old_pose_schema = {  # the old codec's schema: Foxglove's fields, numbers or null, extras
        "type": "object",
        "title": "foxglove.PoseInFrame",
        "properties": {"frame_id": {"type": "string"}, "status": {"type": "integer"}},
        "additionalProperties": True,
    }
    with path.open("wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="cdpr-recorder")
        w.add_attachment(T0, T0, "rig/flat_optimum.toml", "application/toml", rig_text.encode())
        sid = w.register_schema("cdpr.tensions", "jsonschema", b'{"type":"object"}')
        ct = w.register_channel("/tensions", "json", sid, {"stream": "tensions"})
        sid = w.register_schema("foxglove.PoseInFrame", "jsonschema",
                                json.dumps(old_pose_schema).encode())  # fmt: skip
        cp = w.register_channel("/pose", "json", sid, {"stream": "pose", "rate_hz": "30.0"})
        for r in sorted([*tensions, *poses], key=lambda r: r.t_ns):
            if r.stream == "pose":
                w.add_message(cp, r.t_ns, _old_pose_body(r), r.t_ns)
            else:
                body = json.dumps({**r.values, "status": r.status}).encode()
                w.add_message(ct, r.t_ns, body, r.t_ns)
        w.finish()


def test_a_run_of_the_old_layout_reads_as_the_new_one(tmp_path: Path) -> None:
    """The same camera frames written in the old layout (one /pose channel, nulls) and in the new
    one (/pose + /pose_status): ``open_run`` gives the same table (the new one adds ``has_pose``;
    a frame without a pose has no ``frame_id``), and the analysis's loader the same poses,
    covariances and bad frames, which are the lost and the flagged frames."""
    from cdpr.pipelines.analyze import load_run
    from cdpr.pipelines.config import load_rig

    rig_file = ROOT / "data_samples" / "flat_optimum.toml"
    cables = list(load_rig(str(rig_file)).cable_names)
    tensions = _tension_readings(cables)
    poses = [_camera_reading(k) for k in range(18)]
    old, new = tmp_path / "old.mcap", tmp_path / "new.mcap"
    _write_old_layout(old, rig_file.read_text(), tensions, poses)
    w = McapRunWriter(new)
    w.add_attachment("rig/flat_optimum.toml", rig_file.read_bytes(), "application/toml")
    for r in sorted([*tensions, *poses], key=lambda r: r.t_ns):
        w.write(r)
    w.finish()

    with open_run(old) as a, open_run(new) as b:
        assert "/pose_status" not in a.streams and b.streams["/pose_status"].count == 18
        assert a.streams["/pose"].count == b.streams["/pose"].count == 18
        ta, tb = a.table("/pose"), b.table("/pose")
    lost = np.array([k % 7 in (2, 3, 6) for k in range(18)])
    assert list(tb.drop(columns="has_pose").columns) == list(ta.columns)
    assert tb["has_pose"].tolist() == (~lost).astype(int).tolist()
    assert tb["frame_id"].tolist() == [None if x else "O" for x in lost]
    assert ta["frame_id"].tolist() == ["O"] * 18
    for c in ta.columns.drop("frame_id"):
        np.testing.assert_array_equal(ta[c].to_numpy(np.float64), tb[c].to_numpy(np.float64), c)
    assert np.isnan(ta["x_m"].to_numpy()).tolist() == lost.tolist()
    np.testing.assert_array_equal(ta["x_m"][~lost], [0.5 + 1e-4 * k for k in np.flatnonzero(~lost)])

    ra, rb = load_run(old), load_run(new)
    bad = lost.copy()
    bad[5] = True  # a pose with numbers, flagged: bad too
    assert ra.pose_bad.tolist() == rb.pose_bad.tolist() == bad.tolist()
    np.testing.assert_array_equal(ra.poses, rb.poses)
    np.testing.assert_array_equal(ra.pose_t_ns, rb.pose_t_ns)
    # the frames without a pose carry no covariance, the run keeps the camera's covariance
    assert ra.pose_cov is not None and rb.pose_cov is not None
    np.testing.assert_array_equal(ra.pose_cov, rb.pose_cov)
    good = ~bad
    np.testing.assert_allclose(rb.pose_cov[good][:, 0, 0], [1e-8 * (1 + 0.1 * k)
                               for k in np.flatnonzero(good)])  # fmt: skip
    assert ra.pose_source == rb.pose_source == "camera (/pose stream)"
