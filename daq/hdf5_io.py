"""HDF5 export of a run: one table per stream, metadata as attributes, attachments as byte arrays.

The run is read with :func:`cdpr.daq.run_reader.open_run`, so the tables have the reader's columns.
Layout (read it with h5py, then ``pandas.DataFrame(f["streams/tensions"][()])``; ``h5dump`` shows it):

- ``/streams/<stream>``: a compound (table) dataset, one row per message (a per-source stream
  ``/<source>/<stream>`` is named ``<source>.<stream>``): ``t_ns`` (int64, the message log time, ns
  since the Unix epoch) then the columns of ``open_run(...).table(topic)`` (pose: ``x_m, y_m, z_m,
  qw, qx, qy, qz, cov_00..cov_55, ...``; tensions: ``T_<cable>_N``, ...): numbers float64 (NaN where
  missing) or int64, text as variable-length UTF-8.  Attributes: ``topic``, ``schema``, ``units``
  (JSON), ``rate_hz``.
- ``/blobs/<stream>/<field>``: variable-length uint8 rows for byte columns (camera images, the data
  bytes of raw CAN frames).
- ``/metadata/<record>``: an empty group per MCAP metadata record with one attribute per key.
- ``/attachments/<name>``: the attached file's bytes (uint8), attribute ``media_type``.
- root attributes: ``source_file``, ``source_sha256``, ``source_complete``, ``format`` =
  ``cdpr-run-hdf5/2``.

The file is written to a temporary name and moved into place only when complete.  A cut-off or
damaged run (no summary, or a chunk that does not decompress or fails its CRC) is exported through
the recovery path (every readable chunk, before and after the damage): ``source_complete`` False,
``recovery_warning`` says what was lost, and :func:`export_hdf5` returns it as ``partial`` (the CLI
says it in one line and exits 3, as ``cdpr recover`` does for a partial salvage).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from cdpr.analysis.errors import InputError

from .run_reader import DamagedRunError, Run, open_run

FORMAT = "cdpr-run-hdf5/2"


def _table(df: Any) -> tuple[np.ndarray, dict[str, list[bytes]]]:
    """A DataFrame as a compound array (numbers, text) plus its byte columns (blobs)."""
    import h5py

    cols: list[tuple[str, Any, Any]] = []
    blobs: dict[str, list[bytes]] = {}
    for name in df.columns:
        v = df[name].to_numpy()
        if v.dtype.kind in "iub":
            cols.append((str(name), np.dtype(np.int64), v.astype(np.int64)))
        elif v.dtype.kind == "f":
            cols.append((str(name), np.dtype(np.float64), v))
        elif len(v) and all(isinstance(x, bytes | bytearray) for x in v):
            blobs[str(name)] = [bytes(x) for x in v]
        else:
            arr = np.empty(len(v), dtype=object)
            arr[:] = ["" if x is None or x != x else str(x) for x in v]
            cols.append((str(name), h5py.string_dtype("utf-8"), arr))
    table = np.empty(len(df), dtype=[(k, dt) for k, dt, _ in cols])
    for k, _, arr in cols:
        table[k] = arr
    return table, blobs


class ExportResult(NamedTuple):
    """What :func:`export_hdf5` wrote: rows per stream, and why the export is partial (None: the
    run was complete and read whole)."""

    counts: dict[str, int]
    partial: str | None


def export_hdf5(run_path: str | os.PathLike[str], out_path: str | os.PathLike[str]) -> ExportResult:
    """Write the HDF5 export of ``run_path`` to ``out_path`` (never overwrites; atomic).

    A cut-off or damaged run is exported through the recovery path as far as it reads, and the
    result's ``partial`` says so (``recovery_warning`` in the file).
    """
    src = Path(run_path)
    dst = Path(out_path)
    if dst.exists():
        raise InputError(f"{dst}: exists already; an export is never overwritten")
    run = None
    try:
        try:
            run = open_run(src)
            counts = _write(run, src, dst)
        except DamagedRunError as exc:
            # a part the summary points at is damaged: read what the recovery path salvages
            if run is not None:
                run.close()
            run = open_run(src, recover=True)
            run.warning = f"{exc}; exported what the recovery path salvaged"
            counts = _write(run, src, dst)
    finally:
        if run is not None:
            run.close()
    return ExportResult(counts, run.warning if run.recovered else None)


def _h5_text(src: Path, where: str, text: str, name: bool = True) -> str:
    """``text`` if HDF5 can hold it as a group, dataset or attribute name (``name``: not empty,
    ``.`` or ``..``) or as a string value (no NUL byte); else one line naming the file and the
    part (a damaged metadata record can hold anything: MCAP checks no CRC on it)."""
    if "\x00" in text or (name and text in ("", ".", "..")):
        what = "name" if name else "value"
        shown = repr(text) if len(text) <= 40 else repr(text[:40]) + f" ({len(text)} characters)"
        raise InputError(f"{src}: {where}: {shown} cannot be an HDF5 {what} (empty or a NUL byte)")
    return text


def _write(run: Run, src: Path, dst: Path) -> dict[str, int]:
    import h5py

    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.part")
    counts: dict[str, int] = {}
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["source_file"] = src.name
            f.attrs["source_sha256"] = hashlib.sha256(src.read_bytes()).hexdigest()
            f.attrs["source_complete"] = not run.recovered
            if run.warning:
                f.attrs["recovery_warning"] = run.warning
            streams = f.create_group("streams")
            for topic, info in run.streams.items():
                if info.metadata.get("view_of"):
                    continue  # the per-sample view of a block stream: a copy of some samples
                if info.metadata.get("status_of") in run.streams:
                    continue  # a pose's status channel: joined into the pose stream's table
                name = topic.lstrip("/").replace("/", ".") or "root"
                table, blobs = _table(run.table(topic))
                ds = streams.create_dataset(name, data=table, chunks=True if len(table) else None)
                ds.attrs["topic"] = topic
                ds.attrs["schema"] = info.schema_name
                ds.attrs["units"] = json.dumps(info.units, separators=(",", ":"))
                ds.attrs["rate_hz"] = info.rate_hz
                for fld, rows in blobs.items():
                    vl = f.create_dataset(
                        f"blobs/{name}/{fld}",
                        shape=(len(rows),),
                        dtype=h5py.vlen_dtype(np.dtype(np.uint8)),
                    )
                    for i, b in enumerate(rows):
                        vl[i] = np.frombuffer(b, dtype=np.uint8)
                counts[name] = len(table)
            run.verify()  # the chunks no table needed (views) are checked too
            meta = f.create_group("metadata")
            for rec_name, kv in run.metadata.items():
                g = meta.create_group(_h5_text(src, "metadata record", rec_name))
                for k, v in kv.items():
                    where = f"metadata record {rec_name!r}"
                    key = _h5_text(src, f"{where}, a key", k)
                    g.attrs[key] = _h5_text(src, f"{where}, key {key!r}", v, False)
            att = f.create_group("attachments")
            for a_name, (media, data) in run.attachments.items():
                where = f"attachment {a_name!r}"
                d = att.create_dataset(
                    _h5_text(src, "attachment", a_name.replace("/", "_")),
                    data=np.frombuffer(data, np.uint8),
                )
                d.attrs["media_type"] = _h5_text(src, f"{where}, media type", media, False)
                d.attrs["name"] = _h5_text(src, where, a_name, False)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        if dst.exists():
            raise InputError(f"{dst}: exists already; an export is never overwritten")
        os.replace(tmp, dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return counts
