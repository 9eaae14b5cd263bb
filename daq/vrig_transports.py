"""The virtual rig's transports: :class:`RigRun` sends a :class:`~cdpr.daq.virtual_rig.VirtualRig`'s
samples in real time (or scaled) through a python-can virtual bus, an slcan adapter emulated on a
pseudo-terminal or the ``$LC`` serial line protocol on a pty, and the tunnel's ``$TUN`` lines on a
second pty.  Built by :meth:`VirtualRig.start`.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from .virtual_rig import VirtualRig

TRANSPORTS = ("virtual", "slcan", "serial")


class RigRun:
    """A running virtual rig (a sender thread); created by :meth:`VirtualRig.start`."""

    def __init__(
        self,
        vr: VirtualRig,
        transport: str,
        channel: str | None,
        link: str | os.PathLike[str] | None,
        tunnel_link: str | os.PathLike[str] | None,
        wait_reader_s: float,
        speed: float,
    ) -> None:
        if transport not in TRANSPORTS:
            raise ValueError(f"transport: expected one of {TRANSPORTS}, got {transport!r}")
        if transport != "virtual" and link is None:
            raise ValueError(f"transport {transport!r} needs a pty link path")
        self.vr = vr
        self.transport = transport
        self.channel = channel or "vrig"
        self.link = None if link is None else Path(link)
        self.tunnel_link = None if tunnel_link is None else Path(tunnel_link)
        self.wait_reader_s = float(wait_reader_s)
        self.speed = float(speed)
        self.samples_sent = 0
        self.frames_sent = 0
        self.tunnel_sent = 0
        self.test_points_sent = 0
        self.error: BaseException | None = None
        self.done = threading.Event()
        self.started = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name="virtual-rig", daemon=True)
        self._send_sample: Callable[[int], int] | None = None
        self._closers: list[Callable[[], None]] = []
        self._vanishers: list[tuple[Callable[[], None], Callable[[], None]]] = []
        self._tunnel_port: Any = None
        self._setup()

    def _setup(self) -> None:
        vr = self.vr
        if self.transport in ("virtual", "slcan"):
            ids, data = vr.can_frames()
            self._frame_ids, self._frame_data = ids, data
        if self.transport == "virtual":
            import can

            bus = can.Bus(
                interface="virtual",
                channel=self.channel,
                bitrate=vr.schedule.bitrate,
                receive_own_messages=False,
            )
            self._closers.append(bus.shutdown)

            def send_virtual(k: int) -> int:
                for j, fid in enumerate(self._frame_ids):
                    bus.send(
                        can.Message(
                            arbitration_id=fid,
                            data=self._frame_data[k, j].tobytes(),
                            is_extended_id=False,
                            timestamp=time.time(),
                        )
                    )
                return len(self._frame_ids)

            self._send_sample = send_virtual
        elif self.transport == "slcan":
            from .slcan_emulator import SlcanEmulator

            assert self.link is not None
            emu = SlcanEmulator(self.link)
            self.emulator = emu
            self._closers.append(emu.close)
            self._vanishers.append((emu.vanish, emu.restore))

            def send_slcan(k: int) -> int:
                n = 0
                for j, fid in enumerate(self._frame_ids):
                    n += emu.send(fid, self._frame_data[k, j].tobytes())
                return n

            self._send_sample = send_slcan
        else:
            from .slcan_emulator import PtyPort

            assert self.link is not None
            port = PtyPort(self.link)
            self.port = port
            self._closers.append(port.close)
            self._vanishers.append((port.vanish, port.restore))

            def send_serial(k: int) -> int:
                return int(port.write(vr.serial_line(k)))

            self._send_sample = send_serial
        if self.tunnel_link is not None:
            from .slcan_emulator import PtyPort

            tp = PtyPort(self.tunnel_link)
            self._tunnel_port = tp
            self._closers.append(tp.close)

    def _wait_reader(self) -> None:
        if self.wait_reader_s <= 0 or self.transport == "virtual":
            return
        end = time.monotonic() + self.wait_reader_s
        while time.monotonic() < end and not self._stop.is_set():
            if self.transport == "slcan":
                if self.emulator.is_open and self.emulator.port.reader_attached():
                    break
            elif self.port.reader_attached():
                break
            time.sleep(0.005)
        if self._tunnel_port is not None:
            while time.monotonic() < end and not self._tunnel_port.reader_attached():
                time.sleep(0.005)

    def start(self) -> None:
        self._thread.start()

    def _main(self) -> None:
        vr = self.vr
        try:
            self._wait_reader()
            lat_ns = int(vr.schedule.sensor.latency_s * 1e9)
            # the controller's $TPT lines (schedule test_points_on_link) go out on the tunnel link
            tpt_t, tpt_lines = (
                vr.test_point_link_events()
                if self._tunnel_port is not None
                else (np.zeros(0, np.int64), [])
            )
            nt, np_ = vr.tunnel_t_rel_ns.shape[0], tpt_t.shape[0]
            ev_t = np.concatenate([vr.t_rel_ns + lat_ns, vr.tunnel_t_rel_ns, tpt_t])
            ev_kind = np.concatenate(
                [
                    np.zeros(vr.n_samples, np.int8),
                    np.ones(nt, np.int8),
                    np.full(np_, 2, np.int8),
                ]
            )
            ev_idx = np.concatenate([np.arange(vr.n_samples), np.arange(nt), np.arange(np_)])
            order = np.argsort(ev_t, kind="stable")
            vanished = False
            # the schedule's start on both clocks at once (the truth's t_ns = t0 + t_rel / speed
            # is when each sample is sent, not a few ms before: building the lists above takes
            # milliseconds at 1 kHz)
            mono0 = time.monotonic_ns()
            vr.t0_ns = time.time_ns()
            vr.speed = self.speed
            self.started.set()
            for e in order:
                if self._stop.is_set():
                    break
                target = mono0 + int(ev_t[e] / self.speed)
                delay = (target - time.monotonic_ns()) * 1e-9
                if delay > 0:
                    self._flush_ports()
                    if self._stop.wait(max(0.0, (target - time.monotonic_ns()) * 1e-9)):
                        break
                k = int(ev_idx[e])
                if ev_kind[e] == 1:
                    if self._tunnel_port is not None:
                        self.tunnel_sent += int(self._tunnel_port.write(vr.tunnel_line(k)))
                    continue
                if ev_kind[e] == 2:
                    assert self._tunnel_port is not None
                    self.test_points_sent += int(self._tunnel_port.write(tpt_lines[k]))
                    continue
                up = bool(vr.port_up[k])
                if not up and not vanished and self._vanishers:
                    for v, _ in self._vanishers:
                        v()
                    vanished = True
                elif up and vanished:
                    for _, r in self._vanishers:
                        r()
                    vanished = False
                if vr.sent[k] and up:
                    assert self._send_sample is not None
                    n = self._send_sample(k)
                    self.frames_sent += n
                    self.samples_sent += int(n > 0)
            if vanished:
                for _, r in self._vanishers:
                    r()
            end = time.monotonic() + 2.0  # drain what the ptys have not taken yet
            while self._flush_ports() and time.monotonic() < end and not self._stop.is_set():
                time.sleep(0.005)
        except BaseException as exc:  # reported to the caller through wait()
            self.error = exc
        finally:
            self.done.set()

    def _flush_ports(self) -> int:
        """Flush every pty; the bytes still pending."""
        ports = [getattr(self, "port", None), self._tunnel_port]
        if self.transport == "slcan":
            ports.append(self.emulator.port)
        return sum(p.flush() for p in ports if p is not None)

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the schedule to finish; re-raises an error of the sender thread."""
        self._thread.join(timeout_s)
        if self.error is not None:
            raise self.error
        return self.done.is_set()

    def stop(self) -> None:
        """Stop sending and close the transports (idempotent)."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(5.0)
        while self._closers:
            closer = self._closers.pop()
            with contextlib.suppress(Exception):
                closer()

    def __enter__(self) -> RigRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
