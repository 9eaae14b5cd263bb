"""The run in Foxglove while it records (``--live-server [HOST:]PORT``), and the on-line results.

::

    recorder writer thread --(after each write)--> tap: bounded deque, oldest batch dropped
        --> [publisher thread] --> Foxglove SDK channels --> WebSocket clients (the SDK keeps a
                 |                                            bounded backlog per client, oldest
                 |                                            dropped: a slow client never waits)
                 +--> on-line feed (every reading) --> [on-line thread, >= 1 Hz] --> /online,
                                                        the terminal view, and per ended point an
                                                        ``online_result`` event on /events

The writer only appends a batch reference to a deque (:meth:`LiveServer.__call__`): it never waits
for the publisher, and the file keeps every sample whatever a client does.  What the publisher
falls behind on is dropped oldest first and counted (:attr:`LiveServer.dropped_batches`); an
on-line result computed after the live path dropped batches is flagged ``live_dropped_batches``.

Topics and schema names are those of the run file (docs/recording.md): every declared stream
``/<stream>``, with Foxglove's well-known types as the SDK sends them (protobuf):
``foxglove.PoseInFrame`` (``/pose``: only frames with a pose; every frame's status, flags and
covariance on ``/pose_status`` as JSON, as in the file), ``foxglove.Log`` (``/event``,
``/events``: fault events are the alarms; a Log message has no extra fields, so a test point's
fields are appended to its text as ``key=value``), ``foxglove.CompressedImage``; our own schemas as
JSON with the file's schema (``cdpr.<stream>``).  A stream the file stores as column blocks
(``/tensions``) is served as its per-sample view ``/tensions/view`` (schema ``cdpr.tensions``,
the first sample of every 20 ms, as in the file); every other stream is decimated the same way
(at most one message per 20 ms: ``/can_raw`` at 50 Hz), events never.  Live only: ``/scene``
(``foxglove.SceneUpdate``, :mod:`cdpr.daq.live_scene`), ``/tf`` (``foxglove.FrameTransforms``,
O -> P), ``/tensions/limits`` (``cdpr.tension_limits``) and ``/online`` (``cdpr.online``).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rotations import rotation_from_euler, rotation_from_quaternion

from . import column_blocks
from .mcap_writer import LOG_LEVELS, codec_for, encode_json, is_frame_batch, topic_of
from .source import Reading, StreamDescription

DEFAULT_HOST = "127.0.0.1"
"""The live server listens here unless a host is given: a lab network is no place for an open
port."""
QUEUE_BATCHES = 2048
"""Batches held between the recorder's writer and the publisher; past that the oldest is dropped."""
DISPLAY_PERIOD_NS = column_blocks.VIEW_PERIOD_NS
"""At most one message per stream in each 20 ms of sample time (the file's ``/tensions/view``)."""
SCENE_HZ = 5.0
ONLINE_PERIOD_S = 1.0
"""The on-line reduction runs once a second while a point is open (each update starts a period
after the previous one started; an update that takes longer delays the next)."""
CLIENT_BACKLOG = 1024
"""Messages the SDK buffers per client; a slow client loses the oldest (never the recorder)."""

ONLINE_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "cdpr.online",
    "description": "The on-line reduction of the open test point (cdpr analyze's core on the "
    "samples so far): wrench at the moment reference point in {O} axes with sigma, body and wind "
    "axes, coefficients with sigma, q; final = true when the point has ended.",
    "additionalProperties": True,
}
LIMITS_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "cdpr.tension_limits",
    "description": "Cable tension limits of the rig (N) and each cable's state: t_min_N / "
    "t_max_N (over the cables), T_<cable>_min_N, T_<cable>_max_N, state_<cable>.",
    "additionalProperties": True,
}


@dataclass(frozen=True)
class LiveAddress:
    """Where the live server listens."""

    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


def parse_address(text: str, option: str = "--live-server") -> LiveAddress:
    """``[HOST:]PORT`` -> :class:`LiveAddress` (host :data:`DEFAULT_HOST` when not given; port 0
    picks a free one).  Bad input is a ``ConfigError`` naming the option."""
    host, _, port_s = text.rpartition(":")
    host = host.strip("[]") or DEFAULT_HOST
    try:
        port = int(port_s)
    except ValueError:
        raise ConfigError(option, text, "expected [HOST:]PORT, e.g. 8765 or 0.0.0.0:8765") from None
    if not 0 <= port <= 65535:
        raise ConfigError(option, text, f"port {port} is outside 0..65535")
    return LiveAddress(host, port)


class OnlineFeed(Protocol):
    """The on-line reduction the live server drives (:mod:`cdpr.pipelines.online` implements
    it; the command passes it in, so ``daq`` does not import ``pipelines``)."""

    def feed(self, readings: Sequence[Reading]) -> None:
        """Every reading the recorder wrote (publisher thread; quick)."""

    def update(
        self, final: bool = False
    ) -> tuple[Mapping[str, Any] | None, list[Mapping[str, Any]]]:
        """(the open point's current result or None, the results of points that ended); with
        ``final`` the ended points are reduced now, without waiting for later samples."""
        ...

    def pending(self) -> int:
        """Ended points whose result is not out yet."""
        ...


@dataclass
class _Out:
    """One live channel: ``kind`` (``json``, ``pose``, ``log``, ``image``), the SDK channel, the
    encoder (reading -> JSON body, for ``json``) and whether it is decimated."""

    kind: str
    channel: Any
    encode: Callable[[Reading], Any] | None
    decimate: bool
    #: the ``/<stream>_status`` channel and its encoder (a pose's status, flags, covariance: what
    #: the well-known schema has no field for; one message per reading, as in the file)
    status: tuple[Any, Callable[[Reading], Any]] | None = None


def _finite(v: Any) -> bool:
    try:
        return all(math.isfinite(float(x)) for x in v)
    except (TypeError, ValueError):
        return False


class LiveServer:
    """The live publisher (see the module docstring).

    address: where the Foxglove SDK server listens; None: no server (the on-line reduction alone,
        for the terminal view).
    rig: the scene, the cable limits and the reference pose (None: no scene).
    geometry: the model's moment reference point and mounting (body axes in the scene).
    online: the on-line reduction (:class:`OnlineFeed`), or None.
    """

    def __init__(
        self,
        address: LiveAddress | None,
        *,
        rig: Any = None,
        geometry: Any = None,
        online: OnlineFeed | None = None,
        name: str = "cdpr",
        queue_batches: int = QUEUE_BATCHES,
        scene_hz: float = SCENE_HZ,
        online_period_s: float = ONLINE_PERIOD_S,
        client_backlog: int = CLIENT_BACKLOG,
    ) -> None:
        self.address = address
        self.rig = rig
        self.geometry = geometry
        self.online = online
        self.name = name
        self.scene_period_s = 1.0 / scene_hz
        self.online_period_s = online_period_s
        self._client_backlog = client_backlog
        self._queue: deque[Sequence[Reading]] = deque(maxlen=queue_batches)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._ctx: Any = None
        self._server: Any = None
        self._outs: dict[str, _Out] = {}
        self._last_bin: dict[str, int] = {}
        self._declared = threading.Event()
        self._online_lock = threading.Lock()
        self._record_event: Callable[..., None] | None = None
        self._tensions: tuple[int, dict[str, Any]] | None = None
        self._pose: tuple[int, Any, Any] | None = None
        self._airspeed: float | None = None
        self.latest_online: Mapping[str, Any] | None = None
        #: the scene's aerodynamic force arrow (3,) N in {O} when set (``cdpr play``'s analysis
        #: overlay); else the open point's on-line result
        self.force_O_N: Sequence[float] | None = None
        self._extra_channels: dict[str, Any] = {}
        self.results: list[Mapping[str, Any]] = []
        # counters (the publisher's; read by tests and the bench)
        self.batches_in = 0
        self.batches_done = 0
        self.dropped_batches = 0
        self.published = 0
        self.online_costs_s: list[float] = []
        #: CPU time of the publisher thread (s): the batches (decimation, encoding, the on-line
        #: feed) and the scene (``/scene``, ``/tf``, ``/tensions/limits``)
        self.cpu_s = {"batches": 0.0, "scene": 0.0}
        #: (log time, time handed to the SDK) of the last published ``/tensions/view`` messages,
        #: ns: the recorder's share of the latency (the bench)
        self.view_lag: deque[tuple[int, int]] = deque(maxlen=100_000)
        self.error: str | None = None

    # lifecycle -------------------------------------------------------------------------------
    @property
    def port(self) -> int | None:
        return None if self._server is None else int(self._server.port)

    @property
    def url(self) -> str | None:
        if self._server is None or self.address is None:
            return None
        return f"ws://{self.address.host}:{self.port}"

    def start(self) -> None:
        """Bind the server (before the recording starts: a port in use is a ``ConfigError``,
        exit 2, no run file) and start the publisher and on-line threads."""
        if self.address is not None:
            import foxglove

            self._ctx = foxglove.Context()
            try:
                self._server = foxglove.start_server(
                    name=self.name,
                    host=self.address.host,
                    port=self.address.port,
                    context=self._ctx,
                    message_backlog_size=self._client_backlog,
                )
            except RuntimeError as exc:
                why = str(exc).removeprefix("FoxgloveError: ")
                if "in use" in why:
                    why = f"port {self.address.port} is in use on {self.address.host} ({why})"
                raise ConfigError("--live-server", str(self.address), why) from None
            self._declare_live_only()
        t = threading.Thread(target=self._publish_loop, name="live-publisher", daemon=True)
        self._threads.append(t)
        t.start()
        if self.online is not None:
            t = threading.Thread(target=self._online_loop, name="live-online", daemon=True)
            self._threads.append(t)
            t.start()

    def attach(self, recorder: Any) -> None:
        """Feed from ``recorder`` (its tap) and record the on-line results on its ``/events``
        (``/event`` when the run has no ``/events`` stream)."""
        recorder.add_tap(self)

        def record(message: str, **fields: Any) -> None:
            for stream in ("events", "event"):
                try:
                    recorder.stream_event(stream, message, **fields)
                    return
                except Exception:
                    continue

        self._record_event = record

    def stop(self) -> None:
        """Stop the threads and the server (idempotent)."""
        self._stop.set()
        self._wake.set()
        for t in self._threads:
            t.join(timeout=10.0)
        self._threads = []
        if self._server is not None:
            self._server.stop()
            self._server = None

    def finish_points(self, timeout_s: float = 5.0) -> None:
        """Before the recorder stops: let the publisher catch up, then reduce the points that
        ended (their ``online_result`` events go into the file)."""
        if self.online is None:
            return
        end = time.monotonic() + timeout_s
        while not self.idle():
            if time.monotonic() > end or not self._threads:
                break
            self._wake.set()
            time.sleep(0.01)
        self._online_step(final=True)

    # the recorder's tap ----------------------------------------------------------------------
    def streams(self, descriptions: Mapping[str, StreamDescription]) -> None:
        """Declare a live channel per stream (the file's topics and schema names)."""
        if self._ctx is not None:
            for stream, desc in descriptions.items():
                self._declare(stream, desc)
        self._declared.set()

    def __call__(self, batch: Sequence[Reading]) -> None:
        """The writer's path: append and return (the deque drops its oldest batch when full)."""
        q = self._queue
        if len(q) == q.maxlen:
            self.dropped_batches += 1
        q.append(batch)
        self.batches_in += 1
        self._wake.set()

    # channels --------------------------------------------------------------------------------
    def _json_channel(
        self, topic: str, schema_name: str, schema: Any, meta: Mapping[str, str]
    ) -> Any:
        import foxglove

        data = schema if isinstance(schema, bytes) else json.dumps(schema).encode()
        return foxglove.Channel(
            topic,
            schema=foxglove.Schema(name=schema_name, encoding="jsonschema", data=data),
            message_encoding="json",
            context=self._ctx,
            metadata=dict(meta),
        )

    def _declare(self, stream: str, desc: StreamDescription | None) -> None:
        from foxglove.channels import CompressedImageChannel, LogChannel, PoseInFrameChannel

        codec = codec_for(stream, desc)
        topic = topic_of(stream)
        meta = {"stream": stream}
        if desc is not None:
            meta["rate_hz"] = repr(float(desc.rate_hz))
            units = {k: f.unit for k, f in desc.fields.items() if f.unit}
            if units:
                meta["units"] = json.dumps(units, separators=(",", ":"))
        kinds = {
            "foxglove.PoseInFrame": ("pose", PoseInFrameChannel),
            "foxglove.Log": ("log", LogChannel),
            "foxglove.CompressedImage": ("image", CompressedImageChannel),
        }
        if codec.schema_name in kinds:
            kind, cls = kinds[codec.schema_name]
            status = None
            st = getattr(codec, "status", None)
            if st is not None:  # the file's /<stream>_status beside the well-known channel
                smeta = {**meta, "stream": f"{stream}_status", "status_of": topic}
                status = (self._json_channel(topic + "_status", st.schema_name, st.schema, smeta),
                          st.encode)  # fmt: skip
            self._outs[stream] = _Out(
                kind, cls(topic, context=self._ctx, metadata=meta), codec.encode, kind != "log",
                status,
            )  # fmt: skip
            return
        if desc is not None and (
            codec.block_layout is not None
            or (codec.schema_name == f"cdpr.{stream}" and column_blocks.uses_blocks(desc))
        ):
            # the file stores it as column blocks (a sensor's columns, or CAN frame blocks):
            # live, its per-sample view (same decimation)
            topic += "/view"
            meta["view_of"] = topic_of(stream)
            meta["view_period_ns"] = str(DISPLAY_PERIOD_NS)
            if self.rig is not None and stream.rsplit("/", 1)[-1] == "tensions":
                meta["limits_N"] = json.dumps(
                    {n: [lo, hi] for n, lo, hi in zip(self.rig.cable_names, self.rig.t_min_N,
                                                      self.rig.t_max_N, strict=True)}
                )  # fmt: skip
        ch = self._json_channel(topic, codec.schema_name, codec.schema, meta)
        self._outs[stream] = _Out("json", ch, codec.encode, True)

    def _declare_live_only(self) -> None:
        from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel

        ctx = self._ctx
        self._scene = SceneUpdateChannel("/scene", context=ctx) if self.rig is not None else None
        self._tf = FrameTransformsChannel("/tf", context=ctx) if self.rig is not None else None
        self._limits = (
            self._json_channel("/tensions/limits", "cdpr.tension_limits", LIMITS_SCHEMA, {})
            if self.rig is not None
            else None
        )
        self._online_ch = self._json_channel("/online", "cdpr.online", ONLINE_SCHEMA, {})

    def publish_json(
        self, topic: str, schema: Mapping[str, Any], body: Mapping[str, Any], t_ns: int
    ) -> None:
        """Publish ``body`` on a live-only JSON ``topic`` (declared on first use with ``schema``,
        whose ``title`` is the schema name), e.g. ``cdpr play``'s ``/analysis`` overlay."""
        if self._ctx is None:
            return
        ch = self._extra_channels.get(topic)
        if ch is None:
            ch = self._extra_channels[topic] = self._json_channel(
                topic, str(schema["title"]), dict(schema), {}
            )
        ch.log(encode_json(body), log_time=int(t_ns))
        self.published += 1

    def new_session(self) -> None:
        """Tell the clients to reset (a replay that starts again from the beginning)."""
        self._last_bin.clear()
        if self._server is not None:
            self._server.clear_session()

    def idle(self) -> bool:
        """Every batch handed in has been published (or dropped)."""
        return self.batches_done + self.dropped_batches >= self.batches_in

    # publishing ------------------------------------------------------------------------------
    def _publish(self, out: _Out, r: Reading) -> None:
        if out.kind == "json":
            assert out.encode is not None
            body = out.encode(r)
            out.channel.log(body if type(body) is bytes else encode_json(body), log_time=r.t_ns)
        elif out.kind == "pose":
            if out.status is not None:  # every frame, with or without a pose
                ch, enc = out.status
                ch.log(encode_json(enc(r)), log_time=r.t_ns)
                self.published += 1
            msg = pose_message(r)
            if msg is None:  # a frame without a pose is not a PoseInFrame (its status says why)
                return
            out.channel.log(msg, log_time=r.t_ns)
        elif out.kind == "log":
            out.channel.log(log_message(r), log_time=r.t_ns)
        else:
            out.channel.log(image_message(r), log_time=r.t_ns)
        self.published += 1

    def _readings(self, readings: Sequence[Reading]) -> None:
        outs = self._outs
        last = self._last_bin
        period = DISPLAY_PERIOD_NS
        for r in readings:
            stream = r.stream
            out = outs.get(stream)
            base = stream.rsplit("/", 1)[-1]
            if out is not None and out.decimate:
                b = r.t_ns // period
                if last.get(stream) == b:
                    continue
                last[stream] = b
            if base == "tensions":
                self._tensions = (r.t_ns, dict(r.values))
            elif base == "pose" and r.status == 0:
                self._pose_from(r)
            elif base == "tunnel":
                v = r.values.get("airspeed_mps")
                if isinstance(v, int | float):
                    self._airspeed = float(v)
            if out is not None:
                self._publish(out, r)
                if base == "tensions":
                    self.view_lag.append((r.t_ns, time.time_ns()))

    def _pose_from(self, r: Reading) -> None:
        v = r.values
        p = v.get("position_O_m")
        q = v.get("quaternion_wxyz")
        if p is not None and q is not None and _finite(p) and _finite(q):
            R = rotation_from_quaternion(np.asarray(q, np.float64))
            self._pose = (r.t_ns, np.asarray(p, np.float64), R)

    def _frames(self, batch: Any) -> None:
        """A CAN frame batch: its frames decimated with numpy, its decoded readings one by one."""
        stream = batch.stream
        n = batch.n_frames
        out = self._outs.get(stream)
        if n and out is not None:
            t = np.asarray(batch.t_ns[:n], np.int64)
            bins = t // DISPLAY_PERIOD_NS
            pick = np.flatnonzero(np.diff(bins, prepend=self._last_bin.get(stream, -1)) != 0)
            self._last_bin[stream] = int(bins[-1])
            for i in pick.tolist():
                self._publish(out, batch.frame_reading(i))
        if batch.others:
            self._readings([r for _, r in batch.others])

    def _batch(self, batch: Sequence[Reading]) -> None:
        frames = is_frame_batch(batch)
        if self.online is not None:
            self.online.feed([r for _, r in batch.others] if frames else batch)  # type: ignore[attr-defined]
        if frames:
            self._frames(batch)
        else:
            self._readings(batch)

    def _publish_loop(self) -> None:
        self._declared.wait()
        next_scene = next_limits = time.monotonic()
        q = self._queue
        try:
            while not self._stop.is_set():
                self._wake.wait(0.05)
                self._wake.clear()
                c0 = time.thread_time()
                while q:
                    try:
                        batch = q.popleft()
                    except IndexError:
                        break
                    self._batch(batch)
                    self.batches_done += 1
                c1 = time.thread_time()
                self.cpu_s["batches"] += c1 - c0
                now = time.monotonic()
                if self._ctx is not None and self.rig is not None and now >= next_scene:
                    next_scene = now + self.scene_period_s
                    self._publish_scene()
                    if now >= next_limits:
                        next_limits = now + 1.0
                        self._publish_limits()
                    self.cpu_s["scene"] += time.thread_time() - c1
        except Exception as exc:  # never take the recording down; say it
            self.error = f"{type(exc).__name__}: {exc}"
            if self._record_event is not None:
                self._record_event(f"live server stopped: {self.error}", level="error",
                                   name="live_server")  # fmt: skip
            raise

    # scene -----------------------------------------------------------------------------------
    def _scene_inputs(self) -> tuple[int, list[float], Any, Any] | None:
        if self._tensions is None:
            return None
        t_ns, values = self._tensions
        T = [float(values.get(f"T_{c}_N", math.nan) or math.nan) for c in self.rig.cable_names]
        if self._pose is not None:
            _, p, R = self._pose
        else:
            p, R = (
                self.rig.reference_position_O_m,
                rotation_from_euler(self.rig.reference_euler_rad),
            )
        return t_ns, T, p, R

    def _publish_scene(self) -> None:
        from .live_scene import frame_transforms, scene_geometry, scene_update

        got = self._scene_inputs()
        if got is None:
            return
        t_ns, T, p, R = got
        force = self.force_O_N
        on = self.latest_online
        if (
            force is None
            and on is not None
            and not on.get("final")
            and all(isinstance(on.get(k), int | float) for k in ("fx_N", "fy_N", "fz_N"))
        ):
            force = [on["fx_N"], on["fy_N"], on["fz_N"]]
        g = self.geometry
        kw: dict[str, Any] = {}
        if g is not None:
            kw = {"mrp_P_m": g.mrp_P_m, "nose_P": g.nose_P, "up_P": g.up_P}
        geo = scene_geometry(self.rig, p, R, T, airspeed_mps=self._airspeed, force_O_N=force, **kw)
        self._scene.log(scene_update(geo, t_ns, self.rig.cable_names), log_time=t_ns)
        self._tf.log(frame_transforms(p, R, t_ns), log_time=t_ns)
        self.published += 2

    def _publish_limits(self) -> None:
        from .live_scene import cable_states

        got = self._scene_inputs()
        rig = self.rig
        t_ns = got[0] if got is not None else time.time_ns()
        T = got[1] if got is not None else [math.nan] * rig.n_cables
        body: dict[str, Any] = {
            "t_min_N": float(np.min(rig.t_min_N)),
            "t_max_N": float(np.max(rig.t_max_N)),
        }
        states = cable_states(T, rig.t_min_N, rig.t_max_N)
        for c, lo, hi, s in zip(rig.cable_names, rig.t_min_N, rig.t_max_N, states, strict=True):
            body[f"T_{c}_min_N"], body[f"T_{c}_max_N"] = float(lo), float(hi)
            body[f"state_{c}"] = s
        self._limits.log(encode_json(body), log_time=t_ns)
        self.published += 1

    # on-line ---------------------------------------------------------------------------------
    def _online_step(self, final: bool = False) -> None:
        assert self.online is not None
        with self._online_lock:
            t0 = time.perf_counter()
            msg, results = self.online.update(final=final)
            if msg is not None or results:
                self.online_costs_s.append(time.perf_counter() - t0)
            for res in [*(results or ()), *([msg] if msg is not None else [])]:
                res = dict(res)
                if self.dropped_batches:
                    res["flags"] = ";".join(
                        filter(None, [str(res.get("flags", "")), "live_dropped_batches"])
                    )
                if res.get("final"):
                    self.results.append(res)
                    if self._record_event is not None:
                        self._record_event(
                            f"on-line result of point {res.get('point', '')}",
                            level="info",
                            name="online_result",
                            **{k: v for k, v in res.items() if k not in _NOT_EVENT_FIELDS},
                        )
                self.latest_online = res
                if self._ctx is not None:
                    t_ns = int(res.get("t_ns") or time.time_ns())
                    self._online_ch.log(encode_json(res), log_time=t_ns)
                    self.published += 1

    def _online_loop(self) -> None:
        # one update every period, counted from the start of the last (not from its end): the
        # update's own cost does not stretch the interval while it stays below the period
        due = time.monotonic() + self.online_period_s
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            due = max(due + self.online_period_s, time.monotonic())
            try:
                self._online_step()
            except Exception as exc:  # said once per distinct error; the next period tries again
                error = f"on-line reduction: {type(exc).__name__}: {exc}"
                if error != self.error and self._record_event is not None:
                    self._record_event(error, level="error", name="live_server")
                self.error = error

    def online_line(self) -> str | None:
        """The terminal view's line of the latest on-line result (None before the first)."""
        on = self.latest_online
        if on is None:
            return None
        return online_text(on)


def online_text(on: Mapping[str, Any]) -> str:
    """One line: the point, steadiness, the wrench (N, N m at the MRP, {O} axes) and the
    coefficients with σ."""

    def num(k: str, f: str) -> str:
        v, s = on.get(k), on.get(f"sd_{k}")
        if not isinstance(v, int | float) or not math.isfinite(v):
            return f"{k} –"
        sd = f" ± {s:{f}}" if isinstance(s, int | float) and math.isfinite(s) else ""
        return f"{k} {v:{f}}{sd}"

    head = f"on-line  {on.get('point', '?')}"
    state = "final" if on.get("final") else ("steady" if on.get("steady") else "UNSTEADY")
    head += f" ({state}, {on.get('n_samples', 0)} samples)"
    w = "  ".join(num(k, ".2f") for k in ("fx_N", "fy_N", "fz_N"))
    c = "  ".join(num(k, ".4f") for k in ("CL", "CD", "Cm"))
    flags = on.get("flags") or ""
    return f"{head}  {w}  {c}" + (f"  [{flags}]" if flags else "")


def pose_message(r: Reading) -> Any:
    """``foxglove.PoseInFrame`` of a pose reading, or None for a frame without a pose (a
    non-finite position or orientation), as the run file writes ``/pose``."""
    from foxglove.messages import PoseInFrame

    v = r.values
    p = v.get("position_O_m")
    if "quaternion_wxyz" in v:
        q = v["quaternion_wxyz"]
        q_xyzw = None if q is None else [q[1], q[2], q[3], q[0]]
    else:
        q_xyzw = v.get("quaternion_xyzw")
    if p is None or q_xyzw is None or not (_finite(p) and _finite(q_xyzw)):
        return None
    return PoseInFrame(**_pose_fields(r.t_ns, str(v.get("frame_id", "O")), p, q_xyzw))


def _pose_fields(
    t_ns: int, frame_id: str, p: Sequence[float], q_xyzw: Sequence[float]
) -> dict[str, Any]:
    from foxglove.messages import Pose, Quaternion, Timestamp, Vector3

    x, y, z, w = (float(c) for c in q_xyzw)
    return {
        "timestamp": Timestamp(*divmod(int(t_ns), 1_000_000_000)),
        "frame_id": frame_id,
        "pose": Pose(
            position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=Quaternion(x=x, y=y, z=z, w=w),
        ),
    }


_LOG_KEYS = ("message", "level", "name", "file", "line")
#: an on-line result's fields that are not copied into its event (the event's own time is its
#: log time; a reader's tables have their own ``t_ns`` column)
_NOT_EVENT_FIELDS = frozenset({*_LOG_KEYS, "t_ns", "timestamp", "status"})


def log_message(r: Reading) -> Any:
    """``foxglove.Log`` of an event reading; the fields a Log message has no room for (a test
    point's ``point``, ``phase``, targets ...) are appended to the text as ``key=value``."""
    from foxglove.messages import Log, LogLevel, Timestamp

    v = r.values
    level = v.get("level", 2)
    if isinstance(level, str):
        level = LOG_LEVELS.get(level.lower(), 0)
    extra = " ".join(
        f"{k}={x:g}" if isinstance(x, float) else f"{k}={x}"
        for k, x in v.items()
        if k not in _LOG_KEYS and x is not None and x != ""
    )
    text = str(v.get("message", "")) + (f" ({extra})" if extra else "")
    levels = (LogLevel.Unknown, LogLevel.Debug, LogLevel.Info, LogLevel.Warning, LogLevel.Error,
              LogLevel.Fatal)  # fmt: skip
    return Log(
        timestamp=Timestamp(*divmod(int(r.t_ns), 1_000_000_000)),
        level=levels[min(max(int(level), 0), 5)],
        message=text,
        name=str(v.get("name", r.stream)),
        file=str(v.get("file", "")),
        line=int(v.get("line", 0) or 0),
    )


def image_message(r: Reading) -> Any:
    """``foxglove.CompressedImage`` of an image reading."""
    from foxglove.messages import CompressedImage, Timestamp

    v = r.values
    return CompressedImage(
        timestamp=Timestamp(*divmod(int(r.t_ns), 1_000_000_000)),
        frame_id=str(v.get("frame_id", "camera")),
        data=bytes(v.get("data", b"")),
        format=str(v.get("format", "jpeg")),
    )
