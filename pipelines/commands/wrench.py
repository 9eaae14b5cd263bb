"""``cdpr wrench``: recover the external (aerodynamic) wrench from measured tensions and poses.

Inputs: a rig file; a pose CSV with ``x_m, y_m, z_m, roll_rad, pitch_rad, yaw_rad`` (P in {O}, Z-Y-X
Euler angles); a tension CSV with one ``T_<cable>_N`` column per cable of the rig and one row per
pose; optionally wind-off tare tensions (same columns, one row for all poses or one per pose).

Methods: with ``--tare`` the tare method ``W_ext = A (T0 - Tw)`` (paper eq. 7), otherwise the
absolute method ``W_ext = -A Tw - G`` from the rig's mass model.  ``--dynamic`` also adds back the
inertia wrench ``M qdd + C`` (Newton: ``A T + G + W_ext = M qdd + C``) computed from the pose time
series (needs an integer ``t_ns`` column).

Output: the pose table's columns, then ``fx_N, fy_N, fz_N, mx_Nm, my_Nm, mz_Nm`` (W_ext on the
platform at P, {O} axes, moments about P) and their standard deviations ``sd_fx_N ... sd_mz_Nm``
from the linearised noise model (load-cell noise ``--tension-sigma-N`` on every tension, pose noise
``--pose-sigma-m`` on each position coordinate and ``--pose-sigma-rad`` on each Euler angle).
"""

from __future__ import annotations

import argparse
import math
import sys

from .analyze import add_geometry_arguments

DEFAULT_TENSION_SIGMA_N = 0.05
DEFAULT_POSE_SIGMA_M = 0.5e-3
DEFAULT_POSE_SIGMA_RAD = math.radians(0.1)


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "wrench",
        help="external wrench (and its standard deviation) from tensions and poses",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--rig", required=True, help="rig file (TOML)")
    p.add_argument("--poses", required=True, help="pose CSV (one row per sample)")
    p.add_argument("--tensions", required=True, help="wind-on tension CSV (one row per pose)")
    p.add_argument("--tare", help="wind-off tension CSV at the same poses (tare method)")
    p.add_argument(
        "--tension-sigma-N",
        dest="tension_sigma_N",
        type=float,
        default=DEFAULT_TENSION_SIGMA_N,
        help=f"load-cell noise, standard deviation per tension (N, default {DEFAULT_TENSION_SIGMA_N})",
    )
    p.add_argument(
        "--pose-sigma-m",
        dest="pose_sigma_m",
        type=float,
        default=DEFAULT_POSE_SIGMA_M,
        help="pose position noise, standard deviation per axis (m, default 0.0005: the paper's camera)",
    )
    p.add_argument(
        "--pose-sigma-rad",
        dest="pose_sigma_rad",
        type=float,
        default=DEFAULT_POSE_SIGMA_RAD,
        help="pose angle noise, standard deviation per Euler angle (rad, default 0.1 deg)",
    )
    p.add_argument(
        "--mass-sd-rel",
        dest="mass_sd_rel",
        type=float,
        default=0.0,
        help="absolute method: relative sd of the rig file's mass, in σ (default 0)",
    )
    p.add_argument(
        "--com-sd-m",
        dest="com_sd_m",
        type=float,
        default=0.0,
        help="absolute method: sd of the rig file's centre of mass per axis (m, default 0)",
    )
    p.add_argument(
        "--dynamic",
        action="store_true",
        help="add M qdd + C from the pose time series back (Newton-Euler; needs a t_ns column)",
    )
    aero = p.add_argument_group("aerodynamic coefficients (optional)")
    aero.add_argument("--airspeed-mps", dest="airspeed_mps", type=float, help="free-stream speed")
    aero.add_argument("--density-kgpm3", dest="density_kgpm3", type=float, help="air density")
    aero.add_argument("--pressure-Pa", dest="pressure_Pa", type=float, help="static pressure")
    aero.add_argument("--temperature-K", dest="temperature_K", type=float, help="air temperature")
    add_geometry_arguments(aero)
    aero.add_argument(
        "--nose-P",
        dest="nose_P",
        type=float,
        nargs=3,
        default=(-1.0, 0.0, 0.0),
        metavar=("X", "Y", "Z"),
        help="model nose direction in {P} (default -1 0 0: upstream)",
    )
    aero.add_argument(
        "--up-P",
        dest="up_P",
        type=float,
        nargs=3,
        default=(0.0, 0.0, 1.0),
        metavar=("X", "Y", "Z"),
        help="model up direction in {P} (default 0 0 1)",
    )
    p.add_argument("--out", required=True, help="output wrench CSV")
    p.set_defaults(func=run)


def _aero_setup(args: argparse.Namespace) -> tuple[float, str, float] | None:
    """Dynamic pressure (Pa), a provenance note and the density (kg/m^3), or None without
    ``--airspeed-mps``."""
    from cdpr.analysis.aero import dynamic_pressure
    from cdpr.analysis.errors import ConfigError
    from cdpr.analysis.flow import air_density

    given = [
        f
        for f in ("density_kgpm3", "pressure_Pa", "temperature_K", "area_m2", "span_m", "chord_m")
        if getattr(args, f) is not None
    ]
    if args.airspeed_mps is None:
        if given:
            flag = "--" + given[0].replace("_", "-")
            raise ConfigError("command line", flag, "needs --airspeed-mps")
        return None
    for f in ("airspeed_mps", "area_m2", "span_m", "chord_m"):
        v = getattr(args, f)
        flag = "--" + f.replace("_", "-")
        if v is None:
            raise ConfigError("command line", flag, "required for the aerodynamic coefficients")
        if not (math.isfinite(v) and v > 0):
            raise ConfigError("command line", flag, f"expected a finite value > 0, got {v}")
    if args.density_kgpm3 is not None:
        if args.pressure_Pa is not None or args.temperature_K is not None:
            raise ConfigError(
                "command line", "--density-kgpm3", "give either it or --pressure-Pa/--temperature-K"
            )
        rho = args.density_kgpm3
        if not (math.isfinite(rho) and rho > 0):
            raise ConfigError("command line", "--density-kgpm3", f"expected > 0, got {rho}")
        note = f"rho {rho:g} kg/m^3"
    else:
        if args.pressure_Pa is None or args.temperature_K is None:
            raise ConfigError(
                "command line",
                "--density-kgpm3",
                "required (or both --pressure-Pa and --temperature-K)",
            )
        for flag, v in (
            ("--pressure-Pa", args.pressure_Pa),
            ("--temperature-K", args.temperature_K),
        ):
            if not (math.isfinite(v) and v > 0):
                raise ConfigError("command line", flag, f"expected a finite value > 0, got {v}")
        rho = float(air_density(args.pressure_Pa, args.temperature_K))
        note = (
            f"rho {rho:.6g} kg/m^3 from p {args.pressure_Pa:g} Pa, T {args.temperature_K:g} K "
            "(ideal gas, dry air)"
        )
    q = float(dynamic_pressure(rho, args.airspeed_mps))
    note = (
        f"V {args.airspeed_mps:g} m/s, {note}, q {q:.6g} Pa; S {args.area_m2:g} m^2, "
        f"b {args.span_m:g} m, c {args.chord_m:g} m; MRP_P {list(args.mrp_P_m)} m; "
        f"nose_P {list(args.nose_P)}, up_P {list(args.up_P)}; AIAA body/wind axes"
    )
    return q, note, rho


def run(args: argparse.Namespace) -> int:

    import numpy as np

    from cdpr.analysis.conventions import COEFFICIENTS, WRENCH_COLUMNS
    from cdpr.analysis.errors import ConfigError
    from cdpr.analysis.kinematics import cable_vectors
    from cdpr.analysis.reduction import POSE, POSE_COV, WRENCH, new_points, run_stages
    from cdpr.analysis.rotations import rotation_from_euler
    from cdpr.analysis.stages import ReduceSettings, core_stages
    from cdpr.analysis.wrench import pose_derivatives

    from .. import __version__
    from ..config import file_sha256, load_rig, read_poses, read_tensions, write_table
    from .analyze import geometry_from_args

    for flag, v in (
        ("--tension-sigma-N", args.tension_sigma_N),
        ("--pose-sigma-m", args.pose_sigma_m),
        ("--pose-sigma-rad", args.pose_sigma_rad),
        ("--mass-sd-rel", args.mass_sd_rel),
        ("--com-sd-m", args.com_sd_m),
    ):
        if not (math.isfinite(v) and v >= 0):
            raise ConfigError("command line", flag, f"expected a finite value >= 0, got {v}")

    aero = _aero_setup(args)
    geometry = geometry_from_args(args, need=True) if aero is not None else None
    rig = load_rig(args.rig)
    table, poses = read_poses(args.poses)
    n = len(poses)
    Tw = read_tensions(args.tensions, rig)
    if len(Tw) != n:
        raise ConfigError(
            args.tensions,
            "rows",
            f"expected {n} rows (one per pose in {args.poses}), got {len(Tw)}",
        )
    T0 = read_tensions(args.tare, rig, n) if args.tare else None
    if T0 is not None and n > 1 and np.ptp(poses, axis=0).max() > 1e-9:
        import pandas as pd

        if len(pd.read_csv(args.tare, comment="#")) == 1:
            print(
                f"cdpr wrench: warning: one tare row in {args.tare} used for poses that differ; "
                "the tare method assumes T0 measured at each pose",
                file=sys.stderr,
            )

    lengths = np.linalg.norm(
        cable_vectors(
            rig.anchors_O_m, rig.attach_P_m, poses[:, :3], rotation_from_euler(poses[:, 3:])
        ),
        axis=-1,
    )
    bad = np.argwhere(lengths < 1e-9)
    if bad.size:
        i, j = bad[0]
        raise ConfigError(
            args.poses, f"row {i + 2}", f"cable {rig.cable_names[j]} has zero length at this pose"
        )

    motion = None
    if args.dynamic:
        if "t_ns" not in table.columns:
            raise ConfigError(args.poses, "column t_ns", "missing (needed by --dynamic)")
        t = table["t_ns"]
        if t.dtype.kind not in "iu":
            raise ConfigError(args.poses, "column t_ns", "expected integer nanoseconds")
        t_ns = t.to_numpy(dtype=np.int64)
        back = np.flatnonzero(np.diff(t_ns) <= 0)
        if back.size:
            raise ConfigError(args.poses, f"row {back[0] + 3}, column t_ns", "not increasing")
        if n < 3:
            raise ConfigError(args.poses, "rows", f"--dynamic needs at least 3 poses, got {n}")
        motion = pose_derivatives(poses, t_ns)

    # every row is a test point; with --tare, its tare is a wind-off point at the same pose, placed
    # next to it in time so that the core pairs them (rows 3i and 3i + 1)
    m = rig.n_cables
    pose_cov = np.diag([args.pose_sigma_m**2] * 3 + [args.pose_sigma_rad**2] * 3)
    t_cov = np.eye(m) * args.tension_sigma_N**2
    speed = args.airspeed_mps if aero is not None else np.nan
    rho = aero[2] if aero is not None else np.nan
    kind = ["wind_on"] * n
    T_all, q_all, start = Tw, poses, 3 * np.arange(n)
    if T0 is not None:
        kind += ["tare"] * n
        T_all = np.concatenate([Tw, np.broadcast_to(T0, Tw.shape)])
        q_all = np.concatenate([poses, poses])
        start = np.concatenate([start, start + 1])
    k = len(kind)
    pts = new_points(
        kind=kind,
        start_ns=start,
        tension_N=T_all,
        tension_cov_N2=np.broadcast_to(t_cov, (k, m, m)),
        **{POSE: q_all, POSE_COV: np.broadcast_to(pose_cov, (k, 6, 6))},
        airspeed_mps=np.full(k, speed),
        density_kgpm3=np.full(k, rho),
    )
    settings = ReduceSettings(
        allow_nominal_weight=True,
        prior_mass_rel_sd=args.mass_sd_rel,
        prior_com_sd_m=args.com_sd_m,
        fit_weight_model=False,
        tare_shares_pose=True,
    )
    if motion is not None and T0 is not None:  # the tare rows are at rest
        motion = (
            np.concatenate([motion[0], np.zeros_like(motion[0])]),
            np.concatenate([motion[1], np.zeros_like(motion[1])]),
        )
    res = run_stages(
        pts,
        core_stages(rig, geometry, settings, motion=motion, coefficients=aero is not None),  # type: ignore[arg-type]
    )
    rows = np.arange(n)
    W = res[WRENCH][rows]
    sd = np.sqrt(np.clip(np.diagonal(res.wrench_cov[rows], axis1=1, axis2=2), 0.0, None))

    out = table.copy()
    out["flags"] = res.flag_text()[:n]
    for k_, col in enumerate(WRENCH_COLUMNS):
        out[col] = W[:, k_]
    for k_, col in enumerate(WRENCH_COLUMNS):
        out[f"sd_{col}"] = sd[:, k_]
    if aero is not None:
        out["aoa_rad"] = res["aoa_rad"][rows]
        out["sideslip_rad"] = res["sideslip_rad"][rows]
        for name in COEFFICIENTS:
            out[name] = res[name][rows]
        for name in COEFFICIENTS:
            out[f"sd_{name}"] = res[f"sd_{name}"][rows]
    if T0 is not None:
        method = "tare: W_ext = A (T0 - Tw)"
    else:
        method = "absolute: W_ext = -A Tw - G with the rig file's mass (flag weight_nominal)"
    if motion is not None:
        method += " + (M qdd + C)"
    header = {
        "cdpr": f"wrench {__version__}",
        "rig": f"{args.rig} sha256={file_sha256(args.rig)}",
        "poses": f"{args.poses} sha256={file_sha256(args.poses)}",
        "tensions": f"{args.tensions} sha256={file_sha256(args.tensions)}",
        "tare": f"{args.tare} sha256={file_sha256(args.tare)}" if args.tare else "none",
        "method": method,
        "noise model": (
            f"tension sd {args.tension_sigma_N:g} N per cable"
            + (" (wind-on and tare)" if T0 is not None else "")
            + f"; pose sd {args.pose_sigma_m:g} m, {args.pose_sigma_rad:g} rad; linearised"
            + (
                f"; rig mass sd {args.mass_sd_rel:g} (relative), CoM sd {args.com_sd_m:g} m"
                if T0 is None
                else ""
            )
        ),
        "core": " -> ".join(st.name for st in res.steps),
        "units": "W_ext on the platform at P, {O} axes; N and N m; sd_* standard deviations",
    }
    if aero is not None:
        header["aero"] = aero[1]
    write_table(args.out, out, header)
    print(f"cdpr wrench: {n} poses, {method.split(':')[0]} method, wrote {args.out}")
    return 0
