"""Stream codecs of run files: how a stream's readings become JSON messages and which JSON schema
describes them, and the registry that picks a stream's codec by its name.

- :func:`flat_codec` (the default): the reading's values as they are, plus ``status``;
- Foxglove's well-known schemas, embedded exactly as Foxglove publishes them
  (:mod:`cdpr.daq.foxglove_schemas`): streams whose name contains ``pose`` use
  ``foxglove.PoseInFrame`` (only for a frame with a pose; every frame's status, flags, covariance
  ... go on ``/<stream>_status``, schema ``cdpr.<stream>_status``: :attr:`StreamCodec.status`),
  else ``image`` ``foxglove.CompressedImage``; ``event*`` use ``foxglove.Log``;
- drivers register more (:func:`register_stream_codec`: the CAN driver registers ``can_raw``,
  :mod:`cdpr.daq.can_raw`) and their batch types (:func:`register_frame_batch_type`).

The writer (:class:`cdpr.daq.mcap_writer.McapRunWriter`) asks :func:`codec_for` once per stream.
"""

from __future__ import annotations

import base64
import fnmatch
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from . import foxglove_schemas
from .source import FieldDescription, Reading, StreamDescription

_JSON_TYPES = {
    "float64": {"type": "number"},
    "float32": {"type": "number"},
    "float": {"type": "number"},
    "int64": {"type": "integer"},
    "int32": {"type": "integer"},
    "int": {"type": "integer"},
    "uint8": {"type": "integer"},
    "bool": {"type": "boolean"},
    "str": {"type": "string"},
    "bytes": {"type": "array", "items": {"type": "integer", "minimum": 0, "maximum": 255}},
}


def _default(obj: Any) -> Any:
    """JSON fallback for numpy scalars and arrays, bytes and other sequences."""
    if isinstance(obj, bytes | bytearray | memoryview):
        return list(bytes(obj))
    tolist = getattr(obj, "tolist", None)
    if tolist is not None:
        return tolist()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    raise TypeError(f"cannot encode {type(obj).__name__} as JSON")


def _sanitize(obj: Any) -> Any:
    """Replace non-finite floats (not valid JSON) by ``None``, recursively."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {k: _sanitize(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_sanitize(v) for v in obj]
    if isinstance(obj, bytes | bytearray | memoryview):
        return list(bytes(obj))
    tolist = getattr(obj, "tolist", None)
    if tolist is not None:
        return _sanitize(tolist())
    return obj


_dumps = json.JSONEncoder(default=_default, separators=(",", ":"), allow_nan=True).encode


def encode_json(body: Mapping[str, Any]) -> bytes:
    """Compact JSON bytes of ``body``; NaN and infinities become ``null`` (strict JSON)."""
    text = _dumps(body)
    if "NaN" in text or "Infinity" in text:
        text = _dumps(_sanitize(body))
    return text.encode()


def ns_to_time(t_ns: int) -> dict[str, int]:
    """Foxglove ``time`` object ``{"sec", "nsec"}`` of an integer ns timestamp."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


# -------------------------------------------------------------------------------------------------
# codecs


@dataclass
class StreamCodec:
    """Schema and encoder of one stream.

    schema_name: MCAP schema name (``foxglove.PoseInFrame``, ``cdpr.tensions``, ...).
    schema: JSON schema (dict).
    encode: reading -> message body (a dict, encoded to JSON by the writer, or JSON bytes), or
        None: no message on this channel for that reading (a camera frame without a pose).
    encode_frames: optional batch encoder of raw CAN frames (``can.Message`` objects, see
        :class:`cdpr.daq.can_raw.CanFrameBatch`) -> :class:`FrameRecords`.
    block_layout: the ``layout`` of the stream stored as column blocks when it is added with a
        description and not ``blocks=False`` (its columns written with
        :meth:`~cdpr.daq.mcap_writer.McapRunWriter.write_columns`, or by a frame batch's
        ``frame_block()``; no view), e.g. ``can_frames`` (:mod:`cdpr.daq.can_raw`); None: no
        block layout.
    block_rows: with a block layout: readings -> ``(t_ns, columns, status, values)`` for
        ``write_columns`` (a single reading written into a block stream).
    status: the codec of a second channel, ``/<stream>_status`` (channel metadata ``status_of``),
        that gets one message for every reading, whether ``encode`` gave one or not: what a
        well-known schema has no field for (a pose's status, flags, covariance).  ``open_run``
        joins the two back into one table per reading.
    """

    schema_name: str
    schema: dict[str, Any]
    encode: Callable[[Reading], Any]
    encode_frames: Callable[[Any], FrameRecords] | None = None
    block_layout: str | None = None
    status: StreamCodec | None = None
    block_rows: Callable[[Sequence[Reading]], Any] | None = None


#: a float that may be missing: NaN is written as JSON ``null`` (strict JSON has no NaN)
_NUMBER_OR_NULL = {"type": ["number", "null"], "description": "null: missing (NaN)"}


def _field_schema(desc: Any) -> dict[str, Any]:
    base = dict(_JSON_TYPES.get(getattr(desc, "dtype", "float64"), {}))
    if base.get("type") == "number":
        base = dict(_NUMBER_OR_NULL)
    shape = tuple(getattr(desc, "shape", ()) or ())
    for n in reversed(shape):
        base = {"type": "array", "items": base, "minItems": n, "maxItems": n}
    unit = getattr(desc, "unit", "")
    if unit:
        base["description"] = f"unit: {unit}" + (
            "; null: missing (NaN)" if "description" in base else ""
        )
    return base


def flat_codec(stream: str, description: StreamDescription | None) -> StreamCodec:
    """The default codec: the reading's values as they are, plus ``status``.

    The schema lists the described fields (type, shape, unit) and allows extra ones.
    """
    props: dict[str, Any] = {}
    if description is not None:
        for name, fd in description.fields.items():
            props[name] = _field_schema(fd)
    props["status"] = {
        "type": "integer",
        "description": "0 = good, else bit field: 1 saturated, 2 slack, 4 stale, 8 bad frame, 16 gap",
    }
    schema = {
        "type": "object",
        "title": f"cdpr.{stream}",
        "description": (description.doc if description is not None else "")
        + " Time is the message log_time (ns since the Unix epoch).",
        "properties": props,
        "additionalProperties": True,
    }

    def encode(r: Reading) -> Mapping[str, Any]:
        body = dict(r.values)
        body["status"] = r.status
        return body

    return StreamCodec(f"cdpr.{stream}", schema, encode)


def _pose_parts(r: Reading) -> tuple[list[float], list[float], str, dict[str, Any]]:
    """A pose reading's position (3), quaternion ``[x, y, z, w]``, frame id and other values."""
    v = dict(r.values)
    p = [float(x) for x in v.pop("position_O_m", (math.nan,) * 3)]
    if "quaternion_wxyz" in v:  # the project's convention elsewhere (scalar first)
        w_, x_, y_, z_ = (float(x) for x in v.pop("quaternion_wxyz"))
        q = [x_, y_, z_, w_]
    else:
        q = [float(x) for x in v.pop("quaternion_xyzw", (0.0, 0.0, 0.0, 1.0))]
    return p, q, str(v.pop("frame_id", "O")), v


def _pose_codec(stream: str, description: StreamDescription | None) -> StreamCodec:
    """``foxglove.PoseInFrame`` (Foxglove's schema, nothing added) for a frame with a pose, and
    ``/<stream>_status`` (``cdpr.<stream>_status``) for every frame.  Values: ``position_O_m``
    (3,), ``quaternion_xyzw`` (4,) or ``quaternion_wxyz`` (4,, scalar first), optional
    ``frame_id`` (default ``"O"``); a frame has a pose when these 7 numbers are finite.  The status
    message holds every other value (``covariance``, ``flags``, ``reprojection_px``, ...),
    ``has_pose`` (1: this frame has its ``PoseInFrame`` message) and ``status``."""
    pose_keys = ("position_O_m", "quaternion_xyzw", "quaternion_wxyz", "frame_id")
    fields = {} if description is None else dict(description.fields)
    fields = {k: f for k, f in fields.items() if k not in pose_keys}
    fields["has_pose"] = FieldDescription("", "int64")
    rate = 0.0 if description is None else description.rate_hz
    status = flat_codec(
        f"{stream}_status",
        StreamDescription(
            fields,
            rate,
            f"Every frame of /{stream}, with or without a pose: what foxglove.PoseInFrame has no "
            f"field for; has_pose = 1 when the frame has its /{stream} message (same log time).",
        ),
    )

    def encode(r: Reading) -> Mapping[str, Any] | None:
        p, q, frame_id, _ = _pose_parts(r)
        if not all(math.isfinite(x) for x in (*p, *q)):
            return None  # no pose: not a PoseInFrame message (its status says why)
        return {
            "timestamp": ns_to_time(r.t_ns),
            "frame_id": frame_id,
            "pose": {
                "position": {"x": p[0], "y": p[1], "z": p[2]},
                "orientation": {"x": q[0], "y": q[1], "z": q[2], "w": q[3]},
            },
        }

    def encode_status(r: Reading) -> Mapping[str, Any]:
        p, q, _, body = _pose_parts(r)
        body["has_pose"] = int(all(math.isfinite(x) for x in (*p, *q)))
        body["status"] = r.status
        return body

    return StreamCodec(
        "foxglove.PoseInFrame",
        foxglove_schemas.POSE_IN_FRAME,
        encode,
        status=StreamCodec(status.schema_name, status.schema, encode_status),
    )


def _image_codec(stream: str, description: StreamDescription | None) -> StreamCodec:
    """``foxglove.CompressedImage``; values ``data`` (bytes: JPEG/PNG), ``format`` (``"jpeg"``,
    ``"png"``), optional ``frame_id`` (default ``"camera"``); the other values (``width``,
    ``height``, ``frame_index``, ``status``) ride along as extra fields, which Foxglove's schema
    allows."""

    def encode(r: Reading) -> Mapping[str, Any]:
        v = dict(r.values)
        data = bytes(v.pop("data", b""))
        body: dict[str, Any] = {
            "timestamp": ns_to_time(r.t_ns),
            "frame_id": str(v.pop("frame_id", "camera")),
            "data": base64.b64encode(data).decode("ascii"),
            "format": str(v.pop("format", "jpeg")),
        }
        body.update(v)
        body["status"] = r.status
        return body

    return StreamCodec("foxglove.CompressedImage", foxglove_schemas.COMPRESSED_IMAGE, encode)


LOG_LEVELS = {
    "unknown": 0,
    "debug": 1,
    "info": 2,
    "warning": 3,
    "error": 4,
    "fatal": 5,
    "critical": 5,
}


def _log_codec(stream: str, description: StreamDescription | None) -> StreamCodec:
    """``foxglove.Log``; values ``message`` (str), optional ``level`` (name or 0-5, default info;
    anything else is 0, unknown), ``name`` (origin, default the stream); the other values (a test
    point's ``point``, ``phase``, ...; ``status``) ride along as extra fields, which Foxglove's
    schema allows."""

    def encode(r: Reading) -> Mapping[str, Any]:
        v = dict(r.values)
        level = v.pop("level", 2)
        if isinstance(level, str):
            level = LOG_LEVELS.get(level.lower(), 0)
        elif level not in range(6):
            level = 0
        body: dict[str, Any] = {
            "timestamp": ns_to_time(r.t_ns),
            "level": int(level),
            "message": str(v.pop("message", "")),
            "name": str(v.pop("name", stream)),
            "file": str(v.pop("file", "")),
            "line": int(v.pop("line", 0)),
        }
        body.update(v)
        body["status"] = r.status
        return body

    return StreamCodec("foxglove.Log", foxglove_schemas.LOG, encode)


@dataclass
class FrameRecords:
    """Message bodies of a batch of frames, as a codec's ``encode_frames`` returns them: ``ok[i]``
    says frame ``i`` has its body in ``bodies[j]`` (``j`` counts the ok frames; fixed-length rows
    of uint8); the others are encoded one by one from their readings."""

    ok: Any
    bodies: Any


# -------------------------------------------------------------------------------------------------
# the registry: codecs by stream name, batch types of raw frames

#: batch types whose frames the writer hands to the stream codec's ``encode_frames`` at once
#: (registered by the drivers, e.g. :class:`cdpr.daq.can_source.CanFrameBatch`)
_FRAME_BATCH_TYPES: set[type] = set()


def register_frame_batch_type(batch_type: type) -> None:
    """Have :meth:`~cdpr.daq.mcap_writer.McapRunWriter.write_many` treat ``batch_type`` as a batch
    of frames: it has ``stream``, ``messages``, ``t_ns`` (one per frame), ``others``,
    ``frame_reading(i)`` and, for a block stream, ``frame_block()`` (see
    :class:`cdpr.daq.can_raw.CanFrameBatch`)."""
    _FRAME_BATCH_TYPES.add(batch_type)


def is_frame_batch(batch: Any) -> bool:
    """True for an instance of a registered frame-batch type (:func:`register_frame_batch_type`)."""
    return type(batch) in _FRAME_BATCH_TYPES


CodecFactory = Callable[[str, "StreamDescription | None"], StreamCodec]
_CODECS: list[tuple[str, CodecFactory]] = [
    ("pose*", _pose_codec),
    ("*pose*", _pose_codec),  # camera_pose, platform_pose, ...
    ("image*", _image_codec),
    ("*image*", _image_codec),  # camera_image, ...
    ("event*", _log_codec),
]


def register_stream_codec(pattern: str, factory: CodecFactory) -> None:
    """Use ``factory(stream, description)`` for streams whose name matches ``pattern`` (fnmatch);
    later registrations win."""
    _CODECS.insert(0, (pattern, factory))


def codec_for(stream: str, description: StreamDescription | None) -> StreamCodec:
    """The codec of ``stream``: the first registered pattern that matches, else :func:`flat_codec`."""
    base = stream.rsplit("/", 1)[-1]
    for pattern, factory in _CODECS:
        if fnmatch.fnmatchcase(base, pattern):
            return factory(stream, description)
    return flat_codec(stream, description)


def topic_of(stream: str) -> str:
    """MCAP topic of a stream: ``/<stream>``."""
    return "/" + stream
