"""``cdpr rig``: show a rig file, or write the paper's reference rigs."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cdpr.analysis.rig import Rig


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("rig", help="rig files: show, write the paper's rigs, import from CASPR")
    rs = p.add_subparsers(dest="rig_command", metavar="ACTION")
    rs.required = True

    show = rs.add_parser("show", help="validate a rig file and print its summary")
    show.add_argument("rig", help="rig file (TOML)")
    show.set_defaults(func=run_show)

    paper = rs.add_parser("paper", help="write the paper's reference rig files into a folder")
    paper.add_argument("--out", required=True, help="output folder")
    paper.set_defaults(func=run_paper)

    caspr = rs.add_parser(
        "import-caspr", help="make a rig file from a single-body CASPR model (bodies + cables XML)"
    )
    caspr.add_argument("bodies", help="CASPR MODEL_bodies.xml")
    caspr.add_argument("--cables", help="CASPR cables XML (default: MODEL_cables.xml beside it)")
    caspr.add_argument("--cable-set", dest="cable_set", help="cable set id (default: the default)")
    caspr.add_argument(
        "--t-min-N", dest="t_min_N", type=float, default=0.0, help="limit if none given (0 N)"
    )
    caspr.add_argument(
        "--t-max-N", dest="t_max_N", type=float, default=1000.0, help="limit if none (1000 N)"
    )
    caspr.add_argument("--out", required=True, help="output rig file (TOML)")
    caspr.set_defaults(func=run_import_caspr)


def run_show(args: argparse.Namespace) -> int:
    import numpy as np

    from cdpr.analysis.kinematics import structure_matrix
    from cdpr.analysis.rotations import rotation_from_euler

    from ..config import load_rig

    rig = load_rig(args.rig)
    R = rotation_from_euler(rig.reference_euler_rad)
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, rig.reference_position_O_m, R)
    sv = np.linalg.svd(A, compute_uv=False)
    print(f"rig {rig.name}: {rig.n_cables} cables, mass {rig.mass_kg:g} kg")
    print(f"  reference pose: p = {rig.reference_position_O_m.tolist()} m")
    for i, name in enumerate(rig.cable_names):
        winch = "".join(
            f", {what} <= {v:g} {unit}"
            for what, v, unit in (
                ("speed", rig.cable_max_speed_mps[i], "m/s"),
                ("acceleration", rig.cable_max_accel_mps2[i], "m/s^2"),
            )
            if np.isfinite(v)
        )
        print(
            f"  {name:24s} b = {np.round(rig.anchors_O_m[i], 4).tolist()} m, "
            f"pp = {np.round(rig.attach_P_m[i], 4).tolist()} m, "
            f"T in [{rig.t_min_N[i]:g}, {rig.t_max_N[i]:g}] N{winch}"
        )
    print(f"  singular values of A at the reference pose: {np.round(sv, 5).tolist()}")
    _print_modes(rig)
    for k, v in rig.assumptions.items():
        print(f"  assumption {k}: {v}")
    return 0


_DOF_NAMES = ("x", "y", "z", "roll", "pitch", "yaw")


def _print_modes(rig: Rig) -> None:
    """The rig's natural modes at its reference pose (wind off), one line per mode."""
    import numpy as np

    from cdpr.analysis.errors import InfeasibleError, InputError
    from cdpr.analysis.rotations import rotation_from_euler
    from cdpr.analysis.stiffness import dominant_coordinates, mass_matrix, rig_modes

    R_ref = rotation_from_euler(rig.reference_euler_rad)
    try:
        rm = rig_modes(rig)
    except InfeasibleError as exc:
        print(f"  natural modes: not computed: {exc}")
        return
    except InputError as exc:  # e.g. no inertia in the rig file: the rig is still a valid rig
        print(f"  natural modes: not computed ({exc}; give [platform] inertia_P_kgm2)")
        return
    from cdpr.analysis.rig import DEFAULT_CABLE_EA_N

    ea = sorted({float(v) for v in rig.cable_EA_N})
    assumed = " (the default: no EA_N in the rig file)" if ea == [DEFAULT_CABLE_EA_N] else ""
    print(
        f"  natural modes at the reference pose (wind off, tensions by {rm.method}, "
        f"EA = {', '.join(f'{v:g}' for v in ea)} N{assumed}):"
    )
    M = mass_matrix(rig.mass_kg, rig.com_P_m, rig.inertia_P_kgm2, R_ref)
    shares = dominant_coordinates(rm.modes.shapes, M)
    for k in range(6):
        share = shares[:, k]  # each coordinate's share of the mode's kinetic energy
        parts = ", ".join(
            f"{_DOF_NAMES[j]} {share[j]:.0%}" for j in np.argsort(-share)[:2] if share[j] >= 0.05
        )
        f = rm.modes.frequencies_Hz[k]
        print(f"    mode {k + 1}: {f:8.2f} Hz  ({parts} of the kinetic energy)")


def run_paper(args: argparse.Namespace) -> int:
    from pathlib import Path

    from cdpr.analysis.rigs import paper_rigs

    from ..config import atomic_output, rig_toml

    out = Path(args.out)
    for stem, rig in paper_rigs().items():
        path = out / f"{stem}.toml"
        with atomic_output(path) as fh:
            fh.write(rig_toml(rig, header=f"{rig.description}\nWritten by `cdpr rig paper`."))
        print(f"wrote {path}")
    return 0


def run_import_caspr(args: argparse.Namespace) -> int:
    from ..caspr import import_caspr
    from ..config import atomic_output, file_sha256, rig_toml

    rig = import_caspr(args.bodies, args.cables, args.cable_set, args.t_min_N, args.t_max_N)
    hashes = f"bodies sha256={file_sha256(args.bodies)}; cables sha256={file_sha256(rig.source)}"
    with atomic_output(args.out) as fh:
        fh.write(
            rig_toml(
                rig, header=f"{rig.description}\n{hashes}\nWritten by `cdpr rig import-caspr`."
            )
        )
    print(
        f"cdpr rig import-caspr: {rig.n_cables} cables, mass {rig.mass_kg:g} kg, wrote {args.out}"
    )
    return 0
