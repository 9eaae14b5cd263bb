"""``cdpr import --cable-lengths``: a controller's cable-length log as the run's pose source.

The lengths are written here from a known pitch-and-heave motion with the lab generator's own
geometry (tests/_lab_physics.py, not cdpr's), 20 um of noise; the imported ``/pose`` (read back
with the mcap library, not cdpr's reader) against that motion: errors consistent with the
covariance each frame carries (chi-square per frame about 6, the claimed pitch σ the scatter's);
a jumped length marks its frame bad; the refusals are one line, exit 2 and no file."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import lab_generator as lg
import numpy as np
import pytest
from _lab_physics import LabRig, cable_vectors, rate_matrix
from mcap.reader import make_reader
from measure_coverage import cdpr_command, clean_env


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> lg.LabCase:
    specs = (lg.OscSpec("pitch", 5.0, 2.0, (25.51,), 4),)
    return lg.oscillation_case(tmp_path_factory.mktemp("len") / "case", specs, seed=8)


def _motion(t_s: np.ndarray, rig: LabRig) -> np.ndarray:
    q = np.tile(np.concatenate([rig.reference_pose[:3], [0.0, 0.0, 0.0]]), (len(t_s), 1))
    q[:, 4] = np.radians(4.0) * np.sin(2 * np.pi * 1.3 * t_s)
    q[:, 2] += 0.002 * np.sin(2 * np.pi * 0.7 * t_s)
    return q


def _lengths_csv(case: lg.LabCase, path: Path, sd: float, jump: bool = False) -> np.ndarray:
    rig = LabRig.from_toml(case.files["rig"])
    t0 = case.truth["log_start_ns"]
    t_ns = t0 + 5_000_000 + np.arange(2000, dtype=np.int64) * 2_000_000  # 500 Hz, 4 s
    q = _motion((t_ns - t0) * 1e-9, rig)
    L = cable_vectors(rig, q)[2] + np.random.default_rng(2).normal(0, sd, (len(t_ns), rig.m))
    if jump:
        L[1000, 3] += 0.005  # an encoder slipped by 5 mm at one row
    cols = [f"L_{c}_m" for c in rig.cable_names]
    lg.write_table(path, t_ns, cols, L)
    return q


def _import(case: lg.LabCase, out: Path, extra: list[str]) -> subprocess.CompletedProcess:
    f = case.files
    argv = ["import", "--can-log", str(f["can_log"]), "--dbc", str(f["dbc"]), "--rig", str(f["rig"]),
            "--calibration", str(f["calibration"]), "--rate", "1000", "--out", str(out), *extra]  # fmt: skip
    return subprocess.run(cdpr_command() + argv, capture_output=True, text=True, env=clean_env())


def _poses(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pose (k, 6) [position, roll, pitch, yaw], cov (k, 6, 6), status (k,)) of every frame, by
    the mcap library: ``/pose`` (Foxglove's PoseInFrame, frames with a pose) and ``/pose_status``
    (every frame: covariance, status), joined by log time; a frame without a pose is NaN."""
    poses: dict[int, list[float]] = {}
    cov, st, t = [], [], []
    with open(path, "rb") as fh:
        for _, _ch, msg in make_reader(fh).iter_messages(topics=["/pose", "/pose_status"]):
            b = json.loads(msg.data)
            if _ch.topic == "/pose":
                p, o = b["pose"]["position"], b["pose"]["orientation"]
                poses[msg.log_time] = [p["x"], p["y"], p["z"], o["w"], o["x"], o["y"], o["z"]]
            else:
                t.append(msg.log_time)
                cov.append(b["covariance"])
                st.append(b["status"])
    pq = np.array([poses.get(k, [np.nan] * 7) for k in t])
    w, x, y, z = pq[:, 3:].T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1, 1))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    q = np.column_stack([pq[:, :3], roll, pitch, yaw])
    return q, np.array(cov, dtype=np.float64).reshape(-1, 6, 6), np.array(st)


def test_lengths_give_the_pose_with_an_honest_covariance(small: lg.LabCase, tmp_path: Path) -> None:
    sd = 20e-6
    q_true = _lengths_csv(small, tmp_path / "lengths.csv", sd)
    run = tmp_path / "run.mcap"
    r = _import(small, run, ["--cable-lengths", str(tmp_path / "lengths.csv"),
                             "--length-sd-m", repr(sd)])  # fmt: skip
    assert r.returncode == 0, r.stderr
    q, cov_rv, status = _poses(run)
    assert len(q) == len(q_true) and not status.any()
    # the covariance is in [position, rotation vector in {O}]: back to Euler angles, dpsi = H^-1 dth
    Hi = np.linalg.inv(rate_matrix(q[:, 3:]))
    J = np.zeros((len(q), 6, 6))
    J[:, :3, :3] = np.eye(3)
    J[:, 3:, 3:] = Hi
    cov = J @ cov_rv @ np.swapaxes(J, 1, 2)
    e = q - q_true
    chi2 = np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov), e)
    assert 5.3 < chi2.mean() < 6.8  # 6 degrees of freedom
    claimed = np.sqrt(cov[:, 4, 4].mean())
    assert np.std(e[:, 4]) == pytest.approx(claimed, rel=0.1)
    assert 0.03 < np.degrees(claimed) < 0.1  # the flat rig sees pitch poorly through lengths


def test_a_jumped_length_marks_its_frame(small: lg.LabCase, tmp_path: Path) -> None:
    _lengths_csv(small, tmp_path / "lengths.csv", 20e-6, jump=True)
    run = tmp_path / "run.mcap"
    r = _import(small, run, ["--cable-lengths", str(tmp_path / "lengths.csv"),
                             "--length-sd-m", "2e-5"])  # fmt: skip
    assert r.returncode == 0, r.stderr
    _, _, status = _poses(run)
    assert status[1000] == 8 and status.sum() == 8


@pytest.mark.parametrize(
    "case",
    ["both sources", "no sd", "missing column", "negative length"],
)
def test_refusals_are_one_line_and_write_nothing(
    small: lg.LabCase, tmp_path: Path, case: str
) -> None:
    csv = tmp_path / "lengths.csv"
    _lengths_csv(small, csv, 20e-6)
    text = csv.read_text().splitlines()
    extra = ["--cable-lengths", str(csv), "--length-sd-m", "2e-5"]
    if case == "both sources":
        extra += ["--poses", str(small.files["poses"])]
        want = "one pose source"
    elif case == "no sd":
        extra = extra[:2]
        want = "--length-sd-m"
    elif case == "missing column":
        head = text[0].split(",")
        keep = [i for i, c in enumerate(head) if c != "L_back_right_top_m"]
        csv.write_text("\n".join(",".join(r.split(",")[i] for i in keep) for r in text) + "\n")
        want = "L_back_right_top_m"
    else:
        cells = text[3].split(",")
        cells[2] = "-0.5"
        text[3] = ",".join(cells)
        csv.write_text("\n".join(text) + "\n")
        want = "row 4"
    out = tmp_path / "run.mcap"
    r = _import(small, out, extra)
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and want in lines[0], r.stderr
    assert not out.exists() and not list(tmp_path.glob(".run.mcap*"))
