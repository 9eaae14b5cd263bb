"""The benchmark's campaign-run generator (bench/campaign_run.py): its bulk-formatted tension
bodies are valid JSON with the values asked for, and the file reads back with the ``mcap``
package's own reader."""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from campaign_run import CABLES, fixed_decimal, tension_bodies, write_campaign_run  # noqa: E402


def test_fixed_decimal_is_json_of_one_width_and_the_value() -> None:
    v = np.array([1.0, 35.123456789, 99.999999996, 99.99999994, 160.5, 999.9999999951, 9999.5])
    out = fixed_decimal(v)
    assert out.shape == (len(v), 10)
    texts = [bytes(r).decode() for r in out]
    assert texts[2] == "100.000000" and texts[3] == "99.9999999"  # rounding carries a digit
    for x, s in zip(v, texts, strict=True):
        assert float(json.loads(s)) == pytest.approx(x, rel=6e-9), s
        assert not s.startswith("0")
    with pytest.raises(ValueError):
        fixed_decimal(np.array([0.5]))


def test_tension_bodies_parse_as_json() -> None:
    T = np.array([[35.0 + k + 0.123456 for k in range(8)], [300.0 - k for k in range(8)]])
    bodies = tension_bodies(T, np.array([1_000_000, 1_000_001]))
    for row, t, seq in zip(bodies, T, (1_000_000, 1_000_001), strict=True):
        b = json.loads(bytes(row))
        assert [b[f"T_{c}_N"] for c in CABLES] == pytest.approx(t.tolist(), rel=1e-8)
        assert b["seq"] == seq and b["status"] == 0
        assert all(b[f"status_{c}"] == 0 for c in CABLES)


def test_a_short_run_reads_back_with_the_mcap_reader(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    out = write_campaign_run(tmp_path / "r.mcap", duration_s=45.0, point_s=15.0, ramp_s=5.0)
    assert out["counts"] == {"tensions": 45_000, "pose": 1350, "tunnel": 450, "events": 6}
    counts: Counter[str] = Counter()
    last_seq = None
    with open(tmp_path / "r.mcap", "rb") as fh:
        reader = make_reader(fh)
        for _, channel, msg in reader.iter_messages(log_time_order=True):
            counts[channel.topic] += 1
            body = json.loads(msg.data)
            if channel.topic == "/tensions":
                T = [body[f"T_{c}_N"] for c in CABLES]
                assert all(35.0 - 1 < x < 300.0 + 1 for x in T)  # the rig file's limits + noise
                assert last_seq is None or body["seq"] == last_seq + 1
                last_seq = body["seq"]
            elif channel.topic == "/events":
                assert body["name"] == "test_point" and body["phase"] in ("start", "end")
        attachments = [a.name for a in reader.iter_attachments()]
    assert counts == {"/tensions": 45_000, "/pose": 1350, "/tunnel": 450, "/events": 6}
    assert attachments == ["rig/flat_experiment2.toml"]
