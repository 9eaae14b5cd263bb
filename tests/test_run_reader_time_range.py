"""``open_run`` on streams written in blocks (one stream's minute, then another's, as the campaign
generator and bulk writers do): the chunk that ends last may hold only early messages of a stream,
and neither the stream's time range nor window-by-window reading may lose its later messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cdpr.daq.mcap_writer import McapRunWriter
from cdpr.daq.run_reader import open_run
from cdpr.daq.source import Reading

S = 10**9


def test_time_range_and_windows_of_a_stream_written_in_blocks(tmp_path: Path) -> None:
    path = tmp_path / "blocks.mcap"
    w = McapRunWriter(path, chunk_size=4096)
    a_t = np.arange(0, 100 * S, S // 10)  # a: 0 .. 99.9 s at 10 Hz
    b_t = np.arange(0, 90 * S, S // 2)  # b: 0 .. 89.5 s at 2 Hz, written after all of a
    for t in a_t.tolist():
        w.write(Reading("a", t, {"x": 1.0}))
    for t in b_t.tolist():
        w.write(Reading("b", t, {"y": 2.0}))
    w.finish()
    with open_run(path) as run:
        b = run.streams["/b"]
        assert (b.count, b.start_ns, b.stop_ns) == (len(b_t), 0, int(b_t[-1]))
        a = run.streams["/a"]
        assert (a.start_ns, a.stop_ns) == (0, int(a_t[-1]))
        for topic, times in (("/a", a_t), ("/b", b_t)):
            got = np.concatenate([df["t_ns"].to_numpy() for df in run.iter_tables(topic, 7 * S)])
            np.testing.assert_array_equal(got, times)
