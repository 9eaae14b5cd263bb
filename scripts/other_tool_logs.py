"""Write a recorded run out again as another tool's files, for the import half of the demo.

    python scripts/other_tool_logs.py RUN.mcap OUTDIR

OUTDIR gets what a lab without cdpr would have after a run: ``can.log`` (candump -L, written by
python-can's own logger, the first frame dropped so the log starts in the middle of a sample, as
almost every real candump log does), ``poses.csv`` (the camera's poses: ``t_ns, x_m, y_m, z_m,
roll_rad, pitch_rad, yaw_rad``), ``tunnel.csv`` (``t_ns, airspeed_mps, static_pressure_Pa,
temperature_K`` or ``density_kgpm3``, and ``relative_humidity`` when the run has it) and
``events.csv`` (the test points' start and end).
"""

from __future__ import annotations

import sys
from pathlib import Path

import can
import numpy as np
import pandas as pd

from cdpr.analysis.rotations import euler_from_quaternion
from cdpr.daq.run_reader import open_run


def main(run_path: str, out_dir: str) -> int:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with open_run(run_path) as run:
        frames = run.table("/can_raw")
        pose = run.table("/pose")
        tunnel = run.table("/tunnel")
        events = run.table("/events")
    logger = can.Logger(str(out / "can.log"))
    try:
        for row in frames.iloc[1:].itertuples(index=False):  # starts mid-sample
            logger.on_message_received(
                can.Message(
                    timestamp=row.t_ns / 1e9,
                    arbitration_id=int(row.arbitration_id),
                    is_extended_id=bool(row.is_extended),
                    data=bytes(row.data),
                    channel="can0",
                )
            )
    finally:
        logger.stop()
    ok = pose[["x_m", "qw"]].notna().all(axis=1) & (pose["status"].fillna(0) == 0)
    pose = pose[ok]
    eul = euler_from_quaternion(pose[["qw", "qx", "qy", "qz"]].to_numpy(np.float64))
    pd.DataFrame(
        {
            "t_ns": pose["t_ns"],
            "x_m": pose["x_m"],
            "y_m": pose["y_m"],
            "z_m": pose["z_m"],
            "roll_rad": eul[:, 0],
            "pitch_rad": eul[:, 1],
            "yaw_rad": eul[:, 2],
        }
    ).to_csv(out / "poses.csv", index=False)
    cols = ["t_ns", "airspeed_mps"] + [
        c
        for c in ("static_pressure_Pa", "temperature_K", "density_kgpm3", "relative_humidity")
        if c in tunnel
    ]
    if "static_pressure_Pa" in cols and "density_kgpm3" in cols:
        cols.remove("density_kgpm3")
    tunnel[cols].to_csv(out / "tunnel.csv", index=False)
    ev = events[events["name"] == "test_point"]
    keep = [
        "t_ns", "point", "phase", "kind", "target_aoa_deg", "target_sideslip_deg",
        "target_airspeed_mps", "repeat_of",
    ]  # fmt: skip
    ev[keep].to_csv(out / "events.csv", index=False)
    print(
        f"wrote {out}/can.log ({len(frames) - 1} frames, the first dropped), poses.csv "
        f"({len(pose)}), tunnel.csv ({len(tunnel)}), events.csv ({len(ev)})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
