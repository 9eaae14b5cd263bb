"""Side tables of ``cdpr import``: platform poses, tunnel conditions and test-point events from other
tools' CSVs.

Every file has a time column, ``t_ns`` (integer ns since the Unix epoch) or ``t_s`` (seconds from
the first CAN frame of the imported log), non-decreasing; ``#`` lines are comments.

- pose CSV: ``x_m, y_m, z_m, roll_rad, pitch_rad, yaw_rad`` (platform {P} in {O}, Z-Y-X Euler
  angles) and optionally its covariance ``cov_00 .. cov_55``: the 6x6 covariance of that row's
  ``(x, y, z, roll, pitch, yaw)`` in m^2, m rad and rad^2, row-major (``cov_ij`` row i, column j),
  all 36 columns with a number in every row (symmetric, positive semi-definite) or none.  Each
  row becomes a ``/pose`` message whose ``covariance`` is in the camera's parametrisation
  ``[position_O_m, rotation vector in {O}]`` (:func:`cdpr.analysis.rotations.pose_cov_from_euler`),
  the layout of the recorder's ``/pose``.  Without the columns, a stated per-frame standard
  deviation (``cdpr import --pose-sd``) may stand for it.

- tunnel CSV: ``airspeed_mps`` and either ``density_kgpm3`` or ``static_pressure_Pa`` +
  ``temperature_K`` (density then ``p / (R T)``, moist air with the humidity); optional
  ``relative_humidity`` (fraction 0..1) or ``relative_humidity_pct`` (percent, divided by 100;
  not both), an empty cell meaning not measured at that row (null in the stream, the analysis
  flags the point ``humidity_not_given``); each row becomes a ``/tunnel`` message.
- events CSV: ``point`` (label), ``phase`` (``start`` | ``end``), ``kind`` (``wind_on`` | ``tare`` |
  ``zero`` | ``windage``), optional ``target_aoa_deg``, ``target_sideslip_deg``,
  ``target_airspeed_mps`` (empty cell: unknown, written as null) and ``repeat_of``; each row
  becomes a ``test_point`` event on ``/events``.  Every point starts, then ends, before the next
  starts.  An ``oscillation`` / ``oscillation_tare`` row (docs/dynamic_tests.md) also needs
  ``motion_axis``, ``motion_amplitude`` (SI: rad or m), ``motion_frequency_Hz``,
  ``motion_cycles`` and ``motion_settling_cycles`` (whole numbers >= 1), optionally
  ``inertia_tare`` (a label); steady rows leave those cells empty.

Errors are ``ConfigError(file, "row N, column C", problem)`` with N counted as a spreadsheet shows
it (the header is row 1), raised before anything is written.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from cdpr.analysis.conventions import POSE_COLUMNS
from cdpr.analysis.errors import ConfigError, InputError
from cdpr.analysis.flow import air_density, saturation_vapour_pressure
from cdpr.analysis.rotations import pose_cov_from_euler, quaternion_from_euler
from cdpr.daq.source import FieldDescription, Reading, StreamDescription

from .campaign import KINDS
from .config import read_table, require_numbers

EVENT_TARGETS = ("target_aoa_deg", "target_sideslip_deg", "target_airspeed_mps")


@dataclass(frozen=True)
class TimedTable:
    """A side table: its time column name (``t_ns`` or ``t_s``), times, and columns."""

    path: str
    time_column: str
    times: NDArray[Any]
    columns: dict[str, NDArray[Any]]

    def t_ns(self, first_can_ns: int | None) -> NDArray[np.int64]:
        """Epoch ns of every row (``t_s`` rows are counted from the first CAN frame)."""
        if self.time_column == "t_ns":
            return self.times.astype(np.int64)
        if first_can_ns is None:
            raise ConfigError(self.path, "column t_s", "relative times need CAN frames in the log")
        return first_can_ns + np.round(self.times.astype(np.float64) * 1e9).astype(np.int64)


def _text(value: Any) -> str:
    """A CSV cell for a message: quoted text, plain numbers."""
    return repr(value) if isinstance(value, str) else str(value)


def table_times(path: str, df: pd.DataFrame) -> tuple[str, NDArray[Any]]:
    """The time column of a side table (``t_ns`` or ``t_s``): finite, never decreasing, ``t_ns``
    integers.  Returns ``(column, values)``."""
    if "t_ns" in df.columns:
        tcol = "t_ns"
    elif "t_s" in df.columns:
        tcol = "t_s"
    else:
        raise ConfigError(path, "column t_ns", "missing: need a t_ns or t_s column")
    raw = df[tcol]
    num = pd.to_numeric(raw, errors="coerce").to_numpy(dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(num))
    if bad.size:
        i = int(bad[0])
        raise ConfigError(
            path,
            f"row {i + 2}, column {tcol}",
            f"expected a finite number, got {_text(raw.iloc[i])}",
        )
    if tcol == "t_ns":
        if not pd.api.types.is_integer_dtype(raw):
            frac = np.flatnonzero(num != np.round(num))
            i = int(frac[0]) if frac.size else 0
            raise ConfigError(
                path,
                f"row {i + 2}, column t_ns",
                f"expected integer ns since the Unix epoch, got {_text(raw.iloc[i])}",
            )
        tv: NDArray[Any] = raw.to_numpy(dtype=np.int64)
    else:
        tv = num
    back = np.flatnonzero(np.diff(tv) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise ConfigError(
            path, f"row {i + 2}, column {tcol}", f"time goes backwards ({tv[i]} after {tv[i - 1]})"
        )
    return tcol, tv


def _check_range(path: str, df: pd.DataFrame, col: str, lo: float, strict: bool) -> None:
    v = df[col].to_numpy(dtype=np.float64)
    bad = np.flatnonzero((v <= lo) if strict else (v < lo))
    if bad.size:
        i = int(bad[0])
        raise ConfigError(
            path,
            f"row {i + 2}, column {col}",
            f"must be {'>' if strict else '>='} {lo:g}, got {v[i]:g}",
        )


def read_tunnel_csv(path: str | os.PathLike[str]) -> TimedTable:
    """Read and check a tunnel-conditions CSV (see the module docstring)."""
    p = str(path)
    head = read_table(p, (), "tunnel table")
    if "density_kgpm3" in head.columns:
        req: tuple[str, ...] = ("airspeed_mps", "density_kgpm3")
    elif "static_pressure_Pa" in head.columns or "temperature_K" in head.columns:
        req = ("airspeed_mps", "static_pressure_Pa", "temperature_K")
    else:
        raise ConfigError(
            p,
            "column density_kgpm3",
            "missing: need density_kgpm3 or static_pressure_Pa + temperature_K",
        )
    df = read_table(p, req, "tunnel table")
    tcol, tv = table_times(p, df)
    _check_range(p, df, "airspeed_mps", 0.0, False)
    cols = {"airspeed_mps": df["airspeed_mps"].to_numpy(dtype=np.float64)}
    if "density_kgpm3" in req:
        _check_range(p, df, "density_kgpm3", 0.0, True)
        cols["density_kgpm3"] = df["density_kgpm3"].to_numpy(dtype=np.float64)
    else:
        _check_range(p, df, "static_pressure_Pa", 0.0, True)
        _check_range(p, df, "temperature_K", 0.0, True)
        cols["static_pressure_Pa"] = df["static_pressure_Pa"].to_numpy(dtype=np.float64)
        cols["temperature_K"] = df["temperature_K"].to_numpy(dtype=np.float64)
        cols["density_kgpm3"] = air_density(cols["static_pressure_Pa"], cols["temperature_K"])
    rh = _humidity(p, df)
    if rh is not None:
        cols["relative_humidity"] = rh
        have = np.isfinite(rh)
        if "static_pressure_Pa" in cols and have.any():
            ps, tk = cols["static_pressure_Pa"][have], cols["temperature_K"][have]
            try:
                cols["density_kgpm3"][have] = air_density(ps, tk, rh[have])
            except InputError:  # vapour pressure above p: name the first such row
                e = rh[have] * saturation_vapour_pressure(tk)
                i = int(np.flatnonzero(have)[np.flatnonzero(e >= ps)[0]])
                raise ConfigError(
                    p,
                    f"row {i + 2}, column {next(c for c in _RH_COLUMNS if c in df)}",
                    "vapour pressure at this humidity is above the static pressure",
                ) from None
    return TimedTable(p, tcol, tv, cols)


_RH_COLUMNS = ("relative_humidity", "relative_humidity_pct")


def _humidity(path: str, df: pd.DataFrame) -> NDArray[np.float64] | None:
    """The optional humidity column as a fraction 0..1 (NaN: empty cell, not measured), or
    None without one; a value outside 0..1 (0..100 %) or not a number names its row."""
    have = [c for c in _RH_COLUMNS if c in df.columns]
    if not have:
        return None
    if len(have) == 2:
        raise ConfigError(path, "column relative_humidity_pct", "give relative_humidity or "
                          "relative_humidity_pct, not both")  # fmt: skip
    c = have[0]
    scale, hi = (1.0, 1.0) if c == "relative_humidity" else (0.01, 100.0)
    num = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=np.float64)
    given = df[c].notna().to_numpy()
    bad = np.flatnonzero(given & ~((num >= 0.0) & (num <= hi)))  # NaN and inf fail
    if bad.size:
        i = int(bad[0])
        raise ConfigError(
            path,
            f"row {i + 2}, column {c}",
            f"expected a number in 0..{hi:g}{' %' if hi > 1 else ''} or an empty cell, "
            f"got {_text(df[c].iloc[i])}",
        )
    return np.where(given, num * scale, np.nan)


def read_events_csv(path: str | os.PathLike[str]) -> TimedTable:
    """Read and check a test-point events CSV (see the module docstring)."""
    p = str(path)
    df = read_table(p, (), "events table")
    for c in ("point", "phase", "kind"):
        if c not in df.columns:
            raise ConfigError(p, f"column {c}", f"missing (have: {list(df.columns)})")
    tcol, tv = table_times(p, df)
    cols: dict[str, NDArray[Any]] = {}
    for c in ("point", "phase", "kind", "repeat_of"):
        s = df[c] if c in df.columns else pd.Series([""] * len(df))
        s = s.astype(object).where(s.notna(), "")
        cols[c] = s.astype(str).str.strip().to_numpy(dtype=object)
    for i, (pt, ph, kd) in enumerate(zip(cols["point"], cols["phase"], cols["kind"], strict=True)):
        if not pt:
            raise ConfigError(p, f"row {i + 2}, column point", "empty label")
        if ph not in ("start", "end"):
            raise ConfigError(p, f"row {i + 2}, column phase", f"expected start or end, got {ph!r}")
        if kd not in KINDS:
            raise ConfigError(
                p, f"row {i + 2}, column kind", f"expected one of {list(KINDS)}, got {kd!r}"
            )
    for c in EVENT_TARGETS:
        if c in df.columns:
            num = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=np.float64)
            bad = np.flatnonzero(df[c].notna().to_numpy() & ~np.isfinite(num))
            if bad.size:
                i = int(bad[0])
                raise ConfigError(
                    p,
                    f"row {i + 2}, column {c}",
                    f"expected a number or an empty cell, got {_text(df[c].iloc[i])}",
                )
            cols[c] = num
        else:
            cols[c] = np.full(len(df), np.nan)
    _motion_columns(p, df, cols)
    _check_pairs(p, cols["point"], cols["phase"])
    return TimedTable(p, tcol, tv, cols)


def _motion_columns(path: str, df: pd.DataFrame, cols: dict[str, NDArray[Any]]) -> None:
    """The motion of the oscillation rows (required there, empty elsewhere), into ``cols``."""
    from cdpr.analysis.conventions import OSCILLATION_POINT_KINDS
    from cdpr.analysis.motion import MOTION_AXES
    from cdpr.daq.vrig_events import MOTION_EVENT_FIELDS

    moving = np.isin(cols["kind"], OSCILLATION_POINT_KINDS)
    n = len(df)
    for c in MOTION_EVENT_FIELDS:
        have = c in df.columns
        given = df[c].notna().to_numpy() if have else np.zeros(n, dtype=bool)
        if have and df[c].dtype == object:
            given &= df[c].astype(str).str.strip().ne("").to_numpy()
        bad = np.flatnonzero(given & ~moving)
        if bad.size:
            i = int(bad[0])
            raise ConfigError(path, f"row {i + 2}, column {c}",
                              f"only an oscillation row has a motion (kind {cols['kind'][i]!r})")  # fmt: skip
        need = moving & ~given
        if c != "inertia_tare" and need.any():
            i = int(np.flatnonzero(need)[0])
            raise ConfigError(path, f"row {i + 2}, column {c}",
                              f"an {cols['kind'][i]} row needs it")  # fmt: skip
        if c in ("motion_axis", "inertia_tare"):
            v = (df[c].astype(object).where(df[c].notna(), "").astype(str).str.strip()
                 .to_numpy(dtype=object) if have else np.full(n, "", dtype=object))  # fmt: skip
            if c == "motion_axis":
                bad = np.flatnonzero(moving & ~np.isin(v, MOTION_AXES))
                if bad.size:
                    i = int(bad[0])
                    raise ConfigError(path, f"row {i + 2}, column {c}",
                                      f"expected one of {list(MOTION_AXES)}, got {v[i]!r}")  # fmt: skip
            cols[c] = v
            continue
        num = pd.to_numeric(df[c], errors="coerce").to_numpy(np.float64) if have else np.full(
            n, np.nan)  # fmt: skip
        whole = c.endswith("cycles")
        ok = np.isfinite(num) & (num >= 1 if whole else num > 0)
        if whole:
            ok &= num == np.round(num)
        bad = np.flatnonzero(moving & ~ok)
        if bad.size:
            i = int(bad[0])
            want = "a whole number >= 1" if whole else "a number > 0"
            raise ConfigError(path, f"row {i + 2}, column {c}",
                              f"expected {want}, got {_text(df[c].iloc[i])}")  # fmt: skip
        cols[c] = num


def _check_pairs(path: str, points: NDArray[Any], phases: NDArray[Any]) -> None:
    """Every point starts, then ends, before the next one starts; labels are not reused."""
    open_label: str | None = None
    done: set[str] = set()
    for i, (pt, ph) in enumerate(zip(points, phases, strict=True)):
        row = f"row {i + 2}, column phase"
        if ph == "start":
            if open_label is not None:
                raise ConfigError(path, row, f"{pt!r} starts before {open_label!r} ends")
            if pt in done:
                raise ConfigError(path, f"row {i + 2}, column point", f"label {pt!r} used twice")
            open_label = pt
        else:
            if open_label != pt:
                raise ConfigError(path, row, f"end of {pt!r}, which has not started")
            done.add(pt)
            open_label = None
    if open_label is not None:
        raise ConfigError(path, "", f"point {open_label!r} starts and never ends")


TUNNEL_DESCRIPTION = {
    "airspeed_mps": FieldDescription("m/s"),
    "static_pressure_Pa": FieldDescription("Pa"),
    "temperature_K": FieldDescription("K"),
    "density_kgpm3": FieldDescription("kg/m^3"),
    "relative_humidity": FieldDescription("1 (fraction 0..1)"),
}


def tunnel_stream(
    table: TimedTable, first_can_ns: int | None
) -> tuple[StreamDescription, list[Reading]]:
    """The ``/tunnel`` stream description and readings of a tunnel table."""
    t_ns = table.t_ns(first_can_ns)
    names = list(table.columns)
    desc = StreamDescription(
        {k: TUNNEL_DESCRIPTION[k] for k in names}, 0.0, "Imported tunnel conditions."
    )
    cols = [table.columns[k].tolist() for k in names]
    out = [
        Reading("tunnel", int(t), dict(zip(names, row, strict=True)))
        for t, row in zip(t_ns.tolist(), zip(*cols, strict=True), strict=True)
    ]
    return desc, out


def event_stream(
    table: TimedTable, first_can_ns: int | None
) -> tuple[StreamDescription, list[Reading]]:
    """The ``/events`` stream description and ``test_point`` readings of an events table."""
    from cdpr.daq.vrig_events import EVENT_FIELDS

    t_ns = table.t_ns(first_can_ns).tolist()
    c = table.columns
    out = []
    for i, t in enumerate(t_ns):
        values: dict[str, Any] = {
            "message": f"test point {c['point'][i]} {c['phase'][i]}",
            "name": "test_point",
            "point": str(c["point"][i]),
            "phase": str(c["phase"][i]),
            "kind": str(c["kind"][i]),
            "repeat_of": str(c["repeat_of"][i]),
        }
        for k in EVENT_TARGETS:
            x = float(c[k][i])
            values[k] = x if np.isfinite(x) else None
        if c["motion_axis"][i]:  # an oscillation row: its motion (read_events_csv checked it)
            values.update(
                motion_axis=str(c["motion_axis"][i]),
                motion_amplitude=float(c["motion_amplitude"][i]),
                motion_frequency_Hz=float(c["motion_frequency_Hz"][i]),
                motion_cycles=int(c["motion_cycles"][i]),
                motion_settling_cycles=int(c["motion_settling_cycles"][i]),
                inertia_tare=str(c["inertia_tare"][i]),
            )
        out.append(Reading("events", int(t), values))
    return StreamDescription(dict(EVENT_FIELDS), 0.0, "Imported test-point events."), out


#: the pose CSV's covariance columns: ``cov_<i><j>``, row i and column j of the 6x6 covariance of
#: ``(x_m, y_m, z_m, roll_rad, pitch_rad, yaw_rad)``
POSE_COV_COLUMNS = tuple(f"cov_{i}{j}" for i in range(6) for j in range(6))
#: relative asymmetry |C_ij - C_ji| / sqrt(C_ii C_jj) a covariance written with few digits may have
_COV_SYMMETRY_TOL = 1e-6


def read_pose_csv(path: str | os.PathLike[str]) -> TimedTable:
    """Read and check a pose CSV (see the module docstring): columns ``pose`` (k, 6) and, with the
    covariance columns, ``covariance_euler`` (k, 6, 6) (symmetrised)."""
    p = str(path)
    df = read_table(p, POSE_COLUMNS, "pose table")
    tcol, tv = table_times(p, df)
    cols: dict[str, NDArray[Any]] = {"pose": df[list(POSE_COLUMNS)].to_numpy(dtype=np.float64)}
    have = [c for c in df.columns if c.startswith("cov_")]
    if have:
        odd = [c for c in have if c not in POSE_COV_COLUMNS]
        if odd:
            raise ConfigError(p, f"column {odd[0]}", "not a covariance column (cov_00 .. cov_55)")
        missing = [c for c in POSE_COV_COLUMNS if c not in df.columns]
        if missing:
            raise ConfigError(
                p,
                f"column {missing[0]}",
                f"missing: a pose covariance is all 36 columns cov_00 .. cov_55, the file has "
                f"{len(have)} of them",
            )
        require_numbers(p, df, POSE_COV_COLUMNS)  # an empty or NaN cell names its row
        cols["covariance_euler"] = _checked_covariance(
            p, df[list(POSE_COV_COLUMNS)].to_numpy(dtype=np.float64).reshape(-1, 6, 6)
        )
    return TimedTable(p, tcol, tv, cols)


def _checked_covariance(path: str, C: NDArray[np.float64]) -> NDArray[np.float64]:
    """``C`` (k, 6, 6) symmetrised, or a ConfigError naming the first row and column that is not
    a covariance (a negative variance, an asymmetry, a negative eigenvalue)."""
    d = np.diagonal(C, axis1=1, axis2=2)
    neg = np.argwhere(d < 0)
    if len(neg):
        i, j = (int(x) for x in neg[0])
        raise ConfigError(path, f"row {i + 2}, column cov_{j}{j}", f"negative variance {d[i, j]:g}")
    scale = np.sqrt(d[:, :, None] * d[:, None, :])
    asym = np.argwhere(np.abs(C - np.swapaxes(C, 1, 2)) > _COV_SYMMETRY_TOL * scale)
    if len(asym):
        i, a, b = (int(x) for x in asym[0])
        raise ConfigError(
            path,
            f"row {i + 2}, column cov_{a}{b}",
            f"not symmetric: {C[i, a, b]:g} against cov_{b}{a} = {C[i, b, a]:g}",
        )
    S = 0.5 * (C + np.swapaxes(C, 1, 2))
    lo = np.linalg.eigvalsh(S)[:, 0]
    tol = 1e-9 * np.max(d, axis=1)
    neg_ev = np.flatnonzero(lo < -tol)
    if len(neg_ev):
        i = int(neg_ev[0])
        raise ConfigError(
            path,
            f"row {i + 2}, columns cov_00 .. cov_55",
            f"not a covariance: an eigenvalue is {lo[i]:g} < 0 (the variances and correlations "
            "disagree)",
        )
    return S


POSE_DESCRIPTION = {
    "position_O_m": FieldDescription("m", shape=(3,)),
    "quaternion_xyzw": FieldDescription("", shape=(4,)),
    "euler_rad": FieldDescription("rad", shape=(3,)),
    "covariance": FieldDescription("m, rad (6x6 row-major)", shape=(36,)),
}


def pose_stream(
    table: TimedTable, first_can_ns: int | None, pose_sd: Any = None
) -> tuple[StreamDescription, list[Reading]]:
    """The ``/pose`` stream description and readings of a pose table: position, orientation, Euler
    angles and, from the table's covariance columns or else the stated per-frame standard
    deviations ``pose_sd`` (6,) (x, y, z m; roll, pitch, yaw rad), the covariance in the camera's
    parametrisation ``[position_O_m, rotation vector in {O}]`` (none without either)."""
    t_ns = table.t_ns(first_can_ns).tolist()
    q6 = table.columns["pose"]
    cov = table.columns.get("covariance_euler")
    if cov is None and pose_sd is not None:
        sd = np.asarray(pose_sd, dtype=np.float64)
        cov = np.broadcast_to(np.diag(sd**2), (len(q6), 6, 6))
    fields = dict(POSE_DESCRIPTION)
    if cov is None:
        del fields["covariance"]
    desc = StreamDescription(
        fields,
        0.0,
        "Imported platform pose, P in {O}"
        + ("; covariance order [position_O_m, rotation_O_rad]" if cov is not None else "."),
    )
    q_wxyz = quaternion_from_euler(q6[:, 3:6])
    q_xyzw = np.concatenate([q_wxyz[:, 1:], q_wxyz[:, :1]], axis=1).tolist()
    stored = None if cov is None else pose_cov_from_euler(q6[:, 3:6], cov).reshape(-1, 36).tolist()
    pos, eul = q6[:, :3].tolist(), q6[:, 3:].tolist()
    out = []
    for k, t in enumerate(t_ns):
        values: dict[str, Any] = {
            "position_O_m": pos[k],
            "quaternion_xyzw": q_xyzw[k],
            "euler_rad": eul[k],
            "frame_id": "O",
        }
        if stored is not None:
            values["covariance"] = stored[k]
        out.append(Reading("pose", int(t), values))
    return desc, out
