"""Configuration and data files are loaded here, in one place.

Every loader raises :class:`~cdpr.analysis.errors.ConfigError` naming the file, the key (or row and
column) and the problem; the CLI turns that into one line and exit code 2.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rig import Rig, rig_to_mapping
from cdpr.daq.files import atomic_output as atomic_output  # defined there, used by every pipeline
from cdpr.daq.files import load_json as load_json
from cdpr.daq.files import load_toml as load_toml
from cdpr.daq.files import one_line, read_text
from cdpr.daq.files import toml_inline_arrays as _toml_inline_arrays
from cdpr.daq.schema import load_rig as load_rig  # the rig file's schema

PLAUSIBLE_POSITION_M = 1e3
"""Largest ``|x|, |y|, |z|`` (m) a pose table may hold: beyond it a value is a typo (1e300)."""
PLAUSIBLE_ANGLE_RAD = 1e2
"""Largest ``|roll|, |pitch|, |yaw|`` (rad) a pose table may hold (unwrapped angles allowed)."""
PLAUSIBLE_LOAD_N = 1e7
"""Largest force (N), moment (N m) or tension (N) a wrench or tension table may hold."""


def rig_toml(rig: Rig, header: str = "") -> str:
    """A rig as TOML text, with optional comment lines on top."""
    text = _toml_inline_arrays(rig_to_mapping(rig))
    if header:
        text = "".join(f"# {line}\n" for line in header.splitlines()) + "\n" + text
    return text


def file_sha256(path: str | os.PathLike[str]) -> str:
    """Hex SHA-256 of a file's bytes (provenance of every input)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_table(
    path: str | os.PathLike[str],
    required: Sequence[str],
    what: str = "table",
    max_abs: Mapping[str, tuple[float, str]] | None = None,
) -> pd.DataFrame:
    """Read a CSV file and check that ``required`` columns exist and hold finite numbers.

    Lines starting with ``#`` are comments.  Errors name the file, the row (1-based data row, as a
    spreadsheet shows it counting the header as row 1) and the column, or the line of the file for
    its structure: bytes that are not UTF-8, a column named twice in the header, a row with more
    fields than the header (never read as an index column).  ``max_abs`` maps a column to the
    largest plausible ``|value|`` and its unit: a value beyond it (1e300 m) is refused.
    """
    p = Path(path)
    text = read_text(p)
    header_line = _check_header(p, text, what)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            df = pd.read_csv(io.StringIO(text), comment="#", skipinitialspace=True, index_col=False)
        except pd.errors.EmptyDataError:
            raise ConfigError(
                str(p), "", f"empty file, expected a {what} with a header row"
            ) from None
        except pd.errors.ParserError as exc:
            msg = one_line(exc)
            m = re.search(r"Expected (\d+) fields in line (\d+), saw (\d+)", msg)
            if m:
                raise ConfigError(
                    str(p),
                    f"line {m[2]}",
                    f"{m[3]} fields, the header (line {header_line}) has {m[1]}",
                ) from None
            raise ConfigError(str(p), "", f"cannot parse CSV: {msg}") from None
    if any(issubclass(w.category, pd.errors.ParserWarning) for w in caught):
        _too_many_fields(p, text, header_line)  # pandas would drop the extra fields
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise ConfigError(str(p), f"column {missing[0]}", f"missing (have: {list(df.columns)})")
    if len(df) == 0:
        raise ConfigError(str(p), "", f"no data rows in the {what}")
    require_numbers(p, df, required, max_abs)
    return df


def require_numbers(
    path: str | os.PathLike[str],
    df: pd.DataFrame,
    columns: Sequence[str],
    max_abs: Mapping[str, tuple[float, str]] | None = None,
) -> None:
    """Make ``columns`` of a table :func:`read_table` read float64, each value finite (and within
    ``max_abs``), else a ConfigError naming the file, row and column."""
    p = Path(path)
    for c in columns:
        col = pd.to_numeric(df[c], errors="coerce")
        values = col.to_numpy(dtype=np.float64)
        bad = ~np.isfinite(values)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ConfigError(
                str(p),
                f"row {i + 2}, column {c}",
                f"expected a finite number, got {_cell_text(df[c].iloc[i])}",
            )
        if max_abs and c in max_abs:
            limit, unit = max_abs[c]
            far = np.flatnonzero(np.abs(values) > limit)
            if far.size:
                i = int(far[0])
                raise ConfigError(
                    str(p),
                    f"row {i + 2}, column {c}",
                    f"absurd value {values[i]:g} (expected |value| <= {limit:g} {unit})",
                )
        df[c] = col


def _check_header(p: Path, text: str, what: str) -> int:
    """The header's line number; a column named twice (pandas would rename it) is an error."""
    for k, line in enumerate(text.splitlines(), start=1):
        if line.strip() and not line.lstrip().startswith("#"):
            names = [n.strip() for n in next(csv.reader([line]))]
            seen: set[str] = set()
            for name in names:
                if name in seen:
                    raise ConfigError(
                        str(p), f"line {k}, column {name}", "named twice in the header"
                    )
                seen.add(name)
            return k
    raise ConfigError(str(p), "", f"empty file, expected a {what} with a header row")


def _too_many_fields(p: Path, text: str, header_line: int) -> None:
    """Raise for the first data line with more fields than the header (error path only)."""
    lines = text.splitlines()
    n = len(next(csv.reader([lines[header_line - 1]])))
    for k in range(header_line, len(lines)):
        line = lines[k]
        if line.strip() and not line.lstrip().startswith("#"):
            fields = len(next(csv.reader([line.split("#", 1)[0]])))
            if fields > n:
                raise ConfigError(
                    str(p),
                    f"line {k + 1}",
                    f"{fields} fields, the header (line {header_line}) has {n}",
                )
    raise ConfigError(str(p), "", "rows do not match the header")  # pragma: no cover


def _cell_text(value: Any) -> str:
    """A CSV cell as the user typed it: ``'abc'`` for text, ``nan`` or ``inf`` for numbers."""
    if isinstance(value, str):
        return repr(value)
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "an empty cell or nan"
    return str(value)


def write_table(path: str | os.PathLike[str], df: pd.DataFrame, header: Mapping[str, Any]) -> None:
    """Write ``df`` as CSV atomically, with ``# key: value`` provenance lines on top."""
    with atomic_output(path) as fh:
        for k, v in header.items():
            fh.write(f"# {k}: {v}\n")
        df.to_csv(fh, index=False)


def tension_columns(rig: Rig) -> list[str]:
    """CSV column names of the cable tensions of ``rig``: ``T_<cable name>_N``."""
    return [f"T_{name}_N" for name in rig.cable_names]


def read_poses(path: str | os.PathLike[str]) -> tuple[pd.DataFrame, np.ndarray]:
    """Read a pose CSV (columns :data:`~cdpr.analysis.conventions.POSE_COLUMNS`).

    Returns the table and the poses (n, 6) as ``[x_m, y_m, z_m, roll_rad, pitch_rad, yaw_rad]``.
    """
    from cdpr.analysis.conventions import POSE_COLUMNS

    limits = {c: (PLAUSIBLE_POSITION_M, "m") for c in POSE_COLUMNS[:3]}
    limits |= {c: (PLAUSIBLE_ANGLE_RAD, "rad") for c in POSE_COLUMNS[3:]}
    df = read_table(path, POSE_COLUMNS, "pose table", limits)
    return df, df[list(POSE_COLUMNS)].to_numpy(dtype=np.float64)


def read_wrenches(path: str | os.PathLike[str], n_rows: int) -> np.ndarray:
    """Read a wrench CSV (columns :data:`~cdpr.analysis.conventions.WRENCH_COLUMNS`), (n, 6).

    A single row applies to every pose; otherwise the row count must equal ``n_rows``.
    """
    from cdpr.analysis.conventions import WRENCH_COLUMNS

    limits = {c: (PLAUSIBLE_LOAD_N, "N or N m") for c in WRENCH_COLUMNS}
    df = read_table(path, WRENCH_COLUMNS, "wrench table", limits)
    w = df[list(WRENCH_COLUMNS)].to_numpy(dtype=np.float64)
    if len(w) == 1:
        return np.repeat(w, n_rows, axis=0)
    if len(w) != n_rows:
        raise ConfigError(
            str(path), "rows", f"expected 1 or {n_rows} rows (one per pose), got {len(w)}"
        )
    return w


def read_tensions(path: str | os.PathLike[str], rig: Rig, n_rows: int | None = None) -> np.ndarray:
    """Read a tension CSV with one ``T_<cable>_N`` column per cable of ``rig``, (n, m) in N."""
    cols = tension_columns(rig)
    df = read_table(path, cols, "tension table", {c: (PLAUSIBLE_LOAD_N, "N") for c in cols})
    extra = [c for c in df.columns if c.startswith("T_") and c.endswith("_N") and c not in cols]
    if extra:
        raise ConfigError(
            str(path),
            f"column {extra[0]}",
            f"not a cable of rig {rig.name!r} (expected {rig.n_cables} cables: {cols})",
        )
    T = df[cols].to_numpy(dtype=np.float64)
    if n_rows is not None and len(T) not in (1, n_rows):
        raise ConfigError(str(path), "rows", f"expected 1 or {n_rows} rows, got {len(T)}")
    if n_rows is not None and len(T) == 1:
        T = np.repeat(T, n_rows, axis=0)
    return T


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


def read_balance_fit(path: str | None) -> Any:
    """The fit covariance of the balance model :func:`read_balance_calibration` returns (the
    second-order model's where the file has one, else the interaction matrix's) as a
    :class:`cdpr.analysis.systematic.BalanceFitCovariance`; None without a file or when the file
    does not give it (written before the fit covariance was: the reduction flags
    ``interaction_matrix_sd_not_given``)."""
    if path is None:
        return None
    from cdpr.analysis.errors import InputError
    from cdpr.analysis.systematic import BalanceFitCovariance

    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(path, "", f"cannot read the balance calibration: {exc}") from None
    so = doc.get("second_order")
    key, fit = (
        ("second_order.fit", so.get("fit"))
        if isinstance(so, dict)
        else ("interaction_matrix_fit", doc.get("interaction_matrix_fit"))
    )
    if fit is None:
        return None
    if not isinstance(fit, dict):
        raise ConfigError(path, key, "expected an object (residual_cov, inverse_gram, dof)")
    for k in ("residual_cov", "inverse_gram", "dof"):
        if k not in fit:
            raise ConfigError(path, f"{key}.{k}", "missing")
    p = 27 if key == "second_order.fit" else 6
    try:
        S = np.asarray(fit["residual_cov"], dtype=np.float64)
        M = np.asarray(fit["inverse_gram"], dtype=np.float64)
        dof = float(fit["dof"])
    except (TypeError, ValueError):
        raise ConfigError(path, key, "expected numbers") from None
    if S.shape != (6, 6) or M.shape != (p, p):
        raise ConfigError(
            path, key, f"expected residual_cov (6, 6), inverse_gram ({p}, {p}), got {S.shape}, "
            f"{M.shape}",
        )  # fmt: skip
    if np.any(np.diagonal(S) < 0) or np.any(np.diagonal(M) < 0):
        raise ConfigError(path, key, "a variance is negative")
    try:
        return BalanceFitCovariance(S, M, dof)
    except InputError as exc:
        raise ConfigError(path, key, str(exc)) from None
