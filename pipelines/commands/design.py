"""``cdpr design``: choose a rig geometry that maximises an objective under feasibility and
conditioning constraints, and plot sensitivity against feasibility margin (Pareto front).

Design variables (bounds by ``--bound NAME=LO:HI``):

- ``--family flat``: K21, K22, H_m, X_m of the paper's flat rig (default bounds: Table 3's ranges,
  X down to 0.3 m);
- ``--family cubic``: k1, k2, k3, Z_m of the cubic rig (0.025 <= k3 <= k2 <= k1 <= 0.4, Z 0.3-1.1 m).

Objectives (``--objective``, all maximised): ``sensitivity`` (S of eq. 12 at the design load),
``margin`` (worst tension slack over the full load range, N), ``condition`` (minus the condition
number of A), ``uncertainty`` (minus the largest force standard deviation for the load-cell noise),
``stiffness`` (the lowest natural frequency at the reference pose, wind off, Hz: cables EA/l plus
the tension term, platform mass and inertia; EA by ``--EA-N``).
Constraints: margin >= ``--min-margin`` (default 0 N: every cable within its limits for every load
of the range), condition number <= ``--max-condition`` (default 1000) and lowest natural frequency
>= ``--min-frequency-Hz`` (default 0: none).  Optimiser: scipy's
differential evolution over the batched evaluator (a whole population per call), seeded.

Writes into ``--out``: ``design.md`` (the optimum, its metrics, the paper's design for comparison),
``design_rig.toml`` (the optimum as a rig file for ``cdpr solve``), ``pareto_samples.csv``,
``pareto.png`` (S vs margin of random feasible designs, the non-dominated front, the optimum) and
``stiffness_pareto.png`` (S vs the lowest natural frequency: what stiffness costs in sensitivity).
"""

from __future__ import annotations

import argparse
from typing import Any

FAMILIES = {
    "flat": {
        "names": ("K21", "K22", "H_m", "X_m"),
        "bounds": {
            "K21": (46.0, 96.0),
            "K22": (25.0, 55.0),
            "H_m": (0.52, 0.92),
            "X_m": (0.3, 0.95),
        },
        "paper": (51.0, 28.0, 0.67, 0.5),
    },
    "cubic": {
        "names": ("k1", "k2", "k3", "Z_m"),
        "bounds": {"k1": (0.025, 0.4), "k2": (0.025, 0.4), "k3": (0.025, 0.4), "Z_m": (0.3, 1.1)},
        "paper": (0.15, 0.075, 0.075, 0.7),
    },
}
VALID = {
    "K21": (1.0, float("inf")),
    "K22": (1.0, float("inf")),
    "H_m": (0.0, float("inf")),
    "X_m": (0.015, 0.985),
    "k1": (0.0, 1.0),
    "k2": (0.0, 1.0),
    "k3": (0.0, 1.0),
    "Z_m": (0.0, 1.4),
}
"""Open ranges of the design variables for the default rigs (X: inside the 1 m frame less half the
platform length; Z: inside the 1.4 m frame; the study options may narrow them further)."""
OBJECTIVES = ("sensitivity", "margin", "condition", "uncertainty", "stiffness")


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "design",
        help="optimise a rig geometry (sensitivity, margin, conditioning) with a Pareto plot",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--family", required=True, choices=sorted(FAMILIES))
    p.add_argument("--objective", default="sensitivity", choices=OBJECTIVES)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--config", help="study options TOML (as for cdpr sensitivity)")
    p.add_argument("--method", default="exact", help="tension distribution method (default exact)")
    p.add_argument("--min-margin", type=float, default=0.0, help="N (default 0)")
    p.add_argument("--max-condition", type=float, default=1000.0, help="default 1000")
    p.add_argument(
        "--min-frequency-Hz", dest="min_frequency_Hz", type=float, default=0.0,
        help="lowest natural frequency at least this, Hz (default 0: no constraint)",
    )  # fmt: skip
    p.add_argument(
        "--EA-N", dest="EA_N", type=float, default=None,
        help="cable axial stiffness E*A, N (default the rig files' assumed 7e4 N)",
    )  # fmt: skip
    p.add_argument("--speed", type=float, help="flat: design airspeed, m/s (default the largest)")
    p.add_argument("--direction", choices=("x", "y"), default="x", help="cubic: design force axis")
    p.add_argument("--bound", action="append", default=[], metavar="NAME=LO:HI")
    p.add_argument("--maxiter", type=int, default=40, help="differential evolution generations")
    p.add_argument("--popsize", type=int, default=20, help="population per design variable")
    p.add_argument("--samples", type=int, default=4000, help="random designs for the Pareto plot")
    p.add_argument("--seed", type=int, default=1)
    p.set_defaults(func=run)


def _parse_bounds(family: str, items: list[str]) -> dict[str, tuple[float, float]]:
    from cdpr.analysis.errors import InputError

    spec = FAMILIES[family]
    bounds = dict(spec["bounds"])  # type: ignore[call-overload]
    for item in items:
        try:
            name, rng = item.split("=", 1)
            lo_s, hi_s = rng.split(":", 1)
            lo, hi = float(lo_s), float(hi_s)
        except ValueError:
            raise InputError(f"--bound: expected NAME=LO:HI, got {item!r}") from None
        if name not in bounds:
            raise InputError(f"--bound {name}: unknown design variable (have {list(bounds)})")
        if not lo < hi:
            raise InputError(f"--bound {name}: expected LO < HI, got {lo} and {hi}")
        bounds[name] = (lo, hi)
    for name, (lo, hi) in bounds.items():
        vmin, vmax = VALID[name]
        if not (lo > vmin and hi < vmax):
            raise InputError(
                f"--bound {name}: expected {vmin:g} < LO < HI < {vmax:g} (valid geometry), "
                f"got {lo:g}:{hi:g}"
            )
    return bounds


class Evaluator:
    """Batched design evaluation: X (n, 4) -> S, margin, condition, force std, validity."""

    def __init__(
        self,
        family: str,
        opts: Any,
        method: str,
        speed: float | None,
        direction: str,
        EA_N: float | None = None,
    ):
        import numpy as np

        from cdpr.analysis import sensitivity as sens
        from cdpr.analysis.rig import DEFAULT_CABLE_EA_N
        from cdpr.pipelines import sensitivity_study as sr

        self.family, self.o, self.method = family, opts, method
        self.EA_N = DEFAULT_CABLE_EA_N if EA_N is None else float(EA_N)
        if family == "flat":
            f = opts.flat
            V = max(opts.aero.speeds_mps) if speed is None else speed
            self.W = sr.flat_loads(opts.aero, [V])[0]
            self.loads = sr.flat_margin_loads(opts.aero)
            self.G = sens.gravity_load(f.mass_kg)
            self.lim = (f.t_min_N, f.t_max_N)
            self.load_text = f"aerodynamic wrench at {V:g} m/s (SDM-like model)"
        else:
            c = opts.cubic
            F = max(c.forces_N)
            self.W = np.zeros(6)
            self.W[0 if direction == "x" else 1] = F
            W, _, _ = sr.cubic_loads(c.forces_N)
            self.loads = np.concatenate([W, -W])
            self.G = sens.gravity_load(c.mass_kg)
            self.lim = (c.t_min_N, c.t_max_N)
            self.load_text = f"force of {F:g} N along {direction}"

    def geometry_ok(self, X: Any) -> Any:
        import numpy as np

        if self.family == "cubic":
            c = self.o.cubic
            k1, k2, k3, Z = X.T
            half = 0.5 * k3 * c.H_m
            return (k3 <= k2) & (k2 <= k1) & (Z - half > 0.01) & (Z + half < c.H_m - 0.01)
        return np.ones(len(X), dtype=bool)

    def __call__(self, X: Any) -> dict[str, Any]:
        import numpy as np

        from cdpr.analysis import sensitivity as sens

        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        ok = self.geometry_ok(X)
        n = len(X)
        out = {
            "S_N": np.full(n, np.nan),
            "margin_N": np.full(n, -np.inf),
            "condition": np.full(n, np.inf),
            "std_force_N": np.full(n, np.inf),
            "f1_Hz": np.full(n, np.nan),
            "valid": ok.copy(),
        }
        if not ok.any():
            return out
        Xo = X[ok]
        if self.family == "flat":
            f = self.o.flat
            geo = sens.flat_geometry(
                Xo[:, 0],
                Xo[:, 1],
                Xo[:, 2],
                Xo[:, 3],
                L_m=f.L_m,
                l_m=f.l_m,
                w1_m=f.w1_m,
                w2_m=f.w2_m,
            )
        else:
            c = self.o.cubic
            geo = sens.cubic_geometry(
                Xo[:, 0], Xo[:, 1], Xo[:, 2], Z_m=Xo[:, 3], L_m=c.L_m, W_m=c.W_m, H_m=c.H_m,
                layout=c.layout,
            )  # fmt: skip
        A = sens.structure_matrices(geo)
        res = sens.sensitivity(A, self.W, self.G, *self.lim, self.method)
        sv = sens.singular_value_metrics(A)
        out["S_N"][ok] = res.S_N
        out["margin_N"][ok] = sens.feasibility_margin(
            A, self.G, self.loads, *self.lim, self.o.study.margin_method
        )
        out["condition"][ok] = sv.condition
        out["std_force_N"][ok] = sens.wrench_std(A, self.o.study.sigma_T_N)[:, :3].max(axis=1)
        out["valid"][ok] = np.isfinite(res.S_N) & res.feasible
        out["f1_Hz"][ok] = self.lowest_frequency(geo, Xo, res.T0_N)
        return out

    def lowest_frequency(self, geo: Any, Xo: Any, T0: Any) -> Any:
        """Lowest natural frequency (n,) at the reference pose under the wind-off tensions T0."""
        import numpy as np

        from cdpr.analysis import rigs
        from cdpr.analysis.stiffness import mass_matrix, natural_modes, stiffness_matrix

        if self.family == "flat":
            mass = self.o.flat.mass_kg
            inertia = rigs.rod_inertia(mass, rigs.FLAT_DEFAULTS["model_length_m"])
        else:
            c = self.o.cubic
            mass = c.mass_kg
            inertia = rigs.box_inertia(mass, Xo[:, 0] * c.L_m, Xo[:, 1] * c.W_m, Xo[:, 2] * c.H_m)
        f1 = np.full(len(Xo), np.nan)
        good = np.all(np.isfinite(T0), axis=-1)
        if not good.any():
            return f1
        st = stiffness_matrix(
            geo.anchors_O_m[good], geo.attach_P_m[good], geo.position_O_m[good], np.eye(3),
            T0[good], self.EA_N, mass,
        )  # fmt: skip
        M = mass_matrix(mass, np.zeros(3), inertia[good] if np.ndim(inertia) == 3 else inertia,
                        np.eye(3))  # fmt: skip
        f1[good] = natural_modes(st.K, M).frequencies_Hz[:, 0]
        return f1


def objective_value(name: str, ev: dict[str, Any]) -> Any:
    """The maximised objective (n,) from an evaluation."""
    if name == "sensitivity":
        return ev["S_N"]
    if name == "margin":
        return ev["margin_N"]
    if name == "condition":
        return -ev["condition"]
    if name == "stiffness":
        return ev["f1_Hz"]
    return -ev["std_force_N"]


def pareto_front(a: Any, b: Any) -> Any:
    """Mask of the points not dominated when maximising both ``a`` and ``b`` (n,)."""
    import numpy as np

    order = np.lexsort((-b, -a))  # by a descending, ties by b descending
    front = np.zeros(len(a), dtype=bool)
    best_b = -np.inf
    for i in order:
        if b[i] > best_b:
            front[i] = True
            best_b = b[i]
    return front


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import pandas as pd
    from scipy.optimize import differential_evolution

    from cdpr.analysis import rigs
    from cdpr.analysis.errors import InfeasibleError, InputError
    from cdpr.analysis.tension import METHODS

    from .. import __version__
    from ..config import atomic_output, rig_toml, write_table
    from ..plotting import png_figure
    from ..sensitivity_options import StudyOptions, options_from_toml

    if args.method not in METHODS:
        raise InputError(f"--method: expected one of {sorted(METHODS)}, got {args.method!r}")
    for name, v, lo in (("--maxiter", args.maxiter, 1), ("--popsize", args.popsize, 2),
                        ("--samples", args.samples, 10)):  # fmt: skip
        if v < lo:
            raise InputError(f"{name}: expected >= {lo}, got {v}")
    if not args.max_condition > 1:
        raise InputError(f"--max-condition: expected > 1, got {args.max_condition}")
    if args.speed is not None and not (np.isfinite(args.speed) and args.speed > 0):
        raise InputError(f"--speed: expected a finite airspeed > 0 m/s, got {args.speed}")
    if args.speed is not None and args.family != "flat":
        raise InputError("--speed: applies to --family flat only (the cubic rig's load is a force)")
    if not np.isfinite(args.min_margin):
        raise InputError(f"--min-margin: expected a finite number of N, got {args.min_margin}")
    opts = options_from_toml(args.config) if args.config else StudyOptions()
    bounds = _parse_bounds(args.family, args.bound)
    names = FAMILIES[args.family]["names"]
    lo = np.array([bounds[n][0] for n in names])
    hi = np.array([bounds[n][1] for n in names])
    if not (np.isfinite(args.min_frequency_Hz) and args.min_frequency_Hz >= 0):
        raise InputError(f"--min-frequency-Hz: expected >= 0 Hz, got {args.min_frequency_Hz}")
    if args.EA_N is not None and not (np.isfinite(args.EA_N) and args.EA_N > 0):
        raise InputError(f"--EA-N: expected a finite E*A > 0 N, got {args.EA_N}")
    ev_fn = Evaluator(args.family, opts, args.method, args.speed, args.direction, args.EA_N)

    def constraint_violation(ev: dict[str, Any]) -> Any:
        v = np.maximum(args.min_margin - ev["margin_N"], 0.0) / 10.0
        v = v + np.maximum(np.log10(ev["condition"] / args.max_condition), 0.0)
        if args.min_frequency_Hz > 0:
            v = v + np.maximum(args.min_frequency_Hz - np.nan_to_num(ev["f1_Hz"], nan=0.0), 0.0)
        v = np.where(ev["valid"], v, np.inf)
        return np.nan_to_num(v, nan=1e6, posinf=1e6)

    def cost(x: Any) -> Any:
        X = np.asarray(x, dtype=np.float64)
        X = X.T if X.ndim == 2 else X[None, :]
        ev = ev_fn(X)
        obj = np.nan_to_num(objective_value(args.objective, ev), nan=-1e6, neginf=-1e6)
        viol = constraint_violation(ev)
        c = np.where(viol > 0, 1e6 + 1e3 * viol, -obj)
        return c if np.asarray(x).ndim == 2 else float(c[0])

    # Random designs: the Pareto cloud and a check that the constraints can be met at all.
    rng = np.random.default_rng(args.seed)
    Xs = lo + (hi - lo) * rng.random((args.samples, len(names)))
    if args.family == "cubic":  # sample the ordered ratios directly
        Xs[:, :3] = np.sort(Xs[:, :3], axis=1)[:, ::-1]
    evs = ev_fn(Xs)
    viol = constraint_violation(evs)
    if not np.any(viol == 0):
        raise InfeasibleError(
            f"design --family {args.family}: none of {args.samples} random designs within the "
            f"bounds {bounds} meets --min-margin {args.min_margin:g} N, --max-condition "
            f"{args.max_condition:g} and --min-frequency-Hz {args.min_frequency_Hz:g}; widen "
            "--bound, relax the constraints or check the rig options"
        )
    # Start the evolution from the best random designs (constraint-meeting ones first), so the
    # optimum is never worse than the random search that draws the Pareto cloud.
    n_pop = max(5, args.popsize * len(names))
    rank = np.lexsort((-np.nan_to_num(objective_value(args.objective, evs), nan=-1e6), viol))
    init = Xs[rank[:n_pop]]
    result = differential_evolution(
        cost,
        list(zip(lo, hi, strict=True)),
        maxiter=args.maxiter,
        popsize=args.popsize,
        rng=args.seed,
        vectorized=True,
        updating="deferred",
        polish=False,
        init=init,
        tol=1e-8,
    )
    xbest = np.asarray(result.x)
    ev_best = ev_fn(xbest[None])
    if constraint_violation(ev_best)[0] > 0:  # fall back to the best random feasible design
        ok = np.flatnonzero(viol == 0)
        xbest = Xs[ok[np.argmax(objective_value(args.objective, evs)[ok])]]
        ev_best = ev_fn(xbest[None])
    paper = np.array(FAMILIES[args.family]["paper"])
    ev_paper = ev_fn(paper[None])

    samples = pd.DataFrame(Xs, columns=list(names))
    for k in ("S_N", "margin_N", "condition", "std_force_N", "f1_Hz"):
        samples[k] = evs[k]
    samples["meets_constraints"] = (viol == 0).astype(int)
    feas = viol == 0
    front = np.zeros(len(Xs), dtype=bool)
    front[feas] = pareto_front(evs["S_N"][feas], evs["margin_N"][feas])
    samples["pareto"] = front.astype(int)

    from pathlib import Path

    out = Path(args.out)
    header = {"cdpr": f"design {__version__}", "family": args.family, "objective": args.objective,
              "method": args.method, "load": ev_fn.load_text}  # fmt: skip
    with png_figure(out / "pareto.png", size=(7.2, 5.0)) as (fig, axes):
        ax = axes[0, 0]
        sc = ax.scatter(
            evs["margin_N"][feas], evs["S_N"][feas], c=np.log10(evs["condition"][feas]), s=6,
            cmap="viridis", alpha=0.6,
        )  # fmt: skip
        fig.colorbar(sc, ax=ax, label="log10 condition number of A")
        fx = np.flatnonzero(front)
        fx = fx[np.argsort(evs["margin_N"][fx])]
        ax.plot(evs["margin_N"][fx], evs["S_N"][fx], "r-o", ms=3, lw=1.2, label="Pareto front")
        ax.plot(
            ev_best["margin_N"], ev_best["S_N"], "k*", ms=14, label=f"optimum ({args.objective})"
        )
        if np.isfinite(ev_paper["S_N"][0]):
            ax.plot(ev_paper["margin_N"], ev_paper["S_N"], "bs", ms=8, label="paper's design")
        ax.set_xlabel("feasibility margin over the load range (N)")
        ax.set_ylabel("sensitivity S (N)")
        ax.set_title(f"{args.family} rig: {ev_fn.load_text}, {args.method}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    front_f = np.zeros(len(Xs), dtype=bool)
    front_f[feas] = pareto_front(evs["S_N"][feas], np.nan_to_num(evs["f1_Hz"][feas], nan=-1.0))
    samples["pareto_stiffness"] = front_f.astype(int)
    write_table(out / "pareto_samples.csv", samples, header)
    with png_figure(out / "stiffness_pareto.png", size=(7.2, 5.0)) as (fig, axes):
        ax = axes[0, 0]
        ax.scatter(evs["f1_Hz"][feas], evs["S_N"][feas], s=6, alpha=0.5, label="feasible designs")
        fx = np.flatnonzero(front_f)
        fx = fx[np.argsort(evs["f1_Hz"][fx])]
        ax.plot(evs["f1_Hz"][fx], evs["S_N"][fx], "r-o", ms=3, lw=1.2, label="S-f1 Pareto front")
        ax.plot(ev_best["f1_Hz"], ev_best["S_N"], "k*", ms=14, label=f"optimum ({args.objective})")
        if np.isfinite(ev_paper["S_N"][0]):
            ax.plot(ev_paper["f1_Hz"], ev_paper["S_N"], "bs", ms=8, label="paper's design")
        ax.set_xlabel(f"lowest natural frequency (Hz), EA = {ev_fn.EA_N:g} N")
        ax.set_ylabel("sensitivity S (N)")
        ax.set_title(f"{args.family} rig: stiffness against sensitivity", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if args.family == "flat":
        f = opts.flat
        rig = rigs.flat_rig(*xbest, L_m=f.L_m, l_m=f.l_m, w1_m=f.w1_m, w2_m=f.w2_m,
                            mass_kg=f.mass_kg, t_min_N=f.t_min_N, t_max_N=f.t_max_N,
                            name="flat-design")  # fmt: skip
    else:
        c = opts.cubic
        rig = rigs.cubic_rig(*xbest[:3], Z_m=xbest[3], L_m=c.L_m, W_m=c.W_m, H_m=c.H_m,
                             mass_kg=c.mass_kg, t_min_N=c.t_min_N, t_max_N=c.t_max_N,
                             layout=c.layout, name="cubic-design")  # fmt: skip
    with atomic_output(out / "design_rig.toml") as fh:
        fh.write(rig_toml(rig, f"Written by cdpr design --family {args.family} --objective "
                              f"{args.objective}"))  # fmt: skip

    def row(label: str, x: Any, e: dict[str, Any]) -> str:
        vals = ", ".join(f"{n} = {v:.4g}" for n, v in zip(names, x, strict=True))
        return (f"| {label} | {vals} | {e['S_N'][0]:.4g} | {e['margin_N'][0]:.4g} | "
                f"{e['condition'][0]:.4g} | {e['std_force_N'][0]:.3g} | {e['f1_Hz'][0]:.3g} | "
                f"{'yes' if constraint_violation(e)[0] == 0 else 'no'} |")  # fmt: skip

    text = "\n".join(
        [
            f"# cdpr design: {args.family} rig, objective {args.objective}\n",
            f"Load for S: {ev_fn.load_text}; method `{args.method}`; margin over the full load "
            f"range with `{opts.study.margin_method}`; constraints: margin >= {args.min_margin:g} "
            f"N, condition <= {args.max_condition:g}; bounds {bounds}.\n",
            f"Differential evolution: {result.nit} generations, {result.nfev} evaluations, "
            f"message: {result.message}\n",
            "| design | variables | S (N) | margin (N) | condition | max force std (N) | "
            "lowest mode (Hz) | meets constraints |",
            "|---|---|---|---|---|---|---|---|",
            row("optimum", xbest, ev_best),
            row("paper", paper, ev_paper),
            "",
            f"{int(feas.sum())} of {args.samples} random designs meet the constraints; "
            f"{int(front.sum())} are on the S-margin Pareto front (`pareto.png`, "
            f"`pareto_samples.csv`) and {int(front_f.sum())} on the S-frequency front "
            f"(`stiffness_pareto.png`; lowest natural frequency at the reference pose, wind off, "
            f"EA = {ev_fn.EA_N:g} N). The optimum is written as `design_rig.toml`.",
            "",
        ]
    )
    with atomic_output(out / "design.md") as fh:
        fh.write(text)
    print(text)
    print(
        f"cdpr design: wrote {out}/design.md, design_rig.toml, pareto.png, stiffness_pareto.png, "
        "pareto_samples.csv"
    )
    return 0
