"""Planning the motion of a test matrix's oscillation points before the tunnel (``cdpr plan``).

For every ``oscillation`` and ``oscillation_tare`` point (docs/dynamic_tests.md):

- the commanded pose trajectory (:func:`cdpr.analysis.motion.oscillation_motion`: ramp up over
  the settling cycles, the cycles analysed, one ramp-down cycle) sampled at ``rate_hz``, and by
  inverse kinematics each cable's length, speed and acceleration (the table the rig's motion
  controller follows);
- the feed-forward tensions over the motion from the dynamic tension distribution
  (:func:`cdpr.analysis.motion.motion_tensions`: gravity, the rig file's mass and inertia, and the
  expected aerodynamic load of the matrix's ``[aero_estimate]`` with its dynamic derivatives, wind
  on), their smallest margins to ``t_min`` and ``t_max``, and the cable speeds and accelerations
  against the winch limits of the rig file (``max_speed_mps``, ``max_accel_mps2``);
- the frequency and its first harmonics against the rig's natural modes (the stiffness model of
  ``cdpr rig show``, under the feed-forward tensions, over a cycle at full amplitude).

A point is **refused** (one line naming it and the reason) when no tension distribution keeps every
cable within its limits at some instant (slack or over t_max), a cable's speed or acceleration
exceeds its winch's limit, or the fundamental lies within ``mode_band`` of a mode; it is
**flagged** when a harmonic (2nd and above) lies within ``mode_band`` of a mode, when no
oscillation tare serves it (``no_inertia_tare``), or when the aero load is the aero model's
defaults (``aero_estimate_default``: the matrix has no ``[aero_estimate]``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.motion import (
    CableMotion,
    Motion,
    MotionTensions,
    Oscillation,
    cable_motion,
    motion_tensions,
    oscillation_motion,
)
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.analysis.stiffness import (
    HarmonicCheck,
    dominant_coordinates,
    harmonic_check,
    mass_matrix,
    modes_at,
)
from cdpr.analysis.tension import distribute
from cdpr.daq.aero_model import AeroModel, aero_from_mapping

from .campaign import TestMatrix, TestPoint

FloatArray = NDArray[np.float64]

DEFAULT_RATE_HZ = 500.0
"""Rows per second of the controller's table (``--rate-hz``)."""
DEFAULT_HARMONICS = 3
"""Harmonics of the motion's frequency checked against the modes (``--harmonics``)."""
DEFAULT_MODE_BAND = 0.10
"""A harmonic within this fraction of a mode's frequency meets it (``--mode-band``)."""
MODE_PHASES = 36
"""Phases of a full-amplitude cycle at which the modes are computed (their range over it)."""
DOF_NAMES = ("x", "y", "z", "roll", "pitch", "yaw")


@dataclass(frozen=True)
class ModeCheck:
    """The rig's modes over a cycle (``lo_Hz``, ``hi_Hz`` (6,) each mode's range; ``dof`` its
    dominant coordinate) and the motion's harmonics against them (:class:`HarmonicCheck`)."""

    lo_Hz: FloatArray
    hi_Hz: FloatArray
    dof: tuple[str, ...]
    harmonics: HarmonicCheck


@dataclass
class PointPlan:
    """The plan of one oscillation point: its times from the motion's start ``t_s`` (n,), the
    commanded motion, the cables' motion, the feed-forward tensions, the expected aero wrench
    (n, 6), the modes check, and the verdict: ``refused`` (reasons, the first said in one line),
    ``flags`` (warnings), ``notes``; ``numbers`` the summary's values."""

    point: TestPoint
    oscillation: Oscillation
    t_s: FloatArray
    motion: Motion
    cables: CableMotion
    tensions: MotionTensions
    aero_O: FloatArray
    needed_N: FloatArray
    modes: ModeCheck | None
    refused: list[str] = field(default_factory=list)
    flags: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    numbers: dict[str, Any] = field(default_factory=dict)

    @property
    def verdict(self) -> str:
        return "refused" if self.refused else ("flagged" if self.flags else "ok")


def aero_estimate(matrix: TestMatrix) -> tuple[AeroModel, bool]:
    """The aero model the plan loads the motion with: ``[aero_estimate]`` over the aero model's
    defaults, reference geometry and MRP from ``[model]``; and whether the matrix gave one."""
    m = matrix.model
    data = dict(matrix.aero_estimate or {})
    data.update(c_ref_m=m.chord_m, b_ref_m=m.span_m, s_ref_m2=m.area_m2, mrp_P_m=list(m.mrp_P_m))
    return aero_from_mapping(
        data, matrix.source, key="aero_estimate"
    ), matrix.aero_estimate is not None


def _phase_deg(t_s: FloatArray, f: float) -> FloatArray:
    return np.asarray(np.mod(360.0 * f * t_s, 360.0))


def plan_point(
    rig: Rig,
    point: TestPoint,
    aero: AeroModel,
    aero_given: bool = True,
    rate_hz: float = DEFAULT_RATE_HZ,
    method: str = "exact",
    n_harmonics: int = DEFAULT_HARMONICS,
    mode_band: float = DEFAULT_MODE_BAND,
) -> PointPlan:
    """Plan one oscillation point (see the module docstring)."""
    osc = point.oscillation
    if osc is None:
        raise ValueError(f"{point.label}: not an oscillation point")
    f = osc.frequency_Hz
    names = rig.cable_names
    n = int(math.floor(osc.duration_s * rate_hz + 1e-9)) + 1
    t = np.arange(n) / rate_hz
    pos = rig.reference_position_O_m if point.position_O_m is None else point.position_O_m
    mean = np.array([*pos, *point.euler_rad], dtype=np.float64)
    mo = oscillation_motion(t, mean, osc)
    cab = cable_motion(rig.anchors_O_m, rig.attach_P_m, mo.pose, mo.rate, mo.accel)
    wind = np.full(n, point.airspeed_mps)
    W = aero.wrench_moving_O(wind, mo.pose, mo.rate, mo.accel)
    mt = motion_tensions(rig, mo, W, method)
    res = mt.result
    T = np.asarray(res.tensions_N)
    ok = np.asarray(res.feasible, dtype=bool)
    needed = np.full_like(T, np.nan)
    plan = PointPlan(point, osc, t, mo, cab, mt, W, needed, None)
    nums = plan.numbers
    nums.update(
        point=point.label, kind=point.kind, axis=osc.axis,
        amplitude=osc.amplitude, amplitude_unit="rad" if osc.angular else "m",
        amplitude_shown=(f"{math.degrees(osc.amplitude):g} deg" if osc.angular
                         else f"{osc.amplitude * 1e3:g} mm"),
        frequency_Hz=f, cycles=osc.cycles, settling_cycles=osc.settling_cycles,
        airspeed_mps=point.airspeed_mps, aoa_deg=point.aoa_deg, sideslip_deg=point.sideslip_deg,
        duration_s=osc.duration_s, rows=n, method=res.method,
    )  # fmt: skip

    # -- tensions within the limits at every instant ----------------------------------------
    bad = np.flatnonzero(~ok)
    nums["infeasible_fraction"] = bad.size / n
    if bad.size:
        R = rotation_from_euler(mo.pose[bad, 3:])
        A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, mo.pose[bad, :3], R)
        cf = np.asarray(
            distribute(
                "closed-form", A, mt.cable_wrench_O[bad], rig.t_min_N, rig.t_max_N
            ).tensions_N
        )
        needed[bad] = cf
        low = rig.t_min_N - cf
        high = cf - rig.t_max_N
        worst_low, worst_high = float(low.max()), float(high.max())
        slack = worst_low >= worst_high
        k, c = np.unravel_index(np.argmax(low if slack else high), low.shape)
        i = int(bad[k])
        what = "slack" if slack else "over t_max"
        limit = f"< t_min {rig.t_min_N[c]:g} N" if slack else f"> t_max {rig.t_max_N[c]:g} N"
        plan.refused.append(
            f"{what}: no tensions within [t_min, t_max] over {100 * bad.size / n:.0f} % of the "
            f"motion (from t = {t[bad[0]]:.3f} s); at its worst (t = {t[i]:.3f} s, phase "
            f"{_phase_deg(t[i : i + 1], f)[0]:.0f} deg) {names[c]} would need {cf[k, c]:.1f} N "
            f"{limit} (closed form, min |T - T_mid|)"
        )
    good = np.flatnonzero(ok)
    if good.size:
        lo_m = T[good] - rig.t_min_N
        hi_m = rig.t_max_N - T[good]
        k, c = np.unravel_index(np.argmin(lo_m), lo_m.shape)
        k2, c2 = np.unravel_index(np.argmin(hi_m), hi_m.shape)
        nums.update(
            t_min_margin_N=_at_least_zero(lo_m[k, c]), t_min_margin_cable=names[c],
            t_min_margin_t_s=float(t[good[k]]),
            t_max_margin_N=_at_least_zero(hi_m[k2, c2]), t_max_margin_cable=names[c2],
            t_max_margin_t_s=float(t[good[k2]]),
            tension_min_N=float(T[good].min()), tension_max_N=float(T[good].max()),
        )  # fmt: skip
    else:
        nums.update(t_min_margin_N=math.nan, t_max_margin_N=math.nan)

    # -- cable speeds and accelerations against the winches --------------------------------
    for what, arr, lim, unit in (
        ("speed", cab.speed_mps, rig.cable_max_speed_mps, "m/s"),
        ("accel", cab.accel_mps2, rig.cable_max_accel_mps2, "m/s^2"),
    ):
        peak = np.abs(arr).max(axis=0)
        c = int(np.argmax(peak / np.where(np.isfinite(lim), lim, 1.0)))
        nums[f"max_cable_{what}"] = float(peak[c])
        nums[f"max_cable_{what}_cable"] = names[c]
        nums[f"cable_{what}_limit"] = float(lim[c])
        over = np.flatnonzero(peak > lim)
        if over.size:
            j = int(over[np.argmax(peak[over] / lim[over])])
            plan.refused.append(
                f"cable {what}: {names[j]} reaches {peak[j]:.3g} {unit} > its winch's "
                f"{lim[j]:g} {unit}"
            )
    if not np.all(np.isfinite(rig.cable_max_speed_mps) & np.isfinite(rig.cable_max_accel_mps2)):
        plan.notes.append(
            "cable speed and acceleration not checked: no max_speed_mps / max_accel_mps2 "
            "in the rig file"
        )
    nums["cable_stroke_m"] = float((cab.length_m.max(axis=0) - cab.length_m.min(axis=0)).max())

    # -- the motion's harmonics against the rig's modes --------------------------------------
    plan.modes = _mode_check(rig, mean, osc, aero, point.airspeed_mps, method, n_harmonics,
                             mode_band, plan)  # fmt: skip

    if point.kind == "oscillation":
        if not point.inertia_tare:
            plan.flags.append("no_inertia_tare")
        if not aero_given:
            plan.flags.append("aero_estimate_default")
    nums["inertia_tare"] = point.inertia_tare
    nums["peak_inertia_wrench"] = float(np.abs(mt.inertia_O).max())
    nums["peak_aero_wrench"] = float(np.abs(W).max())
    return plan


def _at_least_zero(x: float) -> float:
    """A margin; a sample at its limit within the solver's tolerance (1e-6 N) shows 0."""
    return max(float(x), 0.0) if float(x) > -1e-6 else float(x)


def _mode_check(
    rig: Rig,
    mean: FloatArray,
    osc: Oscillation,
    aero: AeroModel,
    airspeed: float,
    method: str,
    n_harmonics: int,
    band: float,
    plan: PointPlan,
) -> ModeCheck | None:
    """Modes over a full-amplitude cycle under its feed-forward tensions, and the harmonics."""
    f = osc.frequency_Hz
    tau = osc.window_s[0] + np.arange(MODE_PHASES) / (MODE_PHASES * f)
    mo = oscillation_motion(tau, mean, osc)
    W = aero.wrench_moving_O(np.full(tau.size, airspeed), mo.pose, mo.rate, mo.accel)
    mt = motion_tensions(rig, mo, W, method)
    ok = np.asarray(mt.result.feasible, dtype=bool)
    if not ok.any():
        plan.notes.append("modes not computed: no feasible tensions over the cycle")
        return None
    R = rotation_from_euler(mo.pose[ok, 3:])
    _, modes = modes_at(rig, mo.pose[ok, :3], R, np.asarray(mt.result.tensions_N)[ok])
    fr = modes.frequencies_Hz
    if np.any(modes.unstable):
        plan.refused.append(
            "unstable: the cables' stiffness does not hold the platform at some phase (a mode "
            "with a negative stiffness)"
        )
        return None
    M = mass_matrix(rig.mass_kg, rig.com_P_m, rig.inertia_P_kgm2, R[0])
    share = dominant_coordinates(modes.shapes[0], M)
    dof = tuple(DOF_NAMES[int(j)] for j in np.argmax(share, axis=0))
    lo, hi = fr.min(axis=0), fr.max(axis=0)
    hc = harmonic_check(f, lo, hi, n_harmonics, band)
    mc = ModeCheck(lo, hi, dof, hc)
    nums = plan.numbers
    nums["modes_Hz"] = " ".join(
        f"{a:.2f}" if abs(b - a) < 0.005 else f"{a:.2f}-{b:.2f}"
        for a, b in zip(lo, hi, strict=True)
    )
    j = int(np.argmin(hc.distance_rel))
    nums["nearest_harmonic"] = int(j + 1)
    nums["nearest_harmonic_Hz"] = float(hc.harmonic_Hz[j])
    nums["nearest_mode"] = int(hc.mode[j] + 1)
    nums["nearest_mode_Hz"] = float(lo[hc.mode[j]])
    nums["nearest_mode_distance"] = float(hc.distance_rel[j])
    for h in np.flatnonzero(hc.near):
        k = int(hc.mode[h])
        text = (
            f"harmonic {h + 1} ({hc.harmonic_Hz[h]:.4g} Hz) is within {100 * band:g} % of mode "
            f"{k + 1} ({dof[k]}, {_mode_range(lo[k], hi[k])}): {100 * hc.distance_rel[h]:.1f} % away"
        )
        if h == 0:
            plan.refused.append("resonance: the " + text.replace("harmonic 1", "frequency", 1))
        else:
            if "harmonic_near_mode" not in plan.flags:
                plan.flags.append("harmonic_near_mode")
            plan.notes.append(text)
    return mc


def _mode_range(lo: float, hi: float) -> str:
    return f"{lo:.2f} Hz" if abs(hi - lo) < 0.005 else f"{lo:.2f}-{hi:.2f} Hz"


def plan_matrix(
    matrix: TestMatrix,
    rig: Rig,
    rate_hz: float = DEFAULT_RATE_HZ,
    method: str = "exact",
    n_harmonics: int = DEFAULT_HARMONICS,
    mode_band: float = DEFAULT_MODE_BAND,
    points: Sequence[str] | None = None,
) -> list[PointPlan]:
    """Plans of the matrix's oscillation points in run order (``points``: only these labels)."""
    aero, given = aero_estimate(matrix)
    out = []
    for p in matrix.points:
        if p.oscillation is None or (points is not None and p.label not in points):
            continue
        out.append(plan_point(rig, p, aero, given, rate_hz, method, n_harmonics, mode_band))
    return out


def refusal_line(plan: PointPlan) -> str:
    """The one line that refuses a point: its label and the first reason (others counted)."""
    more = f" (and {len(plan.refused) - 1} more: see the plan)" if len(plan.refused) > 1 else ""
    return f"{plan.point.label}: {plan.refused[0]}{more}"


def check_matrix_motion(matrix: TestMatrix, rig: Rig, method: str = "exact") -> None:
    """Before anything is recorded: plan every oscillation point (checks only, at 100 samples a
    cycle) and raise ``ConfigError(matrix, "points (<label>)", "refused by the motion plan: ...")``
    for the first one refused."""
    aero, given = aero_estimate(matrix)
    for p in matrix.points:
        osc = p.oscillation
        if osc is None:
            continue
        plan = plan_point(rig, p, aero, given, rate_hz=100.0 * osc.frequency_Hz, method=method)
        if plan.refused:
            raise ConfigError(
                matrix.source,
                f"points ({p.label})",
                f"refused by the motion plan (cdpr plan): {plan.refused[0]}",
            )


def summary_line(plan: PointPlan) -> str:
    """One line per point for stdout: verdict, margins, cable speed/acceleration, modes."""
    n = plan.numbers
    if plan.refused:
        return f"refused: {refusal_line(plan)}"
    lim = "" if math.isfinite(n["cable_speed_limit"]) else " (no winch limits: not checked)"
    text = (
        f"{plan.verdict}: {plan.point.label}: {n['axis']} {n['amplitude_shown']} at "
        f"{n['frequency_Hz']:g} Hz, {n['airspeed_mps']:g} m/s: tension margins "
        f"{n['t_min_margin_N']:.1f} N to t_min ({n['t_min_margin_cable']}), "
        f"{n['t_max_margin_N']:.1f} N to t_max ({n['t_max_margin_cable']}); cable speed "
        f"{n['max_cable_speed']:.3g} m/s, acceleration {n['max_cable_accel']:.3g} m/s^2{lim}"
    )
    if plan.modes is not None:
        text += (
            f"; nearest: harmonic {n['nearest_harmonic']} ({n['nearest_harmonic_Hz']:.3g} Hz) "
            f"and mode {n['nearest_mode']} ({n['nearest_mode_Hz']:.2f} Hz), "
            f"{100 * n['nearest_mode_distance']:.0f} % away"
        )
    if plan.flags:
        text += f"; flags: {' '.join(plan.flags)}"
    return text


# --------------------------------------------------------------------------------------------
# outputs
# --------------------------------------------------------------------------------------------
def table_columns(rig: Rig) -> list[str]:
    """Columns of the controller's table: time, pose, each cable's length, speed and
    acceleration, the feed-forward tensions."""
    cols = ["t_s", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad"]
    for pre, unit in (("L", "m"), ("Ldot", "mps"), ("Lddot", "mps2"), ("T", "N")):
        cols += [f"{pre}_{c}_{unit}" for c in rig.cable_names]
    return cols


def write_controller_table(
    plan: PointPlan, rig: Rig, path: str | os.PathLike[str], header: dict[str, Any]
) -> None:
    """The controller's table of one point (CSV, ``# key: value`` lines first), written whole."""
    from .config import atomic_output

    data = np.column_stack(
        [plan.t_s, plan.motion.pose, plan.cables.length_m, plan.cables.speed_mps,
         plan.cables.accel_mps2, plan.tensions.result.tensions_N]
    )  # fmt: skip
    with atomic_output(path) as fh:
        for k, v in header.items():
            fh.write(f"# {k}: {v}\n")
        fh.write(",".join(table_columns(rig)) + "\n")
        np.savetxt(fh, data, delimiter=",", fmt="%.9g")


SUMMARY_COLUMNS = (
    "point", "kind", "verdict", "reason", "flags", "axis", "amplitude", "amplitude_unit",
    "frequency_Hz", "cycles", "settling_cycles", "airspeed_mps", "aoa_deg", "sideslip_deg",
    "duration_s", "inertia_tare", "t_min_margin_N", "t_min_margin_cable", "t_max_margin_N",
    "t_max_margin_cable", "tension_min_N", "tension_max_N", "infeasible_fraction",
    "max_cable_speed", "max_cable_speed_cable", "cable_speed_limit", "max_cable_accel",
    "max_cable_accel_cable", "cable_accel_limit", "cable_stroke_m", "modes_Hz",
    "nearest_harmonic", "nearest_harmonic_Hz", "nearest_mode", "nearest_mode_Hz",
    "nearest_mode_distance", "peak_inertia_wrench", "peak_aero_wrench", "notes", "table",
)  # fmt: skip
"""Columns of ``summary.csv`` (speeds in m/s, accelerations in m/s^2, margins in N)."""


def summary_rows(plans: Sequence[PointPlan], tables: dict[str, str]) -> list[dict[str, Any]]:
    rows = []
    for p in plans:
        r = {k: p.numbers.get(k, "") for k in SUMMARY_COLUMNS}
        r.update(
            verdict=p.verdict,
            reason=" | ".join(p.refused),
            flags=" ".join(p.flags),
            notes=" | ".join(p.notes),
            table=tables.get(p.point.label, ""),
        )
        rows.append(r)
    return rows


def plot_point(plan: PointPlan, rig: Rig, path: str | os.PathLike[str], band: float) -> None:
    """Tensions over a full-amplitude cycle against the limits (the needed least-norm tensions
    dashed where none fits), and the motion's harmonics against the rig's modes."""
    from .plotting import png_figure

    osc = plan.oscillation
    f = osc.frequency_Hz
    t0 = osc.window_s[0]
    sel = np.flatnonzero((plan.t_s >= t0) & (plan.t_s < t0 + 1.0 / f))
    ph = _phase_deg(plan.t_s[sel] - t0, f)
    T = np.asarray(plan.tensions.result.tensions_N)[sel]
    ok = np.asarray(plan.tensions.result.feasible)[sel]
    with png_figure(path, 1, 2, size=(11.0, 4.8), width_ratios=[1.6, 1.0]) as (_, axes):
        ax = axes[0, 0]
        for c, name in enumerate(rig.cable_names):
            y = np.where(ok, T[:, c], np.nan)
            line = ax.plot(ph, y, lw=1.2, label=name)[0]
            need = plan.needed_N[sel, c]
            if np.isfinite(need).any():
                ax.plot(ph, need, ls="--", lw=1.0, color=line.get_color())
        ax.axhline(float(rig.t_min_N.min()), color="k", lw=1.0)
        ax.axhline(float(rig.t_max_N.max()), color="k", lw=1.0)
        ax.axhspan(float(rig.t_min_N.min()) - 1e4, float(rig.t_min_N.min()), color="r", alpha=0.08)
        ax.axhspan(float(rig.t_max_N.max()), float(rig.t_max_N.max()) + 1e4, color="r", alpha=0.08)
        lo = np.nanmin(np.concatenate([T[ok].ravel(), plan.needed_N[sel].ravel(), rig.t_min_N]))
        hi = np.nanmax(np.concatenate([T[ok].ravel(), plan.needed_N[sel].ravel(), rig.t_max_N]))
        ax.set_ylim(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo))
        ax.set_xlim(0, 360)
        ax.set_xticks(range(0, 361, 90))
        ax.set_xlabel("phase of the motion (deg, one cycle at full amplitude)")
        ax.set_ylabel("feed-forward tension (N)")
        n = plan.numbers
        margin = (
            f"margins {n['t_min_margin_N']:.1f} N to t_min, {n['t_max_margin_N']:.1f} N to t_max"
            if np.isfinite(n.get("t_min_margin_N", np.nan))
            else "no feasible tensions"
        )
        ax.set_title(f"{plan.point.label}: {plan.verdict}\n{margin}", fontsize=9)
        ax.legend(fontsize=6, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.16))
        ax = axes[0, 1]
        mc = plan.modes
        if mc is None:
            ax.text(0.5, 0.5, "modes not computed", ha="center", transform=ax.transAxes)
        else:
            for k in range(mc.lo_Hz.size):
                ax.axvspan(mc.lo_Hz[k] * (1 - band), mc.hi_Hz[k] * (1 + band), color="0.85")
                ax.axvspan(mc.lo_Hz[k], max(mc.hi_Hz[k], mc.lo_Hz[k] * 1.002), color="0.3")
                ax.text(mc.lo_Hz[k], 0.93 - 0.07 * (k % 3), f"{k + 1} {mc.dof[k]}", fontsize=7)
            for h, fh in enumerate(mc.harmonics.harmonic_Hz):
                near = bool(mc.harmonics.near[h])
                ax.axvline(fh, color="r" if near else "C0", lw=1.5)
                ax.text(fh, 0.05 + 0.1 * h, f" {h + 1}f", color="r" if near else "C0", fontsize=8)
            ax.set_xscale("log")
            ax.set_ylim(0, 1)
            ax.set_yticks([])
            ax.set_xlabel("frequency (Hz)")
            ax.set_title(f"harmonics of {f:g} Hz vs modes (grey: +-{100 * band:g} %)", fontsize=9)


def _header(matrix: TestMatrix, rig: Rig, options: dict[str, Any]) -> dict[str, Any]:
    from . import __version__
    from .config import file_sha256

    return {
        "cdpr": f"plan {__version__}",
        "matrix": f"{matrix.source} sha256={file_sha256(matrix.source)}",
        "rig": f"{matrix.rig_path} sha256={file_sha256(matrix.rig_path)}",
        **options,
    }


def write_plan(
    plans: Sequence[PointPlan],
    matrix: TestMatrix,
    rig: Rig,
    out: str | os.PathLike[str],
    options: dict[str, Any],
    band: float,
    plots: bool = True,
) -> dict[str, Path]:
    """Write the plan into ``out``: per accepted point ``<label>.csv`` (the controller's table),
    per point ``<label>.png``, and ``summary.csv`` and ``summary.md``; returns the paths."""
    import pandas as pd

    from .config import atomic_output, write_table

    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    head = _header(matrix, rig, options)
    written: dict[str, Path] = {}
    tables: dict[str, str] = {}
    for p in plans:
        label = p.point.label
        if not p.refused:
            path = folder / f"{label}.csv"
            write_controller_table(p, rig, path, {
                **head, "point": label,
                "units": "t_s from the motion's start (the point's start event); pose m, rad "
                         "(Z-Y-X); L cable length platform point to anchor (m), Ldot m/s, "
                         "Lddot m/s^2, T feed-forward tension N",
            })  # fmt: skip
            tables[label] = path.name
            written[f"{label}.csv"] = path
        if plots:
            png = folder / f"{label}.png"
            plot_point(p, rig, png, band)
            written[f"{label}.png"] = png
    rows = summary_rows(plans, tables)
    df = pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
    write_table(folder / "summary.csv", df, head)
    written["summary.csv"] = folder / "summary.csv"
    with atomic_output(folder / "summary.md") as fh:
        fh.write(summary_markdown(plans, head, band))
    written["summary.md"] = folder / "summary.md"
    return written


def summary_markdown(plans: Sequence[PointPlan], head: dict[str, Any], band: float) -> str:
    """The plan as a page to read: refused and flagged points first, then one section per point."""
    out = ["# Motion plan", ""]
    out += [f"- {k}: `{v}`" for k, v in head.items()]
    refused = [p for p in plans if p.refused]
    flagged = [p for p in plans if not p.refused and p.flags]
    out += ["", f"{len(plans)} oscillation points: {len(plans) - len(refused) - len(flagged)} ok, "
            f"{len(flagged)} flagged, {len(refused)} refused.", ""]  # fmt: skip
    if refused:
        out += ["## Refused", ""] + [f"- {refusal_line(p)}" for p in refused] + [""]
    if flagged:
        out += ["## Flagged", ""]
        out += [f"- {p.point.label}: {' '.join(p.flags)}" for p in flagged] + [""]
    out += [
        "| point | verdict | motion | airspeed | margin to t_min | margin to t_max | cable speed "
        "| cable accel | nearest harmonic / mode |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for p in plans:
        n = p.numbers
        near = (
            f"{n['nearest_harmonic']}f = {n['nearest_harmonic_Hz']:.3g} Hz / mode "
            f"{n['nearest_mode']} {n['nearest_mode_Hz']:.2f} Hz ({100 * n['nearest_mode_distance']:.0f} %)"
            if "nearest_mode" in n
            else "-"
        )
        out.append(
            f"| {p.point.label} | {p.verdict} | {n['axis']} {n['amplitude_shown']} at "
            f"{n['frequency_Hz']:g} Hz | {n['airspeed_mps']:g} m/s | "
            f"{n['t_min_margin_N']:.1f} N | {n['t_max_margin_N']:.1f} N | "
            f"{n['max_cable_speed']:.3g} m/s | {n['max_cable_accel']:.3g} m/s^2 | {near} |"
        )
    out.append("")
    for p in plans:
        out += [f"## {p.point.label}", "", f"![{p.point.label}]({p.point.label}.png)", ""]
        out += [f"- refused: {r}" for r in p.refused]
        out += [f"- flag: {f}" for f in p.flags]
        out += [f"- {t}" for t in p.notes]
        if p.modes is not None:
            mc = p.modes
            out.append(
                "- modes over the cycle: "
                + ", ".join(
                    f"{k + 1} {mc.dof[k]} {_mode_range(a, b)}"
                    for k, (a, b) in enumerate(zip(mc.lo_Hz, mc.hi_Hz, strict=True))
                )  # fmt: skip
            )
            out.append(
                "- harmonics: "
                + ", ".join(
                    f"{h + 1}f = {fh:.3g} Hz ({100 * d:.0f} % from mode {int(k) + 1})"
                    for h, (fh, d, k) in enumerate(
                        zip(
                            mc.harmonics.harmonic_Hz,
                            mc.harmonics.distance_rel,
                            mc.harmonics.mode,
                            strict=True,
                        )
                    )
                )
            )
        out.append("")
    return "\n".join(out)
