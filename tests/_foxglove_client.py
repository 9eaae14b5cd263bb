"""A Foxglove WebSocket client for the tests and the bench, written from the protocol (the
``websockets`` package, subprotocol ``foxglove.sdk.v1``): it reads the server's ``serverInfo`` and
``advertise`` messages, subscribes to every channel (also those advertised later), and decodes
each binary ``messageData`` frame (opcode 1, subscription id uint32 LE, log time uint64 LE,
payload): JSON channels with ``json.loads``, protobuf channels with the message class built from
the FileDescriptorSet the server advertises (``google.protobuf``'s descriptor pool).  It never
imports the SDK.

The client runs its own asyncio loop in a thread; ``stall_after`` makes it stop reading after that
many messages (a client that hangs, its socket buffers filling up).
"""

from __future__ import annotations

import asyncio
import base64
import json
import re
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

SUBPROTOCOL = "foxglove.sdk.v1"


@dataclass
class Received:
    topic: str
    schema_name: str
    log_time_ns: int
    arrival_ns: int
    body: Any  # dict (JSON) or a protobuf message


@dataclass
class Channel:
    id: int
    topic: str
    encoding: str
    schema_name: str
    schema_encoding: str
    schema: str
    metadata: dict[str, str] = field(default_factory=dict)


def _protobuf_class(schema_b64: str, name: str) -> Any:
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:  # dependencies come first in the set the server sends
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


class FoxgloveClient:
    """Connect to ``ws://host:port``, subscribe to everything, keep what arrives."""

    def __init__(self, url: str, *, stall_after: int | None = None, keep_bodies: bool = True):
        self.url = url
        self.stall_after = stall_after
        self.keep_bodies = keep_bodies
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[int, Channel] = {}
        self.received: list[Received] = []
        self.transcript: list[str] = []
        self.error: BaseException | None = None
        self.closed = False
        self.subprotocol: str | None = None
        self.subscribed = threading.Event()
        self._stop = threading.Event()
        self._classes: dict[int, Any] = {}
        self._sub_of: dict[int, int] = {}
        self._thread = threading.Thread(target=self._run, name="foxglove-client", daemon=True)
        self._lock = threading.Lock()

    def start(self) -> FoxgloveClient:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)

    def topics(self) -> dict[str, Channel]:
        return {c.topic: c for c in self.channels.values()}

    def of(self, topic: str) -> list[Received]:
        with self._lock:
            return [r for r in self.received if r.topic == topic]

    def wait_for(self, pred: Any, timeout_s: float) -> bool:
        """Wait until ``pred(self)`` is true (polling; the server pushes)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.error is not None:
                raise self.error
            if pred(self):
                return True
            time.sleep(0.02)
        return bool(pred(self))

    def _run(self) -> None:
        import websockets

        try:
            asyncio.run(self._main())
        except websockets.ConnectionClosed:  # the server went away (the run ended)
            self.closed = True
        except BaseException as exc:  # reported to the test
            self.error = exc

    async def _main(self) -> None:
        import websockets

        async with websockets.connect(
            self.url, subprotocols=[SUBPROTOCOL], max_size=None, open_timeout=30
        ) as ws:
            self.subprotocol = ws.subprotocol
            n_sub = 0
            n_msgs = 0
            while not self._stop.is_set():
                if self.stall_after is not None and n_msgs >= self.stall_after:
                    await asyncio.sleep(0.05)  # stop reading: the server's buffers fill up
                    continue
                try:
                    m = await asyncio.wait_for(ws.recv(), 0.1)
                except TimeoutError:
                    continue
                now = time.time_ns()
                if isinstance(m, str):
                    d = json.loads(m)
                    op = d.get("op")
                    if op == "serverInfo":
                        self.server_info = d
                        self.transcript.append(f"serverInfo {json.dumps(d)}")
                    elif op == "advertise":
                        subs = []
                        for c in d["channels"]:
                            ch = Channel(
                                c["id"], c["topic"], c["encoding"], c["schemaName"],
                                c.get("schemaEncoding", ""), c.get("schema", ""),
                                dict(c.get("metadata", {}) or {}),
                            )  # fmt: skip
                            self.channels[ch.id] = ch
                            if ch.encoding == "protobuf":
                                self._classes[ch.id] = _protobuf_class(ch.schema, ch.schema_name)
                            n_sub += 1
                            self._sub_of[n_sub] = ch.id
                            subs.append({"id": n_sub, "channelId": ch.id})
                            self.transcript.append(
                                f"advertise id={ch.id} {ch.topic} encoding={ch.encoding} "
                                f"schema={ch.schema_name} ({ch.schema_encoding})"
                            )
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                        self.subscribed.set()
                    else:
                        self.transcript.append(f"{op} {json.dumps(d)[:200]}")
                        unknown = re.match(r"Unknown channel ID: (\d+)", str(d.get("message", "")))
                        if op == "status" and unknown and int(unknown[1]) in self.channels:
                            # the SDK advertised a channel a moment before it registered it
                            # (a channel created while this client is connected): ask again
                            await asyncio.sleep(0.05)
                            cid = int(unknown[1])
                            n_sub += 1
                            self._sub_of[n_sub] = cid
                            await ws.send(json.dumps(
                                {"op": "subscribe", "subscriptions": [{"id": n_sub, "channelId": cid}]}
                            ))  # fmt: skip
                    continue
                if m[0] != 1:
                    continue
                sub, log_time = struct.unpack_from("<IQ", m, 1)
                payload = m[13:]
                ch = self.channels[self._sub_of[sub]]
                if not self.keep_bodies:
                    body: Any = None
                elif ch.encoding == "json":
                    body = json.loads(payload)
                else:
                    body = self._classes[ch.id].FromString(payload)
                with self._lock:
                    self.received.append(Received(ch.topic, ch.schema_name, log_time, now, body))
                n_msgs += 1
