"""HDF5 export of a run: one table per stream, metadata as attributes, attachments as byte arrays.

Layout (read it with h5py, then ``pandas.DataFrame(f["streams/tensions"][()])``; ``h5dump`` shows it):

- ``/streams/<stream>``: a compound (table) dataset, one row per message (a per-source stream
  ``/<source>/<stream>`` is named ``<source>.<stream>``): ``t_ns`` (int64, the
  message log time, ns since the Unix epoch) then one column per JSON field, flattened: nested objects
  as ``parent_child`` (``pose_position_x``), fixed-length arrays as ``name_0``, ``name_1``, ...;
  numbers are float64 (NaN where missing), integers int64 when every value is one, text as
  variable-length UTF-8.  Attributes: ``topic``, ``schema``, ``units`` (JSON), ``rate_hz``.
- ``/blobs/<stream>/<field>``: variable-length uint8 rows for byte payloads that are not numbers
  (camera images, base64 in the MCAP message, raw bytes here).
- ``/metadata/<record>``: an empty group per MCAP metadata record with one attribute per key.
- ``/attachments/<name>``: the attached file's bytes (uint8), attribute ``media_type``.
- root attributes: ``source_file``, ``source_sha256``, ``format`` = ``cdpr-run-hdf5/1``.

The file is written to a temporary name and moved into place only when complete.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import InputError

from .mcap_io import RunContents, read_run

FORMAT = "cdpr-run-hdf5/1"
_BLOB_FIELDS = {"foxglove.CompressedImage": ("data",)}


def _flatten(obj: Any, prefix: str, out: dict[str, Any]) -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            _flatten(v, f"{prefix}_{k}" if prefix else str(k), out)
    elif isinstance(obj, list) and obj and all(not isinstance(x, dict | list) for x in obj):
        if len(obj) <= 64:
            for i, x in enumerate(obj):
                out[f"{prefix}_{i}"] = x
        else:
            out[prefix] = json.dumps(obj)
    elif isinstance(obj, list):
        out[prefix] = json.dumps(obj)
    else:
        out[prefix] = obj


def _column(values: list[Any]) -> tuple[np.dtype, np.ndarray]:
    """Pick a column dtype: int64 if every present value is an int, float64 if numbers, else text."""
    present = [v for v in values if v is not None]
    if present and all(isinstance(v, bool | int) for v in present) and len(present) == len(values):
        return np.dtype(np.int64), np.asarray(values, dtype=np.int64)
    if all(isinstance(v, bool | int | float) for v in present):
        return np.dtype(np.float64), np.asarray(
            [np.nan if v is None else float(v) for v in values], dtype=np.float64
        )
    import h5py

    dt = h5py.string_dtype("utf-8")
    arr = np.empty(len(values), dtype=object)
    arr[:] = ["" if v is None else (v if isinstance(v, str) else json.dumps(v)) for v in values]
    return dt, arr


def _stream_table(
    msgs: list[tuple[int, dict[str, Any]]], blob_fields: tuple[str, ...]
) -> tuple[np.ndarray, dict[str, list[bytes]]]:
    rows: list[dict[str, Any]] = []
    blobs: dict[str, list[bytes]] = {f: [] for f in blob_fields}
    for _, body in msgs:
        body = dict(body)
        for f in blob_fields:
            raw = body.pop(f, "")
            blobs[f].append(base64.b64decode(raw) if isinstance(raw, str) else bytes(raw or b""))
        flat: dict[str, Any] = {}
        _flatten(body, "", flat)
        rows.append(flat)
    names: list[str] = []
    seen: set[str] = set()
    for r in rows:
        for k in r:
            if k not in seen and k != "t_ns":
                seen.add(k)
                names.append(k)
    cols = [("t_ns", np.dtype(np.int64), np.asarray([m[0] for m in msgs], dtype=np.int64))]
    for k in names:
        dt, arr = _column([r.get(k) for r in rows])
        cols.append((k, dt, arr))
    table = np.empty(len(msgs), dtype=[(k, dt) for k, dt, _ in cols])
    for k, _, arr in cols:
        table[k] = arr
    return table, blobs


def export_hdf5(
    run_path: str | os.PathLike[str], out_path: str | os.PathLike[str]
) -> dict[str, int]:
    """Write the HDF5 export of ``run_path`` to ``out_path`` (never overwrites; atomic).

    Returns the number of rows written per stream.  A truncated run is exported as far as it reads.
    """
    import h5py

    src = Path(run_path)
    dst = Path(out_path)
    if dst.exists():
        raise InputError(f"{dst}: exists already; an export is never overwritten")
    contents: RunContents = read_run(src)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.part")
    counts: dict[str, int] = {}
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["source_file"] = src.name
            f.attrs["source_sha256"] = hashlib.sha256(src.read_bytes()).hexdigest()
            f.attrs["source_complete"] = bool(contents.complete)
            streams = f.create_group("streams")
            for topic, msgs in contents.messages.items():
                name = topic.lstrip("/").replace("/", ".") or "root"
                ch = contents.channels.get(topic)
                blob_fields = _BLOB_FIELDS.get(ch.schema_name if ch else "", ())
                table, blobs = _stream_table(msgs, blob_fields)
                ds = streams.create_dataset(name, data=table, chunks=True if len(table) else None)
                ds.attrs["topic"] = topic
                if ch is not None:
                    ds.attrs["schema"] = ch.schema_name
                    ds.attrs["units"] = ch.metadata.get("units", "{}")
                    ds.attrs["rate_hz"] = float(ch.metadata.get("rate_hz", "0") or 0)
                for fld, rows in blobs.items():
                    vl = f.create_dataset(
                        f"blobs/{name}/{fld}",
                        shape=(len(rows),),
                        dtype=h5py.vlen_dtype(np.dtype(np.uint8)),
                    )
                    for i, b in enumerate(rows):
                        vl[i] = np.frombuffer(b, dtype=np.uint8)
                counts[name] = len(table)
            meta = f.create_group("metadata")
            for rec_name, kv in contents.metadata.items():
                g = meta.create_group(rec_name)
                for k, v in kv.items():
                    g.attrs[k] = v
            att = f.create_group("attachments")
            for a_name, (media, data) in contents.attachments.items():
                d = att.create_dataset(a_name.replace("/", "_"), data=np.frombuffer(data, np.uint8))
                d.attrs["media_type"] = media
                d.attrs["name"] = a_name
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        if dst.exists():
            raise InputError(f"{dst}: exists already; an export is never overwritten")
        os.replace(tmp, dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return counts
