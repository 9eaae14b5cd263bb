"""Which analysis results are current: a result folder is current when its recorded fingerprint
equals the fingerprint of its inputs now.

The fingerprint of a run's analysis is the SHA-256 of the run file, of every other input file
(balance calibration, test matrix, the virtual rig's truth file beside the run, ...), the options
(as JSON) and the software version.  ``cdpr analyze`` records it in ``summary.json`` and, on the
next call, skips the runs whose folder is current (``--force`` recomputes them).  Hashing reads
each file once, in 1 MiB blocks; a file's hash is reused while its size and modification time
(ns) are unchanged within one process.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .config import file_sha256

_HASHES: dict[tuple[str, int, int], str] = {}


def _sha256_cached(path: Path) -> str:
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    h = _HASHES.get(key)
    if h is None:
        h = _HASHES[key] = file_sha256(path)
    return h


def fingerprint(
    run: str | os.PathLike[str],
    options: Mapping[str, Any],
    software_version: str,
    inputs: Sequence[str | os.PathLike[str] | None] = (),
) -> dict[str, Any]:
    """The fingerprint of one run's analysis.

    run: the run file; options: the analysis options as JSON-able values; inputs: other files the
    result depends on (``None`` entries and files that do not exist are recorded as absent, so a
    truth file that appears later makes the result stale).
    """
    files: dict[str, str | None] = {}
    for f in inputs:
        if f is None:
            continue
        p = Path(f)
        files[p.name] = _sha256_cached(p) if p.is_file() else None
    opts = json.dumps(options, sort_keys=True, default=str)
    return {
        "run_sha256": _sha256_cached(Path(run)),
        "inputs_sha256": files,
        "options_sha256": hashlib.sha256(opts.encode()).hexdigest(),
        "software_version": software_version,
    }


def is_current(folder: str | os.PathLike[str], fp: Mapping[str, Any]) -> bool:
    """True when ``folder/summary.json`` exists, reads, and records exactly ``fp`` (its
    ``fingerprint`` entry); any doubt (missing, unreadable, another version) is False."""
    summary = Path(folder) / "summary.json"
    try:
        recorded = json.loads(summary.read_text()).get("fingerprint")
    except (OSError, ValueError, AttributeError):
        return False
    return isinstance(recorded, dict) and recorded == dict(fp)
