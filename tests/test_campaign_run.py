"""The benchmark's campaign-run generator (bench/campaign_run.py): the file reads back with the
``mcap`` package's own reader (the tensions' column blocks decoded by tests/_block_reader.py)."""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from _block_reader import block_rows, is_block_channel  # noqa: E402
from campaign_run import CABLES, write_campaign_run  # noqa: E402


def test_a_short_run_reads_back_with_the_mcap_reader(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    out = write_campaign_run(tmp_path / "r.mcap", duration_s=45.0, point_s=15.0, ramp_s=5.0)
    assert out["counts"] == {"tensions": 45_000, "pose": 1350, "tunnel": 450, "events": 6}
    counts: Counter[str] = Counter()
    last_seq = None
    with open(tmp_path / "r.mcap", "rb") as fh:
        reader = make_reader(fh)
        for _, channel, msg in reader.iter_messages(log_time_order=True):
            body = json.loads(msg.data)
            if channel.topic == "/tensions":
                assert is_block_channel(channel)  # 1 kHz: column blocks
                for row in block_rows(msg.data):
                    counts["/tensions"] += 1
                    T = [row[f"T_{c}_N"] for c in CABLES]
                    assert all(35.0 - 1 < x < 300.0 + 1 for x in T)  # rig limits + noise
                    assert last_seq is None or row["seq"] == last_seq + 1
                    last_seq = row["seq"]
                continue
            counts[channel.topic] += 1
            if channel.topic == "/events":
                assert body["name"] == "test_point" and body["phase"] in ("start", "end")
        attachments = [a.name for a in reader.iter_attachments()]
    # the per-sample view beside the blocks: every 20th sample (50 Hz)
    assert counts == {
        "/tensions": 45_000,
        "/tensions/view": 2250,
        "/pose": 1350,
        "/pose_status": 1350,  # one per frame, with or without a pose (every frame has one here)
        "/tunnel": 450,
        "/events": 6,
    }
    assert attachments == ["rig/flat_experiment2.toml"]
