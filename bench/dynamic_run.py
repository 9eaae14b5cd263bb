"""An hour of forced-oscillation points, written fast through the project's own MCAP writer.

``write_dynamic_run(path, duration_s)`` writes what an hour of dynamic tests records: 8 load cells
at 1 kHz (``/tensions`` with ``seq`` and the per-cable status, column blocks), the camera's pose at
200 Hz (``camera_hz``) with its covariance and a 3 ms clock offset (``/pose``, one message a frame
as the pose camera writes them), 10 Hz tunnel conditions and the test-point events with their motion fields.
The physics is the independent lab generator's (``tests/_lab_physics.py``: Newton-Euler with the
centre of mass off P, the controller's tension distribution; ``tests/_lab_aero.py``: the aero
model with its dynamic derivatives), on the flat optimum rig.  A block of points repeats for as
long as the run lasts: a wind-off zero, then per frequency (2 Hz, 1 Hz) the wind-off oscillation
(the inertia tare) and the wind-on ones at 25.51 and 41.42 m/s, 5 deg of pitch, 60 cycles after 2
settling cycles and before 1 ramp-down cycle.  Each distinct point's physics is computed once and
repeated with fresh noise (load cells 0.05 N, camera 0.05 mm / 0.01 deg).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from _lab_aero import AeroModel, Geometry, aero_loads  # noqa: E402
from _lab_physics import (  # noqa: E402
    LabRig,
    Motion,
    body_wrench,
    distribute,
    gravity_wrench,
    structure_matrix,
)

from cdpr.daq.source import Reading  # noqa: E402

sys.path.insert(0, str(ROOT / "bench"))
from campaign_run import _quat_xyzw, run_writer  # noqa: E402

RIG_FILE = ROOT / "data_samples" / "flat_optimum.toml"
RATE_HZ = 1000
CAMERA_HZ = 200
TUNNEL_HZ = 10
T0_NS = 1_700_000_000 * 10**9
OFFSET_NS = 3_000_000
GAP_S = 1.0
RHO = 1.17
AMPLITUDE = float(np.deg2rad(5.0))


def _block() -> list[dict[str, Any]]:
    """The points of one block: label stem, kind, frequency, airspeed, duration (s)."""
    out: list[dict[str, Any]] = [{"stem": "zero", "kind": "zero", "f": 0.0, "v": 0.0, "dur": 2.0}]
    for f in (2.0, 1.0):
        dur = (2 + 60 + 1) / f
        out.append(
            {"stem": f"tare-f{f:g}", "kind": "oscillation_tare", "f": f, "v": 0.0, "dur": dur}
        )
        for v in (25.51, 41.42):
            out.append({"stem": f"osc-f{f:g}-v{v:g}", "kind": "oscillation", "f": f, "v": v,
                        "dur": dur, "tare": f"tare-f{f:g}"})  # fmt: skip
    return out


def _physics(rig: LabRig, p: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Tensions (n, m) and true poses (n, 6) over the point, from its start at 1 kHz."""
    n = int(round(p["dur"] * RATE_HZ))
    t = np.arange(n) / RATE_HZ
    q0 = np.concatenate([rig.reference_pose[:3], [0.0, 0.0, 0.0]])
    if p["kind"] == "zero":
        q, qd, qdd = np.tile(q0, (n, 1)), np.zeros((n, 6)), np.zeros((n, 6))
    else:
        mo = Motion("pitch", AMPLITUDE, p["f"], 60, 2, tuple(q0), 0.0)
        q, qd, qdd = mo.states(t)
    ld = aero_loads(AeroModel(), Geometry(), q, qd, qdd, np.full(n, p["v"]), RHO)
    w = body_wrench(rig, q, qd, qdd) - gravity_wrench(rig, q) - ld.wrench_P_O
    T, _ = distribute(structure_matrix(rig, q), w, rig.t_min_N, rig.t_max_N)
    return T, q


def _pose_at(rig: LabRig, p: dict[str, Any], t_s: np.ndarray) -> np.ndarray:
    q0 = np.concatenate([rig.reference_pose[:3], [0.0, 0.0, 0.0]])
    if p["kind"] == "zero":
        return np.tile(q0, (len(t_s), 1))
    return Motion("pitch", AMPLITUDE, p["f"], 60, 2, tuple(q0), 0.0).states(t_s)[0]


def write_dynamic_run(
    path: str | Path, duration_s: float = 3600.0, seed: int = 1, camera_hz: float = CAMERA_HZ
) -> dict[str, Any]:
    """Write the run (the camera at ``camera_hz``); returns counts per stream and the points
    (label, kind, start, end)."""
    rng = np.random.default_rng(seed)
    nominal = LabRig.from_toml(RIG_FILE)
    true = nominal.with_body(
        nominal.mass_kg * 1.02, nominal.com_P_m + np.array([0.002, -0.001, 0.003]),
        nominal.inertia_P_kgm2 * 1.03,
    )  # fmt: skip
    block = _block()
    phys = {p["stem"]: _physics(true, p) for p in block}
    T_gap = phys["zero"][0][0]
    cables = nominal.cable_names
    sd_pose = np.array([0.05e-3] * 3 + [np.deg2rad(0.01)] * 3)
    cov = np.diag(sd_pose**2).reshape(-1).tolist()
    w = run_writer(Path(path), RIG_FILE.name, RIG_FILE.read_bytes(), cables, RATE_HZ)
    counts = {"tensions": 0, "pose": 0, "tunnel": 0, "events": 0}
    points: list[tuple[str, str, int, int]] = []
    t = 0.0
    k = 0
    try:
        while t < duration_s:  # blocks and points, not samples
            for p in block:
                if t + GAP_S + p["dur"] > duration_s:
                    t = duration_s
                    break
                gap_n = int(GAP_S * RATE_HZ)
                T, _ = phys[p["stem"]]
                Tall = np.concatenate([np.tile(T_gap, (gap_n, 1)), T])
                n = len(Tall)
                t_rel = (round(t * RATE_HZ) + np.arange(n)) * (10**9 // RATE_HZ)
                Tn = Tall + rng.normal(0.0, 0.05, Tall.shape)
                cols = {f"T_{c}_N": Tn[:, j] for j, c in enumerate(cables)}
                cols.update({f"status_{c}": np.zeros(n, np.int64) for c in cables})
                cols["seq"] = counts["tensions"] + np.arange(n, dtype=np.int64)
                w.write_columns("tensions", T0_NS + t_rel, cols, 0)
                counts["tensions"] += n
                start_ns = T0_NS + int(t_rel[gap_n])
                end_s = p["dur"] if p["kind"] == "zero" else (2 + 60) / p["f"]
                end_ns = start_ns + int(round(end_s * 1e9))
                label = f"{p['stem']}-{k:02d}"
                readings: list[Reading] = []
                # camera: frames on its clock, OFFSET_NS ahead; the pose at t_cam - offset
                a_ns, b_ns = T0_NS + int(t_rel[0]), T0_NS + int(t_rel[-1])
                tc = np.arange(a_ns + OFFSET_NS, b_ns + OFFSET_NS, int(round(1e9 / camera_hz)))
                ts = (tc - OFFSET_NS - start_ns) * 1e-9
                Q = _pose_at(nominal, p, np.clip(ts, 0.0, None))
                Q = Q + rng.normal(0.0, 1.0, Q.shape) * sd_pose
                xyzw = _quat_xyzw(Q[:, 3:])
                for tt, qq, qx in zip(tc.tolist(), Q[:, :3].tolist(), xyzw.tolist(), strict=True):
                    readings.append(Reading("pose", tt, {"position_O_m": qq,
                                                         "quaternion_xyzw": qx,
                                                         "covariance": cov}))  # fmt: skip
                tt_tun = np.arange(a_ns, b_ns, 10**9 // TUNNEL_HZ)
                V = np.where(tt_tun >= start_ns, p["v"], 0.0)
                V = V + rng.normal(0, 0.02, len(tt_tun)) * (p["v"] > 0)
                for tt, v in zip(tt_tun.tolist(), V.tolist(), strict=True):
                    readings.append(
                        Reading("tunnel", tt, {"airspeed_mps": v, "density_kgpm3": RHO})
                    )
                base: dict[str, Any] = {
                    "name": "test_point", "point": label, "kind": p["kind"],
                    "target_aoa_deg": 0.0, "target_sideslip_deg": 0.0, "target_airspeed_mps": p["v"],
                }  # fmt: skip
                if p["kind"] != "zero":
                    base.update(
                        motion_axis="pitch", motion_amplitude=AMPLITUDE, motion_frequency_Hz=p["f"],
                        motion_cycles=60, motion_settling_cycles=2,
                        inertia_tare=f"{p['tare']}-{k:02d}" if p["kind"] == "oscillation" else "",
                    )  # fmt: skip
                for t_ev, phase in ((start_ns, "start"), (end_ns, "end")):
                    readings.append(Reading("events", t_ev, {**base, "phase": phase}))
                readings.sort(key=lambda r: r.t_ns)
                w.write_many(readings)
                for r in readings:
                    counts[r.stream] += 1
                points.append((label, p["kind"], start_ns, end_ns))
                t += GAP_S + p["dur"]
            k += 1
    finally:
        w.finish()
    return {"counts": counts, "points": points, "path": str(path)}


if __name__ == "__main__":
    import time

    t0 = time.perf_counter()
    out = write_dynamic_run(sys.argv[1], float(sys.argv[2]) if len(sys.argv) > 2 else 3600.0)
    print(out["counts"], len(out["points"]), "points", f"{time.perf_counter() - t0:.1f} s")
