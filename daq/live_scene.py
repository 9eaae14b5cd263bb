"""The 3D scene of the rig for Foxglove's 3D panel (``/scene``, ``foxglove.SceneUpdate``).

:func:`scene_geometry` computes, in the tunnel frame {O}, what the scene draws (pure numpy, tested
against the structure matrix): each cable from its platform point ``p + R·pp_i`` to its anchor
``b_i``, its state (``ok``, ``near_limit``, ``slack``, ``saturated``, ``missing``) from the tension
and the rig's limits, the platform box, the model's body axes at the moment reference point, the
wind arrow and the aerodynamic force arrow.  :func:`scene_update` turns it into the SDK's
``SceneUpdate`` message (protobuf on the wire); :func:`frame_transforms` gives the O -> P
transform (``/tf``, ``foxglove.FrameTransforms``).

Colours: slack (below ``t_min_N``) blue, near the upper limit (above ``t_max_N - NEAR_LIMIT_SHARE``
of the range) orange, saturated (above ``t_max_N``) red, a missing tension grey, else green.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdpr.analysis.aero import body_axes_in_platform
from cdpr.analysis.rotations import quaternion_from_rotation

FloatArray = NDArray[np.float64]

NEAR_LIMIT_SHARE = 0.1
"""A cable is ``near_limit`` within this share of its range ``t_max - t_min`` below ``t_max``."""
FORCE_SCALE_M_PER_N = 0.02
"""Length of the aerodynamic force arrow per newton (0.5 m for 25 N)."""
WIND_ARROW_M = (0.1, 0.004)
"""Wind arrow length: 0.1 m plus 4 mm per m/s of airspeed."""
AXIS_LENGTH_M = 0.08

COLOURS: dict[str, tuple[float, float, float, float]] = {
    "ok": (0.15, 0.7, 0.25, 1.0),
    "near_limit": (1.0, 0.55, 0.0, 1.0),
    "saturated": (0.9, 0.05, 0.05, 1.0),
    "slack": (0.1, 0.35, 1.0, 1.0),
    "missing": (0.55, 0.55, 0.55, 1.0),
}


def cable_states(
    tension_N: Sequence[float], t_min_N: Sequence[float], t_max_N: Sequence[float]
) -> list[str]:
    """The state of each cable (see the module docstring); NaN is ``missing``."""
    out = []
    for T, lo, hi in zip(tension_N, t_min_N, t_max_N, strict=True):
        if not np.isfinite(T):
            out.append("missing")
        elif T < lo:
            out.append("slack")
        elif T > hi:
            out.append("saturated")
        elif T > hi - NEAR_LIMIT_SHARE * (hi - lo):
            out.append("near_limit")
        else:
            out.append("ok")
    return out


@dataclass(frozen=True)
class SceneGeometry:
    """What the scene draws, in {O} (m): ``platform_points`` (m, 3) ``p + R pp_i``, ``anchors``
    (m, 3) ``b_i``, ``states`` per cable, the platform box (``box_center``, ``box_size`` in {P}
    axes, ``box_rotation`` R), ``axes_origin`` (3,) the moment reference point and ``axes``
    (3, 3) the body axes (x nose, y right wing, z down: rows), ``wind`` (start (3,), direction
    (3,), length) or None, ``force`` (start, vector (3,) N) or None."""

    position: FloatArray
    rotation: FloatArray
    platform_points: FloatArray
    anchors: FloatArray
    tensions_N: FloatArray
    states: list[str]
    box_center: FloatArray
    box_size: FloatArray
    axes_origin: FloatArray
    axes: FloatArray
    wind: tuple[FloatArray, FloatArray, float] | None
    force: tuple[FloatArray, FloatArray] | None


def scene_geometry(
    rig: Any,
    position_O_m: Sequence[float],
    R_O_P: Any,
    tension_N: Sequence[float],
    *,
    airspeed_mps: float | None = None,
    force_O_N: Sequence[float] | None = None,
    mrp_P_m: Sequence[float] = (0.0, 0.0, 0.0),
    nose_P: Sequence[float] = (-1.0, 0.0, 0.0),
    up_P: Sequence[float] = (0.0, 0.0, 1.0),
) -> SceneGeometry:
    """The scene at pose ``(p, R)`` with tensions ``tension_N`` (m,) (see :class:`SceneGeometry`).

    ``force_O_N``: the aerodynamic force (3,) at the MRP in {O} (the on-line result), drawn from
    the MRP; ``airspeed_mps``: the wind arrow, drawn upstream of the platform along +x of {O}
    (downstream) when above 1 m/s."""
    p = np.asarray(position_O_m, dtype=np.float64).reshape(3)
    R = np.asarray(R_O_P, dtype=np.float64).reshape(3, 3)
    pp = np.asarray(rig.attach_P_m, dtype=np.float64)
    ends = pp @ R.T + p
    lo, hi = pp.min(axis=0), pp.max(axis=0)
    size = np.maximum(hi - lo, 0.005)
    centre = R @ ((lo + hi) / 2) + p
    mrp = R @ np.asarray(mrp_P_m, dtype=np.float64) + p
    R_P_B = body_axes_in_platform(tuple(nose_P), tuple(up_P))  # columns: x_B, y_B, z_B in {P}
    axes = (R @ np.asarray(R_P_B, dtype=np.float64)).T  # rows: the body axes in {O}
    wind = None
    if airspeed_mps is not None and np.isfinite(airspeed_mps) and airspeed_mps > 1.0:
        span = float(np.ptp(np.asarray(rig.anchors_O_m)[:, 0])) or 1.0
        start = np.array([p[0] - 0.35 * span, p[1], p[2]])
        wind = (start, np.array([1.0, 0.0, 0.0]), WIND_ARROW_M[0] + WIND_ARROW_M[1] * airspeed_mps)
    force = None
    if force_O_N is not None and np.all(np.isfinite(force_O_N)):
        force = (mrp, np.asarray(force_O_N, dtype=np.float64).reshape(3))
    T = np.asarray(tension_N, dtype=np.float64)
    return SceneGeometry(
        p,
        R,
        ends,
        np.asarray(rig.anchors_O_m, dtype=np.float64),
        T,
        cable_states(T, rig.t_min_N, rig.t_max_N),
        centre,
        size,
        mrp,
        axes,
        wind,
        force,
    )


def _quat_xyzw(R: FloatArray) -> tuple[float, float, float, float]:
    w, x, y, z = (float(v) for v in quaternion_from_rotation(R))
    return x, y, z, w


def _arrow_rotation(direction: FloatArray) -> FloatArray:
    """A rotation taking +x (an arrow primitive's axis) onto ``direction``."""
    d = direction / np.linalg.norm(direction)
    a = np.array([1.0, 0.0, 0.0])
    v = np.cross(a, d)
    c = float(a @ d)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([-1.0, -1.0, 1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.asarray(np.eye(3) + vx + vx @ vx / (1 + c), dtype=np.float64)


def scene_update(
    g: SceneGeometry, t_ns: int, cable_names: Sequence[str], frame_id: str = "O"
) -> Any:
    """The ``foxglove.SceneUpdate`` of :func:`scene_geometry`'s result: entity ``rig`` (anchors,
    cables, platform box, tension labels; its metadata: the pose it is drawn at,
    ``position_O_m`` and ``quaternion_wxyz`` as JSON, and ``state_<cable>``), entity ``model``
    (body axes, wind and force arrows)."""
    from foxglove.messages import (
        ArrowPrimitive,
        Color,
        CubePrimitive,
        KeyValuePair,
        LinePrimitive,
        LinePrimitiveLineType,
        Point3,
        Pose,
        Quaternion,
        SceneEntity,
        SceneUpdate,
        SpherePrimitive,
        TextPrimitive,
        Timestamp,
        Vector3,
    )

    ts = Timestamp(*divmod(int(t_ns), 1_000_000_000))

    identity = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)

    def pose(at: Any, R: Any = None) -> Any:
        if R is None:
            q = identity
        else:
            x, y, z, w = _quat_xyzw(R)
            q = Quaternion(x=x, y=y, z=z, w=w)
        return Pose(position=Vector3(x=float(at[0]), y=float(at[1]), z=float(at[2])), orientation=q)

    def colour(rgba: Sequence[float]) -> Any:
        return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])

    lines = []
    texts = []
    for i, name in enumerate(cable_names):
        c = colour(COLOURS[g.states[i]])
        a, b = g.platform_points[i], g.anchors[i]
        lines.append(
            LinePrimitive(
                type=LinePrimitiveLineType.LineList,
                thickness=0.006,
                points=[Point3(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                        Point3(x=float(b[0]), y=float(b[1]), z=float(b[2]))],
                color=c,
            )
        )  # fmt: skip
        T = g.tensions_N[i]
        label = f"{name} {T:.1f} N" if np.isfinite(T) else f"{name} missing"
        if g.states[i] not in ("ok", "missing"):
            label += f" ({g.states[i]})"
        texts.append(
            TextPrimitive(
                pose=pose((a + b) / 2), billboard=True, font_size=12.0, scale_invariant=True,
                color=c, text=label,
            )
        )  # fmt: skip
    spheres = [
        SpherePrimitive(pose=pose(b), size=Vector3(x=0.02, y=0.02, z=0.02), color=colour(COLOURS["missing"]))
        for b in g.anchors
    ]  # fmt: skip
    cube = CubePrimitive(
        pose=pose(g.box_center, g.rotation),
        size=Vector3(x=float(g.box_size[0]), y=float(g.box_size[1]), z=float(g.box_size[2])),
        color=Color(r=0.8, g=0.8, b=0.85, a=0.6),
    )
    x, y, z, w = _quat_xyzw(g.rotation)
    where = [  # the pose the scene is drawn at
        KeyValuePair(key="position_O_m", value=json.dumps([float(v) for v in g.position])),
        KeyValuePair(key="quaternion_wxyz", value=json.dumps([w, x, y, z])),
    ]
    rig_entity = SceneEntity(
        timestamp=ts, frame_id=frame_id, id="rig", lines=lines, texts=texts, spheres=spheres,
        cubes=[cube],
        metadata=where + [KeyValuePair(key=f"state_{n}", value=s)
                          for n, s in zip(cable_names, g.states, strict=True)],
    )  # fmt: skip

    def arrow(at: Any, direction: Any, length: float, width: float, rgba: Sequence[float]) -> Any:
        """An arrow of ``length`` from ``at`` along ``direction`` (80 % shaft, 20 % head)."""
        return ArrowPrimitive(
            pose=pose(at, _arrow_rotation(np.asarray(direction, dtype=np.float64))),
            shaft_length=0.8 * length, shaft_diameter=width, head_length=0.2 * length,
            head_diameter=3 * width, color=colour(rgba),
        )  # fmt: skip

    axis_rgba = ((0.9, 0.1, 0.1, 1.0), (0.1, 0.8, 0.1, 1.0), (0.1, 0.3, 0.95, 1.0))
    arrows = [arrow(g.axes_origin, g.axes[k], AXIS_LENGTH_M, 0.004, axis_rgba[k]) for k in range(3)]
    if g.wind is not None:
        start, d, length = g.wind
        arrows.append(arrow(start, d, length, 0.01, (0.3, 0.75, 1.0, 0.8)))
    if g.force is not None and np.linalg.norm(g.force[1]) > 1e-9:
        start, F = g.force
        arrows.append(
            arrow(
                start,
                F,
                float(np.linalg.norm(F)) * FORCE_SCALE_M_PER_N,
                0.006,
                (1.0, 0.85, 0.0, 1.0),
            )
        )
    model = SceneEntity(timestamp=ts, frame_id=frame_id, id="model", arrows=arrows)
    return SceneUpdate(entities=[rig_entity, model])


def frame_transforms(position_O_m: Sequence[float], R_O_P: Any, t_ns: int) -> Any:
    """``foxglove.FrameTransforms`` with the transform from {O} (parent) to {P} (child)."""
    from foxglove.messages import FrameTransform, FrameTransforms, Quaternion, Timestamp, Vector3

    x, y, z, w = _quat_xyzw(np.asarray(R_O_P, dtype=np.float64))
    p = [float(v) for v in position_O_m]
    return FrameTransforms(
        transforms=[
            FrameTransform(
                timestamp=Timestamp(*divmod(int(t_ns), 1_000_000_000)),
                parent_frame_id="O",
                child_frame_id="P",
                translation=Vector3(x=p[0], y=p[1], z=p[2]),
                rotation=Quaternion(x=x, y=y, z=z, w=w),
            )
        ]
    )
