"""An independent truth for the reduction: its own few-line statics and quadprog as the controller.

Nothing here imports cdpr: the rotation, the structure matrix, the gravity load and the tension
distribution are written out again (from the paper's definitions), so an error in cdpr's versions
shows up as a disagreement instead of cancelling out.

:func:`alpha_sweep` writes the sample streams of an alpha sweep on the flat prototype rig (the
geometry numbers are read from the rig file as plain numbers): a wind-off tare polar (or only level
tares), then the paper's three speeds over -4..+6 deg of pitch, with ramps between points, the
model's true mass and centre of mass off the rig file's, load-cell and camera noise.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import quadprog

RIG_FILE = Path(__file__).resolve().parents[1] / "data_samples" / "flat_experiment2.toml"
G0 = 9.80665
SPEEDS_MPS = (17.27, 25.51, 41.42)
AOA_DEG = (-4.0, -2.0, 0.0, 2.0, 4.0, 6.0)


def exact_loadcell_calibration(cables: list[str]) -> tuple[str, bytes]:
    """The attachment (name, TOML bytes) of the load-cell calibration this world's tensions were
    made with: exact (σ 0), as the recorder attaches the one its config names."""
    names = ", ".join(f'"{c}"' for c in cables)
    text = (
        "[calibration]\n"
        'kind = "loadcells"\nid = "exact"\n'
        f"cables = [{names}]\n"
        "offset_counts = 0.0\ngain_N_per_count = 1.0\n"
        "sd_offset_counts = 0.0\nsd_gain_N_per_count = 0.0\ncorr_offset_gain = 0.0\n"
        "n_points = 11\n"
    )
    return "calibration/loadcells_exact.toml", text.encode()


def rot(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (
        np.cos(roll),
        np.sin(roll),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(yaw),
        np.sin(yaw),
    )
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def statics(anchors: np.ndarray, attach: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """6 x m matrix mapping tensions to the cables' wrench on the platform at P ({O} axes)."""
    R = rot(*pose[3:])
    cols = []
    for b, pp in zip(anchors, attach, strict=True):
        r = R @ pp
        u = b - pose[:3] - r
        u = u / np.linalg.norm(u)
        cols.append(np.concatenate([u, np.cross(r, u)]))
    return np.array(cols).T


def weight(mass: float, com: np.ndarray, pose: np.ndarray) -> np.ndarray:
    f = np.array([0.0, 0.0, -mass * G0])
    return np.concatenate([f, np.cross(rot(*pose[3:]) @ com, f)])


def controller(A: np.ndarray, load: np.ndarray, tmin: np.ndarray, tmax: np.ndarray) -> np.ndarray:
    """Tensions closest to mid-range with ``A T + load = 0`` and the limits (quadprog)."""
    m = A.shape[1]
    mid = 0.5 * (tmin + tmax)
    C = np.hstack([A.T, np.eye(m), -np.eye(m)])
    b = np.concatenate([-load, tmin, -tmax])
    return np.asarray(quadprog.solve_qp(np.eye(m), mid, C, b, meq=6)[0])


def aero_wrench(aoa_rad: float, speed: float, rho: float) -> np.ndarray:
    """A plausible aerodynamic load at P in {O} axes (drag +x, lift +z)."""
    qs = 0.5 * rho * speed**2 * 0.2441 * 0.0815
    cl = 0.1 + 4.5 * aoa_rad
    return qs * np.array(
        [0.03 + 0.05 * cl**2, 0.004, cl, 0.002, -0.0815 * (0.05 + 0.5 * aoa_rad), 0.001]
    )


def yielded_pose(q: np.ndarray, load: np.ndarray, mass: float, com: np.ndarray) -> np.ndarray:
    """The pose (6,) the platform takes when ``load`` (6,) at P in {O} is added at pose ``q``
    with the winches holding the cable lengths: ``x = K^-1 load``, K the cables' stiffness at q
    and its wind-off tensions (tests/_lab_physics.py's own, by central differences), the rotation
    part turned into Euler angles.  The body ``mass``, ``com`` is this world's."""
    from dataclasses import replace

    from _lab_physics import LabRig, rate_matrix, stiffness

    lab = replace(LabRig.from_toml(RIG_FILE), mass_kg=mass, com_P_m=np.asarray(com, float))
    T0 = controller(
        statics(lab.anchors_O_m, lab.attach_P_m, q), weight(mass, com, q), lab.t_min_N, lab.t_max_N
    )
    K, _ = stiffness(lab, q, T0)
    x = np.linalg.solve(K, load)
    return q + np.concatenate([x[:3], np.linalg.solve(rate_matrix(q[3:]), x[3:])])


@dataclass
class Sweep:
    """Sample streams and the truth of one generated run."""

    t_ns: np.ndarray  # (n,) tension sample times
    tensions_N: np.ndarray  # (n, m)
    airspeed_mps: np.ndarray  # (n,)
    density_kgpm3: np.ndarray  # (n,)
    pose_t_ns: np.ndarray  # (n,) camera frame times (same clock)
    poses: np.ndarray  # (n, 6) measured
    pose_cov: np.ndarray  # (n, 6, 6) what the camera reports
    kind: list[str]  # per point
    start_ns: np.ndarray  # (s,) steady span of each point (truth)
    stop_ns: np.ndarray
    true_wrench: np.ndarray  # (s, 6) at P in {O}
    true_pose: np.ndarray  # (s, 6)
    speed_mps: np.ndarray  # (s,)
    rig_text: str


def alpha_sweep(
    seed: int,
    level_tares_only: bool = False,
    rate_hz: float = 100.0,
    point_s: float = 3.0,
    ramp_s: float = 1.0,
    tension_sd_N: float = 0.05,
    pos_sd_m: float = 0.05e-3,
    ang_sd_rad: float = float(np.deg2rad(0.01)),
    mass_factor: float = 1.02,
    com_offset_m: tuple[float, float, float] = (0.0017, -0.0010, 0.0023),  # |.| = 3 mm
) -> Sweep:
    rng = np.random.default_rng(seed)
    text = RIG_FILE.read_text()
    data = tomllib.loads(text)
    anchors = np.array([c["anchor_O_m"] for c in data["cables"]], float)
    attach = np.array([c["attach_P_m"] for c in data["cables"]], float)
    tmin = np.array([c["t_min_N"] for c in data["cables"]], float)
    tmax = np.array([c["t_max_N"] for c in data["cables"]], float)
    mass = data["platform"]["mass_kg"] * mass_factor
    com = np.array(data["platform"]["com_P_m"], float) + np.array(com_offset_m)
    home = np.array(data["rig"]["reference_position_O_m"], float)
    rho = 1.19

    plan: list[tuple[str, float, float]] = []  # kind, aoa, speed
    tare_aoas = (0.0,) if level_tares_only else AOA_DEG
    plan += [("tare", a, 0.0) for a in tare_aoas]
    for v in SPEEDS_MPS:
        plan += [("wind_on", a, v) for a in AOA_DEG]
    plan += [("tare", 0.0, 0.0)]  # closing level tare

    dt = int(round(1e9 / rate_hz))
    n_pt, n_ramp = int(point_s * rate_hz), int(ramp_s * rate_hz)
    Ts, Vs, Qs, starts, stops, W_true, Q_true = [], [], [], [], [], [], []
    prev_T = prev_V = prev_q = None
    k = 0
    for _kind, aoa_deg, v in plan:
        aoa = np.deg2rad(aoa_deg)
        W = aero_wrench(aoa, v, rho) if v > 0 else np.zeros(6)
        # the nose is -x_P: a positive pitch about y_O turns it to (-cos, 0, +sin), nose up
        q = np.concatenate([home, [0.0, aoa, 0.0]])
        # the platform yields under the load as its cables stretch (not exactly the tare's pose)
        if v > 0:
            q = yielded_pose(q, W, mass, com)
        A = statics(anchors, attach, q)
        T = controller(A, weight(mass, com, q) + W, tmin, tmax)
        if prev_T is not None:
            f = np.linspace(0, 1, n_ramp, endpoint=False)[:, None]
            Ts.append(prev_T + f * (T - prev_T))
            Vs.append(prev_V + f[:, 0] * (v - prev_V))
            Qs.append(prev_q + f * (q - prev_q))
            k += n_ramp
        starts.append(k * dt)
        stops.append((k + n_pt - 1) * dt)
        Ts.append(np.tile(T, (n_pt, 1)))
        Vs.append(np.full(n_pt, v))
        Qs.append(np.tile(q, (n_pt, 1)))
        k += n_pt
        W_true.append(W)
        Q_true.append(q)
        prev_T, prev_V, prev_q = T, v, q
    T_all = np.concatenate(Ts)
    V_all = np.concatenate(Vs)
    Q_all = np.concatenate(Qs)
    n = len(T_all)
    t = np.arange(n, dtype=np.int64) * dt + 1_000_000_000
    T_meas = T_all + rng.normal(0, tension_sd_N, T_all.shape)
    sd = np.array([pos_sd_m] * 3 + [ang_sd_rad] * 3)
    Q_meas = Q_all + rng.normal(0, 1, Q_all.shape) * sd
    V_meas = V_all + rng.normal(0, 0.02, n) * (V_all > 0)
    return Sweep(
        t_ns=t,
        tensions_N=T_meas,
        airspeed_mps=V_meas,
        density_kgpm3=np.full(n, rho),
        pose_t_ns=t.copy(),
        poses=Q_meas,
        pose_cov=np.broadcast_to(np.diag(sd**2), (n, 6, 6)).copy(),
        kind=[p[0] for p in plan],
        start_ns=np.array(starts, np.int64) + 1_000_000_000,
        stop_ns=np.array(stops, np.int64) + 1_000_000_000,
        true_wrench=np.array(W_true),
        true_pose=np.array(Q_true),
        speed_mps=np.array([p[2] for p in plan]),
        rig_text=text,
    )
