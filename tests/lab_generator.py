"""An independent lab: the files a wind-tunnel lab hands to ``cdpr import``, with their truth.

Written separately from the product (issues 21 and 22): nothing here imports cdpr.  The statics,
the controller's tension distribution, the stiffness and modes and the Newton-Euler dynamics are
in ``_lab_physics.py``, the aerodynamic model in ``_lab_aero.py``, the noise processes in
``_lab_noise.py``; this module plans a campaign, runs the physics over every load-cell sample and
camera frame, and writes the lab's files into one folder:

==================  ===========================================================================
``can.log``         candump log of the eight load cells at 1 kHz, encoded per
                    ``data_samples/loadcell.dbc`` (TPDO1..4 = 0x181..0x481, two signed 24-bit
                    channels, a status byte and the shared counter per frame; the sample's four
                    frames 130 us apart, the first at the sample time)
``loadcells.toml``  the load-cell calibration the lab fitted (``counts = offset + T / gain``, the
                    file's ``T = (counts - offset_counts) * gain_N_per_count``) with its fit
                    statistics, or the exact values (``calibration="exact"``)
``poses.csv``       the camera: ``t_ns`` (camera clock), ``x_m, y_m, z_m, roll_rad, pitch_rad,
                    yaw_rad``, and the frame's covariance ``cov_00 .. cov_55`` (row-major 6 x 6
                    in the parametrisation ``Camera.cov_params``: ``"euler"`` = (x, y, z, roll,
                    pitch, yaw); ``"rotvec_O"`` = (x, y, z, rotation vector in {O}))
``tunnel.csv``      ``t_ns, airspeed_mps, static_pressure_Pa, temperature_K, relative_humidity``
``events.csv``      ``t_ns, point, phase, kind, target_aoa_deg, target_sideslip_deg,
                    target_airspeed_mps, repeat_of`` (+ ``motion_*`` and ``inertia_tare`` with
                    oscillation points, helpers/dynamic_spec.md)
``matrix.toml``     the test matrix for ``cdpr analyze --matrix`` (one ``[[points]]`` per point)
``<rig>.toml``      the rig file given to ``cdpr import`` (a copy of data_samples')
``truth.json``      everything the generator used (below); ``truth_points.csv`` one row a point
==================  ===========================================================================

Truth conventions (truth.json, truth_points.csv):

- time: load-cell clock = the run's time (``t_ns``, integer ns since the Unix epoch); a camera frame
  stamped ``t_cam`` was taken at ``t_cam - camera_clock_offset_ns``;
- pose: P in {O} (m) and Z-Y-X Euler angles ``(roll, pitch, yaw)`` (rad); {O} x downstream, z up;
- a point's truth is the **ensemble mean**: the model's noise-free aerodynamic load averaged over
  the point's window (start to end event, both included), not the window mean of one noise draw;
- ``wrench_P_O``: the aerodynamic load **on the model** ``[Fx, Fy, Fz, Mx, My, Mz]`` at P in {O}
  axes (N, N m); ``wrench_mrp_O``: forces in {O}, moments about the MRP in {O} axes (the
  ``fx_N .. mz_Nm`` of cdpr's points.csv); body loads in AIAA body axes (x nose, y right wing,
  z down; nose upstream: ``R_P_B = diag(-1, 1, -1)``); coefficients ``CD, CY, CL, Cl, Cm, Cn`` on
  ``q S`` (b for Cl and Cn, c for Cm) with the true free-stream q;
- oscillation points: the model's coefficient over the analysed window fitted by
  ``C0 + sum_n (a_n sin(n w tau) + b_n cos(n w tau))``, ``tau = t - t0`` (t0 the start event),
  the motion ``q = q_mean + e A sin(w tau)`` along the pose coordinate of its axis; **in-phase**
  ``a_1 / A`` (per rad or per m) and **out-of-phase** ``b_1 / (A k)`` with ``k = w c/(2V)`` (pitch,
  heave, surge) or ``w b/(2V)`` (yaw, roll, sway).  ``linear`` gives the same from the model's
  derivatives by hand (pitch: ``Cma``, ``Cmq + Cmadot``; yaw about the vertical at mean aoa a:
  sideslip = yaw, body rates p = sin(a) yaw_dot, r = -cos(a) yaw_dot; roll: body p = -roll_dot).

Noise models of the load cells (``LoadCellNoise.case``), each on top of the cells' linear zero drift:
``white`` (0.05 N per sample); ``ar1`` (AR(1) per cell, tau drawn in 10-50 ms, plus a 0.01 N white
floor); ``common`` (0.05 N white plus a fluctuating aerodynamic load: band-limited (vector AR(1))
coefficients scaled by q, through the controller into all eight tensions); ``mode`` (0.05 N
white plus a narrow-band oscillation at the rig's lowest mode, computed here, in its mode shape:
the tensions by the cables' elastic stretch, the camera sees the motion).

API: :func:`steady_plan`, :func:`oscillation_plan` (lists of :class:`PlanPoint`),
:func:`generate` (writes a case, returns a :class:`LabCase`), :func:`steady_case` and
:func:`oscillation_case` (plan + generate), :func:`lab_argv` (the ``cdpr import`` and
``cdpr analyze`` arguments of a case), :func:`read_candump` (an independent decoder of the log).
Run ``python tests/lab_generator.py --help`` to write a case from the command line.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from _lab_aero import (
    COEFFICIENTS,
    AeroModel,
    Geometry,
    aero_loads,
    moist_air_density,
    wrench_from_coefficients,
)
from _lab_noise import ar1, narrowband, vector_ar1, white
from _lab_physics import (
    InfeasibleError,
    LabRig,
    Motion,
    body_wrench,
    cable_vectors,
    distribute,
    euler_of,
    gravity_wrench,
    modes,
    rate_matrix,
    rot,
    rotvec_exp,
    stiffness,
    structure_matrix,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data_samples"
RIGS = {"flat": DATA / "flat_optimum.toml", "cubic": DATA / "cubic_optimum.toml"}
DBC = DATA / "loadcell.dbc"
FRAME_IDS = (0x181, 0x281, 0x381, 0x481)
FRAME_SPACING_NS = 130_000
T_LOG0_NS = 1_700_000_000 * 10**9
SPEEDS_MPS = (17.27, 25.51, 41.42)
AOA_DEG = (-4.0, -2.0, 0.0, 2.0, 4.0, 6.0)
ANGULAR = ("roll", "pitch", "yaw")
STEADY_KINDS = ("wind_on", "tare", "zero", "windage")
OSC_KINDS = ("oscillation", "oscillation_tare")
CONVENTIONS = {
    "time": "load-cell clock = run time (t_ns, ns since the Unix epoch); a camera frame stamped "
    "t_cam was taken at t_cam - camera_clock_offset_ns",
    "wrench": "[Fx, Fy, Fz, Mx, My, Mz] aerodynamic load on the model; *_P_*: at P in {O} axes; "
    "fx_N..mz_Nm: forces in {O}, moments about the MRP in {O} axes (as cdpr's points.csv)",
    "body_axes": "AIAA x nose, y right wing, z down; nose upstream, R_P_B = diag(-1, 1, -1)",
    "coefficients": "CD, CY, CL (q S), Cl, Cn (q S b), Cm (q S c), moments about the MRP, the "
    "true free-stream q",
    "truth": "ensemble mean: the noise-free model load averaged over the point's window "
    "(start..end events)",
    "oscillation": "in-phase a1/A, out-of-phase b1/(A k) of C0 + a1 sin(w tau) + b1 cos(w tau) "
    "+ ..., tau = t - t0, motion q = q_mean + e A sin(w tau) along the pose coordinate of the "
    "axis",
}


# --------------------------------------------------------------------------------------------
# settings


@dataclass(frozen=True)
class LoadCellNoise:
    """The load cells' noise (N) and drift; ``case`` picks the extra model (module docstring)."""

    case: str = "white"
    white_sd_N: float = 0.05
    ar1_sd_N: float = 0.05
    ar1_tau_s: tuple[float, float] = (0.010, 0.050)
    ar1_floor_sd_N: float = 0.01
    common_sd: tuple[float, ...] = (0.002, 0.002, 0.01, 0.0005, 0.002, 0.0005)
    """sd of the fluctuating coefficients CD, CY, CL, Cl, Cm, Cn"""
    common_corr: tuple[tuple[int, int, float], ...] = (
        (2, 4, -0.8),
        (0, 2, 0.5),
        (1, 5, 0.6),
        (1, 3, 0.4),
        (3, 5, 0.3),
    )
    common_tau_s: float = 0.03
    mode_rms_N: float = 0.3
    """rms of the largest cable's tension oscillation at the highest q (20 % of it wind off)"""
    mode_Q: float = 30.0
    drift_sd_N_per_s: float = 0.002
    """sd of each cell's linear drift rate"""

    def __post_init__(self) -> None:
        if self.case not in ("white", "ar1", "common", "mode"):
            raise ValueError(f"noise case: expected white, ar1, common or mode, got {self.case!r}")

    def white_sd(self) -> float:
        return self.ar1_floor_sd_N if self.case == "ar1" else self.white_sd_N

    def common_cov(self) -> np.ndarray:
        sd = np.asarray(self.common_sd, float)
        C = np.eye(6)
        for i, j, r in self.common_corr:
            C[i, j] = C[j, i] = r
        return C * np.outer(sd, sd)


@dataclass(frozen=True)
class Camera:
    """The camera: rate, per-frame noise (position m, rotation vector rad, scaled per frame by a
    factor drawn in [1 - spread, 1 + spread] that its covariance reports), clock offset."""

    rate_hz: float = 100.0
    pos_sd_m: float = 0.05e-3
    ang_sd_rad: float = float(np.deg2rad(0.01))
    sd_spread: float = 0.2
    clock_offset_ns: int = 3_000_000
    cov_params: str = "euler"

    def __post_init__(self) -> None:
        if self.cov_params not in ("euler", "rotvec_O"):
            raise ValueError(f"cov_params: expected euler or rotvec_O, got {self.cov_params!r}")


@dataclass(frozen=True)
class Encoders:
    """The controller's cable-length log (motor encoders): its rate, each length's noise (m) and
    its clock's offset ahead of the load cells' (a row stamped ``t`` holds the lengths at
    ``t - clock_offset_ns``).  The lengths are the true pose's (anchor to attachment point)."""

    rate_hz: float = 500.0
    sd_m: float = 20e-6
    clock_offset_ns: int = 0


@dataclass(frozen=True)
class Tunnel:
    """The tunnel's true air and its instruments (noise per row, airspeed bias)."""

    rate_hz: float = 10.0
    static_pressure_Pa: float = 98_500.0
    temperature_K: float = 293.15
    temperature_rise_K_per_h: float = 2.0
    relative_humidity: float = 0.45
    airspeed_sd_mps: float = 0.02
    airspeed_bias_rel: float = 0.0
    pressure_sd_Pa: float = 2.0
    temperature_sd_K: float = 0.05
    humidity_sd: float = 0.005


@dataclass(frozen=True)
class Body:
    """The model's true mass properties relative to the rig file's: mass factor, centre-of-mass
    offset (m, in {P}), inertia factor and products of inertia added (kg m^2)."""

    mass_factor: float = 1.02
    com_offset_P_m: tuple[float, float, float] = (0.002, -0.001, 0.003)
    inertia_factor: float = 1.03
    products_kgm2: tuple[float, float, float] = (2e-5, -1e-5, 3e-5)  # Ixy, Ixz, Iyz

    def apply(self, rig: LabRig) -> LabRig:
        I = rig.inertia_P_kgm2 * self.inertia_factor
        I = I.copy()
        xy, xz, yz = self.products_kgm2
        I[0, 1] += xy
        I[1, 0] += xy
        I[0, 2] += xz
        I[2, 0] += xz
        I[1, 2] += yz
        I[2, 1] += yz
        return rig.with_body(
            rig.mass_kg * self.mass_factor, rig.com_P_m + np.asarray(self.com_offset_P_m), I
        )


@dataclass(frozen=True)
class PlanPoint:
    """One test point of the plan (SI amplitude: rad for angles, m for translations)."""

    label: str
    kind: str
    aoa_deg: float = 0.0
    sideslip_deg: float = 0.0
    airspeed_mps: float = 0.0
    duration_s: float = 3.0
    repeat_of: str = ""
    axis: str = ""
    amplitude: float = 0.0
    frequency_Hz: float = 0.0
    cycles: int = 0
    settling_cycles: int = 2
    inertia_tare: str = ""

    @property
    def oscillating(self) -> bool:
        return self.kind in OSC_KINDS


# --------------------------------------------------------------------------------------------
# plans


def _num(x: float) -> str:
    return f"{x:g}"


def steady_plan(
    n_wind_on: int = 100,
    aoa_deg: tuple[float, ...] = AOA_DEG,
    sideslip_deg: tuple[float, ...] = (0.0,),
    speeds_mps: tuple[float, ...] = SPEEDS_MPS,
    duration_s: float = 3.0,
) -> list[PlanPoint]:
    """Blocks as a campaign runs them, until ``n_wind_on`` wind-on points: a level wind-off zero,
    the tare polar (one wind-off point per attitude), the wind-on sweep (speed outermost); a
    closing zero.  Blocks after the first repeat the first's points (``repeat_of``)."""
    att = [(a, b) for b in sideslip_deg for a in aoa_deg]
    per = len(att) * len(speeds_mps)
    blocks = max(1, math.ceil(n_wind_on / per))
    plan: list[PlanPoint] = []
    for k in range(1, blocks + 1):
        plan.append(PlanPoint(f"zero-{k}", "zero", duration_s=duration_s))
        plan += [
            PlanPoint(f"tare{k}-a{_num(a)}-b{_num(b)}", "tare", a, b, duration_s=duration_s)
            for a, b in att
        ]
        for v in speeds_mps:
            for a, b in att:
                tail = f"a{_num(a)}-b{_num(b)}-v{_num(v)}"
                plan.append(
                    PlanPoint(
                        f"on{k}-{tail}",
                        "wind_on",
                        a,
                        b,
                        v,
                        duration_s,
                        repeat_of="" if k == 1 else f"on1-{tail}",
                    )  # fmt: skip
                )
    plan.append(PlanPoint(f"zero-{blocks + 1}", "zero", duration_s=duration_s))
    return plan


@dataclass(frozen=True)
class OscSpec:
    """Oscillation points of one motion: its wind-off tare, then one point per airspeed.
    ``amplitude`` in deg for angular axes, m for translations."""

    axis: str
    amplitude: float
    frequency_Hz: float
    speeds_mps: tuple[float, ...]
    cycles: int
    aoa_deg: float = 0.0
    sideslip_deg: float = 0.0
    settling_cycles: int = 2


ISSUE22_SPECS = (
    OscSpec("pitch", 5.0, 1.0, (25.51, 41.42), 60),
    OscSpec("pitch", 5.0, 2.0, (25.51, 41.42), 120),
    OscSpec("pitch", 2.0, 0.5, (17.27,), 30),
    OscSpec("yaw", 0.6, 1.0, (25.51,), 60),
)
"""The issue-22 points: pitch 5 deg at 1 and 2 Hz at 25.51 and 41.42 m/s for 60 s, pitch 2 deg at
0.5 Hz at 17.27 m/s, a feasible yaw (0.6 deg at 1 Hz)."""


def oscillation_plan(
    specs: tuple[OscSpec, ...] = ISSUE22_SPECS, zero_s: float = 2.0
) -> list[PlanPoint]:
    """A level zero, then per motion its ``oscillation_tare`` and its ``oscillation`` points
    (``inertia_tare`` naming the tare), a closing zero."""
    plan = [PlanPoint("zero-1", "zero", duration_s=zero_s)]
    for s in specs:
        amp = float(np.deg2rad(s.amplitude)) if s.axis in ANGULAR else float(s.amplitude)
        unit = "d" if s.axis in ANGULAR else "m"
        tag = f"{s.axis}-A{_num(s.amplitude)}{unit}-f{_num(s.frequency_Hz)}-a{_num(s.aoa_deg)}"
        common = dict(
            aoa_deg=s.aoa_deg, sideslip_deg=s.sideslip_deg, axis=s.axis, amplitude=amp,
            frequency_Hz=s.frequency_Hz, cycles=s.cycles, settling_cycles=s.settling_cycles,
        )  # fmt: skip
        tare = f"osc-tare-{tag}"
        plan.append(PlanPoint(tare, "oscillation_tare", **common))  # type: ignore[arg-type]
        plan += [
            PlanPoint(
                f"osc-{tag}-v{_num(v)}", "oscillation", airspeed_mps=v, inertia_tare=tare, **common
            )  # type: ignore[arg-type]
            for v in s.speeds_mps
        ]
    plan.append(PlanPoint("zero-2", "zero", duration_s=zero_s))
    return plan


# --------------------------------------------------------------------------------------------
# the timeline: what the platform and the tunnel do


@dataclass
class _Segment:
    t_a: float
    t_b: float
    q0: np.ndarray
    q1: np.ndarray
    V0: float
    V1: float
    motion: Motion | None = None


def _ramp(u: np.ndarray, D: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cycloidal 0 -> 1 over D seconds: zero rate and acceleration at both ends."""
    s = u - np.sin(2 * np.pi * u) / (2 * np.pi)
    return s, (1 - np.cos(2 * np.pi * u)) / D, 2 * np.pi * np.sin(2 * np.pi * u) / D**2


class Timeline:
    """Piecewise states: holds, cycloidal ramps (pose and airspeed) and oscillations."""

    def __init__(self) -> None:
        self.segments: list[_Segment] = []

    @property
    def end_s(self) -> float:
        return self.segments[-1].t_b

    def add(self, seg: _Segment) -> None:
        self.segments.append(seg)

    def states(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """q, qd, qdd (n, 6) and the true airspeed V (n,) at sorted times t (s)."""
        n = len(t)
        q, qd, qdd = np.zeros((n, 6)), np.zeros((n, 6)), np.zeros((n, 6))
        V = np.zeros(n)
        covered = np.zeros(n, bool)
        last = len(self.segments) - 1
        for j, s in enumerate(self.segments):
            i0 = int(np.searchsorted(t, s.t_a, "left"))
            i1 = int(np.searchsorted(t, s.t_b, "right" if j == last else "left"))
            if j == 0:
                i0 = 0
            if j == last:
                i1 = n
            if i1 <= i0:
                continue
            tt = t[i0:i1]
            covered[i0:i1] = True
            if s.motion is not None:
                q[i0:i1], qd[i0:i1], qdd[i0:i1] = s.motion.states(tt)
                V[i0:i1] = s.V0
                continue
            D = s.t_b - s.t_a
            u = np.clip((tt - s.t_a) / D, 0.0, 1.0)
            r, rd, rdd = _ramp(u, D)
            dq = s.q1 - s.q0
            q[i0:i1] = s.q0 + r[:, None] * dq
            qd[i0:i1] = rd[:, None] * dq
            qdd[i0:i1] = rdd[:, None] * dq
            V[i0:i1] = s.V0 + r * (s.V1 - s.V0)
        if not covered.all():
            raise ValueError(f"timeline: no segment at t = {t[~covered][0]:.6f} s")
        return q, qd, qdd, V


# --------------------------------------------------------------------------------------------
# results


@dataclass
class LabCase:
    """A written case: its folder, files and truth (``truth`` is what truth.json holds)."""

    folder: Path
    files: dict[str, Path]
    truth: dict[str, Any]
    points: pd.DataFrame = field(repr=False)


# --------------------------------------------------------------------------------------------
# the generator


def _apply_displacement(q: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Pose q (..., 6) moved by ``[dp; dtheta]`` x (..., 6), dtheta a rotation vector in {O}."""
    R = rotvec_exp(x[..., 3:]) @ rot(q[..., 3:])
    return np.concatenate([q[..., :3] + x[..., :3], euler_of(R)], axis=-1)


def _command_pose(rig: LabRig, p: PlanPoint) -> np.ndarray:
    """The steady pose of a point: P at the rig's reference position, roll 0, pitch = aoa,
    yaw = sideslip (the model nose upstream)."""
    return np.concatenate(
        [rig.reference_pose[:3], [0.0, np.deg2rad(p.aoa_deg), np.deg2rad(p.sideslip_deg)]]
    )


def _air_density(tun: Tunnel, t_s: np.ndarray) -> np.ndarray:
    T = tun.temperature_K + tun.temperature_rise_K_per_h * np.asarray(t_s) / 3600.0
    return moist_air_density(tun.static_pressure_Pa, T, tun.relative_humidity)


def generate(
    plan: list[PlanPoint],
    out_dir: str | Path,
    *,
    rig: str | Path = "flat",
    noise: LoadCellNoise | None = None,
    camera: Camera | None = None,
    tunnel: Tunnel | None = None,
    body: Body | None = None,
    model: AeroModel | None = None,
    geometry: Geometry | None = None,
    seed: int = 0,
    rate_hz: float = 1000.0,
    transition_s: float = 1.0,
    settle_s: float = 0.5,
    lead_s: float = 1.0,
    deflection: bool = True,
    calibration: str = "fitted",
    name: str = "lab",
    chunk: int = 50_000,
    encoders: Encoders | None = None,
) -> LabCase:
    """Run the physics of ``plan`` and write the lab's files into ``out_dir`` (module docstring).

    rig: ``"flat"`` / ``"cubic"`` (data_samples' optimum rigs) or a rig file; body: the model's
    true mass properties against the rig file's; deflection: the platform yields ``K^-1 W`` under
    a steady point's aerodynamic load (K: the stiffness at the point); calibration: ``"fitted"``
    (a lab's fit over hung loads, with its statistics) or ``"exact"``.  Deterministic by ``seed``
    (each noise source its own stream)."""
    noise = noise or LoadCellNoise()
    camera = camera or Camera()
    tunnel = tunnel or Tunnel()
    body = body or Body()
    model = model or AeroModel()
    geometry = geometry or Geometry()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rig_file = Path(RIGS.get(str(rig), rig))
    nominal = LabRig.from_toml(rig_file)
    true = body.apply(nominal)
    m = nominal.m
    streams = np.random.SeedSequence(seed).spawn(10)
    rng = {k: np.random.default_rng(s) for k, s in zip(
        ("white", "ar1", "common", "mode", "drift", "camera", "tunnel", "cal", "tau", "spare"),
        streams, strict=True)}  # fmt: skip
    rng["encoders"] = np.random.default_rng(np.random.SeedSequence([seed, 11]))
    dt = 1.0 / rate_hz
    dt_ns = int(round(1e9 / rate_hz))

    # --- targets: the true pose of every point (the steady deflection under its load)
    rho0 = float(_air_density(tunnel, np.array(0.0)))
    targets = []
    deflections = []
    for p in plan:
        q = _command_pose(nominal, p)
        x = np.zeros(6)
        if deflection and p.kind == "wind_on":
            W = aero_loads(
                model, geometry, q[None], None, None, np.array([p.airspeed_mps]), rho0
            ).wrench_P_O[0]
            T0, _ = distribute(
                structure_matrix(true, q[None]),
                (-gravity_wrench(true, q[None]) - W),
                true.t_min_N,
                true.t_max_N,
            )
            K, _ = stiffness(true, q, T0[0])
            x = np.linalg.solve(K, W)
            q = _apply_displacement(q, x)
        targets.append(q)
        deflections.append(x)

    # --- the timeline and the events (load-cell clock, s from the log start)
    tl = Timeline()
    q_prev, V_prev = targets[0], 0.0
    t = 0.0
    ev: list[dict[str, Any]] = []
    windows: list[tuple[float, float]] = []
    motions: list[Motion | None] = []

    def ms(x: float) -> float:  # boundaries on the sample grid
        return round(x * rate_hz) / rate_hz

    tl.add(_Segment(t, ms(lead_s), q_prev, q_prev, 0.0, 0.0))
    t = ms(lead_s)
    for p, q in zip(plan, targets, strict=True):
        V = p.airspeed_mps
        if not (np.allclose(q, q_prev, atol=1e-12) and V == V_prev):
            tl.add(_Segment(t, ms(t + transition_s), q_prev, q, V_prev, V))
            t = ms(t + transition_s)
        tl.add(_Segment(t, ms(t + settle_s), q, q, V, V))
        t = ms(t + settle_s)
        start = t
        if p.oscillating:
            mo = Motion(
                p.axis, p.amplitude, p.frequency_Hz, p.cycles, p.settling_cycles, tuple(q), start
            )
            tl.add(_Segment(start, mo.stop_s, q, q, V, V, motion=mo))
            end = mo.window_s[1]
            tl.add(_Segment(mo.stop_s, ms(mo.stop_s + settle_s), q, q, V, V))
            t = ms(mo.stop_s + settle_s)
            motions.append(mo)
        else:
            end = ms(start + p.duration_s)
            tl.add(_Segment(start, end, q, q, V, V))
            t = end
            motions.append(None)
        windows.append((start, end))
        ev.append({"t": start, "phase": "start", "p": p})
        ev.append({"t": end, "phase": "end", "p": p})
        q_prev, V_prev = q, V
    tl.add(_Segment(t, ms(t + settle_s), q_prev, q_prev, V_prev, V_prev))
    n = int(round(tl.end_s * rate_hz)) + 1
    t_s = np.arange(n) / rate_hz  # as ms() rounds the boundaries
    t_ns = T_LOG0_NS + np.arange(n, dtype=np.int64) * dt_ns

    # --- the lowest mode (wind off, at the reference pose, the true body)
    q_ref = nominal.reference_pose
    T_ref, _ = distribute(
        structure_matrix(true, q_ref[None]),
        -gravity_wrench(true, q_ref[None]),
        true.t_min_N,
        true.t_max_N,
    )
    freqs, shapes = modes(true, q_ref, T_ref[0])
    phi1 = shapes[:, 0] / np.linalg.norm(shapes[:, 0])
    _, lv_ref, l_ref = cable_vectors(true, q_ref[None])
    k_ref = true.EA_N / l_ref[0]
    per_unit = np.abs(
        k_ref * (structure_matrix(true, q_ref[None])[0].T @ phi1)
    )  # N per unit of phi1

    # --- noise processes over all samples
    W_sd = noise.white_sd()
    T_white = white(rng["white"], n, m, W_sd)
    taus = rng["tau"].uniform(*noise.ar1_tau_s, size=m)
    T_ar1 = (
        ar1(rng["ar1"], n, np.full(m, noise.ar1_sd_N), taus, dt) if noise.case == "ar1" else None
    )
    dC = (
        vector_ar1(rng["common"], n, noise.common_cov(), noise.common_tau_s, dt)
        if noise.case == "common"
        else None
    )
    mode_s = (
        narrowband(rng["mode"], n, float(freqs[0]), noise.mode_Q, dt)
        if noise.case == "mode"
        else None
    )
    drift_rate = rng["drift"].normal(0.0, noise.drift_sd_N_per_s, m)

    # --- the physics at every load-cell sample, in chunks
    rho = _air_density(tunnel, t_s)
    q_all, V_all = np.empty((n, 6)), np.empty(n)
    T_det = np.empty((n, m))
    W_P = np.empty((n, 6))
    W_mrp = np.empty((n, 6))
    C_det = np.full((n, 6), np.nan)
    F_B = np.empty((n, 3))
    M_B = np.empty((n, 3))
    aoa_all, beta_all = np.empty(n), np.empty(n)
    D_minus_G = np.empty((n, 6))
    T_fluct = np.zeros((n, m)) if noise.case in ("common", "mode") else None
    qbar_max = 0.5 * rho0 * max([p.airspeed_mps for p in plan] + [1.0]) ** 2
    n_qp = 0
    for i0 in range(0, n, chunk):
        sl = slice(i0, min(n, i0 + chunk))
        q, qd, qdd, V = tl.states(t_s[sl])
        ld = aero_loads(model, geometry, q, qd, qdd, V, rho[sl])
        D = body_wrench(true, q, qd, qdd)
        G = gravity_wrench(true, q)
        A = structure_matrix(true, q)
        w = D - G - ld.wrench_P_O
        try:
            T, k = distribute(A, w, true.t_min_N, true.t_max_N)
        except InfeasibleError as exc:
            ts = float(t_s[sl][exc.index])
            j = (
                int(np.searchsorted([a for a, _ in windows], ts + transition_s + settle_s, "right"))
                - 1
            )
            at = plan[max(j, 0)].label
            raise InfeasibleError(f"{at} (or its ramp) at t = {ts:.3f} s: {exc}") from None
        n_qp += k
        if dC is not None:
            dW = wrench_from_coefficients(
                dC[sl], ld.aoa_rad, ld.sideslip_rad, ld.R_O_B, ld.q_Pa, geometry, ld.r_mrp_O
            )[0]
            T_all_fluct, k = distribute(A, w - dW, true.t_min_N, true.t_max_N)
            n_qp += k
            T_fluct[sl] = T_all_fluct - T  # type: ignore[index]
        if mode_s is not None:
            amp = noise.mode_rms_N / per_unit.max() * np.maximum(0.2, ld.q_Pa / qbar_max)
            x = phi1[None, :] * (amp * mode_s[sl])[:, None]
            _, _, ln = cable_vectors(true, q)
            T_fluct[sl] = -(true.EA_N / ln) * np.einsum("nij,ni->nj", A, x)  # type: ignore[index]
        q_all[sl], V_all[sl] = q, V
        T_det[sl] = T
        W_P[sl], W_mrp[sl] = ld.wrench_P_O, ld.wrench_mrp_O
        C_det[sl] = ld.coefficients
        F_B[sl], M_B[sl] = ld.force_B_N, ld.moment_B_Nm
        aoa_all[sl], beta_all[sl] = ld.aoa_rad, ld.sideslip_rad
        D_minus_G[sl] = D - G
    if (T_det < true.t_min_N).any() or (T_det > true.t_max_N).any():
        raise ValueError("tensions outside the limits after the distribution")
    drift = drift_rate[None, :] * (t_s - t_s[0])[:, None]
    T_meas = T_det + T_white + drift
    if T_ar1 is not None:
        T_meas += T_ar1
    if T_fluct is not None:
        T_meas += T_fluct

    # --- the amplifier: counts, and the calibration the lab fitted
    gain = true.t_max_N * 1.1 / 2**23 * (1 + 0.01 * rng["cal"].standard_normal(m))
    offset = rng["cal"].uniform(-50_000, 50_000, m)
    counts = np.rint(offset + T_meas / gain).astype(np.int64)
    if (np.abs(counts) >= 2**23).any():
        raise ValueError("counts beyond the 24-bit range")
    cal = _calibration(rng["cal"], nominal, offset, gain, calibration)

    # --- the camera
    cam_period_ns = int(round(1e9 / camera.rate_hz))
    t_cam = np.arange(
        T_LOG0_NS + camera.clock_offset_ns + 1_700_000,
        t_ns[-1] + camera.clock_offset_ns,
        cam_period_ns,
        dtype=np.int64,
    )
    t_true_s = (t_cam - camera.clock_offset_ns - T_LOG0_NS) * 1e-9
    q_cam_true, _, _, _ = tl.states(t_true_s)
    if mode_s is not None:
        amp_cam = noise.mode_rms_N / per_unit.max()
        q_dot_disp = np.interp(t_true_s, t_s, mode_s)
        qb = np.interp(t_true_s, t_s, 0.5 * rho * V_all**2)
        x = phi1[None, :] * (amp_cam * q_dot_disp * np.maximum(0.2, qb / qbar_max))[:, None]
        q_cam_true = _apply_displacement(q_cam_true, x)
    k_f = len(t_cam)
    scale = 1 + camera.sd_spread * rng["camera"].uniform(-1, 1, k_f)
    dp = rng["camera"].standard_normal((k_f, 3)) * (camera.pos_sd_m * scale)[:, None]
    dth = rng["camera"].standard_normal((k_f, 3)) * (camera.ang_sd_rad * scale)[:, None]
    q_cam = _apply_displacement(q_cam_true, np.concatenate([dp, dth], axis=1))
    cov = np.zeros((k_f, 6, 6))
    cov[:, :3, :3] = np.eye(3) * ((camera.pos_sd_m * scale) ** 2)[:, None, None]
    cov[:, 3:, 3:] = np.eye(3) * ((camera.ang_sd_rad * scale) ** 2)[:, None, None]
    if camera.cov_params == "euler":  # dpsi = H^-1 dtheta
        Hi = np.linalg.inv(rate_matrix(q_cam[:, 3:]))
        cov[:, 3:, 3:] = Hi @ cov[:, 3:, 3:] @ np.swapaxes(Hi, 1, 2)
        cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))  # exactly symmetric as written

    # --- the controller's cable lengths (motor encoders)
    enc_t = enc_L = None
    if encoders is not None:
        enc_t = np.arange(
            T_LOG0_NS + encoders.clock_offset_ns + 1_300_000,
            t_ns[-1] + encoders.clock_offset_ns,
            int(round(1e9 / encoders.rate_hz)),
            dtype=np.int64,
        )
        q_enc, _, _, _ = tl.states((enc_t - encoders.clock_offset_ns - T_LOG0_NS) * 1e-9)
        enc_L = cable_vectors(true, q_enc)[2]
        enc_L = enc_L + rng["encoders"].normal(0.0, encoders.sd_m, enc_L.shape)

    # --- the tunnel instruments
    t_tun = np.arange(T_LOG0_NS, t_ns[-1] + 1, int(round(1e9 / tunnel.rate_hz)), dtype=np.int64)
    tt = (t_tun - T_LOG0_NS) * 1e-9
    _, _, _, V_tun = tl.states(tt)
    nt = len(t_tun)
    r_t = rng["tunnel"]
    V_meas = np.where(
        V_tun > 0,
        V_tun * (1 + tunnel.airspeed_bias_rel) + r_t.normal(0, tunnel.airspeed_sd_mps, nt),
        0.0,
    )
    V_meas = np.maximum(V_meas, 0.0)
    tun_names = ["airspeed_mps", "static_pressure_Pa", "temperature_K", "relative_humidity"]
    tun_values = np.column_stack([
        V_meas,
        tunnel.static_pressure_Pa + r_t.normal(0, tunnel.pressure_sd_Pa, nt),
        tunnel.temperature_K + tunnel.temperature_rise_K_per_h * tt / 3600
        + r_t.normal(0, tunnel.temperature_sd_K, nt),
        np.clip(tunnel.relative_humidity + r_t.normal(0, tunnel.humidity_sd, nt), 0, 1),
    ])  # fmt: skip

    # --- truth per point
    rows = []
    for j, (p, (a, b), mo) in enumerate(zip(plan, windows, motions, strict=True)):
        i0 = int(round(a * rate_hz))
        i1 = int(math.floor(b * rate_hz + 1e-9)) + 1
        sel = slice(i0, i1)
        row: dict[str, Any] = {
            "point": p.label, "kind": p.kind, "start_ns": int(T_LOG0_NS + round(a * 1e9)),
            "end_ns": int(T_LOG0_NS + round(b * 1e9)), "n_samples": i1 - i0,
            "airspeed_mps": float(V_all[sel].mean()), "density_kgpm3": float(rho[sel].mean()),
            "q_Pa": float((0.5 * rho[sel] * V_all[sel] ** 2).mean()),
            "repeat_of": p.repeat_of, "target_aoa_deg": p.aoa_deg,
            "target_sideslip_deg": p.sideslip_deg, "target_airspeed_mps": p.airspeed_mps,
        }  # fmt: skip
        pose = q_all[sel].mean(axis=0)
        for k2, c in enumerate(("x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad")):
            row[f"true_{c}"] = float(pose[k2])
        row["aoa_rad"], row["sideslip_rad"] = (
            float(aoa_all[sel].mean()),
            float(beta_all[sel].mean()),
        )
        for k2, c in enumerate(("fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")):
            row[c] = float(W_mrp[sel, k2].mean())
            row[f"{c.split('_')[0]}_P_{c.split('_')[1]}"] = float(W_P[sel, k2].mean())
        for k2, c in enumerate(("fx_B_N", "fy_B_N", "fz_B_N")):
            row[c] = float(F_B[sel, k2].mean())
        for k2, c in enumerate(("mx_B_Nm", "my_B_Nm", "mz_B_Nm")):
            row[c] = float(M_B[sel, k2].mean())
        on = p.airspeed_mps > 0
        for k2, c in enumerate(COEFFICIENTS):
            row[c] = float(C_det[sel, k2].mean()) if on else float("nan")
        row["deflection"] = deflections[j].tolist()
        row["tension_true_mean_N"] = T_det[sel].mean(axis=0).tolist()
        row["drift_mean_N"] = drift[sel].mean(axis=0).tolist()
        row["white_mean_N"] = T_white[sel].mean(axis=0).tolist()
        if T_ar1 is not None:
            row["ar1_mean_N"] = T_ar1[sel].mean(axis=0).tolist()
        if T_fluct is not None:
            row["fluctuation_mean_N"] = T_fluct[sel].mean(axis=0).tolist()
        if mo is not None:
            row["oscillation"] = _oscillation_truth(
                p, mo, model, geometry, t_s[sel], C_det[sel], aoa_all[sel], beta_all[sel],
                W_P[sel], D_minus_G[sel], F_B[sel], row["q_Pa"] * geometry.area_m2,
            )  # fmt: skip
        rows.append(row)

    # --- the files
    files = {
        "can_log": out / "can.log",
        "calibration": out / "loadcells.toml",
        "poses": out / "poses.csv",
        "tunnel": out / "tunnel.csv",
        "events": out / "events.csv",
        "matrix": out / "matrix.toml",
        "rig": out / rig_file.name,
        "truth": out / "truth.json",
        "truth_points": out / "truth_points.csv",
        "dbc": DBC,
    }
    shutil.copyfile(rig_file, files["rig"])
    write_candump(files["can_log"], t_ns, counts)
    files["calibration"].write_text(cal["text"])
    write_poses(files["poses"], t_cam, q_cam, cov)
    write_table(files["tunnel"], t_tun, tun_names, tun_values)
    write_events(files["events"], ev)
    files["matrix"].write_text(matrix_text(plan, files["rig"].name, geometry, transition_s, name))
    if enc_t is not None and enc_L is not None:
        files["cable_lengths"] = out / "lengths.csv"
        write_table(files["cable_lengths"], enc_t, [f"L_{c}_m" for c in nominal.cable_names], enc_L)
    truth: dict[str, Any] = {
        "generator": "tests/lab_generator.py (independent of cdpr: _lab_physics, _lab_aero, "
        "_lab_noise)",
        "seed": seed,
        "name": name,
        "rig_file": rig_file.name,
        "rig_cables": list(nominal.cable_names),
        "conventions": CONVENTIONS,
        "load_cell_rate_hz": rate_hz,
        "log_start_ns": int(t_ns[0]),
        "log_end_ns": int(t_ns[-1]),
        "n_samples": n,
        "samples_solved_by_slsqp": n_qp,
        "camera": {
            **asdict(camera),
            "camera_clock_offset_ns": camera.clock_offset_ns,
            "n_frames": k_f,
        },
        "tunnel": asdict(tunnel),
        "encoders": None if encoders is None else asdict(encoders),
        "load_cells": {
            "noise": asdict(noise),
            "white_sd_N_used": W_sd,
            "ar1_tau_s": taus.tolist() if T_ar1 is not None else None,
            "drift_N_per_s": drift_rate.tolist(),
            "offset_counts_true": offset.tolist(),
            "gain_N_per_count_true": gain.tolist(),
            "calibration_file": {k: v for k, v in cal.items() if k != "text"},
        },
        "lowest_mode": {
            "frequency_Hz": float(freqs[0]),
            "frequencies_Hz": freqs.tolist(),
            "shape": phi1.tolist(),
            "tension_rms_per_unit_N": per_unit.tolist(),
        },
        "body_true": {
            "mass_kg": true.mass_kg,
            "com_P_m": true.com_P_m.tolist(),
            "inertia_P_kgm2": true.inertia_P_kgm2.tolist(),
        },
        "body_rig_file": {
            "mass_kg": nominal.mass_kg,
            "com_P_m": nominal.com_P_m.tolist(),
            "inertia_P_kgm2": nominal.inertia_P_kgm2.tolist(),
        },
        "aero_model": model.as_dict(),
        "geometry": asdict(geometry),
        "deflection": deflection,
        "points": rows,
    }
    files["truth"].write_text(json.dumps(truth, indent=1, default=_json_default))
    flat = pd.DataFrame(
        [{k: v for k, v in r.items() if not isinstance(v, list | dict)} for r in rows]
    )
    flat.to_csv(files["truth_points"], index=False)
    return LabCase(out, files, truth, flat)


def _json_default(x: Any) -> Any:
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating):
        return float(x)
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(type(x))


def _calibration(
    rng: np.random.Generator, rig: LabRig, offset: np.ndarray, gain: np.ndarray, how: str
) -> dict[str, Any]:
    """The load-cell calibration file: ``exact`` (the amplifiers' values), or ``fitted`` as a lab
    does it: 9 hung loads 0..80 % of t_max per cell, each the mean of 2000 readings with 0.05 N
    noise, a least-squares line ``counts = offset + load / gain`` with its parameter sd."""
    names = list(rig.cable_names)
    if how == "exact":
        off, g = offset.copy(), gain.copy()
        extra: dict[str, Any] = {"source": "exact (lab generator)"}
    elif how == "fitted":
        off, g = np.empty(len(names)), np.empty(len(names))
        sd_off, sd_g, rms, corr = [], [], [], []
        for i in range(len(names)):
            L = np.linspace(0.0, 0.8 * rig.t_max_N[i], 9)
            c = offset[i] + (L + rng.normal(0, 0.05 / np.sqrt(2000), L.size)) / gain[i]
            X = np.column_stack([np.ones_like(L), L])
            beta, res, *_ = np.linalg.lstsq(X, c, rcond=None)
            r = c - X @ beta
            s2 = float(r @ r) / (L.size - 2)
            cov = s2 * np.linalg.inv(X.T @ X)
            off[i], g[i] = beta[0], 1.0 / beta[1]
            sd_off.append(float(np.sqrt(cov[0, 0])))
            sd_g.append(float(np.sqrt(cov[1, 1]) / beta[1] ** 2))
            # gain = 1/beta1: its error is -d(beta1)/beta1^2, so the correlation changes sign
            corr.append(float(-cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1])))
            rms.append(float(np.sqrt(np.mean(r**2))) * g[i])
        extra = {
            "source": "lab generator: 9 hung loads per cell, 2000 readings each, 0.05 N noise",
            "sd_offset_counts": sd_off,
            "sd_gain_N_per_count": sd_g,
            "corr_offset_gain": corr,
            "residual_rms_N": rms,
            "n_points": [9] * len(names),
        }
    else:
        raise ValueError(f"calibration: expected fitted or exact, got {how!r}")

    def arr(v: Any) -> str:
        return (
            "["
            + ", ".join(repr(float(x)) if not isinstance(x, str) else json.dumps(x) for x in v)
            + "]"
        )

    lines = [
        "# Load-cell calibration: T_N = (counts - offset_counts) * gain_N_per_count",
        "[calibration]",
        'kind = "loadcells"',
        'id = "lab-generator"',
        "cables = " + arr(names),
        "offset_counts = " + arr(off),
        "gain_N_per_count = " + arr(g),
    ]
    for k, v in extra.items():
        lines.append(f"{k} = " + (json.dumps(v) if isinstance(v, str) else arr(v)))
    return {
        "text": "\n".join(lines) + "\n",
        "how": how,
        "offset_counts": off.tolist(),
        "gain_N_per_count": g.tolist(),
        **{k: v for k, v in extra.items()},
    }


def _harmonics(tau: np.ndarray, y: np.ndarray, w: float, n_h: int = 3) -> np.ndarray:
    """Least-squares ``[C0, a1, b1, a2, b2, ...]`` (2 n_h + 1, k) of y (n, k) on
    ``C0 + sum a_n sin(n w tau) + b_n cos(n w tau)``."""
    cols = [np.ones_like(tau)]
    for h in range(1, n_h + 1):
        cols += [np.sin(h * w * tau), np.cos(h * w * tau)]
    X = np.column_stack(cols)
    return np.linalg.lstsq(X, y, rcond=None)[0]


def _oscillation_truth(
    p: PlanPoint,
    mo: Motion,
    model: AeroModel,
    geom: Geometry,
    t_s: np.ndarray,
    C: np.ndarray,
    aoa: np.ndarray,
    beta: np.ndarray,
    W_P: np.ndarray,
    DmG: np.ndarray,
    F_B: np.ndarray,
    qS: float,
) -> dict[str, Any]:
    """In-phase and out-of-phase derivatives of the model over the analysed window (whole cycles;
    module docstring), the harmonics of the aerodynamic and the inertia-plus-gravity wrench."""
    a_s, b_s = mo.window_s
    sel = (t_s >= a_s - 1e-9) & (t_s <= b_s + 1e-9)
    tau = t_s[sel] - mo.t0_s
    w = mo.omega
    A = mo.amplitude
    out: dict[str, Any] = {
        "axis": mo.axis, "amplitude": A, "frequency_Hz": mo.frequency_Hz, "omega_rad_s": w,
        "t0_ns": int(T_LOG0_NS + round(mo.t0_s * 1e9)),
        "window_ns": [int(T_LOG0_NS + round(a_s * 1e9)), int(T_LOG0_NS + round(b_s * 1e9))],
        "cycles": mo.cycles, "settling_cycles": mo.settling_cycles, "q_mean": list(mo.q_mean),
    }  # fmt: skip
    out["inertia_gravity_harmonics_P_O"] = _harmonics(tau, DmG[sel], w).T.tolist()
    out["aero_wrench_harmonics_P_O"] = _harmonics(tau, W_P[sel], w).T.tolist()
    V = p.airspeed_mps
    if V <= 0:
        return out
    lref = geom.chord_m if mo.axis in ("pitch", "heave", "surge") else geom.span_m
    k = w * lref / (2 * V)
    # normal and axial force coefficients (body axes): CN = -F_zB/(qS), CA = -F_xB/(qS)
    Cfull = np.column_stack([C[sel], -F_B[sel, 2] / qS, -F_B[sel, 0] / qS])
    names = [*COEFFICIENTS, "CN", "CA"]
    h = _harmonics(tau, Cfull, w)
    out["reduced_frequency"] = k
    out["reference_length_m"] = lref
    out["coefficient_harmonics"] = {nm: h[:, i].tolist() for i, nm in enumerate(names)}
    out["inphase"] = {nm: float(h[1, i] / A) for i, nm in enumerate(names)}
    out["outphase"] = {nm: float(h[2, i] / (A * k)) for i, nm in enumerate(names)}
    a0 = float(np.deg2rad(p.aoa_deg))
    lin: dict[str, float] = {}
    if mo.axis == "pitch":
        lin = {"Cma": model.Cma, "Cmq_plus_Cmadot": model.Cmq + model.Cmadot,
               "CLa": model.CLa, "CLq_plus_CLadot": model.CLq + model.CLadot}  # fmt: skip
        out["named"] = {
            "Cma": out["inphase"]["Cm"], "Cmq_plus_Cmadot": out["outphase"]["Cm"],
            "CLa": out["inphase"]["CL"], "CLq_plus_CLadot": out["outphase"]["CL"],
            "CNa": out["inphase"]["CN"], "CNq_plus_CNadot": out["outphase"]["CN"],
        }  # fmt: skip
    elif mo.axis == "yaw":
        lin = {"Cn_inphase": model.Cnb,
               "Cn_outphase": -model.Cnr * np.cos(a0) + model.Cnp * np.sin(a0) + model.Cnbdot,
               "Cl_inphase": model.Clb,
               "Cl_outphase": model.Clp * np.sin(a0) - model.Clr * np.cos(a0),
               "CY_inphase": model.CYb}  # fmt: skip
        out["named"] = {"Cnb": out["inphase"]["Cn"], "Clb": out["inphase"]["Cl"],
                        "CYb": out["inphase"]["CY"]}  # fmt: skip
    elif mo.axis == "roll":
        lin = {"Cl_inphase": -model.Clb * np.sin(a0), "Cl_outphase": -model.Clp,
               "Cn_inphase": -model.Cnb * np.sin(a0), "Cn_outphase": -model.Cnp}  # fmt: skip
    out["linear"] = {k2: float(v) for k2, v in lin.items()}
    return out


# --------------------------------------------------------------------------------------------
# writers


def _digits(values: np.ndarray, width: int) -> np.ndarray:
    """ASCII decimal digits (n, width) of non-negative integers, zero-padded."""
    v = values.astype(np.int64).copy()
    out = np.empty((len(v), width), np.uint8)
    for j in range(width - 1, -1, -1):
        out[:, j] = 48 + (v % 10)
        v //= 10
    return out


_HEXCHARS = np.frombuffer(b"0123456789ABCDEF", np.uint8)


def _frame_bytes(counts: np.ndarray) -> np.ndarray:
    """(n, 4, 8) data bytes of the four TPDOs: two signed 24-bit little-endian channels, the status
    byte (0: no flag) and the sample counter."""
    n = len(counts)
    u = (counts & 0xFFFFFF).astype(np.uint32)
    data = np.zeros((n, 4, 8), np.uint8)
    for f in range(4):
        for c in range(2):
            v = u[:, 2 * f + c]
            for b in range(3):
                data[:, f, 3 * c + b] = (v >> (8 * b)) & 0xFF
    data[:, :, 7] = (np.arange(n) % 256)[:, None]
    return data


def write_candump(path: Path, t_ns: np.ndarray, counts: np.ndarray) -> None:
    """A candump log (``(<s>.<us>) can0 <id>#<16 hex digits>``), four frames a sample, the first
    at the sample time, the others ``FRAME_SPACING_NS`` apart; written with numpy in blocks."""
    with open(path, "wb") as fh:
        for i0 in range(0, len(t_ns), 100_000):
            tt = t_ns[i0 : i0 + 100_000]
            data = _frame_bytes(counts[i0 : i0 + 100_000])
            data[:, :, 7] = ((np.arange(i0, i0 + len(tt))) % 256)[:, None]
            ft = (tt[:, None] + np.arange(4) * FRAME_SPACING_NS).ravel()
            us = ft // 1000
            k = len(ft)
            line = np.empty((k, 46), np.uint8)
            line[:, 0] = ord("(")
            line[:, 1:11] = _digits(us // 1_000_000, 10)
            line[:, 11] = ord(".")
            line[:, 12:18] = _digits(us % 1_000_000, 6)
            line[:, 18:25] = np.frombuffer(b") can0 ", np.uint8)
            ids = np.tile(
                np.array([f"{i:03X}".encode() for i in FRAME_IDS]).view(np.uint8).reshape(4, 3),
                (len(tt), 1),
            )
            line[:, 25:28] = ids
            line[:, 28] = ord("#")
            d = data.reshape(k, 8)
            line[:, 29:45:2] = _HEXCHARS[d >> 4]
            line[:, 30:46:2] = _HEXCHARS[d & 15]
            line[:, 45] = ord("\n")
            fh.write(line.tobytes())


def read_candump(path: Path, n_cells: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """An independent decoder of :func:`write_candump`'s logs: the sample times (ns, the first
    frame's) and counts (n, 8) (fixed-width lines of this generator only)."""
    raw = np.fromfile(path, np.uint8).reshape(-1, 46)
    sec = (raw[:, 1:11] - 48).astype(np.int64) @ (10 ** np.arange(9, -1, -1, dtype=np.int64))
    us = (raw[:, 12:18] - 48).astype(np.int64) @ (10 ** np.arange(5, -1, -1, dtype=np.int64))
    t_ns = (sec * 1_000_000 + us) * 1000
    lut = np.zeros(256, np.int64)
    lut[np.frombuffer(b"0123456789ABCDEF", np.uint8)] = np.arange(16)
    nib = lut[raw[:, 29:45]]
    byts = nib[:, 0::2] * 16 + nib[:, 1::2]  # (k, 8)
    k = len(raw) // 4
    byts = byts[: 4 * k].reshape(k, 4, 8)
    counts = np.empty((k, n_cells), np.int64)
    for f in range(4):
        for c in range(2):
            v = byts[:, f, 3 * c] | (byts[:, f, 3 * c + 1] << 8) | (byts[:, f, 3 * c + 2] << 16)
            counts[:, 2 * f + c] = np.where(v >= 2**23, v - 2**24, v)
    return t_ns[0 : 4 * k : 4], counts


POSE_COLUMNS = ("x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad")
COV_COLUMNS = tuple(f"cov_{i}{j}" for i in range(6) for j in range(6))


def write_table(path: Path, t_ns: np.ndarray, names: list[str], values: np.ndarray) -> None:
    """A CSV of an integer ``t_ns`` column and float columns (``%.10g``; pandas' writer is ten
    times slower on these tables)."""
    fmt = "%d," + ",".join(["%.10g"] * len(names))
    body = "\n".join(fmt % (t, *r) for t, r in zip(t_ns.tolist(), values.tolist(), strict=True))
    Path(path).write_text(",".join(["t_ns", *names]) + "\n" + body + "\n")


def write_poses(path: Path, t_cam: np.ndarray, q: np.ndarray, cov: np.ndarray) -> None:
    """The camera's pose CSV: ``t_ns``, the pose and its covariance (row-major 6 x 6)."""
    write_table(path, t_cam, [*POSE_COLUMNS, *COV_COLUMNS], np.hstack([q, cov.reshape(len(q), 36)]))


def write_events(path: Path, ev: list[dict[str, Any]]) -> None:
    rows = []
    for e in sorted(ev, key=lambda e: e["t"]):
        p: PlanPoint = e["p"]
        r: dict[str, Any] = {
            "t_ns": int(T_LOG0_NS + round(e["t"] * 1e9)),
            "point": p.label, "phase": e["phase"], "kind": p.kind,
            "target_aoa_deg": p.aoa_deg, "target_sideslip_deg": p.sideslip_deg,
            "target_airspeed_mps": p.airspeed_mps, "repeat_of": p.repeat_of,
        }  # fmt: skip
        if any(x["p"].oscillating for x in ev):
            r.update(
                motion_axis=p.axis, motion_amplitude=p.amplitude if p.oscillating else "",
                motion_frequency_Hz=p.frequency_Hz if p.oscillating else "",
                motion_cycles=p.cycles if p.oscillating else "",
                motion_settling_cycles=p.settling_cycles if p.oscillating else "",
                inertia_tare=p.inertia_tare,
            )  # fmt: skip
        rows.append(r)
    pd.DataFrame(rows).to_csv(path, index=False, float_format="%.12g")


def matrix_text(
    plan: list[PlanPoint], rig_name: str, geom: Geometry, transition_s: float, name: str
) -> str:
    """The test matrix TOML (docs/campaign.md; oscillation keys per helpers/dynamic_spec.md)."""
    mrp = ", ".join(repr(float(x)) for x in geom.mrp_P_m)
    out = [
        "# Test matrix written by tests/lab_generator.py (one [[points]] per point, run order)",
        "[campaign]",
        f'name = "{name}"',
        f'rig = "{rig_name}"',
        "",
        "[model]",
        'name = "SDM (lab generator)"',
        f"area_m2 = {geom.area_m2!r}",
        f"span_m = {geom.span_m!r}",
        f"chord_m = {geom.chord_m!r}",
        f"mrp_P_m = [{mrp}]",
        "",
        "[defaults]",
        f"transition_s = {transition_s!r}",
    ]
    for p in plan:
        out += ["", "[[points]]", f'label = "{p.label}"', f'kind = "{p.kind}"']
        if p.kind != "zero":
            out += [f"aoa_deg = {p.aoa_deg!r}", f"sideslip_deg = {p.sideslip_deg!r}"]
        if p.airspeed_mps > 0:
            out.append(f"airspeed_mps = {p.airspeed_mps!r}")
        if p.oscillating:
            key = "amplitude_deg" if p.axis in ANGULAR else "amplitude_m"
            amp = float(np.rad2deg(p.amplitude)) if p.axis in ANGULAR else p.amplitude
            out += [
                f'axis = "{p.axis}"', f"{key} = {round(amp, 12)!r}",
                f"frequency_Hz = {p.frequency_Hz!r}", f"cycles = {p.cycles}",
                f"settling_cycles = {p.settling_cycles}",
            ]  # fmt: skip
            if p.inertia_tare:
                out.append(f'inertia_tare = "{p.inertia_tare}"')
        else:
            out.append(f"duration_s = {p.duration_s!r}")
        if p.repeat_of:
            out.append(f'repeat_of = "{p.repeat_of}"')
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------------------------
# conveniences


def steady_case(
    out_dir: str | Path,
    case: str = "white",
    n_wind_on: int = 100,
    *,
    rig: str | Path = "flat",
    duration_s: float = 3.0,
    seed: int = 0,
    plan_kw: dict[str, Any] | None = None,
    **kw: Any,
) -> LabCase:
    """Issue 21: ``n_wind_on`` steady wind-on points (and their zeros and tares) under the noise
    ``case`` (white | ar1 | common | mode); other keywords go to :func:`generate`."""
    plan = steady_plan(n_wind_on, duration_s=duration_s, **(plan_kw or {}))
    noise = kw.pop("noise", None) or LoadCellNoise(case=case)
    return generate(plan, out_dir, rig=rig, noise=noise, seed=seed, name=f"steady-{case}", **kw)


def oscillation_case(
    out_dir: str | Path,
    specs: tuple[OscSpec, ...] = ISSUE22_SPECS,
    *,
    seed: int = 0,
    **kw: Any,
) -> LabCase:
    """Issue 22: the oscillation points of ``specs`` with their wind-off tares; a 200 Hz camera
    with 0.05 mm / 0.01 deg and a 3 ms clock offset, load cells at 1 kHz with 0.05 N white noise
    (no drift) unless ``camera`` / ``noise`` say otherwise."""
    kw.setdefault("camera", Camera(rate_hz=200.0))
    kw.setdefault("noise", LoadCellNoise(case="white", drift_sd_N_per_s=0.0))
    return generate(oscillation_plan(specs), out_dir, seed=seed, name="oscillation", **kw)


def lab_argv(
    case: LabCase, run: str | Path, analysis: str | Path, pose: str = "camera"
) -> tuple[list[str], list[str]]:
    """The ``cdpr import`` and ``cdpr analyze --matrix`` arguments (without the program name);
    ``pose="lengths"``: the controller's cable-length log instead of the camera."""
    f = case.files
    if pose == "lengths":
        sd = case.truth["encoders"]["sd_m"]
        src = ["--cable-lengths", str(f["cable_lengths"]), "--length-sd-m", repr(sd)]
    else:
        src = ["--poses", str(f["poses"])]
    imp = [
        "import", "--can-log", str(f["can_log"]), "--dbc", str(f["dbc"]), "--rig", str(f["rig"]),
        "--calibration", str(f["calibration"]), *src,
        "--tunnel", str(f["tunnel"]), "--events", str(f["events"]), "--rate", "1000",
        "--label", case.truth["name"], "--out", str(run),
    ]  # fmt: skip
    ana = [
        "analyze",
        str(run),
        "--out",
        str(analysis),
        "--matrix",
        str(f["matrix"]),
        "--workers",
        "1",
        "--no-progress",
    ]
    return imp, ana


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    s = sub.add_parser("steady", help="issue 21: steady points under a noise case")
    s.add_argument("--case", default="white", choices=["white", "ar1", "common", "mode"])
    s.add_argument("--points", type=int, default=100, help="wind-on points (at least)")
    s.add_argument("--rig", default="flat")
    s.add_argument("--duration-s", type=float, default=3.0)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True)
    o = sub.add_parser("oscillation", help="issue 22: the forced-oscillation points")
    o.add_argument("--seed", type=int, default=0)
    o.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    if a.what == "steady":
        c = steady_case(a.out, a.case, a.points, rig=a.rig, duration_s=a.duration_s, seed=a.seed)
    else:
        c = oscillation_case(a.out, seed=a.seed)
    print(f"wrote {c.folder}: {len(c.truth['points'])} points, {c.truth['n_samples']} samples")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
