"""``make bench``: run every ``bench/bench_*.py`` module and write ``bench/results.json``.

Each module exposes ``run() -> dict[str, dict]`` mapping a benchmark name to
``{"value": number, "unit": str, "peer": str | None, "peer_value": number | None,
"ratio": number | None}`` (extra keys, such as ``"target"`` or ``"context"``, are kept).  All
benchmarks are measured in the same run; ratios are value / peer_value.  Select modules with
``python bench/run.py NAME ...`` (module name without ``bench_``).
"""

from __future__ import annotations

import importlib.util
import json
import os
import platform
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod
    spec.loader.exec_module(mod)
    return mod


def main(argv: list[str]) -> int:
    wanted = set(argv)
    results: dict[str, dict] = {}
    failures: list[str] = []
    for path in sorted(HERE.glob("bench_*.py")):
        short = path.stem.removeprefix("bench_")
        if wanted and short not in wanted:
            continue
        print(f"== {path.name}", flush=True)
        t0 = time.perf_counter()
        try:
            out = _load(path).run()
        except Exception as exc:  # a failing benchmark is reported, the others still run
            failures.append(f"{path.name}: {type(exc).__name__}: {exc}")
            print(f"   FAILED: {exc}", flush=True)
            continue
        for name, entry in out.items():
            v, pv = entry.get("value"), entry.get("peer_value")
            entry.setdefault("peer", None)
            entry.setdefault("peer_value", None)
            entry["ratio"] = (v / pv) if (v is not None and pv) else entry.get("ratio")
            results[name] = entry
        print(f"   ({time.perf_counter() - t0:.1f} s)", flush=True)
    doc = {
        "_meta": {
            "python": platform.python_version(),
            "machine": platform.machine(),
            "cpus": os.cpu_count(),
            "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        },
        **results,
    }
    out_path = HERE / "results.json"
    tmp = out_path.with_suffix(".json.part")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    tmp.replace(out_path)
    w = max([len(n) for n in results] + [9])
    print(
        f"\n{'benchmark':{w}s} {'value':>14s} {'unit':14s} {'peer_value':>12s} {'ratio':>8s}  peer"
    )
    for name, e in results.items():
        pv = e.get("peer_value")
        r = e.get("ratio")
        print(
            f"{name:{w}s} {e['value']:14.6g} {e['unit']:14s} "
            f"{(f'{pv:.6g}' if pv is not None else '-'):>12s} "
            f"{(f'{r:.3g}' if r is not None else '-'):>8s}  {e.get('peer') or ''}"
        )
    print(f"\nwrote {out_path}")
    for f in failures:
        print(f"FAILED {f}", file=sys.stderr)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
