"""Configuration and data files are loaded here, in one place.

Every loader raises :class:`~cdpr.analysis.errors.ConfigError` naming the file, the key (or row and
column) and the problem; the CLI turns that into one line and exit code 2.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rig import Rig, rig_from_mapping, rig_to_mapping
from cdpr.daq.files import atomic_output, load_toml  # defined there, used by every pipeline
from cdpr.daq.files import toml_inline_arrays as _toml_inline_arrays


def load_rig(path: str | os.PathLike[str]) -> Rig:
    """Load and validate a rig file (layout in :mod:`cdpr.analysis.rig`)."""
    return rig_from_mapping(load_toml(path), source=str(path))


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
    path: str | os.PathLike[str], required: Sequence[str], what: str = "table"
) -> pd.DataFrame:
    """Read a CSV file and check that ``required`` columns exist and hold finite numbers.

    Lines starting with ``#`` are comments.  Errors name the file, the row (1-based data row, as a
    spreadsheet shows it counting the header as row 1) and the column.
    """
    p = Path(path)
    try:
        df = pd.read_csv(p, comment="#", skipinitialspace=True)
    except FileNotFoundError:
        raise ConfigError(str(p), "", "file not found") from None
    except pd.errors.EmptyDataError:
        raise ConfigError(str(p), "", f"empty file, expected a {what} with a header row") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise ConfigError(str(p), "", f"cannot parse CSV: {exc}") from None
    except OSError as exc:  # a folder, no permission, ...
        raise ConfigError(str(p), "", f"cannot read: {exc.strerror or exc}") from None
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise ConfigError(str(p), f"column {missing[0]}", f"missing (have: {list(df.columns)})")
    if len(df) == 0:
        raise ConfigError(str(p), "", f"no data rows in the {what}")
    for c in required:
        col = pd.to_numeric(df[c], errors="coerce")
        bad = ~np.isfinite(col.to_numpy(dtype=np.float64))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ConfigError(
                str(p),
                f"row {i + 2}, column {c}",
                f"expected a finite number, got {_cell_text(df[c].iloc[i])}",
            )
        df[c] = col
    return df


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

    df = read_table(path, POSE_COLUMNS, "pose table")
    return df, df[list(POSE_COLUMNS)].to_numpy(dtype=np.float64)


def read_wrenches(path: str | os.PathLike[str], n_rows: int) -> np.ndarray:
    """Read a wrench CSV (columns :data:`~cdpr.analysis.conventions.WRENCH_COLUMNS`), (n, 6).

    A single row applies to every pose; otherwise the row count must equal ``n_rows``.
    """
    from cdpr.analysis.conventions import WRENCH_COLUMNS

    df = read_table(path, WRENCH_COLUMNS, "wrench table")
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
    df = read_table(path, cols, "tension table")
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
