"""A run file as the arrays the analysis needs: ``load_run`` reads only the topics it uses through
:func:`cdpr.daq.run_reader.open_run` (the one columnar reader) and never sees the message layout.

Tensions with their status words and counter (window by window into preallocated arrays: bounded
memory for an hour at 1 kHz), the tunnel conditions on the tension times, the camera poses with
their covariance (Euler-angle parametrisation), the test-point events, the rig file attached to the
run, and the virtual rig's truth file when one sits beside the run.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.balance import interpolate_at, sample_mask
from cdpr.analysis.clock import sample_clock
from cdpr.analysis.conventions import status_from_channel_bits
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.flow import air_density
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import euler_from_quaternion, pose_cov_to_euler
from cdpr.daq.schema import rig_from_mapping


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
    tension_clock: str = ""
    """Where the tension samples' times come from: the sample counter (the sampling instants, the
    lower envelope of the reception times: :func:`cdpr.analysis.clock.sample_clock`), or the
    reception times when the stream has no counter."""
    sample_counter: np.ndarray | None = None
    """(n,) the tension samples' counter (``seq``), None when the stream has none."""
    loadcell_sd: Any = None
    """The load-cell calibration's own σ (:class:`cdpr.analysis.systematic.LoadCellCalibrationSd`)
    of the calibration that made the tensions, None when no σ is known (see ``loadcell_sd_from``)."""
    loadcell_sd_from: str = "no load-cell calibration attached to the run"
    """Where ``loadcell_sd`` comes from (said in the summary and report)."""


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
    """Times (n,), tensions (n, m) (NaN where a field is missing), the status words (STATUS_*)
    OR-ed over the message and the cables (each cable's channel bits mapped to STATUS_*) (n,),
    the counter ``seq`` (None unless every message has one), and with ``raw`` the
    ``raw_<cable>_counts`` (n, m) (NaN where missing; else None), read window by window into
    arrays sized from the stream's message count."""
    cols = [f"T_{n}_N" for n in rig.cable_names]
    rcols = _raw_columns(rig) if raw else []
    raw_counts = np.empty((run.streams[topic].count, len(rcols)))
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
            raw_counts[i : i + k, j] = _column(df, c)
        for c in scols:  # a cable's own status bits are mapped, the message status is STATUS_*
            if c in df:
                bits = np.nan_to_num(_column(df, c)).astype(np.int64)
                st[i : i + k] |= bits if c == "status" else status_from_channel_bits(bits)
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
    return (
        t_ns[:i],
        T[:i],
        st[:i],
        None if seq is None else seq[:i],
        raw_counts[:i] if raw else None,
    )


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


def _loadcell_sd(run: Any, rig: Rig, p: Path, recalibration: Any) -> tuple[Any, str]:
    """The σ of the load-cell calibration that made the run's tensions and where it comes from:
    the file the tensions are re-derived with (``--loadcell-calibration``), else a load-cell
    calibration attached to the run (the recorder attaches the one its config names); None (flag
    ``loadcell_calibration_sd_not_given``) when that file gives no σ or none is known."""
    from cdpr.daq.loadcell import is_calibration_file, parse_calibration_file

    if recalibration is not None:
        sd = recalibration.sd_for_cables(rig.cable_names)
        return sd, f"{Path(recalibration.path).name} (the tensions re-derived with it)" + (
            "" if sd is not None else ": it gives no σ"
        )
    for name, (_, data) in run.attachments.items():
        if not (name.startswith("calibration/") and name.endswith(".toml")):
            continue
        try:
            doc = tomllib.loads(data.decode())
        except (UnicodeDecodeError, tomllib.TOMLDecodeError):
            continue  # another kind of calibration (the camera's)
        if is_calibration_file(doc):
            sd = parse_calibration_file(f"{p}:{name}", doc).sd_for_cables(rig.cable_names)
            return sd, f"{name} attached to the run" + ("" if sd is not None else ": it gives no σ")
    return None, "no load-cell calibration attached to the run"


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
        lc_sd, lc_from = _loadcell_sd(run, rig, p, loadcell_calibration)
    t_ns, T, bits, seq, clock = tension_arrays(t_ns, T, st, seq)

    tunnel = pressure_temperature = humidity = None
    if tun is not None and len(tun):
        tunnel, pressure_temperature, humidity = tunnel_on(
            t_ns, tun["t_ns"].to_numpy(np.int64),
            *(_column(tun, c) for c in ("airspeed_mps", "density_kgpm3", "static_pressure_Pa",
                                        "temperature_K", "relative_humidity")),
        )  # fmt: skip

    truth = None
    truth_path = p.with_name(p.name.removesuffix(".mcap") + ".truth.npz")
    if truth_path.exists():
        with np.load(truth_path) as z:
            truth = {k: z[k] for k in z.files}

    if lc_sd is None and truth is not None and "no load-cell" in lc_from:
        from cdpr.analysis.systematic import LoadCellCalibrationSd

        m = rig.n_cables  # the virtual rig's counts are made with its calibration: exact
        lc_sd = LoadCellCalibrationSd(np.zeros((m, 2, 2)), np.full(m, np.inf))
        lc_from = f"the virtual rig's load cells (exact; {truth_path.name})"
    sd_fields = {"loadcell_sd": lc_sd, "loadcell_sd_from": lc_from}
    events = _events(ev_df)
    if pose_df is not None and len(pose_df):
        tp = pose_df["t_ns"].to_numpy(np.int64)
        ccols = [f"cov_{i}{j}" for i in range(6) for j in range(6)]
        cov6 = (
            np.column_stack([_column(pose_df, c) for c in ccols]).reshape(-1, 6, 6)
            if all(c in pose_df for c in ccols)
            else None
        )
        poses, pose_cov, bad = camera_poses(
            np.column_stack([_column(pose_df, c) for c in ("x_m", "y_m", "z_m")]),
            np.column_stack([_column(pose_df, c) for c in ("qw", "qx", "qy", "qz")]),
            cov6,
            np.nan_to_num(_column(pose_df, "status", 0.0)),
        )
        if (~bad).sum() >= 2:
            src = "camera (/pose stream)" + ("" if pose_cov is not None else ", no covariance")
            return RunData(
                p, rig, t_ns, T, bits, tunnel, tp, poses, pose_cov, bad, src, events, truth, True,
                pressure_temperature, humidity, recal, clock, seq, **sd_fields,
            )  # fmt: skip
    if truth is not None and "position_O_m" in truth:
        q6 = np.concatenate([truth["position_O_m"], truth["euler_rad"]], axis=1)
        src = f"virtual-rig truth ({truth_path.name}); no camera stream in the run"
        tp = np.asarray(truth["t_ns"], dtype=np.int64)
        return RunData(
            p, rig, t_ns, T, bits, tunnel, tp, q6, None, np.zeros(len(tp), bool), src,
            events, truth, False, pressure_temperature, humidity, recal, clock, seq, **sd_fields,
        )  # fmt: skip
    ref = np.concatenate([rig.reference_position_O_m, rig.reference_euler_rad])
    return RunData(
        p, rig, t_ns, T, bits, tunnel, t_ns.copy(), np.tile(ref, (len(t_ns), 1)), None,
        np.zeros(len(t_ns), bool), "rig reference pose (no pose stream)", events, truth, False,
        pressure_temperature, humidity, recal, clock, seq, **sd_fields,
    )  # fmt: skip


def tension_arrays(
    t_ns: np.ndarray, T: np.ndarray, status: np.ndarray, seq: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, str]:
    """The tension samples as the reduction takes them, from the recorded times (n,) int ns,
    tensions (n, m) N, status words (n,) and sample counter (n,) or None: sorted by time (a
    repeated time keeps its first sample), the mask bits (:func:`sample_mask`: status, counter
    gaps, NaN), and the sampling instants from the counter (:func:`sample_clock`) when it rises
    throughout.  Returns ``(t_ns, T, bits, seq, clock)``, ``clock`` saying where the times come
    from.  One copy for a run file (:func:`load_run`) and the live session
    (:mod:`cdpr.pipelines.online`)."""
    t_ns, T, st = np.asarray(t_ns, np.int64), np.asarray(T, np.float64), np.asarray(status)
    if len(t_ns) > 1 and not np.all(np.diff(t_ns) > 0):
        order = np.argsort(t_ns, kind="stable")
        t_ns, T, st = t_ns[order], T[order], st[order]
        keep = np.concatenate([[True], np.diff(t_ns) > 0])
        t_ns, T, st = t_ns[keep], T[keep], st[keep]
        if seq is not None:
            seq = seq[order][keep]
    bits = sample_mask(T, status=st, counter=seq, counter_modulus=2**62)
    clock = "reception times (the stream has no sample counter)"
    if seq is not None and len(seq) > 1 and np.all(np.diff(seq) > 0):
        # the sampling instants from the sample counter, not the host's reception bursts
        sc = sample_clock(t_ns, seq)
        t_ns = sc.t_ns
        clock = (
            f"the sample counter (sample period {sc.period_ns / 1e6:.4f} ms; reception came up to "
            f"{np.max(sc.latency_ns) / 1e6:.1f} ms after the sampling instant)"
        )
    return t_ns, T, bits, seq, clock


def tunnel_on(
    t_ns: np.ndarray,
    tt: np.ndarray,
    airspeed: np.ndarray,
    density: np.ndarray,
    static_pressure: np.ndarray,
    temperature: np.ndarray,
    humidity: np.ndarray,
) -> tuple[Any, Any, np.ndarray | None]:
    """The tunnel conditions on the tension times ``t_ns`` from the tunnel messages at ``tt``
    (airspeed m/s, density kg/m^3, static pressure Pa, temperature K, relative humidity 0..1,
    NaN where a message has none): ``((airspeed, density), (pressure, temperature), humidity)``
    with None for what no message gives.  Density missing from a message is the dry air of its
    pressure and temperature; airspeed, density, pressure and temperature are interpolated,
    humidity is held from the last message (a point that meets a message without it gets NaN,
    flag ``humidity_not_given``, never a bridged value)."""
    if not len(tt) or not len(t_ns):
        return None, None, None
    v, rho, ps, tk, rh = (np.array(x, np.float64) for x in
                          (airspeed, density, static_pressure, temperature, humidity))  # fmt: skip
    need = ~np.isfinite(rho)
    ok = need & (ps > 0) & (tk > 0)  # NaN compares False
    rho[ok] = air_density(ps[ok], tk[ok])  # dry air: RH 0
    tunnel = None
    good = np.isfinite(v)
    if good.any():
        rg = np.isfinite(rho)
        ri = interpolate_at(t_ns, tt[rg], rho[rg]) if rg.any() else np.full(len(t_ns), np.nan)
        tunnel = (interpolate_at(t_ns, tt[good], v[good]), ri)
    pT = None
    if np.isfinite(ps).any() and np.isfinite(tk).any():
        pT = tuple(interpolate_at(t_ns, tt[np.isfinite(x)], x[np.isfinite(x)]) for x in (ps, tk))
    held = None
    if np.isfinite(rh).any():
        j = np.clip(np.searchsorted(tt, t_ns, side="right") - 1, 0, len(tt) - 1)
        held = rh[j]
    return tunnel, pT, held


def camera_poses(
    position_O_m: np.ndarray,
    quaternion_wxyz: np.ndarray,
    cov_rotvec: np.ndarray | None,
    status: np.ndarray,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """The camera's poses as the reduction takes them: ``(poses (k, 6) [position m, Euler rad],
    covariance (k, 6, 6) in those coordinates or None, bad (k,) bool)`` from the reported
    positions (k, 3), quaternions (k, 4), covariances (k, 6, 6) [position, rotation vector in
    {O}] or None, and status words (k,).  A frame is bad without a finite pose, with a status,
    or with a partly missing covariance; the covariance is None when a usable frame has none at
    all (one lost frame must not cost the run its covariance)."""
    pos = np.asarray(position_O_m, np.float64)
    quat = np.asarray(quaternion_wxyz, np.float64)
    bad = ~(np.isfinite(pos).all(axis=1) & np.isfinite(quat).all(axis=1))
    bad |= np.asarray(status) != 0
    eul = np.full((len(pos), 3), np.nan)
    if (~bad).any():
        eul[~bad] = euler_from_quaternion(quat[~bad])
    cov = None
    if cov_rotvec is not None and np.isfinite(cov_rotvec[~bad]).any(axis=(1, 2)).all():
        cov = pose_cov_to_euler(np.nan_to_num(eul), cov_rotvec)
        bad = bad | ~np.isfinite(cov).all(axis=(1, 2))
    return np.concatenate([pos, eul], axis=1), cov, bad


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
