"""The run writer's fsync thread: :class:`FsyncThread` makes a file durable (``os.fsync``) when
asked, in a thread of its own, so the writer hands a closed chunk to the OS and goes on without
waiting for the disk (a killed process loses nothing handed over; a power cut at most what was
not yet fsynced)."""

from __future__ import annotations

import os
import threading
from typing import Any


class FsyncThread:
    """Fsyncs ``fh`` after each :meth:`request` (requests made while one runs are merged);
    ``count`` fsyncs done.  An error stops the thread quietly: the writer's final, synchronous
    fsync reports it."""

    def __init__(self, fh: Any) -> None:
        self._fh = fh
        self.count = 0
        self._wanted = threading.Event()
        self._stop = False
        self._thread = threading.Thread(target=self._loop, name="mcap-fsync", daemon=True)
        self._thread.start()

    def request(self) -> None:
        """Have the file fsynced soon (returns at once)."""
        self._wanted.set()

    def stop(self, timeout_s: float = 30.0) -> None:
        """End the thread (after the fsync under way, if any)."""
        self._stop = True
        self._wanted.set()
        self._thread.join(timeout=timeout_s)

    def _loop(self) -> None:
        fd = self._fh.fileno()
        while True:
            self._wanted.wait()
            self._wanted.clear()
            if self._stop:
                return
            try:
                os.fsync(fd)
                self.count += 1
            except OSError:  # reported by the final, synchronous fsync in finish()
                return
