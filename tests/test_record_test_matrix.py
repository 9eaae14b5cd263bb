"""``cdpr record --test-matrix``: the operator steps through the points of the campaign file, and
each point's start and end become ``test_point`` events with the agreed fields."""

from __future__ import annotations

from pathlib import Path

from cdpr.daq.live import TestPointStepper
from cdpr.pipelines.commands.record import _test_points

ROOT = Path(__file__).resolve().parents[1]
MATRIX = ROOT / "data_samples" / "campaign_alpha_sweep.toml"


def test_the_matrix_points_become_test_point_events_in_run_order() -> None:
    points = _test_points(str(MATRIX))
    # the sample file, by hand: a zero, 6 tares, 6 x 3 model-off windage points, 6 x 3 wind-on
    # points, a repeat, a closing zero
    assert len(points) == 1 + 6 + 18 + 18 + 1 + 1
    assert [p["kind"] for p in points[:2]] == ["zero", "tare"]
    assert points[-2] == {
        "point": "repeat-a2-v25.51",
        "kind": "wind_on",
        "target_aoa_deg": 2.0,
        "target_sideslip_deg": 0.0,
        "target_airspeed_mps": 25.51,
        "repeat_of": "alpha-a2-b0-v25.51",
    }
    assert sum(p["target_airspeed_mps"] == 41.42 for p in points) == 6 + 6

    said: list[tuple[str, dict]] = []
    stepper = TestPointStepper(points, lambda msg, **kw: said.append((msg, kw)))
    for _ in range(4):  # start and end the first two points
        stepper.toggle()
    assert [(kw["point"], kw["phase"]) for _, kw in said] == [
        ("zero-start", "start"), ("zero-start", "end"), ("tare-a-4-b0-v0", "start"),
        ("tare-a-4-b0-v0", "end"),
    ]  # fmt: skip
    assert all(kw["name"] == "test_point" for _, kw in said)
    assert said[2][1]["target_aoa_deg"] == -4.0 and said[2][1]["kind"] == "tare"


def test_live_view_test_points_go_on_the_topic_analyze_reads(tmp_path: Path) -> None:
    """``cdpr record --test-matrix`` declares ``/events`` (record_run: ``test_point_streams``):
    the points the operator marks land there, not on the recorder's ``/event``, which the
    analysis does not read for test points."""
    import cdpr.daq.drivers  # noqa: F401
    from cdpr.daq.live import LiveView, test_point_streams
    from cdpr.daq.recorder import Recorder
    from cdpr.daq.run_reader import open_run
    from cdpr.daq.source import create_source
    from cdpr.pipelines.run_arrays import _topic

    src = create_source("manual_tunnel", "tun", {"airspeed_mps": 0.0, "rate_hz": 20.0})
    path = tmp_path / "run.mcap"
    points = _test_points(str(MATRIX))[:2]
    with Recorder([src], path, extra_streams=test_point_streams()) as rec:
        lv = LiveView(rec, test_points=points, keys=False)
        assert lv.stepper is not None
        for _ in range(3):  # zero start, end; tare start (ended by finish)
            lv.stepper.toggle()
        lv.stepper.finish()
    with open_run(path) as run:
        assert _topic(run, "events") == "/events"
        ev = run.table("/events")
        log = run.table("/event")
    assert list(zip(ev["point"], ev["phase"], strict=True)) == [
        ("zero-start", "start"), ("zero-start", "end"), ("tare-a-4-b0-v0", "start"),
        ("tare-a-4-b0-v0", "end"),
    ]  # fmt: skip
    assert set(ev["name"]) == {"test_point"} and "test_point" not in set(log.get("name", []))
