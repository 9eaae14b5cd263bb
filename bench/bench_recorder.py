"""``recorder_can_frames``: CAN frames/s the recorder sustains into MCAP with zero drops, one core.

Source (identical for both contestants): a python-can bus (``can.BusABC`` subclass, read through
its own ``recv``) that cycles 50,176 pre-generated ``can.Message`` frames (the shipped DBC's layout:
four 8-byte TPDOs per sample with a rolling counter, epoch timestamps), at full speed or paced.

- cdpr: the CAN load-cell driver (:class:`~cdpr.daq.can_source.CanLoadCellSource`, raw frames only,
  no DBC decoding, like the BLF logger) opens that bus; the recorder's acquisition thread, bounded
  queue and writer thread, ``/can_raw`` frame blocks, zstd chunks closed every 0.25 s and fsynced.
  A 5 s probe measures the capacity C (the bus holds back while 20k frames are queued); then the bus
  is paced at 0.85 C for 60 s and the recorder must drop nothing and keep up (at the end, at most
  0.25 s of frames still queued); else 0.7 C, then 0.5 C are tried (30 s each).  The value is the
  paced rate achieved (frames written / paced duration).  ``frames_per_cpu_s`` (frames / process
  CPU time) is the same capacity, insensitive to other load on the machine.
- peer: python-can's own pipeline, ``can.Notifier`` on the same bus class at full speed calling
  ``can.Logger("x.blf")`` (BLFWriter), 5 s before and 5 s after the paced run (so both see the same
  machine load): frames written / elapsed.

``with_decoding_*``: a 4 s capacity probe of the same driver also decoding every sample into
``/tensions`` (work the BLF logger does not do), frames per CPU-second.

``writer_only_*``: the file writers alone, single thread, on ready-made input (the driver's frame
batches of 2000 into ``McapRunWriter.write_many`` vs ``BLFWriter.on_message_received`` per frame),
frames per CPU-second.

Each contestant runs in its own child process pinned to the same single CPU
(``os.sched_setaffinity``), which also gives a clean peak RSS (``ru_maxrss``) per contestant.
The paced run lasts the issue's 60 s; the module takes about 85 s (5 + 10 + 60 s of measurement,
more when a paced rate fails).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

N_FRAMES = 4 * 256 * 49  # 50,176 frames: the rolling counter wraps cleanly
TARGET = 30_000.0


def _messages():  # noqa: ANN202 - child-process helper
    """The load-cell amplifier's frames (``data_samples/loadcell.dbc`` layout): per sample four
    TPDOs 0x181/0x281/0x381/0x481, each two int24 little-endian counts, a status byte and the
    rolling counter; epoch timestamps 33 us apart (a saturated 1 Mbit/s bus)."""
    import can

    out = []
    for i in range(N_FRAMES):
        s, j = divmod(i, 4)
        a, b = (s * 37 + 2000 * j) & 0x7FFFFF, (s * 53 + 2000 * j + 1000) & 0x7FFFFF
        out.append(
            can.Message(
                arbitration_id=(0x181, 0x281, 0x381, 0x481)[j],
                data=a.to_bytes(3, "little") + b.to_bytes(3, "little") + bytes([0, s & 0xFF]),
                is_extended_id=False,
                timestamp=1_700_000_000.0 + i * 3.3e-5,
            )
        )
    return out


def _cycled_bus_class():  # noqa: ANN202 - child-process helper
    """The bus both contestants read: a python-can bus (``can.BusABC``, read through its ``recv``)
    that yields the pre-generated frames in a cycle, at full speed or paced."""
    import can

    msgs = _messages()

    class CycledBus(can.BusABC):
        def __init__(self, rate_hz: float = 0.0, hold=None) -> None:  # noqa: ANN001
            super().__init__(channel="bench")
            self.i = 0
            self.allowed = 0
            self.rate = rate_hz
            self.hold = hold  # callable: True -> hold back (probe: never outrun the writer)
            self.t0 = time.perf_counter()
            self.quantum = max(1, int(rate_hz * 0.001))

        def _refill(self, timeout: float | None) -> bool:
            if self.hold is not None and self.hold():
                time.sleep(0.002 if timeout is None else min(timeout, 0.002))
                return False
            if self.rate > 0:
                # paced: the frames of each millisecond are released together (as a USB adapter
                # hands them over in 1 ms packets)
                due = int(self.rate * (time.perf_counter() - self.t0))
                if due - self.i < self.quantum:
                    wait = (self.i + self.quantum - due) / self.rate
                    time.sleep(wait if timeout is None else min(timeout, wait))
                    return False
                self.allowed = due
            else:
                self.allowed = self.i + 512
            return True

        def _recv_internal(self, timeout):  # noqa: ANN001, ANN202
            i = self.i
            if i >= self.allowed and not self._refill(timeout):
                return None, False
            self.i = i + 1
            return msgs[i % N_FRAMES], False

        def send(self, msg, timeout=None) -> None:  # noqa: ANN001
            raise can.CanOperationError("the benchmark's cycled bus only receives")

    return CycledBus


def _child_recorder(
    out: str, duration_s: float, rate_hz: float, backpressure: bool = False, decode: bool = False
) -> dict:
    from cdpr.daq.can_source import CanLoadCellSource
    from cdpr.daq.recorder import Recorder, RecorderOptions

    CycledBus = _cycled_bus_class()

    class BenchCanSource(CanLoadCellSource):
        """The CAN load-cell driver (raw frames, no decoding: like the BLF logger) on the bus."""

        def _make_bus(self):  # noqa: ANN202
            hold = (lambda: rec.backlog(self.name) > 20_000) if backpressure else None
            return CycledBus(rate_hz, hold)

    src = BenchCanSource(
        "can0", interface="bench", channel="bench", bitrate=1_000_000, raw=True, decode=decode
    )
    rec = Recorder([src], out, options=RecorderOptions())
    t0 = time.perf_counter()
    c0 = time.process_time()
    rec.start()
    rec.wait(duration_s)
    dt = time.perf_counter() - t0
    backlog_end = rec.backlog("can0")
    rec.stop()
    cpu = time.process_time() - c0
    st = rec.status()
    n = st.counts.get("can_raw", 0)
    return {
        "samples": st.counts.get("tensions", 0),
        "lost": st.sources["can0"].lost,
        "written": n,
        "elapsed_s": dt,
        "cpu_s": cpu,
        "rate": n / dt,
        "per_cpu_s": n / cpu,
        "backlog_end": backlog_end,
        "dropped": rec.dropped,
        "queue_peak": st.extra["queue_peak"]["can0"],
        "bytes": os.path.getsize(out),
    }


def _child_writers(d: str) -> dict:
    """Only the file writers, single thread, 200,000 frames: ``McapRunWriter.write_many`` of the CAN
    driver's frame batches (2000 frames) vs ``can.BLFWriter.on_message_received``; frames per
    CPU-second."""
    import can

    from cdpr.daq.can_raw import DESCRIPTION, CanFrameBatch
    from cdpr.daq.mcap_io import McapRunWriter

    msgs = _messages() * 4
    t = [1_700_000_000_000_000_000 + i for i in range(len(msgs))]
    batches = [
        CanFrameBatch("can_raw", msgs[i : i + 2000], t[i : i + 2000])
        for i in range(0, len(msgs), 2000)
    ]
    w = McapRunWriter(f"{d}/writer_only.mcap")
    w.add_stream("can_raw", DESCRIPTION)  # declared, as the recorder does: frame blocks
    c0 = time.process_time()
    for b in batches:
        w.write_many(b)
    w.finish()
    ours = len(msgs) / (time.process_time() - c0)
    blf = can.BLFWriter(f"{d}/writer_only.blf")
    c0 = time.process_time()
    for m in msgs:
        blf.on_message_received(m)
    blf.stop()
    peer = len(msgs) / (time.process_time() - c0)
    return {"ours": ours, "peer": peer}


def _child_peer(out: str, duration_s: float) -> dict:
    import can

    bus = _cycled_bus_class()()
    logger = can.Logger(out)
    t0 = time.perf_counter()
    c0 = time.process_time()
    notifier = can.Notifier(bus, [logger], timeout=0.1)
    time.sleep(duration_s)
    notifier.stop()  # also stops (flushes and closes) the logger
    n = bus.i
    dt = time.perf_counter() - t0
    cpu = time.process_time() - c0
    bus.shutdown()
    return {
        "written": n,
        "elapsed_s": dt,
        "cpu_s": cpu,
        "rate": n / dt,
        "per_cpu_s": n / cpu,
        "bytes": os.path.getsize(out),
    }


def _in_child(kind: str, *args: object) -> dict:
    """Run one contestant in a child process pinned to one CPU; returns its result and peak RSS."""
    code = (
        "import json, os, resource, sys\n"
        "cpu = min(os.sched_getaffinity(0))\n"
        "os.sched_setaffinity(0, {cpu})\n"
        f"sys.path.insert(0, {str(Path(__file__).resolve().parent)!r})\n"
        "import bench_recorder as b\n"
        f"r = b._child_{kind}(*json.loads(sys.argv[1]))\n"
        "r['peak_rss_MiB'] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024\n"
        "r['cpu'] = cpu\n"
        "print(json.dumps(r))\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, json.dumps(list(args))],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if res.returncode != 0:
        raise RuntimeError(f"{kind} child failed: {res.stderr.strip()[-500:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def run() -> dict[str, dict]:
    with tempfile.TemporaryDirectory(prefix="bench_recorder_") as d:
        probe = _in_child("recorder", f"{d}/probe.mcap", 5.0, 0.0, True)
        # the peer runs in two halves around the paced runs, so both see the same machine load
        peers = [_in_child("peer", f"{d}/peer_0.blf", 5.0)]
        tries = []
        sustained = None
        for factor, duration in ((0.85, 60.0), (0.7, 30.0), (0.5, 30.0)):
            rate = factor * probe["rate"]
            r = _in_child("recorder", f"{d}/paced_{len(tries)}.mcap", duration, rate)
            r["paced_at"] = rate
            tries.append(r)
            # sustained: nothing dropped and the writer kept up (the queue absorbs the hiccups of
            # a shared machine, that is its job, but at the end at most 0.25 s of frames wait)
            if r["dropped"] == 0 and r["backlog_end"] <= rate * 0.25:
                sustained = r
                break
        peers.append(_in_child("peer", f"{d}/peer_1.blf", 5.0))
        # extra: the same driver also decoding the frames into /tensions (the BLF logger doesn't)
        decoding = _in_child("recorder", f"{d}/decode.mcap", 4.0, 0.0, True, True)
        writers = _in_child("writers", d)
    peer = {k: sum(p[k] for p in peers) for k in ("written", "elapsed_s", "cpu_s", "bytes")}
    peer_rate = peer["written"] / peer["elapsed_s"]
    peer_per_cpu = peer["written"] / peer["cpu_s"]
    ok = sustained is not None
    best = sustained or tries[-1]
    return {
        "recorder_can_frames": {
            "value": round(best["rate"], 1) if ok else 0.0,
            "unit": "frames/s",
            "peer": "python-can can.Notifier + can.Logger writing BLF, same bus and frames, max speed",
            "peer_value": round(peer_rate, 1),
            "target": TARGET,
            "dropped": best["dropped"],
            "queue_peak_frames": best["queue_peak"],
            "paced_at_frames_per_s": round(best["paced_at"], 1),
            "duration_s": round(best["elapsed_s"], 2),
            "probe_capacity_frames_per_s": round(probe["rate"], 1),
            "frames_per_cpu_s": round(probe["per_cpu_s"], 1),
            "paced_frames_per_cpu_s": round(best["per_cpu_s"], 1),
            "peer_frames_per_cpu_s": round(peer_per_cpu, 1),
            "ratio_per_cpu_s": round(probe["per_cpu_s"] / peer_per_cpu, 3),
            "cpu_share": round(best["cpu_s"] / best["elapsed_s"], 2),
            "peer_cpu_share": round(peer["cpu_s"] / peer["elapsed_s"], 2),
            "with_decoding_frames_per_cpu_s": round(decoding["per_cpu_s"], 1),
            "with_decoding_samples": decoding["samples"],
            "with_decoding_lost_samples": decoding["lost"],
            "writer_only_frames_per_cpu_s": round(writers["ours"], 1),
            "peer_writer_only_frames_per_cpu_s": round(writers["peer"], 1),
            "bytes_per_frame": round(best["bytes"] / max(best["written"], 1), 2),
            "peer_bytes_per_frame": round(peer["bytes"] / max(peer["written"], 1), 2),
            "peak_rss_MiB": round(best["peak_rss_MiB"], 1),
            "peer_peak_rss_MiB": round(max(p["peak_rss_MiB"] for p in peers), 1),
            "context": (
                "each contestant in its own process pinned to one CPU (shared with whatever else "
                "runs on the machine), both reading the same python-can bus class (can.BusABC.recv) "
                "that cycles the same 50,176 frames (4 TPDOs per sample, DBC layout); cdpr: the "
                "CAN load-cell driver (raw frames, no decoding) in the recorder, 5 s probe of the "
                "capacity (bus held back when 20k "
                "frames are queued), then the bus paced at 0.85x (else 0.7x, 0.5x) that rate for "
                f"{best['elapsed_s']:.0f} s with zero drops and <= 0.25 s of backlog at the end "
                "(the issue's 60 s); /can_raw frame blocks, zstd-1 "
                "chunks closed every 0.25 s and fsynced; peer: can.Notifier + can.Logger(BLF), "
                "2 x 5 s at max speed before and after the paced run (no queue, cannot drop); "
                "frames_per_cpu_s = frames / CPU time of the process (robust to machine load); "
                "cpu_share = CPU time / elapsed (how much of its core the process got); "
                "with_decoding_*: a 4 s probe of the same driver also decoding every sample into "
                "/tensions (DBC, calibration), which the BLF logger does not do"
                + ("" if ok else "; NO zero-drop rate found: value 0")
            ),
            "tries": [
                {k: (round(v, 1) if isinstance(v, float) else v) for k, v in t.items()}
                for t in tries
            ],
        }
    }


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
