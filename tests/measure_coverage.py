"""Coverage of cdpr's error bars on an independent lab case (issue 21's before/after table).

    python tests/measure_coverage.py --case white|ar1|common|mode --points 100 [--rig flat|cubic]
        [--pose camera|truth] [--seed 0] [--keep DIR] [--json results.json]

Generates a case with ``tests/lab_generator.py`` (its own statics, controller, aero model and
noise), runs the lab path as a lab would (``cdpr import`` with the calibration, poses, tunnel and
events, then ``cdpr analyze --matrix``, both as subprocesses, in a temporary folder) and prints,
per wrench component (``fx_N .. mz_Nm``: forces in {O}, moments about the MRP in {O} axes) and per
coefficient, over the wind-on points:

- ``cover95``: the fraction with ``|error| <= 1.96 sd`` (or ``<= U95`` when points.csv has a
  ``U95_<column>`` / ``<column>_U95`` column), error = analysed - truth (the ensemble mean);
- ``rms(e/sd)``: the root mean square of error / sd (1 when sd is honest);
- ``sd/scatter``: the median sd over the rms error (>1: bars too wide); the rms and the largest
  error;
- for the wrench also the same against ``sd_load_cells_*`` alone (the load-cell part of sd, at P;
  the MRP is P in these cases).

``--pose truth`` records the camera at the true pose (no camera noise, covariance 0): the error is
then the load cells' alone, so their part of sd is judged on its own.  Exit 0 unless the lab
path failed (exit 2 of a command).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))

import lab_generator as lg  # noqa: E402

WRENCH = ("fx_N", "fy_N", "fz_N", "mx_Nm", "my_Nm", "mz_Nm")
COEFFS = ("CD", "CY", "CL", "Cl", "Cm", "Cn")


def cdpr_command() -> list[str]:
    """The ``cdpr`` of this interpreter's environment."""
    exe = Path(sys.executable).with_name("cdpr")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "cdpr.pipelines.cli"]


def clean_env() -> dict[str, str]:
    """The environment without python-can's ``CAN_*`` variables (python-can reads them silently)."""
    return {k: v for k, v in os.environ.items() if not k.startswith("CAN_")}


def run_lab_path(case: lg.LabCase, work: Path) -> tuple[pd.DataFrame, dict[str, float], str]:
    """``cdpr import`` then ``cdpr analyze --matrix`` on a case; the points table, the times and
    the analysis' stdout.  A command's exit code 2 (or a crash) raises."""
    run = work / "run.mcap"
    ana = work / "analysis"
    imp, an = lg.lab_argv(case, run, ana)
    times = {}
    env = clean_env()
    out = ""
    for name, argv in (("import", imp), ("analyze", an)):
        t0 = time.perf_counter()
        r = subprocess.run(cdpr_command() + argv, capture_output=True, text=True, env=env)
        times[name] = time.perf_counter() - t0
        out += r.stdout
        if r.returncode not in (0, 1):
            raise RuntimeError(f"cdpr {name} exited {r.returncode}: {r.stderr.strip()[-2000:]}")
    return pd.read_csv(ana / "run" / "points.csv"), times, out


def _u95(points: pd.DataFrame, col: str) -> pd.Series | None:
    for c in (f"U95_{col}", f"{col}_U95", f"u95_{col}"):
        if c in points:
            return points[c]
    return None


def coverage_table(points: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Per component and coefficient over the wind-on points: n, cover95, rms(e/sd),
    sd/scatter, and (wrench) the same against the load-cell sd alone."""
    m = points.merge(truth, on="point", suffixes=("", "_true"), validate="one_to_one")
    m = m[m["kind"] == "wind_on"]
    rows = []
    for c in (*WRENCH, *COEFFS):
        e = (m[c] - m[f"{c}_true"]).to_numpy(float)
        sd = m[f"sd_{c}"].to_numpy(float)
        u = _u95(m, c)
        half = u.to_numpy(float) if u is not None else 1.96 * sd
        row = {
            "component": c,
            "n": int(np.isfinite(e).sum()),
            "cover95": float(np.mean(np.abs(e) <= half)),
            "rms_e_over_sd": float(np.sqrt(np.nanmean((e / sd) ** 2))),
            "sd_over_scatter": float(np.nanmedian(sd) / np.sqrt(np.nanmean(e**2))),
            "rms_error": float(np.sqrt(np.nanmean(e**2))),
            "max_abs_error": float(np.nanmax(np.abs(e))),
            "median_sd": float(np.nanmedian(sd)),
            "bound": "U95" if u is not None else "1.96 sd",
        }
        if f"sd_random_{c}" in m:  # the random part alone (the generator's geometry is exact)
            from scipy.stats import t as student

            sr = m[f"sd_random_{c}"].to_numpy(float)
            nu = m.get(f"dof_random_{c}", pd.Series(np.inf, index=m.index)).to_numpy(float)
            k95 = np.where(np.isfinite(nu), student.ppf(0.975, np.maximum(nu, 1.0)), 1.96)
            row["cover95_random"] = float(np.mean(np.abs(e) <= k95 * sr))
            row["rms_e_over_sd_random"] = float(np.sqrt(np.nanmean((e / sr) ** 2)))
        lc = f"sd_load_cells_{c}"
        if lc in m:
            s2 = m[lc].to_numpy(float)
            row["cover95_load_cells"] = float(np.mean(np.abs(e) <= 1.96 * s2))
            row["rms_e_over_sd_load_cells"] = float(np.sqrt(np.nanmean((e / s2) ** 2)))
        rows.append(row)
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--case", default="white", choices=["white", "ar1", "common", "mode"])
    ap.add_argument("--points", type=int, default=100, help="wind-on points (at least)")
    ap.add_argument("--rig", default="flat", help="flat | cubic | a rig file")
    ap.add_argument("--pose", default="camera", choices=["camera", "truth"],
                    help="truth: the camera records the true pose (no camera noise)")  # fmt: skip
    ap.add_argument("--duration-s", type=float, default=3.0, help="window of a point, s")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", help="work folder to keep (default: a temporary one)")
    ap.add_argument("--json", help="write the table and the run facts here")
    a = ap.parse_args(argv)
    ctx = tempfile.TemporaryDirectory(prefix="cdpr-coverage-") if not a.keep else None
    work = Path(a.keep or ctx.name)  # type: ignore[union-attr]
    work.mkdir(parents=True, exist_ok=True)
    try:
        kw = {}
        if a.pose == "truth":
            kw["camera"] = lg.Camera(pos_sd_m=0.0, ang_sd_rad=0.0)
        t0 = time.perf_counter()
        case = lg.steady_case(
            work / "case", a.case, a.points, rig=a.rig, seed=a.seed, duration_s=a.duration_s, **kw
        )
        t_gen = time.perf_counter() - t0
        points, times, out = run_lab_path(case, work)
        table = coverage_table(points, case.points)
        won = points[points["kind"] == "wind_on"]
        flags = pd.Series(";".join(won["flags"].fillna("")).split(";")).value_counts()
        print(
            f"case {a.case}, rig {a.rig}, pose {a.pose}, seed {a.seed}: {len(won)} wind-on points of "
            f"{a.duration_s:g} s; generated in {t_gen:.1f} s, import {times['import']:.1f} s, "
            f"analyze {times['analyze']:.1f} s"
        )
        print("wind-on flags: " + ", ".join(f"{k} {v}" for k, v in flags.items() if k))
        cols = [
            "component",
            "n",
            "cover95",
            "rms_e_over_sd",
            "sd_over_scatter",
            "rms_error",
            "median_sd",
        ]
        if "cover95_random" in table:
            cols += ["cover95_random", "rms_e_over_sd_random"]
        if "cover95_load_cells" in table:
            cols += ["cover95_load_cells", "rms_e_over_sd_load_cells"]
        print(table[cols].to_string(index=False, float_format=lambda x: f"{x:.4g}"))
        if a.json:
            Path(a.json).write_text(
                json.dumps(
                    {
                        "case": a.case,
                        "rig": a.rig,
                        "pose": a.pose,
                        "seed": a.seed,
                        "points": len(won),
                        "duration_s": a.duration_s,
                        "times_s": {"generate": t_gen, **times},
                        "flags": flags.to_dict(),
                        "table": table.to_dict(orient="records"),
                    },  # fmt: skip
                    indent=1,
                )
            )
    finally:
        if ctx is not None:
            ctx.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
