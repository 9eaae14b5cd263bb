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
from cdpr.analysis.conventions import status_from_channel_bits
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.flow import air_density
from cdpr.analysis.rig import Rig
from cdpr.analysis.rotations import euler_from_quaternion, euler_rate_matrix
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
    seq: np.ndarray | None = None
    """(n,) the load cells' unwrapped sample counter (None when the stream has none): their own
    clock for the dynamic reduction (:func:`cdpr.analysis.oscillation.sample_clock`)."""


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
            rho_src[ok] = air_density(ps[ok], tk[ok])  # dry air: RH 0
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
                C[:, 3:, :] = Hinv @ C[:, 3:, :]  # J C J^T, J = diag(I, H^-1), block by block
                C[:, :, 3:] = C[:, :, 3:] @ np.swapaxes(Hinv, 1, 2)
                pose_cov = C
                bad |= ~np.isfinite(pose_cov).all(axis=(1, 2))
        if (~bad).sum() >= 2:
            src = "camera (/pose stream)" + ("" if pose_cov is not None else ", no covariance")
            return RunData(
                p, rig, t_ns, T, bits, tunnel, tp, poses, pose_cov, bad, src, events, truth, True,
                pressure_temperature, humidity, recal, seq,
            )  # fmt: skip
    if truth is not None and "position_O_m" in truth:
        q6 = np.concatenate([truth["position_O_m"], truth["euler_rad"]], axis=1)
        src = f"virtual-rig truth ({truth_path.name}); no camera stream in the run"
        tp = np.asarray(truth["t_ns"], dtype=np.int64)
        return RunData(
            p, rig, t_ns, T, bits, tunnel, tp, q6, None, np.zeros(len(tp), bool), src,
            events, truth, False, pressure_temperature, humidity, recal, seq,
        )  # fmt: skip
    ref = np.concatenate([rig.reference_position_O_m, rig.reference_euler_rad])
    return RunData(
        p, rig, t_ns, T, bits, tunnel, t_ns.copy(), np.tile(ref, (len(t_ns), 1)), None,
        np.zeros(len(t_ns), bool), "rig reference pose (no pose stream)", events, truth, False,
        pressure_temperature, humidity, recal, seq,
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
