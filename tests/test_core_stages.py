"""The one reduction core: every stage of the canonical order runs the public function it names (the
one its own tests check), the order in docs/analysis.md is the code's, and the core gives the same
numbers whichever of its callers binds it."""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from truth_rig import RIG_FILE, alpha_sweep

from cdpr.analysis.aero import ModelGeometry
from cdpr.analysis.balance import points_from_events, sample_mask
from cdpr.analysis.point_inputs import points_from_samples
from cdpr.analysis.reduction import run_stages, with_updates
from cdpr.analysis.stages import (
    DYNAMIC_STAGES,
    STEADY_STAGES,
    Corrections,
    PointSamples,
    SystematicInputs,
    core_stages,
    dynamic_stages,
    stage_table,
)
from cdpr.daq.schema import load_rig
from cdpr.pipelines.tunnel_section import tunnel_section_from_mapping

ROOT = Path(__file__).resolve().parents[1]
GEOMETRY = ModelGeometry(area_m2=0.0199, span_m=0.2441, chord_m=0.0815)


def test_docs_print_the_canonical_order_from_the_code() -> None:
    docs = (ROOT / "docs" / "analysis.md").read_text()
    assert stage_table() in docs, "docs/analysis.md: paste cdpr.analysis.stages.stage_table()"


def test_every_stage_wraps_one_public_function_of_analysis() -> None:
    names = [st.stage_name for st in STEADY_STAGES]
    assert len(set(names)) == len(names)
    for st in STEADY_STAGES:
        fn = st.wraps
        assert fn is not None and not fn.__name__.startswith("_"), st.stage_name
        assert fn.__module__.startswith("cdpr.analysis."), (st.stage_name, fn.__module__)
        # the stage calls it by the name it is imported under in the stage's own module
        home = sys.modules[st.__module__]
        assert getattr(home, fn.__name__, None) is fn, (st.stage_name, fn.__name__)


def _full_run():
    """An alpha sweep with a zero at each end, a repeat point and a model-off windage point, and
    every setting that makes each stage call its function."""
    sw = alpha_sweep(5)
    kind = list(sw.kind)
    kind[0] = kind[-1] = "zero"  # level tares at both ends double as the zeros
    bits = sample_mask(sw.tensions_N)
    ranges = points_from_events(sw.t_ns, sw.start_ns, sw.stop_ns)
    pts, _ = points_from_samples(
        kind=kind, ranges=ranges, t_ns=sw.t_ns, tensions_N=sw.tensions_N, mask_bits=bits,
        airspeed_mps=sw.airspeed_mps, density_kgpm3=sw.density_kgpm3, pose_t_ns=sw.pose_t_ns,
        poses=sw.poses, pose_cov=sw.pose_cov,
    )  # fmt: skip
    s = pts.n
    on = np.flatnonzero(np.array(kind) == "wind_on")
    group = np.arange(s)
    group[on[1]] = on[0]  # a repeat of the first wind-on point
    arrays = {
        "repeat_group": group,
        "static_pressure_Pa": np.full(s, 101325.0),
        "temperature_K": np.full(s, 293.15),
        "relative_humidity": np.full(s, 0.4),
    }
    pts = with_updates(pts, arrays=arrays)
    octagon = ROOT / "data_samples" / "tunnel_section_octagon.toml"
    doc = tomllib.loads(octagon.read_text())
    tunnel = tunnel_section_from_mapping(doc, str(octagon))
    samples = PointSamples(sw.t_ns, sw.tensions_N, ranges)
    motion = (np.zeros((s, 6)), np.zeros((s, 6)))
    return pts, tunnel, samples, motion


def test_every_stage_calls_the_function_it_names(monkeypatch: pytest.MonkeyPatch) -> None:
    rig = load_rig(RIG_FILE)
    pts, tunnel, samples, motion = _full_run()
    called: list[str] = []
    for st in STEADY_STAGES:
        fn = st.wraps

        def spy(*a, _fn=fn, _name=st.stage_name, **k):
            called.append(_name)
            return _fn(*a, **k)

        monkeypatch.setattr(sys.modules[st.__module__], fn.__name__, spy)
    stages = core_stages(
        rig,
        GEOMETRY,
        interaction=np.eye(6),
        corrections=Corrections(section=tunnel.geometry, walls=tunnel.walls),
        samples=samples,
        motion=motion,
        systematic=SystematicInputs(),
    )
    out = run_stages(pts, stages)
    ran = [step.name for step in out.steps]
    assert ran == [st.stage_name for st in STEADY_STAGES]  # all of them, in the one order
    assert sorted(set(called)) == sorted(ran), set(ran) - set(called)
    for step, st in zip(out.steps, STEADY_STAGES, strict=True):
        assert step.function == f"{st.wraps.__module__}.{st.wraps.__qualname__}"


# ------------------------------------------------------------------------------------------------
# the dynamic order (forced oscillation)
def test_docs_print_the_dynamic_order_from_the_code() -> None:
    docs = (ROOT / "docs" / "analysis.md").read_text()
    assert stage_table("dynamic") in docs, "docs/analysis.md: paste stage_table('dynamic')"


def test_every_dynamic_stage_wraps_one_public_function_of_analysis() -> None:
    names = [st.stage_name for st in DYNAMIC_STAGES]
    assert len(set(names)) == len(names)
    for st in DYNAMIC_STAGES:
        fn = st.wraps
        assert fn is not None and not fn.__name__.startswith("_"), st.stage_name
        assert fn.__module__.startswith("cdpr.analysis."), (st.stage_name, fn.__module__)
        home = sys.modules[st.__module__]
        assert getattr(home, fn.__name__, None) is fn, (st.stage_name, fn.__name__)


@pytest.fixture(scope="module")
def small_oscillation(tmp_path_factory: pytest.TempPathFactory):
    import lab_generator as lg

    specs = (lg.OscSpec("pitch", 5.0, 2.0, (41.42,), 6),)
    return lg.oscillation_case(tmp_path_factory.mktemp("dyn") / "case", specs, seed=4)


def test_every_dynamic_stage_calls_the_function_it_names(
    monkeypatch: pytest.MonkeyPatch, small_oscillation
) -> None:
    """Every stage of the dynamic order runs (a balance matrix and the corrections given), in the
    one order, each calling the function it names; the oscillation point gets its derivatives."""
    from _dynamic_inputs import dynamic_inputs

    rig = load_rig(small_oscillation.files["rig"])
    pts, samples, labels = dynamic_inputs(small_oscillation)
    s = pts.n
    pts = with_updates(
        pts,
        arrays={
            "static_pressure_Pa": np.full(s, 98_500.0),
            "temperature_K": np.full(s, 293.15),
            "relative_humidity": np.full(s, 0.45),
        },
    )
    called: list[str] = []
    for st in DYNAMIC_STAGES:
        fn = st.wraps

        def spy(*a, _fn=fn, _name=st.stage_name, **k):
            called.append(_name)
            return _fn(*a, **k)

        monkeypatch.setattr(sys.modules[st.__module__], fn.__name__, spy)
    geometry = ModelGeometry(area_m2=0.014646, span_m=0.2441, chord_m=0.060)
    stages = dynamic_stages(
        rig, geometry, samples, interaction=np.eye(6), corrections=Corrections()
    )
    out = run_stages(pts, stages)
    ran = [step.name for step in out.steps]
    assert ran == [st.stage_name for st in DYNAMIC_STAGES]
    assert sorted(set(called)) == sorted(ran), set(ran) - set(called)
    for step, st in zip(out.steps, DYNAMIC_STAGES, strict=True):
        assert step.function == f"{st.wraps.__module__}.{st.wraps.__qualname__}"
    i = labels.index("osc-pitch-A5d-f2-a0-v41.42")
    assert np.isfinite(out["Cma"][i]) and np.isfinite(out["Cmq_plus_Cmadot"][i])
    assert out["inertia_method"][i] == "tare"
    assert not np.isfinite(out["Cma"][labels.index("zero-1")])  # the zeros ride along
