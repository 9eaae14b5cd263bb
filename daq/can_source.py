"""CAN load cells (``can_load_cell``): a python-can bus, frames decoded by the load-cell decoder
(:mod:`cdpr.daq.can_decoder`: a DBC through cantools, counts -> newtons).

Streams:

- ``can_raw``: every frame as it was on the bus, every field python-can gives it (layout and codec:
  :mod:`cdpr.daq.can_raw`: frame blocks in the run file);
- ``tensions``: one reading per sample (fields and rules: :mod:`cdpr.daq.can_decoder`): lost
  samples (``stats.lost``), partial ones (``stats.extra["partial_samples"]``), bad frames
  (``stats.bad``) and pauses (``stats.extra["pauses"]``, ``stats.extra["pause_s"]``: the
  recorder makes each one a ``pauses`` fault event).

A read gathers the frames that arrive within a few ms as ``can.Message`` objects and decodes them
as one block (:meth:`~cdpr.daq.can_decoder.LoadCellDecoder.decode_frames`).  Error frames are
counted (``stats.errors``, ``stats.extra["error_frames"]``) and logged; a bus that raises on
receive, reports bus-off (``bus.state == BusState.ERROR``) or floods error frames is shut down and
reopened with exponential backoff (``stats.reopened``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import can
import numpy as np

from cdpr.analysis.errors import ConfigError

from . import can_raw
from .can_decoder import LoadCellDecoder, Samples, build_decoder
from .can_frames import FrameColumns
from .can_raw import CanFrameBatch
from .loadcell import check_frame_budget
from .source import ReopenBackoff, Source, StreamDescription

log = logging.getLogger(__name__)


def add_samples(
    out: CanFrameBatch, decoder: LoadCellDecoder, samples: Samples, stats: Any, framed: bool
) -> None:
    """Put decoded samples in a batch, each after the frame that closed it (``framed``: the batch
    holds the frames), and the decoder's counts in a source's ``stats``."""
    k = np.minimum(samples.done_at + 1, out.n_frames) if framed else np.zeros(len(samples), int)
    out.others.extend(zip(k.tolist(), samples.readings(), strict=True))
    out.bad = samples.bad if framed and samples.bad.any() else out.bad
    stats.lost = decoder.lost
    stats.bad = decoder.bad
    stats.extra["partial_samples"] = decoder.partial
    if decoder.n_pauses != stats.extra.get("pauses", 0):
        stats.extra["pauses"] = decoder.n_pauses
        stats.extra["pause_s"] = tuple(round(d * 1e-9, 3) for _, d in decoder.pauses)


GATHER_S = 0.005
#: error class bit of a SocketCAN error frame's id (linux/can/error.h): the controller is bus-off
CAN_ERR_BUSOFF = 0x40
"""After the first frame of a read, :meth:`CanLoadCellSource.read` keeps receiving for this long (s)."""


class CanLoadCellSource(Source):
    """Load cells on a CAN bus (python-can), decoded with a DBC.

    Settings (keyword arguments; ``interface``, ``channel`` and ``bitrate`` are required and always
    passed to python-can, so ``~/can.conf`` and ``CAN_*`` variables never change the bus):

    interface: python-can interface (``"virtual"``, ``"slcan"``, ``"socketcan"``, ``"pcan"``, ...).
    channel: channel (virtual bus name, serial port of an slcan adapter, ``can0``, ...).
    bitrate: bus bit rate, bit/s.
    rate_hz: nominal sample rate of the amplifier (for the frame budget and ``describe``), Hz.
    dbc: DBC path (default: ``data_samples/loadcell.dbc``).
    cables: cable names in channel order (default ``c1..c8``).
    offset_counts, gain_N_per_count: calibration, one value or one per channel.
    max_bus_load: the largest allowed worst-case bus load fraction (default 0.9).
    bus_options: extra keyword arguments for ``can.Bus`` (e.g. ``sleep_after_open`` for slcan).
    raw: emit the ``can_raw`` stream (default True); decode: emit ``tensions`` (default True).
    reopen_backoff_s: (first, max) delay between reopen attempts, s.
    """

    kind = "can_loadcell"
    accepts_origin = True

    def __init__(
        self,
        name: str,
        interface: str,
        channel: str,
        bitrate: int,
        rate_hz: float = 200.0,
        dbc: str | None = None,
        cables: Sequence[str] | None = None,
        offset_counts: Any = None,
        gain_N_per_count: Any = None,
        max_bus_load: float = 0.9,
        bus_options: dict[str, Any] | None = None,
        raw: bool = True,
        decode: bool = True,
        reopen_backoff_s: Sequence[float] = (0.1, 5.0),
        error_frame_limit: int = 1000,
        origin: str = "<config>",
    ) -> None:
        super().__init__(name)
        prefix = f"sources.{name}"
        self.origin = origin
        # types and ranges: checked by create_source (cdpr.daq.source_schema.CanLoadCellSettings)
        bitrate, rate_hz = int(bitrate), float(rate_hz)
        self.interface = interface
        self.channel = str(channel)
        self.bitrate = bitrate
        self.rate_hz = rate_hz
        self.decoder, self.dbc_path = build_decoder(
            origin, prefix, dbc, cables, offset_counts, gain_N_per_count, rate_hz
        )
        self.budget = check_frame_budget(
            origin,
            prefix,
            bitrate,
            rate_hz,
            self.decoder.frames_per_sample,
            self.decoder.max_frame_bytes,
            self.decoder.extended_ids,
            max_bus_load,
        )
        self.max_bus_load = float(max_bus_load)
        self.bus_options = dict(bus_options or {})
        self.emit_raw = bool(raw)
        self.emit_decoded = bool(decode)
        self.backoff = (float(reopen_backoff_s[0]), float(reopen_backoff_s[1]))
        self.error_frame_limit = int(error_frame_limit)
        self.bus: can.BusABC | None = None
        self._reopen = ReopenBackoff(*self.backoff)
        self._err_window = (0.0, 0)
        self._last_state_check = 0.0
        self._ever_opened = False

    # settings / describe ------------------------------------------------------------------
    def settings(self) -> dict[str, Any]:
        return {
            "interface": self.interface,
            "channel": self.channel,
            "bitrate": self.bitrate,
            "rate_hz": self.rate_hz,
            "dbc": self.dbc_path,
            "cables": list(self.decoder.cables),
            **self.decoder.calibration.to_mapping(),
            "max_bus_load": self.max_bus_load,
            "bus_options": dict(self.bus_options),
            "frame_budget_load": round(self.budget.load, 4),
        }

    def describe(self) -> dict[str, StreamDescription]:
        out: dict[str, StreamDescription] = {}
        if self.emit_raw:
            d = can_raw.DESCRIPTION
            out["can_raw"] = StreamDescription(d.fields, self.budget.frames_per_s, d.doc)
        if self.emit_decoded:
            out["tensions"] = self.decoder.describe(self.rate_hz)
        return out

    # lifecycle ----------------------------------------------------------------------------
    def _make_bus(self) -> can.BusABC:
        return can.Bus(
            interface=self.interface,
            channel=self.channel,
            bitrate=self.bitrate,
            **self.bus_options,
        )

    def _open(self) -> None:
        try:
            self.bus = self._make_bus()
        except (can.CanError, OSError, ValueError) as exc:
            raise ConfigError(
                self.origin,
                f"sources.{self.name}.channel",
                f"cannot open {self.interface} bus {self.channel!r}: {exc}",
            ) from None
        self._ever_opened = True

    def _close(self) -> None:
        self._drop_bus()

    def _drop_bus(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except Exception as exc:  # a dead device can fail to shut down; nothing to save
                log.debug("%s: shutdown failed: %s", self.name, exc)

    def _fail(self, why: str) -> None:
        self.stats.errors += 1
        log.warning("%s: %s; reopening the bus in %.2f s", self.name, why, self._reopen.delay_s)
        self._drop_bus()
        self.decoder.reset()
        self._reopen.failed()

    def _try_reopen(self, timeout_s: float) -> bool:
        if not self._reopen.due(timeout_s):
            return False
        try:
            self.bus = self._make_bus()
        except Exception as exc:
            log.info("%s: reopen failed: %s", self.name, exc)
            self._reopen.failed()
            return False
        self.stats.reopened += 1
        self._reopen.succeeded()
        log.warning("%s: bus reopened", self.name)
        return True

    # data ---------------------------------------------------------------------------------
    def _read(self, timeout_s: float) -> CanFrameBatch:  # type: ignore[override]
        if self.bus is None and not self._try_reopen(timeout_s):
            return CanFrameBatch()
        bus = self.bus
        assert bus is not None
        # the hot path of a busy bus: a frame is only kept with its reception time; the frames of
        # the read are decoded as one block, and turned into readings only when someone looks
        msgs: list[can.Message] = []
        times: list[int] = []
        add_frame = msgs.append
        add_time = times.append
        time_ns = time.time_ns
        recv = bus.recv
        error_frame = self._error_frame
        n = 0
        deadline = time.monotonic() + timeout_s
        gather_until = deadline
        wait = timeout_s
        monotonic = time.monotonic
        failed = ""
        try:
            # bounded by time, not by a frame count: a backlog (a starved process) is handed to the
            # writer in slices of at most ~timeout_s, never held back for seconds
            while True:
                if n & 63 == 63 and monotonic() >= gather_until:
                    break
                msg = recv(timeout=wait)
                if msg is None:
                    now = time.monotonic()
                    if now >= gather_until:
                        break
                    wait = gather_until - now
                    continue
                if n == 0:
                    # after the first frame, gather what follows for a few ms: a busy bus then
                    # gives batches of hundreds of frames instead of one or two per read
                    gather_until = min(deadline, time.monotonic() + GATHER_S)
                wait = 0.0
                n += 1
                add_frame(msg)
                add_time(time_ns())
                if msg.is_error_frame:
                    error_frame(msg)  # raises for a bus-off or a flood
        except (can.CanError, OSError, ValueError) as exc:
            failed = f"receive failed ({type(exc).__name__}: {exc})"
        out = self._batch(msgs, times)
        if failed:
            self._fail(failed)
            return out
        now = time.monotonic()
        if now - self._last_state_check > 1.0:
            self._last_state_check = now
            try:
                state = bus.state
            except Exception:
                state = None
            if state == can.BusState.ERROR:
                self.stats.extra["bus_off"] = self.stats.extra.get("bus_off", 0) + 1
                self._fail("bus-off")
        return out

    def _batch(self, msgs: list[can.Message], times: list[int]) -> CanFrameBatch:
        """The frames of a read (when ``raw``) and the samples they close (when ``decode``)."""
        frames = FrameColumns.from_messages(msgs) if self.emit_decoded and msgs else None
        if self.emit_raw:  # the columns made for decoding serve the writer too
            out = CanFrameBatch(messages=msgs, t_ns=times, frames=frames)
        else:
            out = CanFrameBatch()
        if frames is not None:
            samples = self.decoder.decode_frames(frames, np.array(times, np.int64))
            add_samples(out, self.decoder, samples, self.stats, self.emit_raw)
        return out

    def _error_frame(self, msg: can.Message) -> None:
        """Count and log an error frame; raise for a bus-off or more than
        ``error_frame_limit`` a second."""
        self.stats.errors += 1
        self.stats.extra["error_frames"] = self.stats.extra.get("error_frames", 0) + 1
        t0, k = self._err_window
        now = time.monotonic()
        if now - t0 > 1.0:
            t0, k = now, 0
        k += 1
        self._err_window = (t0, k)
        if k == 1:
            log.warning(
                "%s: CAN error frame (id 0x%X data %s)",
                self.name,
                msg.arbitration_id,
                bytes(msg.data).hex(),
            )
        if msg.arbitration_id & CAN_ERR_BUSOFF:
            # SocketCAN reports bus-off as an error frame of class CAN_ERR_BUSOFF: the
            # controller has left the bus; reopening it restarts the controller
            self.stats.extra["bus_off"] = self.stats.extra.get("bus_off", 0) + 1
            raise can.CanOperationError("bus-off (error frame class CAN_ERR_BUSOFF)")
        if k > self.error_frame_limit:
            self._err_window = (now, 0)
            raise can.CanOperationError(f"more than {self.error_frame_limit} error frames/s")
