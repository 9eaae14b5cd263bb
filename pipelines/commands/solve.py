"""``cdpr solve``: cable tensions for poses (and external wrenches) on a rig.

Input poses: CSV with ``x_m, y_m, z_m, roll_rad, pitch_rad, yaw_rad`` (Z-Y-X Euler angles, {O});
other columns (a ``t_ns`` or a label) are copied to the output.  Optional wrenches: CSV with
``fx_N, fy_N, fz_N, mx_Nm, my_Nm, mz_Nm`` (the external wrench W_ext on the platform at P, {O} axes),
one row for all poses or one per pose.  Output: the input columns, ``T_<cable>_N`` per cable,
``feasible`` (0/1), ``residual_N`` (|A T - w|), ``max_violation_N``; infeasible poses are kept and
flagged.  A pose where a cable has zero length or A loses rank is bad input (exit 2).
"""

from __future__ import annotations

import argparse
import sys

from cdpr.analysis.conventions import TENSION_METHODS


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("solve", help="cable tensions for poses and wrenches", description=__doc__)
    p.add_argument("--rig", required=True, help="rig file (TOML)")
    p.add_argument("--poses", help="pose CSV (default: the rig's reference pose)")
    p.add_argument("--wrench", help="external wrench CSV (default: none, wind off)")
    p.add_argument("--method", default="exact", choices=TENSION_METHODS)
    p.add_argument("--out", required=True, help="output tension CSV")
    p.add_argument("--strict", action="store_true", help="exit 2 if any pose is infeasible")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import pandas as pd

    from cdpr.analysis.conventions import POSE_COLUMNS
    from cdpr.analysis.dynamics import gravity_wrench
    from cdpr.analysis.errors import ConfigError, InputError
    from cdpr.analysis.kinematics import cable_vectors, structure_matrix
    from cdpr.analysis.rotations import rotation_from_euler
    from cdpr.analysis.tension import (
        SOLVE_RANK_DEFICIENT,
        distribute,
        rank_floor,
        sigma_min_unit_rows,
    )

    from .. import __version__
    from ..config import (
        file_sha256,
        load_rig,
        read_poses,
        read_wrenches,
        tension_columns,
        write_table,
    )

    rig = load_rig(args.rig)
    if args.poses:
        table, poses = read_poses(args.poses)
        src = args.poses
    else:
        poses = np.concatenate([rig.reference_position_O_m, rig.reference_euler_rad])[None, :]
        table = pd.DataFrame(poses, columns=list(POSE_COLUMNS))
        src = args.rig
    R = rotation_from_euler(poses[:, 3:])
    lengths = np.linalg.norm(
        cable_vectors(rig.anchors_O_m, rig.attach_P_m, poses[:, :3], R), axis=-1
    )
    bad = np.argwhere(lengths < 1e-9)
    if bad.size:
        i, j = bad[0]
        raise ConfigError(
            src, f"row {i + 2}", f"cable {rig.cable_names[j]} has zero length at this pose"
        )
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, poses[:, :3], R)
    sigma = sigma_min_unit_rows(A)  # the solvers' own rank test, pose by pose
    floor = rank_floor(rig.t_min_N, rig.t_max_N)
    rank_bad = np.flatnonzero(sigma < floor)
    if rank_bad.size:
        i = int(rank_bad[0])
        raise ConfigError(
            src,
            f"row {i + 2}",
            f"structure matrix loses rank at this pose (sigma_min of A with unit rows "
            f"{sigma[i]:.2g} < {float(floor):.2g}, the floor for the rig's tension limits; "
            f"{rank_bad.size} such poses)",
        )
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    W = read_wrenches(args.wrench, len(poses)) if args.wrench else np.zeros_like(G)
    try:
        res = distribute(args.method, A, -(G + W), rig.t_min_N, rig.t_max_N)
    except InputError as exc:  # the inputs are checked above: what is left is the rig's cable count
        raise ConfigError(
            args.rig, "cables", f"{rig.n_cables} cables, --method {args.method}: {exc}"
        ) from None

    out = table.copy()
    for k, col in enumerate(tension_columns(rig)):
        out[col] = res.tensions_N[:, k]
    out["feasible"] = res.feasible.astype(int)
    out["residual_N"] = res.residual_N
    out["max_violation_N"] = res.max_violation_N
    header = {
        "cdpr": f"solve {__version__}",
        "rig": f"{args.rig} sha256={file_sha256(args.rig)}",
        "poses": f"{args.poses} sha256={file_sha256(args.poses)}"
        if args.poses
        else "rig reference",
        "wrench": f"{args.wrench} sha256={file_sha256(args.wrench)}" if args.wrench else "none",
        "method": f"{res.method}: {res.objective}",
        "units": "tensions N; w = -(G + W_ext) at P in {O}",
    }
    n_bad = int((~res.feasible).sum())
    if n_bad and args.strict:
        i = int(np.flatnonzero(~res.feasible)[0])
        raise ConfigError(
            src, f"row {i + 2}", f"infeasible pose ({n_bad} of {len(poses)} infeasible)"
        )
    write_table(args.out, out, header)
    if n_bad:
        i = int(np.flatnonzero(~res.feasible)[0])
        n_rank = int(np.sum(res.status == SOLVE_RANK_DEFICIENT)) if res.status is not None else 0
        why = (
            f", {n_rank} of them because the structure matrix of the cables not at a limit "
            "loses rank at the answer"
            if n_rank
            else ""
        )
        print(
            f"cdpr solve: warning: {n_bad} of {len(poses)} poses infeasible "
            f"(first: {src} row {i + 2}){why}; flagged in column 'feasible'",
            file=sys.stderr,
        )
    print(f"cdpr solve: {len(poses)} poses, method {res.method}, wrote {args.out}")
    return 0
