"""Pseudo-terminal ports and an slcan (LAWICEL) CAN adapter emulated on one.

:class:`PtyPort` is a pseudo-terminal pair (``os.openpty``) whose slave side is published as a
symlink (``link``) that any program opens as a serial port (pyserial, python-can's ``slcan``).
The emulator writes on the master side.  It knows whether a reader has the port open (the master
reports ``POLLHUP`` while no slave is open) and drops output while nobody listens, as a real UART
would.  ``vanish()`` closes the pair and removes the link (a USB adapter pulled out); ``restore()``
creates a new pair at the same link.

:class:`SlcanEmulator` answers the slcan ASCII protocol well enough for ``can.Bus(interface="slcan")``
and common tools; every command ends with ``\\r``:

========  ==========================================  ===================
command   meaning                                     answer
========  ==========================================  ===================
``S0-8``  set bit rate 10k..1M (only when closed)     ``\\r`` (``\\a`` if open)
``sXXYY`` set BTR registers                           ``\\r``
``O``     open the channel                            ``\\r``
``L``     open listen-only                            ``\\r``
``C``     close the channel                           ``\\r``
``V``     hardware/software version                   ``V1013\\r``
``N``     serial number                               ``NCDPR\\r``
``F``     status flags                                ``F00\\r``
``Z0/1``  timestamps off/on                           ``\\r``
``tIIIL…``send standard frame (from the host)         ``z\\r``
``TIIIIIIIIL…`` send extended frame                   ``Z\\r``
other     unknown                                     ``\\a``
========  ==========================================  ===================

Frames to the host: ``t<id:3 hex><dlc><data hex>[<ms:4 hex>]\\r`` (standard) or
``T<id:8 hex><dlc><data hex>[<ms:4 hex>]\\r`` (extended); the 16-bit millisecond timestamp (mod
60000) only after ``Z1``.  Frames are only forwarded while the channel is open (``O``/``L``).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import threading
import time
import tty
from pathlib import Path

log = logging.getLogger(__name__)

SLCAN_BITRATES = {
    "S0": 10_000,
    "S1": 20_000,
    "S2": 50_000,
    "S3": 100_000,
    "S4": 125_000,
    "S5": 250_000,
    "S6": 500_000,
    "S7": 750_000,
    "S8": 1_000_000,
}


class PtyPort:
    """A pseudo-terminal pair published at ``link`` (a symlink to the slave device).

    write(): non-blocking; output is dropped (and counted in ``dropped_bytes``) while no reader
    has the port open or when the pty buffer is full beyond ``max_pending`` bytes.
    """

    def __init__(self, link: str | os.PathLike[str], max_pending: int = 1 << 16) -> None:
        self.link = Path(link)
        self.max_pending = max_pending
        self.dropped_bytes = 0
        self.written_bytes = 0
        self._lock = threading.Lock()
        self._pending = b""
        self.master: int | None = None
        self.slave_name = ""
        self.restore()

    # lifecycle ----------------------------------------------------------------------------
    def restore(self) -> None:
        """Create a new pty pair and point ``link`` at its slave (atomic symlink replace)."""
        with self._lock:
            if self.master is not None:
                return
            m, s = os.openpty()
            tty.setraw(s)
            self.slave_name = os.ttyname(s)
            os.close(s)  # the master now reports POLLHUP until a reader opens the slave
            os.set_blocking(m, False)
            self.master = m
            self._pending = b""
            tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            os.symlink(self.slave_name, tmp)
            os.replace(tmp, self.link)

    def vanish(self) -> None:
        """Remove the link and close the pair: readers see the device disappear."""
        with self._lock:
            with contextlib.suppress(FileNotFoundError):
                self.link.unlink()
            if self.master is not None:
                os.close(self.master)
                self.master = None
            self._pending = b""

    def close(self) -> None:
        self.vanish()

    @property
    def present(self) -> bool:
        return self.master is not None

    def reader_attached(self) -> bool:
        """True when some process has the slave side open."""
        m = self.master
        if m is None:
            return False
        p = select.poll()
        p.register(m, select.POLLIN | select.POLLOUT)
        ev = dict(p.poll(0)).get(m, 0)
        return not ev & select.POLLHUP

    # io -----------------------------------------------------------------------------------
    def write(self, data: bytes) -> bool:
        """Queue and write ``data``; False (and counted as dropped) if nobody listens or full."""
        with self._lock:
            m = self.master
            if m is None:
                self.dropped_bytes += len(data)
                return False
            if not self._pending and not self._attached_locked(m):
                self.dropped_bytes += len(data)
                return False
            if len(self._pending) + len(data) > self.max_pending:
                self.dropped_bytes += len(data)
                self._flush_locked(m)
                return False
            self._pending += data
            self._flush_locked(m)
            return True

    def flush(self) -> int:
        """Write what the pty could not take before; returns the bytes still pending."""
        with self._lock:
            if self.master is not None and self._pending:
                self._flush_locked(self.master)
            return len(self._pending)

    def _attached_locked(self, m: int) -> bool:
        p = select.poll()
        p.register(m, select.POLLOUT)
        return not dict(p.poll(0)).get(m, 0) & select.POLLHUP

    def _flush_locked(self, m: int) -> None:
        while self._pending:
            try:
                n = os.write(m, self._pending)
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EAGAIN):
                    self.dropped_bytes += len(self._pending)
                    self._pending = b""
                    return
                raise
            self.written_bytes += n
            self._pending = self._pending[n:]

    def read(self, timeout_s: float) -> bytes:
        """Bytes the reader wrote to the port (b"" on timeout or while no reader is attached)."""
        m = self.master
        if m is None:
            time.sleep(timeout_s)
            return b""
        try:
            r, _, _ = select.select([m], [], [], timeout_s)
        except (OSError, ValueError):
            return b""
        if not r:
            return b""
        try:
            return os.read(m, 4096)
        except (BlockingIOError, OSError):
            time.sleep(min(timeout_s, 0.01))  # EIO while no slave is open
            return b""


class SlcanEmulator:
    """An slcan adapter on a :class:`PtyPort` (see the module docstring for the protocol).

    ``send(arbitration_id, data, extended)`` forwards a bus frame to the host when the channel is
    open; frames sent by the host are kept in ``received`` (a list of (id, data, extended)).
    """

    def __init__(self, link: str | os.PathLike[str]) -> None:
        self.port = PtyPort(link)
        self.is_open = False
        self.bitrate = 0
        self.timestamps = False
        self.received: list[tuple[int, bytes, bool]] = []
        self.frames_sent = 0
        self.frames_dropped = 0
        self.commands: list[str] = []
        self._t0 = time.monotonic()
        self._stop = threading.Event()
        self._buf = b""
        self._thread = threading.Thread(target=self._serve, name="slcan-emulator", daemon=True)
        self._thread.start()

    @property
    def link(self) -> Path:
        return self.port.link

    def opened_event_wait(self, timeout_s: float) -> bool:
        """Wait until a host opened the channel (``O``); True if it did within ``timeout_s``."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.is_open and self.port.reader_attached():
                return True
            time.sleep(0.005)
        return False

    def send(self, arbitration_id: int, data: bytes, extended: bool = False) -> bool:
        """Forward one frame to the host; False if the channel is closed or nobody listens."""
        if not self.is_open or not self.port.present:
            self.frames_dropped += 1
            return False
        if extended:
            line = b"T%08X%d%s" % (arbitration_id, len(data), data.hex().upper().encode())
        else:
            line = b"t%03X%d%s" % (arbitration_id, len(data), data.hex().upper().encode())
        if self.timestamps:
            line += b"%04X" % (int((time.monotonic() - self._t0) * 1000) % 60000)
        ok = self.port.write(line + b"\r")
        if ok:
            self.frames_sent += 1
        else:
            self.frames_dropped += 1
        return ok

    def vanish(self) -> None:
        """Unplug the adapter: close the pty and remove the link; the channel is closed."""
        self.is_open = False
        self.port.vanish()

    def restore(self) -> None:
        """Plug the adapter back in (a new pty at the same link); the host must send ``O`` again."""
        self._buf = b""
        self.port.restore()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.port.close()

    def __enter__(self) -> SlcanEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # command handling -----------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stop.is_set():
            if not self.port.present:
                time.sleep(0.01)
                continue
            self.port.flush()  # push out frames the pty could not take at once
            data = self.port.read(0.02)
            if not data:
                if not self.port.reader_attached() and self.is_open:
                    self.is_open = False  # the host went away: a real adapter keeps state, but
                    # forwarding into a closed port is pointless; the next host sends O again
                continue
            self._buf += data
            while b"\r" in self._buf:
                cmd, _, self._buf = self._buf.partition(b"\r")
                reply = self._command(cmd.decode("ascii", "replace").strip("\n"))
                self.port.write(reply)

    def _command(self, cmd: str) -> bytes:
        self.commands.append(cmd[:32])
        if not cmd:
            return b"\r"
        c = cmd[0]
        if c in "OL":
            self.is_open = True
            return b"\r"
        if c == "C":
            self.is_open = False
            return b"\r"
        if c == "S":
            if self.is_open or cmd[:2] not in SLCAN_BITRATES:
                return b"\a"
            self.bitrate = SLCAN_BITRATES[cmd[:2]]
            return b"\r"
        if c == "s":
            return b"\r" if not self.is_open else b"\a"
        if c == "V":
            return b"V1013\r"
        if c == "v":
            return b"vCDPR\r"
        if c == "N":
            return b"NCDPR\r"
        if c == "F":
            return b"F00\r"
        if c == "Z":
            self.timestamps = cmd[1:2] == "1"
            return b"\r"
        if c in "tT":
            try:
                n_id = 3 if c == "t" else 8
                fid = int(cmd[1 : 1 + n_id], 16)
                dlc = int(cmd[1 + n_id])
                data = bytes.fromhex(cmd[2 + n_id : 2 + n_id + 2 * dlc])
                if len(data) != dlc:
                    raise ValueError
            except (ValueError, IndexError):
                return b"\a"
            self.received.append((fid, data, c == "T"))
            return b"z\r" if c == "t" else b"Z\r"
        return b"\a"
