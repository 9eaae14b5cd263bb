"""Marker layouts: where the markers are on the model, in the platform frame {P} (or in {O}).

Two kinds:

- ``"fiducial"``: square ArUco/AprilTag markers of a dictionary, each with an id, a centre, a face
  normal, an in-plane x axis and a side length (the black square, as OpenCV counts it).  Its four
  corners follow OpenCV's order: top-left, top-right, bottom-right, bottom-left of the printed marker,
  i.e. ``(-s/2, +s/2), (+s/2, +s/2), (+s/2, -s/2), (-s/2, -s/2)`` in the marker's own (x, y).
- ``"points"``: passive point markers (retro-reflective IR disks like the paper's six marks), each
  with a label, a centre, a face normal and a disk radius.

TOML layout (loaded by ``cdpr.daq.vision_files.load_marker_layout``, schema ``LayoutFile``)::

    kind = "fiducial"            # or "points"
    frame = "P"                  # "O" for targets fixed in the tunnel (extrinsics)
    dictionary = "DICT_4X4_50"   # fiducial only
    quiet_zone_cells = 1.0       # white margin around each marker, in marker cells
    [[marker]]                   # fiducial: id, center_m, normal, x_axis, size_m
    id = 0
    center_m = [-0.11, 0.0, 0.027]
    normal = [0.0, 0.0, 1.0]
    x_axis = [1.0, 0.0, 0.0]
    size_m = 0.03
    [[point]]                    # points: label, center_m, normal, radius_m
    label = "nose"
    center_m = [-0.17, 0.0, 0.02]
    normal = [0.0, 0.0, 1.0]
    radius_m = 0.004
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cdpr.analysis.errors import ConfigError

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Fiducial:
    """One square marker: id, centre (3,) m, rotation R_F_M (3, 3) whose columns are the marker's
    x, y and normal axes in the layout frame F, and side length (m)."""

    id: int
    center_m: F64
    R_F_M: F64
    size_m: float

    @property
    def corners_m(self) -> F64:
        """(4, 3) corners in the layout frame, OpenCV order (TL, TR, BR, BL)."""
        h = self.size_m / 2
        local = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        return self.center_m + local @ self.R_F_M.T


@dataclass(frozen=True)
class PointMarker:
    """One point marker (a flat disk): label, centre (3,) m, unit normal (3,), radius (m)."""

    label: str
    center_m: F64
    normal: F64
    radius_m: float


@dataclass
class MarkerLayout:
    """A set of markers in one frame (``"P"`` on the platform or ``"O"`` fixed in the tunnel)."""

    kind: str
    frame: str = "P"
    dictionary: str = ""
    quiet_zone_cells: float = 1.0
    fiducials: list[Fiducial] = field(default_factory=list)
    points: list[PointMarker] = field(default_factory=list)
    name: str = ""

    @property
    def ids(self) -> NDArray[np.int64]:
        return np.array([f.id for f in self.fiducials], dtype=np.int64)

    @property
    def labels(self) -> list[str]:
        return [p.label for p in self.points]

    @property
    def fiducial_corners_m(self) -> F64:
        """(N, 4, 3) corners of every fiducial in layout order."""
        return (
            np.stack([f.corners_m for f in self.fiducials])
            if self.fiducials
            else np.zeros((0, 4, 3))
        )

    @property
    def point_centers_m(self) -> F64:
        """(N, 3) centres of every point marker in layout order."""
        return np.stack([p.center_m for p in self.points]) if self.points else np.zeros((0, 3))

    @property
    def point_normals(self) -> F64:
        return np.stack([p.normal for p in self.points]) if self.points else np.zeros((0, 3))

    def fiducial_by_id(self) -> dict[int, Fiducial]:
        return {f.id: f for f in self.fiducials}

    def to_mapping(self) -> dict[str, Any]:
        """TOML-ready mapping (inverse of :func:`layout_from_mapping`)."""
        out: dict[str, Any] = {"kind": self.kind, "frame": self.frame}
        if self.name:
            out["name"] = self.name
        if self.kind == "fiducial":
            out["dictionary"] = self.dictionary
            out["quiet_zone_cells"] = self.quiet_zone_cells
            out["marker"] = [
                {
                    "id": f.id,
                    "center_m": f.center_m.tolist(),
                    "normal": f.R_F_M[:, 2].tolist(),
                    "x_axis": f.R_F_M[:, 0].tolist(),
                    "size_m": f.size_m,
                }
                for f in self.fiducials
            ]
        else:
            out["point"] = [
                {
                    "label": p.label,
                    "center_m": p.center_m.tolist(),
                    "normal": p.normal.tolist(),
                    "radius_m": p.radius_m,
                }
                for p in self.points
            ]
        return out


def _frame_from_axes(normal: F64, x_axis: F64) -> F64:
    n = normal / np.linalg.norm(normal)
    x = x_axis - n * (x_axis @ n)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(n, x), n], axis=1)


def layout_from_mapping(data: dict[str, Any], source: str = "<layout>") -> MarkerLayout:
    """A :class:`MarkerLayout` from its mapping, whose keys, types and shapes a schema has checked
    (:class:`cdpr.daq.vision_files.LayoutFile`; ``load_marker_layout`` does both); here what
    relates them: the kind's own keys, a dictionary name or file, ids and labels unique, enough
    markers, a non-zero normal and an x axis not along it.  Errors name the file and key."""
    kind, frame = data["kind"], data.get("frame", "P")
    own = {"fiducial": ("dictionary", "quiet_zone_cells", "marker"), "points": ("point",)}
    for key in ("dictionary", "quiet_zone_cells", "marker", "point"):
        if key in data and key not in own[kind]:
            raise ConfigError(source, key, f"not a key of a {kind} layout")
    layout = MarkerLayout(kind=kind, frame=frame, name=str(data.get("name", "")))
    if kind == "fiducial":
        dictionary = data.get("dictionary")
        is_file = isinstance(dictionary, str) and dictionary.lower().endswith(
            (".yml", ".yaml", ".json", ".xml")
        )
        if not isinstance(dictionary, str) or not (dictionary.startswith("DICT_") or is_file):
            raise ConfigError(
                source,
                "dictionary",
                "expected a name like 'DICT_4X4_50' or a dictionary file (.yml, .yaml, .json, "
                f".xml), got {dictionary!r}",
            )
        if is_file and not os.path.isabs(dictionary) and source not in ("", "<layout>"):
            # a custom dictionary file is found beside the layout file
            dictionary = os.path.join(os.path.dirname(os.path.abspath(source)), dictionary)
        layout.dictionary = dictionary
        layout.quiet_zone_cells = float(data.get("quiet_zone_cells", 1.0))
        items = data.get("marker") or []
        if not items:
            raise ConfigError(source, "marker", "expected at least one [[marker]] table")
        seen: set[int] = set()
        for i, m in enumerate(items):
            where = f"marker[{i}]"
            if m["id"] in seen:
                raise ConfigError(source, f"{where}.id", f"duplicate marker id {m['id']}")
            seen.add(m["id"])
            normal = np.asarray(m["normal"], np.float64)
            x_axis = np.asarray(m["x_axis"], np.float64)
            if np.linalg.norm(normal) < 1e-9 or np.linalg.norm(np.cross(normal, x_axis)) < 1e-9:
                raise ConfigError(
                    source, f"{where}.x_axis", "must be non-zero and not parallel to normal"
                )
            layout.fiducials.append(
                Fiducial(
                    m["id"],
                    np.asarray(m["center_m"], np.float64),
                    _frame_from_axes(normal, x_axis),
                    float(m["size_m"]),
                )
            )
    else:
        items = data.get("point") or []
        if len(items) < 4:
            raise ConfigError(source, "point", "expected at least four [[point]] tables")
        labels: set[str] = set()
        for i, m in enumerate(items):
            where = f"point[{i}]"
            label = m["label"]
            if label in labels:
                raise ConfigError(source, f"{where}.label", f"duplicate label {label!r}")
            labels.add(label)
            normal = np.asarray(m.get("normal", (0.0, 0.0, 1.0)), np.float64)
            if np.linalg.norm(normal) < 1e-9:
                raise ConfigError(source, f"{where}.normal", "must be non-zero")
            layout.points.append(
                PointMarker(
                    label,
                    np.asarray(m["center_m"], np.float64),
                    normal / np.linalg.norm(normal),
                    float(m["radius_m"]),
                )
            )
    return layout


# ---------------------------------------------------------------------------------------------
# The flat prototype's SDM aircraft model (fuselage 53.9 mm, length 377.6 mm, span 244.1 mm) with
# {P} at the platform centre inside the fuselage, x toward the tail (downstream), z up.  The marker
# positions are our assumptions (the paper gives none); the six IR marks are placed asymmetrically
# and not in one plane so that no rigid motion maps the set onto itself (no mirror labelling).
FUSELAGE_RADIUS_M = 0.0539 / 2
MODEL_LENGTH_M = 0.3776
MODEL_SPAN_M = 0.2441


def flat_prototype_fiducial_layout() -> MarkerLayout:
    """Six 30 mm ArUco markers (DICT_4X4_50, ids 0-5) on the fuselage top and the wings."""
    z_top, z_wing = FUSELAGE_RADIUS_M, 0.006
    centres = {
        0: (-0.110, 0.0, z_top),
        1: (0.100, 0.0, z_top),
        2: (-0.005, 0.055, z_wing),
        3: (0.005, 0.100, z_wing),
        4: (-0.005, -0.055, z_wing),
        5: (0.005, -0.100, z_wing),
    }
    return MarkerLayout(
        kind="fiducial",
        dictionary="DICT_4X4_50",
        quiet_zone_cells=1.0,
        name="SDM model, six ArUco markers",
        fiducials=[
            Fiducial(
                i,
                np.array(c),
                _frame_from_axes(np.array([0.0, 0, 1]), np.array([1.0, 0, 0])),
                0.030,
            )
            for i, c in centres.items()
        ],
    )


def flat_prototype_points_layout() -> MarkerLayout:
    """Six retro-reflective disks (radius 4 mm) like the paper's six IR marks."""
    pts = [
        ("nose", (-0.170, 0.000, 0.018), (-0.5, 0.0, 0.866)),
        ("cockpit", (-0.080, 0.000, FUSELAGE_RADIUS_M), (0.0, 0.0, 1.0)),
        ("wing_left_tip", (0.000, 0.105, 0.006), (0.0, 0.0, 1.0)),
        ("wing_right_mid", (0.015, -0.075, 0.006), (0.0, 0.0, 1.0)),
        ("fin_top", (0.165, 0.000, 0.070), (0.0, -0.6, 0.8)),
        ("fuselage_rear", (0.110, 0.012, 0.024), (0.0, 0.4, 0.9165)),
    ]
    return MarkerLayout(
        kind="points",
        name="SDM model, six IR marks",
        points=[
            PointMarker(lab, np.array(c), np.array(n) / np.linalg.norm(n), 0.004)
            for lab, c, n in pts
        ],
    )
