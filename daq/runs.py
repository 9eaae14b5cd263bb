"""Run naming and run metadata.

A run is one MCAP file named ``<YYYYmmdd>_<HHMMSS>_<label>.mcap`` (UTC date and time of the start,
the test-point label made file-name safe).  A run is never overwritten: when the name is taken
(two runs started in the same second), ``_2``, ``_3``, ... is appended, and the writer opens the file
with exclusive create.
"""

from __future__ import annotations

import getpass
import json
import os
import platform
import re
import socket
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from cdpr.analysis.errors import InputError

_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def safe_label(label: str) -> str:
    """``label`` with every run of characters other than letters, digits, ``.``, ``_`` and ``-``
    replaced by ``-`` (at most 64 characters); ``"run"`` if nothing is left."""
    s = _SAFE.sub("-", label.strip()).strip("-.")[:64]
    return s or "run"


def run_name(label: str = "run", t_ns: int | None = None) -> str:
    """``YYYYmmdd_HHMMSS_<label>`` of the UTC time ``t_ns`` (ns since the epoch; now by default)."""
    t = time.gmtime((time.time_ns() if t_ns is None else t_ns) / 1e9)
    return time.strftime("%Y%m%d_%H%M%S", t) + "_" + safe_label(label)


def new_run_path(
    out_dir: str | os.PathLike[str], label: str = "run", t_ns: int | None = None
) -> Path:
    """A path ``out_dir/<run_name>.mcap`` that does not exist yet (``_2``, ``_3``, ... appended)."""
    d = Path(out_dir)
    if d.exists() and not d.is_dir():
        raise InputError(f"{d}: not a folder (runs are written into a folder)")
    base = run_name(label, t_ns)
    p = d / f"{base}.mcap"
    k = 2
    while p.exists() or (d / f"{p.stem}.recovered.mcap").exists():
        p = d / f"{base}_{k}.mcap"
        k += 1
    return p


def host_info() -> dict[str, str]:
    """Host name, OS, Python and user, for the run metadata."""
    try:
        user = getpass.getuser()
    except Exception:  # no user name in some containers
        user = ""
    return {
        "host": socket.gethostname(),
        "os": platform.platform(),
        "python": sys.version.split()[0],
        "user": user,
        "pid": str(os.getpid()),
    }


def iso_utc(t_ns: int) -> str:
    """ISO 8601 UTC text of an integer ns timestamp, with microseconds."""
    sec, ns = divmod(int(t_ns), 1_000_000_000)
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(sec)) + f".{ns // 1000:06d}Z"


def run_metadata(
    *,
    label: str,
    start_ns: int,
    software_version: str,
    rig: str = "",
    rig_sha256: str = "",
    calibration_ids: Mapping[str, str] | None = None,
    config: Mapping[str, Any] | None = None,
    operator: str = "",
    notes: str = "",
    extra: Mapping[str, Any] | None = None,
) -> dict[str, str]:
    """The ``run`` metadata record (all values strings; mappings as JSON)."""
    md: dict[str, str] = {
        "label": label,
        "start_time_ns": str(int(start_ns)),
        "start_time_utc": iso_utc(start_ns),
        "software": "cdpr",
        "software_version": software_version,
        "rig": rig,
        "rig_sha256": rig_sha256,
        "calibration_ids": json.dumps(dict(calibration_ids or {}), sort_keys=True),
        "config": json.dumps(config or {}, sort_keys=True, default=str),
        "operator": operator,
        "notes": notes,
    }
    md.update(host_info())
    for k, v in (extra or {}).items():
        md[str(k)] = v if isinstance(v, str) else json.dumps(v, default=str)
    return md
