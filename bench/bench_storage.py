"""Storage benchmarks (issue 9):

- ``import_candump``: frames/s of ``cdpr import`` of a candump ``.log`` (ten minutes of 8 load
  cells at 1 kHz: 2.4 M frames, the shipped DBC), against python-can's ``LogReader`` just reading
  the same file (one minute imported too, for the fixed costs);
- ``import_asc``, ``import_blf``, ``import_trc``, ``import_csv``: in ``bench_canlog.py`` (the same
  frames in each format, :func:`write_asc` here);
- ``run_read_topic``: rows/s of ``open_run(...).table("/tensions")`` on a run of one minute of 8
  cells at 1 kHz written by the project's writer (column blocks), against the ``mcap`` package's
  reader + ``json.loads`` per message on the same samples stored as per-sample JSON (the usual
  layout);
- ``storage_json_bytes_per_sample``, ``storage_block_bytes_per_sample``: bytes per tension sample
  in either layout (zstd chunks), for the storage notes in docs/recording.md.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"
DBC = ROOT / "data_samples" / "loadcell.dbc"
N_SAMPLES = 60_000  # one minute at 1 kHz
#: the import benchmark's log: ten minutes at 1 kHz (2.4 M frames), a tunnel run's length (a minute
#: is also imported, for the fixed costs: context)
IMPORT_SAMPLES = 600_000
T0_S = 1_700_000_000


def write_candump(path: Path, n_samples: int, seed: int = 0) -> int:
    """A candump -L log of ``n_samples`` samples of the shipped DBC (4 frames a sample: two int24
    little-endian counts, a status byte, the counter), written with numpy; returns the frames."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 1 << 23, (n_samples, 8))
    n = 4 * n_samples
    data = np.zeros((n, 8), np.uint8)
    c = counts.reshape(n, 2)
    for k in range(3):
        data[:, k] = (c[:, 0] >> (8 * k)) & 0xFF
        data[:, 3 + k] = (c[:, 1] >> (8 * k)) & 0xFF
    data[:, 7] = np.repeat(np.arange(n_samples) % 256, 4)
    ids = np.tile([0x181, 0x281, 0x381, 0x481], n_samples)
    us = np.repeat(np.arange(n_samples) * 1000, 4) + np.tile([0, 100, 200, 300], n_samples)
    lines = [
        f"({T0_S + u // 1_000_000}.{u % 1_000_000:06d}) can0 {i:03X}#{d.hex().upper()}\n"
        for u, i, d in zip(us.tolist(), ids.tolist(), [bytes(r) for r in data], strict=True)
    ]
    path.write_text("".join(lines))
    return n


def write_asc(path: Path, n_samples: int, seed: int = 0) -> int:
    """The frames of :func:`write_candump` as a Vector ASC log (times relative to the start, the
    layout of python-can's ``ASCWriter``); returns the frames."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 1 << 23, (n_samples, 8))
    n = 4 * n_samples
    data = np.zeros((n, 8), np.uint8)
    c = counts.reshape(n, 2)
    for k in range(3):
        data[:, k] = (c[:, 0] >> (8 * k)) & 0xFF
        data[:, 3 + k] = (c[:, 1] >> (8 * k)) & 0xFF
    data[:, 7] = np.repeat(np.arange(n_samples) % 256, 4)
    ids = np.tile([0x181, 0x281, 0x381, 0x481], n_samples)
    us = np.repeat(np.arange(n_samples) * 1000, 4) + np.tile([0, 100, 200, 300], n_samples)
    head = (
        "date Wed Nov 25 15:06:13.191 2026\nbase hex  timestamps absolute\n"
        "internal events logged\nBegin Triggerblock Wed Nov 25 15:06:13.191 2026\n"
        "   0.000000 Start of measurement\n"
    )
    lines = [
        f"{u // 1_000_000:4d}.{u % 1_000_000:06d} 1  {i:<15X} Rx   d 8 {d.hex(' ').upper()}\n"
        for u, i, d in zip(us.tolist(), ids.tolist(), [bytes(r) for r in data], strict=True)
    ]
    path.write_text(head + "".join(lines) + "End TriggerBlock\n")
    return n


def write_tension_run(path: Path, n_samples: int, blocks: bool | None = None) -> None:
    """A run of ``n_samples`` tension samples of 8 cells with the recorder's fields, through the
    recorder's path (``write_many`` of readings); ``blocks=False``: per-sample JSON messages
    instead of the column blocks a 1 kHz stream gets."""
    from cdpr.daq.mcap_writer import McapRunWriter
    from cdpr.daq.source import FieldDescription, Reading, StreamDescription

    cables = [f"c{i}" for i in range(1, 9)]
    fields = {f"T_{c}_N": FieldDescription("N") for c in cables}
    fields |= {f"raw_{c}_counts": FieldDescription("counts", "int64") for c in cables}
    fields |= {f"status_{c}": FieldDescription("", "int64") for c in cables}
    fields |= {k: FieldDescription("", "int64") for k in ("counter", "seq")}
    fields["t_bus_ns"] = FieldDescription("ns", "int64")
    rng = np.random.default_rng(1)
    T = rng.uniform(35.0, 300.0, (n_samples, 8)).tolist()
    t0 = T0_S * 10**9
    w = McapRunWriter(path)
    w.add_stream("tensions", StreamDescription(fields, 1000.0, "bench"), blocks=blocks)
    batch = []
    for i in range(n_samples):
        v = {f"T_{c}_N": T[i][j] for j, c in enumerate(cables)}
        v |= {f"raw_{c}_counts": int(T[i][j] * 1000) for j, c in enumerate(cables)}
        v |= {f"status_{c}": 0 for c in cables}
        v |= {"counter": i % 256, "seq": i, "t_bus_ns": t0 + i * 1_000_000 + 7}
        batch.append(Reading("tensions", t0 + i * 1_000_000, v))
        if len(batch) == 1000:
            w.write_many(batch)
            batch = []
    w.write_many(batch)
    w.finish()


def _python_can_read(path: Path) -> int:
    import can

    return sum(1 for _ in can.LogReader(str(path)))


def _mcap_json_read(path: Path) -> int:
    from mcap.reader import make_reader

    with path.open("rb") as fh:
        rows = [
            json.loads(m.data) for _, _, m in make_reader(fh).iter_messages(topics=["/tensions"])
        ]
    return len(rows)


def run() -> dict[str, dict]:
    from cdpr.daq.run_reader import open_run
    from cdpr.pipelines.cli import main
    from cdpr.pipelines.commands import import_run  # noqa: F401  (imports not timed)
    from cdpr.pipelines.config import load_rig  # noqa: F401

    out: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        from cdpr.daq.canlog_candump import read_candump

        def import_log(log: Path, out: Path) -> float:
            t = time.perf_counter()
            rc = main(["import", "--can-log", str(log), "--dbc", str(DBC), "--rig", str(RIG),
                       "--out", str(out)])  # fmt: skip
            assert rc == 0
            return time.perf_counter() - t

        log = tmp / "bench.log"
        n_frames = write_candump(log, IMPORT_SAMPLES)
        t = time.perf_counter()
        assert _python_can_read(log) == n_frames
        peer_s = time.perf_counter() - t
        imp_s = import_log(log, tmp / "imp.mcap")
        t = time.perf_counter()
        assert sum(len(c) for c in read_candump(log)) == n_frames
        parse_s = time.perf_counter() - t
        minute = tmp / "minute.log"
        n_minute = write_candump(minute, N_SAMPLES)
        minute_s = import_log(minute, tmp / "minute.mcap")
        out["import_candump"] = {
            "value": n_frames / imp_s,
            "unit": "frames/s",
            "peer": "python-can LogReader reading the same candump file",
            "peer_value": n_frames / peer_s,
            "context": f"{n_frames} frames (10 min, 8 cells at 1 kHz): import {imp_s:.2f} s, "
            f"LogReader {peer_s:.2f} s; the numpy candump parser alone: "
            f"{n_frames / parse_s:.0f} frames/s ({peer_s / parse_s:.1f}x LogReader); one minute "
            f"({n_minute} frames) imported in {minute_s:.2f} s ({n_minute / minute_s:.0f} frames/s)",
        }

        run_path = tmp / "tensions.mcap"  # the layout runs have: column blocks
        write_tension_run(run_path, N_SAMPLES)
        json_path = tmp / "tensions_json.mcap"  # the same samples as per-sample JSON messages
        write_tension_run(json_path, N_SAMPLES, blocks=False)
        t = time.perf_counter()
        n_peer = _mcap_json_read(json_path)
        peer_s = time.perf_counter() - t
        t = time.perf_counter()
        with open_run(run_path) as r:
            df = r.table("/tensions")
        read_s = time.perf_counter() - t
        t = time.perf_counter()
        with open_run(json_path) as r:
            df_json = r.table("/tensions")
        json_s = time.perf_counter() - t
        assert len(df) == len(df_json) == n_peer == N_SAMPLES
        assert np.array_equal(df.to_numpy(np.float64), df_json[df.columns].to_numpy(np.float64))
        out["run_read_topic"] = {
            "value": N_SAMPLES / read_s,
            "unit": "rows/s",
            "peer": "mcap iter_messages + json.loads per message, same samples as per-sample JSON",
            "peer_value": n_peer / peer_s,
            "context": f"{N_SAMPLES} samples of 8 cells (27 fields) in column blocks, zstd, "
            f"open_run incl. opening the file; open_run on the per-sample JSON file: "
            f"{N_SAMPLES / json_s:.0f} rows/s",
        }
        out.update(_storage_options(tmp, json_path))
        out["storage_json_bytes_per_sample"] = {
            "value": json_path.stat().st_size / N_SAMPLES,
            "unit": "B/sample",
            "context": "file bytes per tension sample (8 cells, 27 fields), per-sample JSON, zstd",
        }
        out["storage_block_bytes_per_sample"] = {
            "value": run_path.stat().st_size / N_SAMPLES,
            "unit": "B/sample",
            "context": "the same samples in column blocks (float64 and narrow integer columns, base64 in "
            "JSON, zstd) with the 50 Hz per-sample view beside them",
        }
        out["storage_block_read_rows"] = {
            "value": N_SAMPLES / read_s,
            "unit": "rows/s",
            "context": "open_run(...).table('/tensions') on column blocks (= run_read_topic)",
        }
    return out


def _storage_options(tmp: Path, json_run: Path) -> dict[str, dict]:
    """The writer option: the ``mcap`` package's ``Writer`` against the project's chunk writer on
    the same JSON messages, chunking and compression."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    from cdpr.daq.mcap_chunks import ChunkedWriter

    with json_run.open("rb") as fh:
        msgs = [(m.log_time, m.data) for _, _, m in make_reader(fh).iter_messages()]
    tt = time.perf_counter()
    with (tmp / "w_mcap.mcap").open("wb") as fh:
        w = Writer(fh, chunk_size=256 * 1024, compression=CompressionType.ZSTD)
        w.start()
        sid = w.register_schema("s", "jsonschema", b"{}")
        cid = w.register_channel("/tensions", "json", sid)
        for k, (ts, data) in enumerate(msgs):
            w.add_message(cid, ts, data, ts, k)
        w.finish()
    mcap_w_s = time.perf_counter() - tt
    tt = time.perf_counter()
    with (tmp / "w_cdpr.mcap").open("wb") as fh:
        cw = ChunkedWriter(fh, 256 * 1024, "zstd")
        cw.start("", "bench")
        sid = cw.register_schema("s", "jsonschema", b"{}")
        cid = cw.register_channel("/tensions", "json", sid, {})
        for k, (ts, data) in enumerate(msgs):
            cw.add_message(cid, ts, data, ts, k)
        cw.finish()
    cdpr_w_s = time.perf_counter() - tt
    n = len(msgs)
    return {
        "storage_writer_messages": {
            "value": n / cdpr_w_s,
            "unit": "messages/s",
            "peer": "mcap package Writer.add_message, same messages and chunking",
            "peer_value": n / mcap_w_s,
        },
    }


if __name__ == "__main__":
    for k, v in run().items():
        print(k, v)
