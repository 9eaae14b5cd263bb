"""CAN log import per format (issue 20): frames/s of ``cdpr import`` of one minute of 8 load cells at
1 kHz (240,000 frames of the shipped DBC, the frames of :func:`bench_storage.write_candump`) in each
format python-can reads, against python-can's ``LogReader`` only reading the same file (the peer a
user would otherwise use; ratio = import / LogReader, as ``import_candump`` in ``bench_storage``):

- ``import_asc``: Vector ASC (times relative to the start, as Vector writes them; written by
  :func:`bench_storage.write_asc`);
- ``import_blf``: Vector BLF (written by python-can's ``BLFWriter``: zlib-compressed containers of
  ``CAN_MESSAGE`` objects);
- ``import_trc``: PEAK TRC (python-can's ``TRCWriter``, version 2.1);
- ``import_csv``: python-can's own CSV layout (``CSVWriter``: base64 data).

The context gives the format's parser alone (``read_log``) in frames/s and its ratio to
``LogReader``.  Run just these with ``python bench/run.py canlog``.
"""

from __future__ import annotations

import importlib.util
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"
N_SAMPLES = 60_000  # one minute at 1 kHz: 240,000 frames


def _storage():  # noqa: ANN202 - the log generators of bench_storage
    mod = sys.modules.get("bench_storage")
    if mod is None:
        spec = importlib.util.spec_from_file_location(
            "bench_storage", Path(__file__).with_name("bench_storage.py")
        )
        assert spec and spec.loader
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    return mod


def _write_with_python_can(src: Path, dst: Path) -> int:
    """The frames of the candump log ``src`` written by python-can's writer for ``dst``'s suffix."""
    import can

    n = 0
    with can.Logger(str(dst)) as w:
        for m in can.LogReader(str(src)):
            w.on_message_received(m)
            n += 1
    return n


def _best_of(k: int, fn) -> float:  # noqa: ANN001
    best = float("inf")
    for _ in range(k):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def run() -> dict[str, dict]:
    import can

    from cdpr.daq.canlog import read_log
    from cdpr.pipelines.cli import main

    out: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        bs = _storage()
        candump = tmp / "bench.log"
        n_frames = bs.write_candump(candump, N_SAMPLES)
        logs = {"asc": tmp / "bench.asc"}
        assert bs.write_asc(logs["asc"], N_SAMPLES) == n_frames
        for fmt in ("blf", "trc", "csv"):
            logs[fmt] = tmp / f"bench.{fmt}"
            assert _write_with_python_can(candump, logs[fmt]) == n_frames
        for fmt, log in logs.items():
            peer_s = _best_of(3, lambda log=log: sum(1 for _ in can.LogReader(str(log))))
            runs = iter(range(100))

            def import_once(log: Path = log, fmt: str = fmt, runs=runs) -> None:  # noqa: ANN001
                out = tmp / f"imp_{fmt}_{next(runs)}.mcap"
                rc = main(["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG),
                           "--out", str(out)])  # fmt: skip
                assert rc == 0

            imp_s = _best_of(3, import_once)
            parse_s = _best_of(3, lambda log=log: sum(len(c) for c in read_log(log)))
            out[f"import_{fmt}"] = {
                "value": n_frames / imp_s,
                "unit": "frames/s",
                "peer": f"python-can LogReader reading the same {fmt.upper()} file",
                "peer_value": n_frames / peer_s,
                "context": f"{n_frames} frames (1 min, 8 cells at 1 kHz), {log.stat().st_size} "
                f"bytes: import {imp_s:.2f} s (best of 3), LogReader {peer_s:.2f} s (best of 3); the parser "
                f"alone (read_log): {n_frames / parse_s:.0f} frames/s "
                f"({peer_s / parse_s:.1f}x LogReader)",
            }
    return out


if __name__ == "__main__":
    for name, entry in run().items():
        print(name, entry)
