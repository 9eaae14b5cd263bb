"""Batch post-processing of recorded runs (``cdpr analyze`` / ``make analyze``) on the reduction core.

For every run (an MCAP file written by the recorder): the embedded rig, the tension stream with its
status bits and counter, the tunnel and pose streams (with the camera's per-frame covariance) and the
test-point events; the test points (from the ``/events`` stream where the run has one, detected
steady points otherwise, :mod:`cdpr.analysis.balance`); then the reduction core
(:mod:`cdpr.pipelines.reduce`): weight model and weight tares, balance interaction matrix, wrench
and σ, axes, moment transfer, coefficients, the tension check.  When the virtual rig's truth file
sits beside the run, the true wrench is compared too.  Runs are processed in parallel on a Dask
cluster (local by default, or an address).

Outputs per run, in ``OUT/<run stem>/`` (written to a temporary folder, then renamed):
``points.csv`` (the per-point table, docs/analysis.md), ``summary.json`` (inputs with SHA-256,
options, stage log, weight model, warnings, software version), ``report.md``, ``tensions.png``,
``wrench.png``, ``check.png``.  ``OUT/index.md`` lists every run.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import tomllib
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.aero import ModelGeometry, air_density, transfer_moment
from cdpr.analysis.balance import (
    MASK_NAMES,
    SteadyRule,
    interpolate_at,
    points_from_events,
    sample_mask,
    steady_points,
)
from cdpr.analysis.conventions import WRENCH_COLUMNS
from cdpr.analysis.errors import CdprError, ConfigError
from cdpr.analysis.reduction import points_from_samples
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import euler_from_quaternion, euler_rate_matrix, rotation_from_euler
from cdpr.daq.schema import rig_from_mapping

from . import __version__
from .config import file_sha256
from .freshness import fingerprint, is_current
from .online_compare import compare_online
from .reduce import (
    ReduceSettings,
    correction_stages,
    point_spectra,
    points_table,
    reduce_points,
    reduction_stages,
    steps_log,
)
from .tunnel_section import TunnelSection

PAPER_POSE_SD: tuple[float, ...] = (5e-4, 5e-4, 5e-4, *(float(np.deg2rad(0.1)),) * 3)
"""The paper's camera precision (0.5 mm, 0.1 deg): the pose σ fallback, used only with a flag."""

INFO_FLAGS: frozenset[str] = frozenset(
    {"tare", "weight_model", "weight_model_prior_com_z", "weight_model_prior_com_x",
     "weight_model_prior_com_y", "weight_model_prior_mass", "geometry_from_options",
     "windage_tare", "wall_corrected", "uncorrected"}
)  # fmt: skip
"""Flag words that describe what was done; every other word is a warning (exit code 1)."""


@dataclass(frozen=True)
class AnalyzeOptions:
    """Settings of the analysis (all recorded in every summary).

    geometry: the model's reference geometry (from the test matrix, or options: flagged); None:
        no coefficients (flag ``no_geometry`` on wind-on points).
    corrections: run the correction stages (zero drift, flow conditions, windage, wall
        corrections, repeatability; ``cdpr analyze --matrix``); tunnel: the matrix's ``[tunnel]``
        (None: no windage model and no wall corrections, flagged); matrix_file: its path.
    pose_sd_fallback: pose σ per frame when the pose stream carries no covariance (flagged).
    balance_file: ``cdpr calibrate balance`` output whose interaction matrix is applied.
    loadcell_calibration_file: a load-cell calibration file (``cdpr calibrate loadcells``): every
        tension is re-derived from the run's recorded raw counts, ``T = (counts - offset) * gain``,
        before the reduction (None: the recorded tensions); loadcell_calibration_from: who named
        it (``--loadcell-calibration`` or the test matrix), said in the summary and report.
    """

    geometry: ModelGeometry | None = None
    pose_sd_fallback: tuple[float, ...] = PAPER_POSE_SD
    balance_file: str | None = None
    rule: SteadyRule = field(default_factory=SteadyRule)
    reduce: ReduceSettings = field(default_factory=ReduceSettings)
    corrections: bool = False
    tunnel: TunnelSection | None = None
    matrix_file: str | None = None
    loadcell_calibration_file: str | None = None
    loadcell_calibration_from: str | None = None


@dataclass
class RunData:
    """The arrays of one run that the analysis needs (what ``open_run`` will hand over)."""

    path: Path
    rig: Rig
    t_ns: np.ndarray  # (n,) tension sample times
    tensions_N: np.ndarray  # (n, m), NaN where a frame was missing
    mask_bits: np.ndarray  # (n,) sample_mask bits (status, counter gaps, NaN)
    tunnel: tuple[np.ndarray, np.ndarray] | None  # airspeed, density on t_ns; None: no stream
    pose_t_ns: np.ndarray  # (k,)
    poses: np.ndarray  # (k, 6)
    pose_cov: np.ndarray | None  # (k, 6, 6) in [position, Euler angles], or None
    pose_bad: np.ndarray  # (k,) bool
    pose_source: str
    events: list[tuple[int, dict[str, Any]]]
    truth: dict[str, np.ndarray] | None
    camera: bool = False
    pressure_temperature: tuple[np.ndarray, np.ndarray] | None = None
    """Static pressure (Pa) and temperature (K) on ``t_ns`` when the tunnel stream has them."""
    humidity: np.ndarray | None = None
    """Relative humidity (0..1) on ``t_ns``, held from the last tunnel message (NaN where that
    message has none); None when no tunnel message carries one."""
    recalibration: dict[str, Any] | None = None
    """When the tensions were re-derived from the raw counts: the calibration's file, id, date and
    the largest change against the recorded tensions per cable (N); None: tensions as recorded."""


def _topic(run: Any, suffix: str) -> str | None:
    """The first topic of ``run`` whose last name is ``suffix`` and that has messages."""
    hits = [t for t, i in run.streams.items() if t.rstrip("/").split("/")[-1] == suffix and i.count]
    return hits[0] if hits else None


def _column(df: pd.DataFrame, name: str, fill: float = np.nan) -> np.ndarray:
    """Column ``name`` of ``df`` as float64 (``fill`` where the column is absent)."""
    if name not in df:
        return np.full(len(df), fill)
    return pd.to_numeric(df[name], errors="coerce").to_numpy(np.float64)


TENSION_WINDOW_NS = 300 * 10**9
"""Tensions are decoded 5 minutes at a time into preallocated arrays (bounded memory)."""


def _raw_columns(rig: Rig) -> list[str]:
    return [f"raw_{n}_counts" for n in rig.cable_names]


def _no_raw_counts(p: Path, topic: str, missing: Sequence[str]) -> ConfigError:
    return ConfigError(
        str(p),
        topic,
        f"no raw counts column {', '.join(missing)}: the tensions cannot be re-derived with "
        "a load-cell calibration (run recorded or imported without raw counts)",
    )


def _tension_columns(
    run: Any, topic: str, rig: Rig, p: Path, raw: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Times (n,), tensions (n, m) (NaN where a field is missing), the status words OR-ed over the
    cables and the message (n,), the counter ``seq`` (None unless every message has one), and with
    ``raw`` the ``raw_<cable>_counts`` (n, m) (NaN where missing; else None), read window by
    window into arrays sized from the stream's message count."""
    cols = [f"T_{n}_N" for n in rig.cable_names]
    rcols = _raw_columns(rig) if raw else []
    R = np.empty((run.streams[topic].count, len(rcols)))
    scols = [f"status_{n}" for n in rig.cable_names] + ["status"]
    n_max = run.streams[topic].count
    t_ns = np.empty(n_max, np.int64)
    T = np.empty((n_max, len(cols)))
    st = np.zeros(n_max, np.int64)
    seq: np.ndarray | None = np.empty(n_max, np.int64)
    seen: set[str] = set()
    i = 0
    for df in run.iter_tables(topic, TENSION_WINDOW_NS):
        k = len(df)
        if i + k > n_max:
            raise ConfigError(str(p), topic, f"more messages than the summary's {n_max}")
        seen.update(df.columns)
        t_ns[i : i + k] = df["t_ns"].to_numpy(np.int64)
        for j, c in enumerate(cols):
            T[i : i + k, j] = _column(df, c)
        for j, c in enumerate(rcols):
            R[i : i + k, j] = _column(df, c)
        for c in scols:
            if c in df:
                st[i : i + k] |= np.nan_to_num(_column(df, c)).astype(np.int64)
        if seq is not None:
            if "seq" in df and df["seq"].notna().all():
                seq[i : i + k] = df["seq"].to_numpy(np.int64)
            else:
                seq = None
        i += k
    if i != n_max:  # never analyse part of a stream silently
        raise ConfigError(str(p), topic, f"read {i} of the summary's {n_max} messages")
    missing = [c for c in cols if c not in seen]
    if missing:
        raise ConfigError(str(p), topic, f"field {missing[0]} missing for rig {rig.name!r}")
    missing = [c for c in rcols if c not in seen]
    if missing:
        raise _no_raw_counts(p, topic, missing)
    return t_ns[:i], T[:i], st[:i], None if seq is None else seq[:i], R[:i] if raw else None


_TUNNEL_COLUMNS = (
    "airspeed_mps", "density_kgpm3", "static_pressure_Pa", "temperature_K", "relative_humidity",
)  # fmt: skip
_POSE_COLUMNS = (
    "x_m", "y_m", "z_m", "qw", "qx", "qy", "qz", "status",
    *(f"cov_{i}{j}" for i in range(6) for j in range(6)),
)  # fmt: skip


def _slim_table(run: Any, topic: str, names: Sequence[str]) -> pd.DataFrame:
    """``t_ns`` and the columns ``names`` that the stream has (float64, NaN where a message lacks
    one), read window by window so that only these columns are kept."""
    parts: list[dict[str, np.ndarray]] = []
    seen: set[str] = set()
    for df in run.iter_tables(topic, TENSION_WINDOW_NS):
        seen.update(c for c in names if c in df)
        part = {c: _column(df, c) for c in names if c in df}
        part["t_ns"] = df["t_ns"].to_numpy(np.int64)
        parts.append(part)
    n_read = sum(len(q["t_ns"]) for q in parts)
    if n_read != run.streams[topic].count:  # never analyse part of a stream silently
        raise ConfigError(
            str(run.path),
            topic,
            f"read {n_read} of the summary's {run.streams[topic].count} messages",
        )
    cols = ["t_ns", *[c for c in names if c in seen]]
    out = {
        c: np.concatenate([q[c] if c in q else np.full(len(q["t_ns"]), np.nan) for q in parts])
        if parts
        else np.empty(0, np.int64 if c == "t_ns" else np.float64)
        for c in cols
    }
    return pd.DataFrame(out)


def _run_rig(run: Any, p: Path) -> Rig:
    """The rig file attached to an open run."""
    rigs = [k for k in run.attachments if k.startswith("rig/")]
    if not rigs:
        raise ConfigError(str(p), "attachments", "no rig file attached to the run")
    rig_text = run.attachments[rigs[0]][1].decode()
    try:
        return rig_from_mapping(tomllib.loads(rig_text), f"{p}:{rigs[0]}")
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}:{rigs[0]}", "", f"invalid TOML: {exc}") from None


def _run_calibration(cal_file: Any, rig: Rig, p: Path) -> Any:
    """``cal_file`` (a :class:`cdpr.daq.loadcell.LoadCellCalibrationFile`) for the run's cables;
    a mismatch names the missing cables and the run."""
    try:
        return cal_file.for_cables(rig.cable_names)
    except ConfigError as exc:
        raise ConfigError(exc.source, exc.key, f"{exc.problem}, for run {p.name}") from None


def check_recalibration(path: str | os.PathLike[str], cal_file: Any) -> None:
    """Before any output: the run's cables match ``cal_file`` and its tension stream declares
    the ``raw_<cable>_counts`` columns (a stream without declared fields is checked on reading)."""
    from cdpr.daq.run_reader import open_run

    p = Path(path)
    with open_run(p) as run:
        rig = _run_rig(run, p)
        topic = _topic(run, "tensions")
        fields = run.streams[topic].fields if topic else {}
    if topic is not None and fields:
        missing = [c for c in _raw_columns(rig) if c not in fields]
        if missing:
            raise _no_raw_counts(p, topic, missing)
    _run_calibration(cal_file, rig, p)


def load_run(path: str | os.PathLike[str], loadcell_calibration: Any = None) -> RunData:
    """Read a run file through :func:`cdpr.daq.run_reader.open_run` (only the topics the analysis
    needs): rig attachment, tensions with status, tunnel conditions, pose (camera with its
    covariance, else the truth file beside the run, else the rig's reference pose), events.

    loadcell_calibration: a :class:`cdpr.daq.loadcell.LoadCellCalibrationFile`; the tensions are
    then re-derived from the recorded ``raw_<cable>_counts`` with it
    (:func:`cdpr.daq.loadcell.tensions_from_raw`, the recorder's conversion)."""
    from cdpr.daq.run_reader import open_run

    p = Path(path)
    recal = None
    with open_run(p) as run:
        rig = _run_rig(run, p)
        cal = (
            None if loadcell_calibration is None else _run_calibration(loadcell_calibration, rig, p)
        )
        topic = _topic(run, "tensions")
        n_tens = run.streams[topic].count if topic else 0
        if topic is None or n_tens < 3:
            raise ConfigError(
                str(p), "/tensions", f"expected a tension stream, got {n_tens} messages"
            )
        t_ns, T, st, seq, raw = _tension_columns(run, topic, rig, p, raw=cal is not None)
        if cal is not None:
            from cdpr.daq.loadcell import tensions_from_raw

            assert raw is not None
            T_new = tensions_from_raw(cal, raw)
            change = np.abs(T_new - T)
            recal = {
                "calibration_id": loadcell_calibration.id,
                "created_utc": loadcell_calibration.extra.get("created_utc"),
                "max_abs_change_N": {
                    n: float(np.nanmax(change[:, j])) if np.isfinite(change[:, j]).any() else None
                    for j, n in enumerate(rig.cable_names)
                },
            }
            T = T_new
        tun_topic = _topic(run, "tunnel")
        tun = _slim_table(run, tun_topic, _TUNNEL_COLUMNS) if tun_topic else None
        pose_topic = _topic(run, "pose")
        pose_df = _slim_table(run, pose_topic, _POSE_COLUMNS) if pose_topic else None
        ev_topic = _topic(run, "events")
        ev_df = run.table(ev_topic) if ev_topic else None
    if not np.all(np.diff(t_ns) > 0):  # the reader sorts; a repeated time keeps its first sample
        order = np.argsort(t_ns, kind="stable")
        t_ns, T, st = t_ns[order], T[order], st[order]
        keep = np.concatenate([[True], np.diff(t_ns) > 0])
        t_ns, T, st = t_ns[keep], T[keep], st[keep]
        if seq is not None:
            seq = seq[order][keep]
    counter = seq
    bits = sample_mask(T, status=st, counter=counter, counter_modulus=2**62)

    tunnel = None
    pressure_temperature: Any = None
    humidity = None
    if tun is not None and len(tun):
        tt = tun["t_ns"].to_numpy(np.int64)
        v = _column(tun, "airspeed_mps")
        rho_src = _column(tun, "density_kgpm3")
        need = ~np.isfinite(rho_src)
        if need.any():
            ps, tk = _column(tun, "static_pressure_Pa"), _column(tun, "temperature_K")
            ok = need & (ps > 0) & (tk > 0)  # NaN compares False
            rho_src[ok] = air_density(ps[ok], tk[ok])
        good = np.isfinite(v)
        if good.sum() >= 1:
            vi = interpolate_at(t_ns, tt[good], v[good])
            rg = np.isfinite(rho_src)
            ri = (
                interpolate_at(t_ns, tt[rg], rho_src[rg])
                if rg.any()
                else np.full(len(t_ns), np.nan)
            )
            tunnel = (vi, ri)
        pT = [_column(tun, k) for k in ("static_pressure_Pa", "temperature_K")]
        if all(np.isfinite(x).any() for x in pT):
            pressure_temperature = tuple(
                interpolate_at(t_ns, tt[np.isfinite(x)], x[np.isfinite(x)]) for x in pT
            )
        rh = _column(tun, "relative_humidity")
        if np.isfinite(rh).any():
            # held from the last message, never interpolated across a message without it: a
            # point that meets a gap gets NaN (flag humidity_not_given), not a bridged value
            j = np.clip(np.searchsorted(tt, t_ns, side="right") - 1, 0, len(tt) - 1)
            humidity = rh[j]

    truth = None
    truth_path = p.with_name(p.name.removesuffix(".mcap") + ".truth.npz")
    if truth_path.exists():
        with np.load(truth_path) as z:
            truth = {k: z[k] for k in z.files}

    events = _events(ev_df)
    if pose_df is not None and len(pose_df):
        tp = pose_df["t_ns"].to_numpy(np.int64)
        pos = np.column_stack([_column(pose_df, c) for c in ("x_m", "y_m", "z_m")])
        quat = np.column_stack([_column(pose_df, c) for c in ("qw", "qx", "qy", "qz")])
        bad = ~(np.isfinite(pos).all(axis=1) & np.isfinite(quat).all(axis=1))
        bad |= np.nan_to_num(_column(pose_df, "status", 0.0)) != 0
        eul = np.full((len(tp), 3), np.nan)
        if (~bad).any():
            eul[~bad] = euler_from_quaternion(quat[~bad])
        poses = np.concatenate([pos, eul], axis=1)
        pose_cov = None
        ccols = [f"cov_{i}{j}" for i in range(6) for j in range(6)]
        if all(c in pose_df for c in ccols):
            C = np.column_stack([_column(pose_df, c) for c in ccols]).reshape(-1, 6, 6)
            # a frame without any covariance value: none for the run; a partly missing one
            # (NaN recorded as null) marks its frame bad
            if np.isfinite(C).any(axis=(1, 2)).all():
                # the camera reports [position, rotation vector in {O}]; Euler angles:
                # dpsi = H^-1 dtheta
                Hinv = np.linalg.inv(euler_rate_matrix(np.nan_to_num(eul)))
                J = np.zeros((len(tp), 6, 6))
                J[:, :3, :3] = np.eye(3)
                J[:, 3:, 3:] = Hinv
                pose_cov = J @ C @ np.swapaxes(J, 1, 2)
                bad |= ~np.isfinite(pose_cov).all(axis=(1, 2))
        if (~bad).sum() >= 2:
            src = "camera (/pose stream)" + ("" if pose_cov is not None else ", no covariance")
            return RunData(
                p, rig, t_ns, T, bits, tunnel, tp, poses, pose_cov, bad, src, events, truth, True,
                pressure_temperature, humidity, recal,
            )  # fmt: skip
    if truth is not None and "position_O_m" in truth:
        q6 = np.concatenate([truth["position_O_m"], truth["euler_rad"]], axis=1)
        src = f"virtual-rig truth ({truth_path.name}); no camera stream in the run"
        tp = np.asarray(truth["t_ns"], dtype=np.int64)
        return RunData(
            p, rig, t_ns, T, bits, tunnel, tp, q6, None, np.zeros(len(tp), bool), src,
            events, truth, False, pressure_temperature, humidity, recal,
        )  # fmt: skip
    ref = np.concatenate([rig.reference_position_O_m, rig.reference_euler_rad])
    return RunData(
        p, rig, t_ns, T, bits, tunnel, t_ns.copy(), np.tile(ref, (len(t_ns), 1)), None,
        np.zeros(len(t_ns), bool), "rig reference pose (no pose stream)", events, truth, False,
        pressure_temperature, humidity, recal,
    )  # fmt: skip


def _events(df: pd.DataFrame | None) -> list[tuple[int, dict[str, Any]]]:
    """The ``test_point`` events as (t_ns, fields as recorded), sorted by time."""
    if df is None or not len(df) or "name" not in df:
        return []
    rows = df[df["name"] == "test_point"]
    out = []
    for t, rec in zip(rows["t_ns"].tolist(), rows.to_dict("records"), strict=True):
        rec.pop("t_ns", None)
        out.append((int(t), {k: v for k, v in rec.items() if v is not None and v == v}))
    return sorted(out, key=lambda e: e[0])


@dataclass
class PointPlan:
    """The test points of a run: index ranges into the tension samples and what is known of each."""

    ranges: list[tuple[int, int]]
    labels: list[str]
    kind: list[str]
    source: str  # "events" | "detected"
    flags: list[str]
    targets: dict[str, list[Any]]


def plan_points(run: RunData, rule: SteadyRule) -> PointPlan:
    """Test points from the ``/events`` stream when the run has one, else detected steady points."""
    if run.events:
        opened: dict[str, tuple[int, dict[str, Any]]] = {}
        pts: list[tuple[int, int, dict[str, Any], str]] = []
        for t, b in run.events:
            label = str(b.get("point", ""))
            phase = b.get("phase")
            if phase == "start":
                for t0, b0 in opened.values():  # a point never ended closes here
                    pts.append((t0, t - 1, b0, "no_end_event"))
                opened = {label: (t, b)}
            elif phase == "end" and label in opened:
                t0, b0 = opened.pop(label)
                pts.append((t0, t, b0, ""))
        for t0, b0 in opened.values():
            pts.append((t0, int(run.t_ns[-1]), b0, "no_end_event"))
        pts.sort(key=lambda x: x[0])
        ranges = points_from_events(run.t_ns, [x[0] for x in pts], [x[1] for x in pts])
        targets = {
            k: [x[2].get(k, np.nan) for x in pts]
            for k in ("target_aoa_deg", "target_sideslip_deg", "target_airspeed_mps", "repeat_of")
        }
        return PointPlan(
            ranges,
            [str(x[2].get("point", "")) for x in pts],
            [str(x[2].get("kind", "wind_on")) for x in pts],
            "events",
            [x[3] for x in pts],
            targets,
        )
    q = interpolate_at(run.t_ns, run.pose_t_ns[~run.pose_bad], run.poses[~run.pose_bad])
    v = run.tunnel[0] if run.tunnel is not None else None
    ranges = steady_points(run.t_ns, v, q, run.mask_bits == 0, rule)
    if v is None:
        kind = ["unknown"] * len(ranges)
    else:
        vm = np.array([np.nanmean(v[a:b]) for a, b in ranges])
        kind = ["tare" if x < rule.wind_off_mps else "wind_on" for x in vm]
    return PointPlan(
        ranges,
        [f"d{i:02d}" for i in range(len(ranges))],
        kind,
        "detected",
        [""] * len(ranges),
        {},
    )


def _correction_inputs(run: RunData, plan: PointPlan) -> dict[str, np.ndarray]:
    """Per-point inputs of the correction stages: ``temperature_K`` and ``static_pressure_Pa``
    (means over each point, NaN without them in the tunnel stream), ``relative_humidity`` (the
    mean over each point; NaN when any sample of the point has none) and ``repeat_group`` (the
    index of the point a point repeats, else its own)."""
    from cdpr.analysis.balance import point_stats

    s = len(plan.ranges)
    out: dict[str, np.ndarray] = {}
    for k, key in enumerate(("static_pressure_Pa", "temperature_K")):
        if run.pressure_temperature is None:
            out[key] = np.full(s, np.nan)
        else:
            v = run.pressure_temperature[k]
            out[key] = point_stats(v, plan.ranges, run.mask_bits).mean[:, 0]
    rh = np.full(s, np.nan)
    if run.humidity is not None:
        for i, (a, b) in enumerate(plan.ranges):
            w = run.humidity[a:b]
            if w.size and np.isfinite(w).all():
                rh[i] = float(np.mean(w))
    out["relative_humidity"] = rh
    first = {lab: i for i, lab in reversed(list(enumerate(plan.labels)))}
    rep = plan.targets.get("repeat_of", [""] * s)
    out["repeat_group"] = np.array(
        [first.get(str(r), i) if isinstance(r, str) and r else i for i, r in enumerate(rep)],
        dtype=np.int64,
    )
    return out


def read_balance_calibration(path: str | None) -> tuple[Any, Any]:
    """The interaction matrix and, where ``cdpr calibrate balance`` could fit it, the second-order
    model ``(K1, K2)`` from its JSON output; ``(None, None)`` without a file."""
    if path is None:
        return None, None
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(path, "", f"cannot read the balance calibration: {exc}") from None
    K = np.asarray(doc.get("interaction_matrix", []), dtype=np.float64)
    if K.shape != (6, 6) or not np.all(np.isfinite(K)):
        raise ConfigError(
            path, "interaction_matrix", f"expected a finite 6x6 matrix, got {K.shape}"
        )
    so = doc.get("second_order")
    if so is None:
        return K, None
    K1 = np.asarray(so.get("K1", []), dtype=np.float64)
    K2 = np.asarray(so.get("K2", []), dtype=np.float64)
    if K1.shape != (6, 6) or K2.shape != (6, 21):
        raise ConfigError(
            path, "second_order", f"expected K1 (6, 6), K2 (6, 21), got {K1.shape}, {K2.shape}"
        )
    if not (np.all(np.isfinite(K1)) and np.all(np.isfinite(K2))):
        raise ConfigError(path, "second_order", "expected finite values")
    return K, (K1, K2)


def analyze_arrays(run: RunData, opts: AnalyzeOptions) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The per-point table of one run and the summary parts of the reduction (stage log, weight
    model, warnings)."""
    rig = run.rig
    plan = plan_points(run, opts.rule)
    if not plan.ranges:
        raise ConfigError(
            str(run.path),
            "/tensions",
            f"no test point ({plan.source}): run too short or never steady?",
        )
    fallback = None if run.pose_cov is not None else np.array(opts.pose_sd_fallback)
    airspeed, density = run.tunnel if run.tunnel is not None else (None, None)
    pts, extra = points_from_samples(
        kind=plan.kind,
        ranges=plan.ranges,
        t_ns=run.t_ns,
        tensions_N=run.tensions_N,
        mask_bits=run.mask_bits,
        airspeed_mps=airspeed,
        density_kgpm3=density,
        pose_t_ns=run.pose_t_ns,
        poses=run.poses,
        pose_cov=run.pose_cov,
        pose_sd_fallback=fallback,
        pose_bad=run.pose_bad,
    )
    from cdpr.analysis.reduction import flags_from_masks, with_updates

    run_words = []
    if not run.camera:
        run_words.append("pose_from_truth" if run.truth is not None else "no_pose_stream")
    if run.tunnel is None:
        run_words.append("no_airspeed")
    words = [";".join(filter(None, [f, *run_words])) for f in plan.flags]
    pts = flags_from_masks(pts, words=words)
    K, second = read_balance_calibration(opts.balance_file)
    corr = None
    spectra = None
    if opts.corrections:
        pts = with_updates(pts, arrays=_correction_inputs(run, plan))
        spectra = point_spectra(rig, run.t_ns, run.tensions_N, plan.ranges, pts["pose"])
        corr = correction_stages(
            rig,
            opts.geometry,
            opts.tunnel,
            wind_off_mps=opts.reduce.wind_off_mps,
            spectra=spectra,
        )
    stages = reduction_stages(
        rig, opts.geometry, opts.reduce, interaction=K, second_order=second, extra=corr
    )
    out = reduce_points(pts, stages)
    if opts.geometry is None:
        on = np.isin(out["kind"], ("wind_on", "unknown"))
        out = flags_from_masks(out, words=["no_geometry" if o else "" for o in on])
    if not opts.corrections:  # balance values: no drift, windage or wall correction (no --matrix)
        on = np.isin(out["kind"], ("wind_on", "unknown"))
        out = flags_from_masks(out, words=["uncorrected" if o else "" for o in on])
    before = {"run": [run.path.name] * out.n}
    after: dict[str, Any] = {
        "source": [plan.source] * out.n,
        "start_ns": extra["start_ns"],
        "stop_ns": extra["stop_ns"],
        "n_samples": extra["n_samples"],
        "n_masked": extra["n_masked"],
        "n_pose_frames": extra["n_pose_frames"],
    }
    for k, vals in plan.targets.items():
        after[k] = vals
    df = points_table(out, rig, plan.labels, before, after)
    # order: identification first
    first = [
        "run",
        "point",
        "kind",
        "source",
        "start_ns",
        "stop_ns",
        "n_samples",
        "n_masked",
        "flags",
    ]
    df = df[first + [c for c in df.columns if c not in first]]
    if run.truth is not None and "wrench_aero_O" in run.truth:
        mid = (extra["start_ns"] + extra["stop_ns"]) // 2
        W_true = interpolate_at(mid, run.truth["t_ns"], run.truth["wrench_aero_O"])
        mrp = np.zeros(3) if opts.geometry is None else np.asarray(opts.geometry.mrp_P_m)
        R = rotation_from_euler(np.nan_to_num(out["pose"][:, 3:]))
        W_true = transfer_moment(W_true, R @ mrp)
        for k, c in enumerate(WRENCH_COLUMNS):
            df[f"true_{c}"] = W_true[:, k]
            df[f"err_{c}"] = df[c] - W_true[:, k]
    flag_sets = [set(filter(None, f.split(";"))) for f in df["flags"]]
    warn_words = sorted(set().union(*flag_sets) - INFO_FLAGS) if flag_sets else []
    wm = out.meta.get("weight_model")
    info: dict[str, Any] = {
        "points": int(out.n),
        "point_source": plan.source,
        "warnings": warn_words,
        "points_with_warnings": int(sum(bool(f - INFO_FLAGS) for f in flag_sets)),
        "stages": steps_log(out),
        "weight_model": None
        if wm is None
        else {
            "mass_kg": wm.mass_kg,
            "com_P_m": wm.com_P_m.tolist(),
            "theta_cov": wm.theta_cov.tolist(),
            "n_tares": wm.n_tares,
            "chi2_per_dof": wm.chi2_per_dof,
            "left_to_prior": list(wm.weak),
        },
        "lines": _warning_lines(run, plan, warn_words),
        "_spectra": spectra,
        "corrections": list(out.meta.get("corrections", []))
        if opts.corrections
        else "not applied (no test matrix given: cdpr analyze --matrix)",
    }
    return df, info


def _warning_lines(run: RunData, plan: PointPlan, words: list[str]) -> list[str]:
    """One sentence per run-level problem (the CLI and the report print them)."""
    lines = []
    if run.tunnel is None:
        lines.append(
            "no airspeed data in the run: no coefficient; "
            + (
                "points come from events"
                if plan.source == "events"
                else "wind-on and wind-off cannot be told apart, so no wrench is reported"
            )
        )
    if "pose_cov_nominal" in words:
        lines.append(
            "the pose stream carries no covariance: pose σ from the configured constant "
            "(flag pose_cov_nominal)"
        )
    if "no_pose_stream" in words:
        lines.append("no pose stream: the rig's reference pose is used (flag no_pose_stream)")
    if "no_tare" in words:
        lines.append("wind-on points without a tare or weight model: no wrench (flag no_tare)")
    if "masked" in words:
        lines.append("samples masked (status bits, counter gaps, NaN): see n_masked and flags")
    if "no_geometry" in words:
        lines.append("no model geometry given: no coefficients (flag no_geometry)")
    if "check_fail" in words:
        lines.append("measured vs simulated tensions above the limit (flag check_fail)")
    if "humidity_not_given" in words:
        lines.append(
            "wind-on points without a humidity reading in the tunnel stream: density of dry air "
            "(up to about 1 % high; flag humidity_not_given)"
        )
    said = {"pose_cov_nominal", "no_pose_stream", "no_tare", "masked", "no_geometry", "check_fail"}
    said |= {"humidity_not_given"}
    said |= {"no_airspeed"} | set(MASK_NAMES.values())
    rest = [w for w in words if w not in said]
    if rest:
        lines.append(f"other flags: {', '.join(rest)} (see the flags column)")
    return lines


def camera_pose_error(run: RunData) -> dict[str, float] | None:
    """RMS position (mm) and rotation (deg) error of the camera poses against the virtual rig's
    truth, when the run has both."""
    if not run.camera or run.truth is None or "position_O_m" not in run.truth:
        return None
    good = ~run.pose_bad
    cam_t, cam_q = run.pose_t_ns[good], run.poses[good]
    q_true = np.concatenate([run.truth["position_O_m"], run.truth["euler_rad"]], axis=1)
    tq = interpolate_at(cam_t, run.truth["t_ns"], q_true)
    pos_err = np.linalg.norm(cam_q[:, :3] - tq[:, :3], axis=1)
    R_rel = np.swapaxes(rotation_from_euler(tq[:, 3:]), -1, -2) @ rotation_from_euler(cam_q[:, 3:])
    cos = np.clip((np.trace(R_rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    ang = np.degrees(np.arccos(cos))
    return {
        "n_poses": int(len(pos_err)),
        "position_rms_mm": float(1e3 * np.sqrt(np.mean(pos_err**2))),
        "position_max_mm": float(1e3 * pos_err.max()),
        "rotation_rms_deg": float(np.sqrt(np.mean(ang**2))),
        "rotation_max_deg": float(ang.max()),
    }


def _plots(run: RunData, df: pd.DataFrame, folder: Path) -> None:
    """tensions.png (min/max envelope of every cable and of the airspeed, test points shaded),
    wrench.png (per wind-on point, ±2σ), check.png (measured − expected tension per point).  The
    cost does not grow with the number of samples: 2000 envelope bins, one shading collection per
    kind; with many points the check plot draws markers and thins its labels."""
    from .plotting import minmax_envelope, png_figure

    t0 = run.t_ns[0]
    t_s = (run.t_ns - t0) * 1e-9
    # min/max envelope over 2000 bins (every spike stays visible), never every sample
    ts, T_env = minmax_envelope(t_s, run.tensions_N)
    tare = df.kind.isin(("tare", "zero")).to_numpy()
    spans = np.column_stack(
        [
            (df.start_ns.to_numpy() - t0) * 1e-9,
            (df.stop_ns.to_numpy() - df.start_ns.to_numpy()) * 1e-9,
        ]
    )
    with png_figure(folder / "tensions.png", 2, 1, (10, 6), sharex=True, height_ratios=[3, 1]) as (
        fig,
        axes,
    ):
        ax = axes[:, 0]
        for k, name in enumerate(run.rig.cable_names):
            ax[0].plot(ts, T_env[:, k], lw=0.8, label=name)
        for a in ax:  # one collection per kind of point, spanning the axes' height
            for sel, color in ((tare, "0.9"), (~tare, "#dde8f7")):
                if sel.any():
                    a.broken_barh(
                        spans[sel].tolist(), (0, 1), transform=a.get_xaxis_transform(),
                        color=color, zorder=0,
                    )  # fmt: skip
        ax[0].set_ylabel("tension (N)")
        ax[0].legend(fontsize=7, ncol=4, loc="upper left")
        ax[0].set_title(
            f"{run.path.name}: tensions (min/max envelope); shaded = test points "
            f"({df['source'].iloc[0]}; grey: tares)"
        )
        if run.tunnel is not None:
            tv, v_env = minmax_envelope(t_s, run.tunnel[0])
            ax[1].plot(tv, v_env, color="k", lw=1)
        else:
            ax[1].text(0.5, 0.5, "no airspeed data", transform=ax[1].transAxes, ha="center")
        ax[1].set_ylabel("airspeed (m/s)")
        ax[1].set_xlabel("time (s)")

    on = df[~df.kind.isin(("tare", "zero"))]
    x = on["airspeed_mps"] if run.tunnel is not None else np.arange(len(on))
    with png_figure(folder / "wrench.png", 2, 3, (11, 6)) as (fig, axes):
        for k, c in enumerate(WRENCH_COLUMNS):
            a = axes.flat[k]
            a.errorbar(
                x, on[c], yerr=2 * on[f"sd_{c}"], fmt="o", capsize=3, label="recovered (±2σ)"
            )
            if f"true_{c}" in on:
                a.plot(x, on[f"true_{c}"], "x", color="C3", label="virtual-rig truth")
            a.set_title(c)
            a.set_xlabel("airspeed (m/s)" if run.tunnel is not None else "point")
            a.grid(alpha=0.3)
        axes.flat[0].legend(fontsize=7, loc="upper left")
        fig.suptitle("Recovered aerodynamic wrench per test point (at the MRP, {O} axes)")

    dcols = [f"dT_{n}_N" for n in run.rig.cable_names]
    with png_figure(folder / "check.png", size=(10, 4)) as (fig, axes):
        ax = axes[0, 0]
        idx = np.arange(len(df))
        if len(df) <= 40:
            width = 0.8 / len(dcols)
            for k, c in enumerate(dcols):
                ax.bar(idx + (k - len(dcols) / 2) * width, df[c], width, label=c[3:-2])
            ax.set_xticks(idx, df["point"], rotation=90, fontsize=6)
        else:  # many points: one marker per cable and point, every k-th label
            for c in dcols:
                ax.plot(idx, df[c], ".", ms=3, label=c[3:-2])
            step = int(np.ceil(len(df) / 40))
            ax.set_xticks(idx[::step], df["point"].iloc[::step], rotation=90, fontsize=6)
        ax.axhline(1.0, color="r", ls="--", lw=1)
        ax.axhline(-1.0, color="r", ls="--", lw=1, label="±1 N (paper)")
        ax.set_ylabel("measured − expected tension (N)")
        ax.set_title("Measured vs simulated tensions (the paper's ≈1 N check)")
        ax.legend(fontsize=7, ncol=5, loc="upper left")


def _spectrum_plot(run: RunData, df: pd.DataFrame, spectra: Any, folder: Path) -> list[str]:
    """``spectrum.png``: the tension spectra of the fastest wind-on point with the rig's modes
    at its pose marked, and ``spectra.png`` (``spectra_1.png``, ... beyond 24 points): every
    point's spectra as small multiples (when the spectrum check ran).  Returns the file names of
    the small-multiples figures."""
    from .report import spectra_grid_figures, spectrum_figure

    if spectra is None:
        return []
    grid = spectra_grid_figures(
        folder,
        [str(x) for x in df["point"]],
        [str(x) for x in df["flags"].fillna("")],
        spectra.freqs_Hz,
        spectra.psd,
        spectra.modes_Hz,
        run.rig.cable_names,
    )
    names = [f.name for f in grid.figures]
    on = np.flatnonzero((df["kind"] == "wind_on").to_numpy())
    on = [i for i in on if spectra.freqs_Hz[i].size]
    if not on:
        return names
    i = max(on, key=lambda k: np.nan_to_num(df["airspeed_mps"].iloc[k]))
    spectrum_figure(
        folder / "spectrum.png",
        spectra.freqs_Hz[i],
        spectra.psd[i],
        run.rig.cable_names,
        spectra.modes_Hz[i],
        f"Tension spectra of point {df['point'].iloc[i]} "
        f"({df['airspeed_mps'].iloc[i]:.2f} m/s) with the rig's modes at its pose",
    )
    return names


def _fmt(v: float, sd: float) -> str:
    return "–" if not np.isfinite(v) else f"{v:.3f} ± {sd:.3f}"


def _report(run: RunData, df: pd.DataFrame, summary: dict[str, Any]) -> str:
    red = summary["reduction"]
    lines = [
        f"# Analysis of `{run.path.name}`",
        "",
        f"- rig: **{run.rig.name}** ({run.rig.n_cables} cables); pose from: {run.pose_source}",
        f"- {len(df)} test points from **{red['point_source']}**"
        f" ({'the /events stream' if red['point_source'] == 'events' else 'steady-point detection'})"
        f", {int(df.kind.isin(('tare', 'zero')).sum())} wind-off",
        f"- measured vs simulated tensions: max |ΔT| = {summary['check_max_abs_dT_N']:.3f} N "
        f"(paper: about 1 N) → **{'pass' if summary['check_pass'] else 'FAIL'}**",
    ]
    lc = summary["loadcell_calibration"]
    if lc["applied"]:
        worst = max((v for v in lc["max_abs_change_N"].values() if v is not None), default=0.0)
        lines.append(
            f"- tensions **re-derived from the recorded raw counts** with the load-cell "
            f"calibration `{lc['name']}` (id `{lc['id']}`, created {lc['created_utc'] or 'not given'},"
            f" sha256 `{lc['sha256']}`, given by {lc['given_by']}): T = (counts − offset) · gain; "
            f"largest change against the recorded tensions {worst:.4g} N"
        )
    else:
        lines.append("- tensions as recorded (no load-cell re-calibration)")
    wm = red["weight_model"]
    if wm:
        lines.append(
            f"- weight model from {wm['n_tares']} wind-off points: mass {wm['mass_kg']:.5f} kg, "
            f"CoM_P {np.round(np.array(wm['com_P_m']) * 1e3, 3).tolist()} mm"
            + (
                f" (left to the prior: {', '.join(wm['left_to_prior'])})"
                if wm["left_to_prior"]
                else ""
            )
        )
    if red["lines"]:
        lines += ["", "**Warnings**", ""] + [f"- {w}" for w in red["lines"]]
    lines += [
        "",
        "| point | kind | V (m/s) | Fx (N) | Fy (N) | Fz (N) | Mx (N m) | My (N m) | Mz (N m) "
        "| CL | CD | max ΔT (N) | masked | flags |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for _, r in df.iterrows():
        w = [_fmt(r[c], r["sd_" + c]) for c in WRENCH_COLUMNS]
        coef = ["–" if not np.isfinite(r[c]) else f"{r[c]:.3f}" for c in ("CL", "CD")]
        lines.append(
            f"| {r.point} | {r.kind} | {r.airspeed_mps:.2f} | "
            + " | ".join(w)
            + " | "
            + " | ".join(coef)
            + f" | {r.check_max_abs_dT_N:.3f} | {int(r.n_masked)} | {r['flags']} |"
        )
    pe = summary.get("camera_pose_error_vs_truth")
    if pe:
        lines += [
            "",
            f"Camera pose against the virtual rig's truth ({pe['n_poses']} poses): position RMS "
            f"{pe['position_rms_mm']:.3f} mm (max {pe['position_max_mm']:.3f}), rotation RMS "
            f"{pe['rotation_rms_deg']:.4f}° (max {pe['rotation_max_deg']:.4f}°).",
        ]
    if "max_abs_error_vs_truth" in summary:
        errs = ", ".join(f"{c} {v:.3g}" for c, v in summary["max_abs_error_vs_truth"].items())
        lines += ["", f"Against the virtual rig's true aerodynamic wrench, max |error|: {errs}."]
    lines += _corrections_section(df, red)
    if summary.get("online"):
        lines += ["", "## On-line against final values", "", *(f"- {x}" for x in summary["online"])]
    lines += ["", "Stages of the reduction:", ""]
    for st in red["stages"]:
        note = f": {st['note']}" if st["note"] else ""
        lines.append(f"1. `{st['stage']}` — {st['points_flagged']} points flagged{note}")
    lines += [
        "",
        "σ: load-cell noise (standard error of each point's mean), the pose covariance (the camera's "
        "per frame, else the configured constant, flagged), the weight model's covariance and the "
        "tare-to-point pose difference, linearised (`cdpr.analysis.reduction`).",
        "",
        "![tensions](tensions.png)",
        "",
        "![wrench](wrench.png)",
        "",
        "![check](check.png)",
        "",
        *(["![spectrum](spectrum.png)", ""] if "lowest_mode_Hz" in df else []),
    ]
    grids = summary.get("spectra_figures") or []
    if grids:
        lines += [
            "Tension spectra of every point (one panel per point: label and spectrum flags in "
            "its title, the rig's modes at its pose dashed):",
            "",
        ]
        lines += [f"![spectra of every point]({g})\n" for g in grids]
    return "\n".join(lines)


def _corrections_section(df: pd.DataFrame, red: dict[str, Any]) -> list[str]:
    """The report's corrections: every record (name, source, values, flags) and per wind-on point
    the size of each correction, the corrected beside the uncorrected coefficients, Re and Mach."""
    recs = red.get("corrections")
    if not isinstance(recs, list):
        return ["", f"Corrections: {recs}."]
    lines = ["", "## Corrections", ""]
    for r in recs:
        flags = f" — flags: {', '.join(r['flags'])}" if r["flags"] else ""
        lines.append(f"- **{r['name']}** ({r['source']}){flags}")
    on = df[df.kind == "wind_on"]
    if on.empty or "corrections" not in on:
        return lines
    cols = [
        ("point", "point", ""), ("V", "airspeed_mps", ".2f"),
        ("ρ (kg/m³)", "density_kgpm3", ".5f"), ("ρ from", "density_source", ""),
        ("RH", "relative_humidity", ".3f"), ("Re", "reynolds", ".3g"),
        ("Mach", "mach", ".4f"), ("drift max (N)", "zero_drift_max_abs_N", ".4f"),
        ("windage", "windage_source", ""), ("windage Fx (N)", "windage_fx_N", ".4f"),
        ("CL", "CL", ".4f"), ("CL corr.", "CL_corrected", ".4f"), ("CD", "CD", ".5f"),
        ("CD corr.", "CD_corrected", ".5f"), ("Cm", "Cm", ".5f"), ("Cm corr.", "Cm_corrected", ".5f"),
        ("σ CL", "sd_CL", ".2g"), ("σ_repeat CL", "sd_repeat_CL", ".2g"),
    ]  # fmt: skip
    cols = [c for c in cols if c[1] in on]
    lines += ["", "| " + " | ".join(c[0] for c in cols) + " |", "|" + "---|" * len(cols)]
    for _, r in on.iterrows():
        cells = []
        for _, key, f in cols:
            v = r[key]
            cells.append(
                str(v) if not f else ("–" if not np.isfinite(float(v)) else format(float(v), f))
            )
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Per point, what was applied and its source (the `corrections` column):", ""]
    lines += [f"- {r.point}: {r.corrections or 'none'}" for r in on.itertuples()]
    return lines


def _options_json(opts: AnalyzeOptions) -> Any:
    return json.loads(
        json.dumps(asdict(opts), default=lambda o: list(o) if isinstance(o, tuple) else str(o))
    )


def run_fingerprint(path: str, opts: AnalyzeOptions) -> dict[str, Any]:
    """The input fingerprint of one run's analysis (:mod:`cdpr.pipelines.freshness`): the run
    file, the balance calibration, the test matrix, the load-cell calibration the tensions are
    re-derived with, the virtual rig's truth file beside the run (absent is recorded too), the
    options and the software version."""
    p = Path(path)
    truth = p.with_name(p.name.removesuffix(".mcap") + ".truth.npz")
    inputs = [opts.balance_file, opts.matrix_file, opts.loadcell_calibration_file, truth]
    return fingerprint(p, _options_json(opts), __version__, inputs)


def loadcell_provenance(run: RunData, opts: AnalyzeOptions) -> dict[str, Any]:
    """Where the run's tensions come from (summary ``loadcell_calibration``; ``tensions_from`` is
    the points.csv column): the recorded tensions, or the ones re-derived from the raw counts with
    a load-cell calibration (file, SHA-256, id, date, who named it, largest change per cable)."""
    if opts.loadcell_calibration_file is None or run.recalibration is None:
        return {
            "applied": False,
            "tensions_from": "recorded tensions (no load-cell re-calibration)",
        }
    f = opts.loadcell_calibration_file
    sha = file_sha256(f)
    rc = run.recalibration
    return {
        "applied": True,
        "file": str(f),
        "name": Path(f).name,
        "sha256": sha,
        "id": rc["calibration_id"],
        "created_utc": rc["created_utc"],
        "given_by": opts.loadcell_calibration_from,
        "tensions_from": f"re-derived from raw counts with {Path(f).name} sha256={sha} "
        f"id={rc['calibration_id']}",
        "formula": "T_N = (raw_counts - offset_counts) * gain_N_per_count",
        "max_abs_change_N": rc["max_abs_change_N"],
    }


def result_folder(path: str, out_dir: str) -> Path:
    """``OUT/<run stem>``: where the results of run ``path`` go."""
    return Path(out_dir) / Path(path).name.removesuffix(".mcap")


def analyze_run(
    path: str, out_dir: str, opts: AnalyzeOptions, fp: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Analyse one run and write its folder atomically; returns the summary (with ``fp``, the
    input fingerprint, computed here when not given)."""
    if fp is None:
        fp = run_fingerprint(path, opts)
    try:
        lc_file = None
        if opts.loadcell_calibration_file is not None:
            from cdpr.daq.loadcell import read_calibration_file

            lc_file = read_calibration_file(opts.loadcell_calibration_file)
        run = load_run(path, lc_file)
        df, red = analyze_arrays(run, opts)
        df, online = compare_online(path, df)  # the on-line results kept in the run
        lc = loadcell_provenance(run, opts)
        df.insert(int(df.columns.get_loc("source")) + 1, "tensions_from", lc["tensions_from"])
    except ConfigError:
        raise
    except CdprError as exc:  # name the file in the one line
        raise ConfigError(str(path), "", str(exc)) from None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    final = result_folder(path, out_dir)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=out))
    try:
        dmax = df["check_max_abs_dT_N"]
        summary: dict[str, Any] = {
            "run": str(run.path),
            "run_sha256": fp["run_sha256"],
            "software_version": __version__,
            "fingerprint": fp,
            "rig": run.rig.name,
            "pose_source": run.pose_source,
            "options": _options_json(opts),
            "balance_file": None
            if opts.balance_file is None
            else f"{opts.balance_file} sha256={file_sha256(opts.balance_file)}",
            "loadcell_calibration": lc,
            "points": len(df),
            "check_max_abs_dT_N": float(dmax.max()) if dmax.notna().any() else float("nan"),
            "check_pass": bool((dmax.dropna() <= opts.reduce.check_limit_N).all()),
            "reduction": {k: v for k, v in red.items() if k != "_spectra"},
            "online": online,
        }
        pose_err = camera_pose_error(run)
        if pose_err is not None:
            summary["camera_pose_error_vs_truth"] = pose_err
        if "err_fx_N" in df:
            on = df[df.kind == "wind_on"]
            summary["max_abs_error_vs_truth"] = {
                c: float(np.abs(on[f"err_{c}"]).max()) for c in WRENCH_COLUMNS
            }
        df.to_csv(tmp / "points.csv", index=False)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
        _plots(run, df, tmp)
        summary["spectra_figures"] = _spectrum_plot(run, df, red.get("_spectra"), tmp)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
        (tmp / "report.md").write_text(_report(run, df, summary))
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    summary["folder"] = str(final)
    return summary


def _safe(path: str, out_dir: str, opts: AnalyzeOptions, fp: dict[str, Any]) -> dict[str, Any]:
    try:
        return analyze_run(path, out_dir, opts, fp)
    except CdprError as exc:
        return {"run": path, "error": str(exc)}


def _current_summary(path: str, out_dir: str, fp: dict[str, Any]) -> dict[str, Any] | None:
    """The recorded summary of run ``path`` when its result folder is current, else None."""
    folder = result_folder(path, out_dir)
    if not is_current(folder, fp):
        return None
    try:
        summary: dict[str, Any] = json.loads((folder / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    summary["folder"] = str(folder)
    summary["skipped"] = "current"
    return summary


class _RunsProgress:
    """A progress bar across runs on stderr (rich), silent when ``enabled`` is False."""

    def __init__(self, total: int, enabled: bool) -> None:
        self._bar = None
        if enabled and total:
            import sys

            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

            self._bar = Progress(
                "[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                TimeElapsedColumn(), console=Console(file=sys.stderr),
            )  # fmt: skip
            self._bar.start()
            self._task = self._bar.add_task("analyze: runs", total=total)

    def advance(self) -> None:
        if self._bar is not None:
            self._bar.advance(self._task)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()


#: settings of the local cluster: no sampling profiler (a stack sample of the task every 10 ms)
#: and no GIL monitor (every 1 ms) in the workers, resource polls once a second (on a machine
#: with as many cores as workers they take CPU from the runs); workers forked from this process
#: once it has imported what a run needs (spawned workers each imported it anew: ~1 s each)
_LOCAL_DASK: dict[str, Any] = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.system-monitor.gil.enabled": False,
    "distributed.admin.system-monitor.interval": "1s",
    "distributed.admin.system-monitor.disk": False,
    "distributed.worker.memory.monitor-interval": "1s",
}
if sys.platform.startswith("linux"):  # fork is not safe on macOS; spawn (Dask's default) there
    _LOCAL_DASK["distributed.worker.multiprocessing-method"] = "fork"


class _ClusterStart:
    """A local Dask cluster of ``n`` single-threaded worker processes, started in a thread (so
    that this process can go on meanwhile); :meth:`cluster` waits for it, :meth:`close` stops it
    (started or not)."""

    def __init__(self, n: int) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(1, thread_name_prefix="cdpr-cluster")
        self._future = self._pool.submit(self._start, n)

    @staticmethod
    def _start(n: int) -> Any:
        import dask
        import matplotlib
        from dask.distributed import LocalCluster

        import cdpr.pipelines.plotting
        import cdpr.pipelines.report  # noqa: F401  (imported here, the forked workers have them)
        from cdpr.daq import run_reader  # noqa: F401

        matplotlib.use("Agg")
        import matplotlib.pyplot  # noqa: F401

        # Dask starts its workers with MALLOC_TRIM_THRESHOLD_ set, which also fixes glibc's mmap
        # threshold: every array over 128 KiB is then mapped and unmapped anew (page faults: a
        # worker spent 4x the system time of one process on the same runs); the workers get
        # glibc's own adaptive thresholds instead
        environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
        environ.pop("MALLOC_TRIM_THRESHOLD_", None)
        with dask.config.set({"distributed.nanny.pre-spawn-environ": environ, **_LOCAL_DASK}):
            return LocalCluster(
                n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None
            )

    def cluster(self) -> Any:
        return self._future.result()

    def close(self) -> None:
        try:
            if self._future.exception() is None:
                self._future.result().close()
        finally:
            self._pool.shutdown()


def analyze_runs(
    paths: Sequence[str],
    out_dir: str,
    opts: AnalyzeOptions,
    scheduler: str | None = None,
    workers: int = 2,
    progress: bool = True,
    force: bool = False,
) -> list[dict[str, Any]]:
    """Analyse runs in parallel on Dask (a local cluster of ``workers`` single-threaded processes,
    unless ``scheduler`` is the address of a running scheduler; with one worker, or one run, and
    no scheduler: one after the other in this process); a bad run is reported in its
    summary (``error``) without stopping the others.  A run whose result folder records the
    fingerprint of its inputs now is not recomputed (its recorded summary comes back with
    ``skipped = "current"``) unless ``force``.  ``progress``: a bar across runs on stderr (when
    more than one run is to be analysed)."""
    if not paths:
        raise ConfigError("runs", "", "no run files given")
    # the local cluster starts (processes, imports) while the inputs are checked and hashed here
    local = (
        _ClusterStart(min(workers, len(paths)))
        if scheduler is None and workers > 1 and len(paths) > 1
        else None
    )
    try:
        if opts.loadcell_calibration_file is not None:  # every run can be re-calibrated: first
            from cdpr.daq.loadcell import read_calibration_file

            lc_file = read_calibration_file(opts.loadcell_calibration_file)
            for p in paths:
                check_recalibration(p, lc_file)
        fps = [run_fingerprint(p, opts) for p in paths]
        results: list[dict[str, Any] | None] = [
            None if force else _current_summary(p, out_dir, fp)
            for p, fp in zip(paths, fps, strict=True)
        ]
        todo = [i for i, r in enumerate(results) if r is None]
        bar = _RunsProgress(len(todo), progress and len(todo) > 1)
        try:
            if scheduler is None and (len(todo) <= 1 or workers == 1):
                if local is not None:  # at most one run to analyse: no use for the cluster
                    local.close()
                    local = None
                for i in todo:  # one worker: in this process, no cluster to start
                    results[i] = _safe(paths[i], out_dir, opts, fps[i])
                    bar.advance()
            elif todo:
                from dask.distributed import Client, as_completed

                client = Client(scheduler or (local.cluster() if local else None))
                try:
                    futures = {
                        client.submit(_safe, paths[i], out_dir, opts, fps[i], pure=False): i
                        for i in todo
                    }
                    for fut in as_completed(futures):
                        results[futures[fut]] = fut.result()
                        bar.advance()
                finally:
                    client.close()
        finally:
            bar.close()
    finally:
        if local is not None:
            local.close()
    done = [r for r in results if r is not None]
    lines = [
        "# Analysed runs",
        "",
        "| run | points | source | warnings | max ΔT (N) | check | report |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in done:
        if "error" in r:
            lines.append(f"| {Path(r['run']).name} | - | - | - | - | error: {r['error']} | - |")
        else:
            rel = Path(r["folder"]).name
            red = r["reduction"]
            lines.append(
                f"| {Path(r['run']).name} | {r['points']} | {red['point_source']} | "
                f"{', '.join(red['warnings']) or '-'} | {r['check_max_abs_dT_N']:.3f} | "
                f"{'pass' if r['check_pass'] else 'FAIL'} | [{rel}/report.md]({rel}/report.md) |"
            )
    index = Path(out_dir) / "index.md"
    index.parent.mkdir(parents=True, exist_ok=True)
    tmp = index.with_suffix(".md.part")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, index)
    return done
