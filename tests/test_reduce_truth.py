"""The reduction core against an independent truth (tests/truth_rig.py: own statics, quadprog).

Alpha sweep -4..+6 deg at 17.27, 25.51, 41.42 m/s on the flat prototype rig; the model's true mass
2 % and centre of mass 3 mm off the rig file; 0.05 N load-cell noise, 0.05 mm / 0.01 deg pose noise.
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from truth_rig import RIG_FILE, alpha_sweep, controller, statics, weight

from cdpr.analysis.aero import ModelGeometry
from cdpr.analysis.balance import (
    points_from_events,
    sample_mask,
    steady_points,
)
from cdpr.analysis.conventions import STATUS_SATURATED, STATUS_SLACK
from cdpr.analysis.point_inputs import points_from_samples
from cdpr.analysis.reduction import run_stages
from cdpr.analysis.stages import ReduceSettings, core_stages
from cdpr.analysis.weight import fit_weight
from cdpr.daq.schema import rig_from_mapping
from cdpr.pipelines.points_table import points_table

RIG = rig_from_mapping(tomllib.loads(RIG_FILE.read_text()), str(RIG_FILE))
GEOMETRY = ModelGeometry(0.2441 * 0.0815, 0.2441, 0.0815)


def _reduce(sw, ranges=None, status=None, airspeed=True, interaction=None, geometry=None):
    bits = sample_mask(sw.tensions_N, status=status)
    if ranges is None:
        ranges = points_from_events(sw.t_ns, sw.start_ns, sw.stop_ns)
    pts, extra = points_from_samples(
        kind=sw.kind,
        ranges=ranges,
        t_ns=sw.t_ns,
        tensions_N=sw.tensions_N,
        mask_bits=bits,
        airspeed_mps=sw.airspeed_mps if airspeed else None,
        density_kgpm3=sw.density_kgpm3 if airspeed else None,
        pose_t_ns=sw.pose_t_ns,
        poses=sw.poses,
        pose_cov=sw.pose_cov,
    )
    stages = core_stages(RIG, geometry, interaction=interaction)
    return run_stages(pts, stages), extra


def _errors(sw, out):
    on = np.array(sw.kind) == "wind_on"
    err = out["wrench_P_O_N_Nm"][on] - sw.true_wrench[on]
    sd = np.sqrt(np.diagonal(out.wrench_cov, axis1=1, axis2=2))[on]
    return err, sd


@pytest.mark.parametrize("level_only", [False, True], ids=["tare-polar", "level-tares"])
def test_accuracy_per_point(level_only: bool) -> None:
    for seed in range(3):
        sw = alpha_sweep(seed, level_tares_only=level_only)
        out, _ = _reduce(sw)
        err, _ = _errors(sw, out)
        assert np.abs(err[:, :3]).max() < 0.1, np.abs(err[:, :3]).max()
        assert np.abs(err[:, 3:]).max() < 0.005, np.abs(err[:, 3:]).max()
        flags = np.array(out.flag_text())[np.array(sw.kind) == "wind_on"]
        if level_only:
            # pitched points have no tare at their pose: the fitted weight model does the work,
            # and c_z (unseen by level tares) is named as left to the prior
            assert sum("weight_model" in f.split(";") for f in flags) == 15
            assert all("weight_model_prior_com_z" in f for f in flags)
        else:
            assert all("tare" in f.split(";") for f in flags)
        wm = out.meta["weight_model"]
        assert wm.mass_kg == pytest.approx(0.64 * 1.02, abs=3 * np.sqrt(wm.theta_cov[0, 0]))


def test_the_nominal_rig_mass_would_be_wrong() -> None:
    # the truth's model is 2 % heavier and 3 mm off: the rig file's mass alone misses by > 0.1 N
    sw = alpha_sweep(0, level_tares_only=True)
    bits = sample_mask(sw.tensions_N)
    ranges = points_from_events(sw.t_ns, sw.start_ns, sw.stop_ns)
    pts, _ = points_from_samples(
        kind=["wind_on" if k == "wind_on" else "windage" for k in sw.kind],
        ranges=ranges,
        t_ns=sw.t_ns,
        tensions_N=sw.tensions_N,
        mask_bits=bits,
        airspeed_mps=sw.airspeed_mps,
        density_kgpm3=sw.density_kgpm3,
        pose_t_ns=sw.pose_t_ns,
        poses=sw.poses,
        pose_cov=sw.pose_cov,
    )
    out = run_stages(pts, core_stages(RIG, None))
    on = np.array(sw.kind) == "wind_on"
    assert np.isnan(
        out["wrench_P_O_N_Nm"][on]
    ).all()  # no tare, no model: NaN, never a nominal value
    assert all("no_tare" in f for f in np.array(out.flag_text())[on])
    nominal = run_stages(pts, core_stages(RIG, None, ReduceSettings(allow_nominal_weight=True)))
    err = nominal["wrench_P_O_N_Nm"][on] - sw.true_wrench[on]
    assert np.abs(err[:, 2]).max() > 0.1
    assert all("weight_nominal" in f for f in np.array(nominal.flag_text())[on])


def test_coverage_of_95_percent_intervals() -> None:
    inside, total = 0, 0
    for level_only in (False, True):
        for seed in range(10, 25):
            sw = alpha_sweep(seed, level_tares_only=level_only)
            out, _ = _reduce(sw)
            err, sd = _errors(sw, out)
            inside += int((np.abs(err) <= 1.96 * sd).sum())
            total += err.size
    coverage = inside / total
    print(f"coverage of 95 % intervals: {coverage:.3f} over {total} components")
    assert 0.90 <= coverage <= 0.99


def test_detected_points_match_the_events_and_keep_the_accuracy() -> None:
    sw = alpha_sweep(3)
    ranges = steady_points(sw.t_ns, sw.airspeed_mps, sw.poses)
    assert len(ranges) == len(sw.kind)
    for (a, b), s0, s1 in zip(ranges, sw.start_ns, sw.stop_ns, strict=True):
        # inside the true steady span (both transitions trimmed), and most of it
        assert s0 <= sw.t_ns[a] and sw.t_ns[b - 1] <= s1
        assert (sw.t_ns[b - 1] - sw.t_ns[a]) > 0.4 * (s1 - s0)
    out, _ = _reduce(sw, ranges=ranges)
    err, _ = _errors(sw, out)
    assert np.abs(err[:, :3]).max() < 0.1 and np.abs(err[:, 3:]).max() < 0.005


def test_saturated_and_slack_samples_are_masked_and_flagged() -> None:
    sw = alpha_sweep(4)
    n = len(sw.t_ns)
    status = np.zeros((n, 8), np.int64)
    k = 10  # a wind-on point
    a = np.searchsorted(sw.t_ns, sw.start_ns[k])
    status[a + 5 : a + 40, 2] = STATUS_SATURATED
    status[a + 50 : a + 60, 5] = STATUS_SLACK
    # what a saturated cell reads: its ceiling, far from the truth
    sw.tensions_N[a + 5 : a + 40, 2] = 285.0
    sw.tensions_N[a + 50 : a + 60, 5] = 0.0
    out, extra = _reduce(sw, status=status, geometry=GEOMETRY)
    words = out.flag_text()[k].split(";")
    assert {"masked", "saturated", "slack"} <= set(words)
    assert extra["n_masked"][k] == 45
    assert all("masked" not in f for i, f in enumerate(out.flag_text()) if i != k)
    err, _ = _errors(sw, out)
    assert np.abs(err[:, :3]).max() < 0.1  # masked samples never reach the mean
    table = points_table(out, RIG, [f"p{i}" for i in range(out.n)])
    assert "saturated" in table.loc[k, "flags"]


def test_nan_edge_and_nan_inside_a_point_poison_nothing() -> None:
    sw = alpha_sweep(5)
    sw.tensions_N[0, :3] = np.nan  # the log starts mid-sample
    a = np.searchsorted(sw.t_ns, sw.start_ns[8])
    sw.tensions_N[a + 3, 4] = np.nan
    out, extra = _reduce(sw)
    assert np.isfinite(out["wrench_P_O_N_Nm"][np.array(sw.kind) == "wind_on"]).all()
    assert extra["n_masked"][8] == 1 and "nan" in out.flag_text()[8]
    err, _ = _errors(sw, out)
    assert np.abs(err[:, :3]).max() < 0.1
    # detection runs over the NaN edge as well
    assert len(steady_points(sw.t_ns, sw.airspeed_mps, sw.poses, sample_mask(sw.tensions_N) == 0))


def test_no_airspeed_says_so_and_never_reports_zero() -> None:
    sw = alpha_sweep(6)
    out, _ = _reduce(sw, airspeed=False, geometry=GEOMETRY)
    on = np.array(sw.kind) == "wind_on"
    assert np.isnan(out["CL"][on]).all() and np.isnan(out["q_Pa"]).all()
    assert all("no_airspeed" in f for f in np.array(out.flag_text())[on])
    err, _ = _errors(sw, out)  # the wrench itself is still the tare-referenced one
    assert np.abs(err[:, :3]).max() < 0.1
    assert np.abs(out["wrench_P_O_N_Nm"][on]).max() > 1.0


def test_interaction_matrix_is_applied_to_wrench_and_sigma() -> None:
    sw = alpha_sweep(7)
    K = np.eye(6) + 0.01 * np.arange(36).reshape(6, 6) / 36
    plain, _ = _reduce(sw)
    cal, _ = _reduce(sw, interaction=K)
    on = np.array(sw.kind) == "wind_on"
    np.testing.assert_allclose(
        cal["wrench_P_O_N_Nm"][on], plain["wrench_P_O_N_Nm"][on] @ K.T, rtol=1e-12
    )
    np.testing.assert_allclose(
        cal.wrench_cov[on], K @ plain.wrench_cov[on] @ K.T, rtol=1e-10, atol=1e-15
    )
    assert any(s.name == "balance_interaction" and "applied" in s.note for s in cal.steps)


def test_coefficients_and_check_columns() -> None:
    sw = alpha_sweep(8)
    out, _ = _reduce(sw, geometry=GEOMETRY)
    on = np.array(sw.kind) == "wind_on"
    qS = 0.5 * sw.density_kgpm3[0] * sw.speed_mps[on] ** 2 * GEOMETRY.area_m2
    # the free stream blows along +x_O: with zero sideslip the drag is the force along +x_O and the
    # lift the force along +z_O whatever the attitude (by hand, from the definitions)
    aoa = out["aoa_rad"][on]
    Wt = sw.true_wrench[on]
    lift, drag = Wt[:, 2], Wt[:, 0]
    np.testing.assert_allclose(out["CL"][on], lift / qS, atol=5 * out["sd_CL"][on].max())
    np.testing.assert_allclose(out["CD"][on], drag / qS, atol=5 * out["sd_CD"][on].max())
    # the angle of attack is the platform pitch with the default mounting (nose upstream, level),
    # to second order in the small roll and yaw the load deflects the platform by (up to 1e-3 rad)
    np.testing.assert_allclose(aoa, out["pose_O_m_rad"][on, 4], atol=2e-6)
    assert np.nanmax(out["check_max_abs_dT_N"]) < 1.0


def test_weight_fit_recovers_an_exact_polar() -> None:
    data = tomllib.loads(RIG_FILE.read_text())
    anchors = np.array([c["anchor_O_m"] for c in data["cables"]])
    attach = np.array([c["attach_P_m"] for c in data["cables"]])
    mass, com = 0.7, np.array([0.004, -0.002, 0.006])
    poses = np.array(
        [[0.5, 0, 0.36, r, p, 0] for r in (-0.1, 0.0, 0.1) for p in np.deg2rad([-6, 0, 6])]
    )
    lo, hi = np.full(8, 35.0), np.full(8, 285.0)
    y = []
    for q in poses:
        A = statics(anchors, attach, q)
        T = controller(A, weight(mass, com, q), lo, hi)
        y.append(-A @ T)
    wm = fit_weight(
        poses, np.array(y), np.tile(np.eye(6) * 1e-8, (9, 1, 1)), RIG.gravity_O_mps2, 0.64,
        np.zeros(3), 0.05, 0.01,
    )  # fmt: skip
    assert wm.mass_kg == pytest.approx(mass, rel=1e-6)
    np.testing.assert_allclose(wm.com_P_m, com, atol=1e-6)
    assert wm.weak == ()


def test_a_stage_inserted_into_the_order_is_logged_and_adds_its_sigma() -> None:
    """The engine's protocol: a plain function on points, wrapped by @stage around the function
    it calls, bound with its settings and placed in the list of stages, is run and logged."""
    import functools

    from cdpr.analysis.reduction import Points, stage, with_updates

    def drag(V: np.ndarray, drag_N: float) -> np.ndarray:
        return np.where(V > 1.0, drag_N, 0.0)

    @stage("windage_model", wraps=drag)
    def windage(p: Points, *, drag_N: float, sd_N: float) -> Points:
        W = p["wrench_P_O_N_Nm"].copy()
        on = p["kind"] == "wind_on"
        W[on, 0] -= drag(p["airspeed_mps"][on], drag_N)
        cov = np.zeros((p.n, 6, 6))
        cov[on, 0, 0] = sd_N**2
        return with_updates(
            p, arrays={"wrench_P_O_N_Nm": W}, terms={"windage": cov}, flag={"windage": on}
        )

    sw = alpha_sweep(9)
    plain, _ = _reduce(sw)
    bits = sample_mask(sw.tensions_N)
    ranges = points_from_events(sw.t_ns, sw.start_ns, sw.stop_ns)
    pts, _ = points_from_samples(
        kind=sw.kind, ranges=ranges, t_ns=sw.t_ns, tensions_N=sw.tensions_N, mask_bits=bits,
        airspeed_mps=sw.airspeed_mps, density_kgpm3=sw.density_kgpm3, pose_t_ns=sw.pose_t_ns,
        poses=sw.poses, pose_cov=sw.pose_cov,
    )  # fmt: skip
    stages = core_stages(RIG, GEOMETRY)
    at = [getattr(st, "func", st).stage_name for st in stages].index("weight_tare") + 1
    stages.insert(at, functools.partial(windage, drag_N=0.2, sd_N=0.01))
    out = run_stages(pts, stages)
    names = [s.name for s in out.steps]
    assert names.index("weight_tare") < names.index("windage_model") < names.index("coefficients")
    step = out.steps[names.index("windage_model")]
    assert step.settings == {"drag_N": 0.2, "sd_N": 0.01} and step.flagged == 18
    assert step.function.endswith("drag")
    on = np.array(sw.kind) == "wind_on"
    np.testing.assert_allclose(out["wrench_P_O_N_Nm"][on, 0], plain["wrench_P_O_N_Nm"][on, 0] - 0.2)
    np.testing.assert_allclose(
        out.wrench_cov[on, 0, 0], plain.wrench_cov[on, 0, 0] + 0.01**2, rtol=1e-12
    )


def test_a_point_without_pose_frames_is_flagged_not_fatal() -> None:
    sw = alpha_sweep(11)
    k = 12  # a wind-on point whose camera frames were all lost
    lost = (sw.pose_t_ns >= sw.start_ns[k]) & (sw.pose_t_ns <= sw.stop_ns[k])
    sw.pose_t_ns, sw.poses, sw.pose_cov = sw.pose_t_ns[~lost], sw.poses[~lost], sw.pose_cov[~lost]
    out, extra = _reduce(sw, geometry=GEOMETRY)
    assert extra["n_pose_frames"][k] == 0
    assert "no_pose" in out.flag_text()[k] and np.isnan(out["wrench_P_O_N_Nm"][k]).all()
    assert np.isnan(out["CL"][k])
    others = np.array(sw.kind) == "wind_on"
    others[k] = False
    assert np.isfinite(out["wrench_P_O_N_Nm"][others]).all()
