"""Coverage of the dynamic derivatives' intervals over many independent lab points (issue 22).

    python tests/measure_dynamic_coverage.py [--seeds 20] [--cycles-scale 0.25] [--seed0 100]
        [--pose camera|lengths|both] [--keep DIR] [--json out.json]

Per seed the independent lab generator (tests/lab_generator.py) writes the issue's points with
their cycles scaled by ``--cycles-scale`` (pitch 5 deg at 1 and 2 Hz at 25.51 and 41.42 m/s, 2 deg
at 0.5 Hz at 17.27 m/s, yaw 0.6 deg at 1 Hz at 25.51 m/s, each with its wind-off tare; 200 Hz
camera with a 3 ms clock offset, 0.05 N load cells; the controller's cable lengths at 500 Hz with
20 um when asked), runs the lab path (``cdpr import``, ``cdpr analyze --matrix``, subprocesses)
and compares every named derivative with the lab's truth (its harmonics of the model's
coefficients over the window).  Prints per derivative and over all: the points, ``cover95``
(|error| <= U95), ``rms(e/sd)``, the median σ; per pose source.  Exit 0 unless the lab path
failed.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))

import lab_generator as lg  # noqa: E402
from measure_coverage import cdpr_command, clean_env  # noqa: E402

from cdpr.analysis.oscillation import NAMED_DERIVATIVES  # noqa: E402


def specs(scale: float) -> tuple[lg.OscSpec, ...]:
    """The issue's points with ``scale`` of their cycles (at least 4)."""
    return tuple(
        lg.OscSpec(
            s.axis,
            s.amplitude,
            s.frequency_Hz,
            s.speeds_mps,
            max(4, round(s.cycles * scale)),
            s.aoa_deg,
            s.sideslip_deg,
            s.settling_cycles,
        )  # fmt: skip
        for s in lg.ISSUE22_SPECS
    )


def rows_of(case: lg.LabCase, pts: pd.DataFrame, pose: str, seed: int) -> list[dict]:
    truth = {p["point"]: p for p in case.truth["points"]}
    out = []
    for _, r in pts[pts["kind"] == "oscillation"].iterrows():
        o = truth[r["point"]]["oscillation"]
        for n, c, part, sgn in NAMED_DERIVATIVES.get(o["axis"], ()):
            t = sgn * (o["inphase"] if part == "in" else o["outphase"])[c]
            out.append({
                "seed": seed, "pose": pose, "point": r["point"], "name": n, "value": r[n],
                "truth": t, "sd": r[f"sd_{n}"], "U95": r[f"U95_{n}"], "window_s": r["window_s"],
                "dwell_s": r[f"dwell_s_{n}"], "flags": r["flags"],
            })  # fmt: skip
    return out


def run_case(case: lg.LabCase, work: Path, pose: str) -> pd.DataFrame:
    import subprocess

    run, ana = work / f"{pose}.mcap", work / f"analysis_{pose}"
    imp, an = lg.lab_argv(case, run, ana, pose=pose)
    for argv in (imp, an):
        r = subprocess.run(cdpr_command() + argv, capture_output=True, text=True, env=clean_env())
        if r.returncode not in (0, 1):
            raise RuntimeError(f"cdpr {argv[0]} exited {r.returncode}: {r.stderr[-1500:]}")
    return pd.read_csv(ana / pose / "points.csv")


def summary(df: pd.DataFrame) -> pd.DataFrame:
    e = df["value"] - df["truth"]
    df = df.assign(err=e, z=e / df["sd"], covered=np.abs(e) <= df["U95"])
    g = df.groupby(["pose", "name"], sort=False)
    out = g.agg(points=("z", "size"), cover95=("covered", "mean"),
                rms_z=("z", lambda z: float(np.sqrt(np.mean(z**2)))), median_sd=("sd", "median"),
                rms_err=("err", lambda x: float(np.sqrt(np.mean(x**2)))))  # fmt: skip
    tot = df.groupby("pose").agg(points=("z", "size"), cover95=("covered", "mean"),
                                 rms_z=("z", lambda z: float(np.sqrt(np.mean(z**2)))))  # fmt: skip
    tot["name"] = "ALL"
    return pd.concat([out.reset_index(), tot.reset_index()], ignore_index=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--seed0", type=int, default=100)
    ap.add_argument("--cycles-scale", type=float, default=0.25)
    ap.add_argument("--pose", choices=["camera", "lengths", "both"], default="camera")
    ap.add_argument("--keep")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    poses = ["camera", "lengths"] if a.pose == "both" else [a.pose]
    rows: list[dict] = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="cdpr-dyncov-") as tmp:
        root = Path(a.keep) if a.keep else Path(tmp)
        for k in range(a.seeds):  # cases, not samples
            seed = a.seed0 + k
            work = root / f"seed{seed}"
            enc = lg.Encoders() if "lengths" in poses else None
            case = lg.oscillation_case(
                work / "case", specs(a.cycles_scale), seed=seed, encoders=enc
            )
            for pose in poses:
                rows += rows_of(case, run_case(case, work, pose), pose, seed)
            print(f"seed {seed}: {len(rows)} derivatives so far, {time.perf_counter() - t0:.0f} s",
                  file=sys.stderr, flush=True)  # fmt: skip
    df = pd.DataFrame(rows)
    s = summary(df)
    print(s.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if a.json:
        Path(a.json).write_text(json.dumps({"rows": rows, "summary": s.to_dict("records")},
                                           indent=1, default=float))  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
