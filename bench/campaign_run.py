"""A long campaign run, written fast through the project's own MCAP writer (``McapRunWriter``).

``write_campaign_run(path, duration_s)`` writes what an hour in the tunnel records: 8 load cells at
1 kHz (``/tensions``: ``T_<cable>_N``, ``status_<cable>``, ``seq``, ``status`` per sample, as the
serial and CAN drivers write them), a 30 Hz camera pose with its covariance (``/pose``), 10 Hz tunnel
conditions (``/tunnel``) and test-point events every ``point_s`` seconds (``/events``: start and end
of each steady span).  The physics is the independent truth of ``tests/truth_rig.py`` (its own
statics, quadprog as the controller, a plausible aerodynamic load): wind-off tare polars, then the
paper's three speeds over -4..+6 deg of pitch, repeated for as long as the run lasts, with linear
ramps between points and load-cell, camera and airspeed noise.

The tensions go in as columns (``McapRunWriter.write_columns``: a 1 kHz stream is stored as column
blocks, ``cdpr.daq.column_blocks``); the pose, tunnel and event readings go through ``write_many``
one by one.  Memory is bounded by the window (60 s of samples).
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from truth_rig import AOA_DEG, RIG_FILE, SPEEDS_MPS, aero_wrench, controller, statics, weight  # noqa: E402

from cdpr.daq.mcap_writer import McapRunWriter  # noqa: E402
from cdpr.daq.source import FieldDescription, Reading, StreamDescription  # noqa: E402

CABLES = (
    "front_left_top",
    "front_left_bottom",
    "front_right_top",
    "front_right_bottom",
    "back_left_top",
    "back_left_bottom",
    "back_right_top",
    "back_right_bottom",
)
RATE_HZ = 1000
CAMERA_HZ = 30
TUNNEL_HZ = 10
T0_NS = 1_700_000_000 * 10**9
SEQ0 = 1_000_000  # the first sample counter


def _plan(n_points: int) -> list[tuple[str, float, float]]:
    """Kind, angle of attack (deg), airspeed (m/s) of each point: a tare polar, the speed sweeps,
    a closing tare, over and over."""
    block = [("tare", a, 0.0) for a in AOA_DEG]
    for v in SPEEDS_MPS:
        block += [("wind_on", a, v) for a in AOA_DEG]
    block += [("tare", 0.0, 0.0)]
    return [block[i % len(block)] for i in range(n_points)]


def write_campaign_run(
    path: str | Path,
    duration_s: float = 3600.0,
    point_s: float = 20.0,
    ramp_s: float = 5.0,
    seed: int = 1,
    window_s: float = 60.0,
) -> dict[str, Any]:
    """Write the run; returns counts per stream and the true points (kind, aoa, speed)."""
    rng = np.random.default_rng(seed)
    text = RIG_FILE.read_text()
    data = tomllib.loads(text)
    anchors = np.array([c["anchor_O_m"] for c in data["cables"]], float)
    attach = np.array([c["attach_P_m"] for c in data["cables"]], float)
    tmin = np.array([c["t_min_N"] for c in data["cables"]], float)
    tmax = np.array([c["t_max_N"] for c in data["cables"]], float)
    names = tuple(c["name"] for c in data["cables"])
    if names != CABLES:
        raise ValueError(f"{RIG_FILE}: cables {names}, expected {CABLES}")
    mass = data["platform"]["mass_kg"] * 1.02
    com = np.array(data["platform"]["com_P_m"], float) + np.array([0.0017, -0.0010, 0.0023])
    home = np.array(data["rig"]["reference_position_O_m"], float)
    rho = 1.19

    n_points = max(2, int(duration_s // point_s))
    plan = _plan(n_points)
    Tp = np.empty((n_points, 8))
    Qp = np.empty((n_points, 6))
    Vp = np.array([p[2] for p in plan])
    cache: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}
    for i, (_kind, aoa_deg, v) in enumerate(plan):
        if (aoa_deg, v) not in cache:
            aoa = np.deg2rad(aoa_deg)
            W = aero_wrench(aoa, v, rho) if v > 0 else np.zeros(6)
            q = np.concatenate([home, [0.0, aoa, 0.0]])
            q[:3] += 2e-5 * W[:3]
            q[4] += 2e-5 * W[4]
            cache[(aoa_deg, v)] = (controller(statics(anchors, attach, q), weight(mass, com, q) + W,
                                              tmin, tmax), q)  # fmt: skip
        Tp[i], Qp[i] = cache[(aoa_deg, v)]

    point_ns = int(point_s * 1e9)
    ramp_ns = int(ramp_s * 1e9)
    total_ns = int(duration_s * 1e9)

    def state(t_rel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tensions, pose, airspeed at times since the start: steady for point_s - ramp_s, then a
        linear ramp to the next point."""
        k = np.minimum(t_rel // point_ns, n_points - 1)
        f = np.clip((t_rel - k * point_ns - (point_ns - ramp_ns)) / ramp_ns, 0.0, 1.0)
        f = np.where(k == n_points - 1, 0.0, f)[:, None]
        k1 = np.minimum(k + 1, n_points - 1)
        return (
            Tp[k] + f * (Tp[k1] - Tp[k]),
            Qp[k] + f * (Qp[k1] - Qp[k]),
            Vp[k] + f[:, 0] * (Vp[k1] - Vp[k]),
        )

    sd_pose = np.array([0.05e-3] * 3 + [np.deg2rad(0.01)] * 3)
    cov = np.diag(sd_pose**2).reshape(-1).tolist()
    path = Path(path)
    w = run_writer(path, RIG_FILE.name, text.encode(), CABLES)
    counts = {"tensions": 0, "pose": 0, "tunnel": 0, "events": 0}
    win_ns = int(window_s * 1e9)
    dt = 10**9 // RATE_HZ
    dt_tun = 10**9 // TUNNEL_HZ
    try:
        for a in range(0, total_ns, win_ns):
            b = min(a + win_ns, total_ns)
            # tensions
            t_rel = np.arange(-(-a // dt) * dt, b, dt, dtype=np.int64)
            T, _, _ = state(t_rel)
            T = T + rng.normal(0.0, 0.05, T.shape)
            i0 = counts["tensions"]
            seq = SEQ0 + i0 + np.arange(len(t_rel))
            t_abs = T0_NS + t_rel
            cols = {f"T_{c}_N": T[:, k] for k, c in enumerate(CABLES)}
            cols.update({f"status_{c}": np.zeros(len(t_abs), np.int64) for c in CABLES})
            cols["seq"] = seq
            w.write_columns("tensions", t_abs, cols, 0)
            counts["tensions"] += len(t_rel)
            readings: list[Reading] = []
            # camera
            k_cam = np.arange(-(-a * CAMERA_HZ // 10**9), -(-b * CAMERA_HZ // 10**9))
            tc = k_cam * 10**9 // CAMERA_HZ  # frame k at floor(k / 30 s)
            _, Q, _ = state(tc)
            Q = Q + rng.normal(0.0, 1.0, Q.shape) * sd_pose
            xyzw = _quat_xyzw(Q[:, 3:])
            for t, q, qq in zip(tc.tolist(), Q[:, :3].tolist(), xyzw.tolist(), strict=True):
                readings.append(Reading("pose", T0_NS + t, {"position_O_m": q,
                                                            "quaternion_xyzw": qq,
                                                            "covariance": cov}))  # fmt: skip
            # tunnel
            tt = np.arange(-(-a // dt_tun) * dt_tun, b, dt_tun, dtype=np.int64)
            _, _, V = state(tt)
            V = V + rng.normal(0.0, 0.02, V.shape) * (V > 0)
            for t, v in zip(tt.tolist(), V.tolist(), strict=True):
                readings.append(
                    Reading("tunnel", T0_NS + t, {"airspeed_mps": v, "density_kgpm3": rho})
                )
            # events: start and end of each steady span in this window
            for k in range(n_points):
                kind, aoa_deg, v = plan[k]
                t_start = k * point_ns + 200_000_000
                t_end = (k + 1) * point_ns - ramp_ns - 200_000_000
                base = {"name": "test_point", "point": f"P{k:03d}", "kind": kind,
                        "target_aoa_deg": aoa_deg, "target_sideslip_deg": 0.0,
                        "target_airspeed_mps": v}  # fmt: skip
                for t_ev, phase in ((t_start, "start"), (t_end, "end")):
                    if a <= t_ev < b:
                        readings.append(Reading("events", T0_NS + t_ev, {**base, "phase": phase}))
            readings.sort(key=lambda r: r.t_ns)
            w.write_many(readings)
            for r in readings:
                counts[r.stream] += 1
    finally:
        w.finish()
    return {"counts": counts, "plan": plan, "path": str(path)}


def run_writer(
    path: Path, rig_name: str, rig_bytes: bytes, cables: Any, rate_hz: float = RATE_HZ
) -> McapRunWriter:
    """The project's writer with the rig attached and the streams of a bench run: ``tensions``
    (``T_<cable>_N``, ``status_<cable>``, ``seq``: column blocks), ``tunnel`` (airspeed,
    density), ``pose``, ``events``."""
    w = McapRunWriter(path, chunk_size=1024 * 1024, background_compression=True)
    w.add_attachment(f"rig/{rig_name}", rig_bytes)
    fields = {f"T_{c}_N": FieldDescription("N") for c in cables}
    fields.update({f"status_{c}": FieldDescription("", "int64") for c in cables})
    fields["seq"] = FieldDescription("", "int64")
    w.add_stream("tensions", StreamDescription(fields, rate_hz, "load-cell tensions"))
    w.add_stream(
        "tunnel",
        StreamDescription(
            {"airspeed_mps": FieldDescription("m/s"), "density_kgpm3": FieldDescription("kg/m^3")},
            TUNNEL_HZ,
        ),
    )
    w.add_stream("pose")
    w.add_stream("events")
    return w


def _quat_xyzw(euler: np.ndarray) -> np.ndarray:
    """Quaternions (x, y, z, w) of Z-Y-X Euler angles (roll, pitch, yaw) (n, 3), written out."""
    r, p, y = euler[:, 0] / 2, euler[:, 1] / 2, euler[:, 2] / 2
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy
    yq = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    return np.stack([x, yq, z, w], axis=1)


if __name__ == "__main__":
    import time

    t0 = time.perf_counter()
    out = write_campaign_run(sys.argv[1], float(sys.argv[2]) if len(sys.argv) > 2 else 3600.0)
    print(out["counts"], f"{time.perf_counter() - t0:.1f} s")
