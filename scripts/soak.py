"""Soak test: ``cdpr record`` with its live view (in a tmux pane, as an operator runs it) reading the
virtual rig at full rate for a long time (30 min by default), then Ctrl-C, ``cdpr inspect`` and
``cdpr analyze``.  Prints frames sent / recorded, drops, faults, the recorder's memory (RSS) over
time and whether the run analyses cleanly.

    .venv/bin/python scripts/soak.py --minutes 30          # make soak

Transports are real: the rig's slcan adapter and its ``$TUN`` tunnel line on two ptys.  Goals:
zero drops and zero faults (the adapter's own drops, when its buffer is full because the recorder
reads too slowly, show as counter gaps: ``lost`` faults, exit 3), RSS growth after the first minute
under 10 %, the run analysed (exit 0, or 1 for the warnings of a run without camera or model
geometry) with no sample masked.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import tomli_w

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
CDPR = ROOT / ".venv" / "bin" / "cdpr"
MCAP_CHECK = ROOT / "tools" / "mcap-check" / "mcap_check.js"
CYCLE = [("tare", 0.0, 20.0), ("v17", 17.27, 40.0), ("v25", 25.51, 40.0), ("v41", 41.42, 40.0)]


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text().split()
        out += [int(x) for x in text]
    return out


def _tmux(*args: str) -> str:
    return subprocess.run(["tmux", *args], capture_output=True, text=True, check=True).stdout


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--rate-hz", type=float, default=200.0, help="load-cell sample rate")
    ap.add_argument("--out", default=str(ROOT / "out" / "soak"), help="run and analysis folder")
    args = ap.parse_args(argv)
    from cdpr.daq.virtual_rig import VirtualRig, schedule_from_mapping
    from cdpr.pipelines.config import load_rig

    try:  # the rig stands for hardware: it must not be the one starved by the load
        os.setpriority(os.PRIO_PROCESS, 0, -15)
    except OSError:
        pass
    duration_s = args.minutes * 60.0
    n_cycles = math.ceil((duration_s + 60.0) / sum(c[2] for c in CYCLE))
    segments = [
        {"label": f"{lab}-{k}", "duration_s": dur, "wind_mps": v, "transition_s": 0.5,
         **({"tare": True} if v == 0 else {})}
        for k in range(n_cycles) for lab, v, dur in CYCLE
    ]  # fmt: skip
    rig = load_rig(RIG)
    sched = schedule_from_mapping(
        {
            "schedule": {"name": "soak", "rate_hz": args.rate_hz, "tunnel_rate_hz": 10.0},
            "segments": segments,
        },
        "<soak>",
        rig,
    )
    vr = VirtualRig(rig, sched)
    out = Path(args.out)
    if out.exists():
        shutil.rmtree(out)
    work = out / "work"
    work.mkdir(parents=True)
    run = vr.start("slcan", link=work / "lc", tunnel_link=work / "tun", wait_reader_s=120.0)
    src = vr.source_settings("slcan", link=str(work / "lc"), tunnel_link=str(work / "tun"))
    cfg = {
        "run": {"label": "soak", "rig": str(RIG), "notes": f"soak {args.minutes:g} min"},
        "recorder": {"startup_timeout_s": 60.0},
        "sources": {name: {"kind": kind, **st} for name, (kind, st) in src.items()},
    }
    (work / "soak.toml").write_bytes(tomli_w.dumps(cfg).encode())
    session = f"cdpr-soak-{os.getpid()}"
    cmd = (
        f"env -u COLUMNS -u LINES {CDPR} record --config {work / 'soak.toml'} --out {out}; "
        f"echo $? > {work / 'rc'}; sleep 5"
    )
    _tmux("new-session", "-d", "-s", session, "-x", "160", "-y", "50", cmd)
    samples: list[tuple[float, int]] = []
    try:
        pane_pid = int(_tmux("list-panes", "-t", session, "-F", "#{pane_pid}").split()[0])
        end = time.monotonic() + 120
        kids: list[int] = []
        while not kids and time.monotonic() < end:
            kids = _children(pane_pid)
            time.sleep(0.2)
        rec_pid = kids[0]
        if not run.started.wait(120.0):
            raise RuntimeError("the recorder never opened the adapter")
        t0 = time.monotonic()
        while time.monotonic() - t0 < duration_s:
            time.sleep(10.0)
            samples.append((time.monotonic() - t0, _rss_kib(rec_pid)))
            if len(samples) % 30 == 0:
                print(
                    f"  {samples[-1][0]:7.0f} s  RSS {samples[-1][1] / 1024:7.1f} MiB", flush=True
                )
        screen = _tmux("capture-pane", "-p", "-t", session)
        sent = run.frames_sent
        emu = getattr(run, "emulator", None)
        adapter_dropped = emu.frames_dropped if emu is not None else 0
        _tmux("send-keys", "-t", session, "C-c")  # the operator's Ctrl-C
        end = time.monotonic() + 120
        while not (work / "rc").exists() and time.monotonic() < end:
            time.sleep(0.2)
        rc = int((work / "rc").read_text())
    finally:
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True)
        run.stop()
    (path,) = sorted(out.glob("*_soak.mcap"))
    (out / "live_view.txt").write_text(screen)
    node = json.loads(
        subprocess.run(
            ["node", "--single-threaded", str(MCAP_CHECK), str(path)],
            capture_output=True,
            text=True,
        ).stdout
    )
    from mcap.reader import make_reader

    with path.open("rb") as fh:  # the run_end record only (the summary's metadata index)
        end_md = next(
            dict(m.metadata) for m in make_reader(fh).iter_metadata() if m.name == "run_end"
        )
    ana = subprocess.run(
        [str(CDPR), "analyze", str(path), "--out", str(out / "analysis")],
        capture_output=True,
        text=True,
    )
    # analysed cleanly: reduced (exit 0, or 1 for the warnings every run without a camera and a
    # model geometry carries) with no sample masked anywhere; the flags are printed as found
    import csv

    n_masked, flags = 0, set()
    for pts in (out / "analysis").glob("*/points.csv"):
        with pts.open() as fh:
            for row in csv.DictReader(fh):
                n_masked += int(row["n_masked"])
                flags |= set(filter(None, row["flags"].split(";")))
    warm = [r for t, r in samples if t >= 60.0] or [r for _, r in samples]
    growth = 100.0 * (warm[-1] - warm[0]) / warm[0]
    frames = node["topics"].get("/can_raw", 0)
    print(f"soak {args.minutes:g} min at {args.rate_hz:g} Hz ({4 * args.rate_hz:g} frames/s)")
    print(f"  record exit code        {rc}")
    print(f"  frames sent / recorded  {sent} / {frames} (file complete: {node['complete']})")
    counts = {**node["topics"], **node["samples"]}  # column-block streams: samples
    print(f"  tensions, tunnel        {counts.get('/tensions')}, "
          f"{counts.get('/tunnel')}")  # fmt: skip
    print(f"  dropped by the adapter  {adapter_dropped} frames (pty full: the reader fell behind)")
    print(f"  dropped                 {end_md['dropped_total']}")
    print(f"  faults                  {end_md.get('faults', '[]')}")
    print(f"  RSS after 1 min / end / max  {warm[0] / 1024:.1f} / {warm[-1] / 1024:.1f} / "
          f"{max(r for _, r in samples) / 1024:.1f} MiB: growth {growth:+.1f} %")  # fmt: skip
    print(f"  analyze exit code       {ana.returncode} {ana.stdout.strip()[-200:]}")
    print(f"  analysis                {n_masked} samples masked; flags: {', '.join(sorted(flags))}")
    print(f"  live view at the end    {out / 'live_view.txt'}")
    ok = (
        rc == 0
        and end_md["dropped_total"] == "0"
        and growth < 10.0
        and ana.returncode in (0, 1)
        and n_masked == 0
        and node["complete"]
    )
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
