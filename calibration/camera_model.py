"""Camera model: intrinsics, lens distortion and extrinsics to the tunnel frame {O}.

Conventions (OpenCV's): pixel centres at integer coordinates, the top-left pixel covers
``[-0.5, 0.5]^2``; camera frame {C} with x right, y down, z along the optical axis.  A point
``x_O`` in {O} maps to ``x_C = R_C_O @ (x_O - position_O_m)``; ``R_O_C = R_C_O.T`` and
``position_O_m`` (the optical centre in {O}) are what the JSON file stores.  Distortion is the OpenCV
model ``[k1, k2, p1, p2, k3]`` (or the 8-term rational model).

JSON layout (``camera.json``)::

    {"id": "cam-1a2b3c4d", "name": "...", "image_size_px": [1280, 1024],
     "camera_matrix": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "dist_coeffs": [k1, k2, p1, p2, k3],
     "extrinsics": {"R_O_C": [[...]], "position_O_m": [x, y, z], "method": "...", ...},
     "calibration": {...}}          # rms_px, std devs, per-view rms, ... (optional)

The id is a hash of the numbers (stable: the same model gives the same id).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.analysis.errors import ConfigError, InputError

F64 = NDArray[np.float64]


@dataclass
class CameraModel:
    """Intrinsics, distortion, image size and extrinsics of one camera.

    K: camera matrix (3, 3), px.  dist: distortion coefficients (5,) or (8,).
    image_size_px: (width, height).  R_O_C: rotation (3, 3) mapping {C} components to {O}.
    position_O_m: optical centre in {O} (3,), m.  calibration: free-form record of how the model
    was obtained (rms, standard deviations, files); extrinsics_info likewise for the extrinsics.
    """

    K: F64
    dist: F64
    image_size_px: tuple[int, int]
    R_O_C: F64 = field(default_factory=lambda: np.eye(3))
    position_O_m: F64 = field(default_factory=lambda: np.zeros(3))
    name: str = "camera"
    calibration: dict[str, Any] = field(default_factory=dict)
    extrinsics_info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.dist = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if self.dist.size not in (4, 5, 8):
            raise InputError(f"dist: expected 4, 5 or 8 coefficients, got {self.dist.size}")
        self.image_size_px = (int(self.image_size_px[0]), int(self.image_size_px[1]))
        self.R_O_C = np.asarray(self.R_O_C, dtype=np.float64).reshape(3, 3)
        self.position_O_m = np.asarray(self.position_O_m, dtype=np.float64).reshape(3)
        err = np.abs(self.R_O_C @ self.R_O_C.T - np.eye(3)).max()
        if err > 1e-6 or np.linalg.det(self.R_O_C) < 0:
            raise InputError(
                f"R_O_C: expected a rotation matrix, got one with |RR^T - I| = {err:g}"
            )

    # -- convenience ------------------------------------------------------------------------
    @property
    def width(self) -> int:
        return self.image_size_px[0]

    @property
    def height(self) -> int:
        return self.image_size_px[1]

    @property
    def R_C_O(self) -> F64:
        return self.R_O_C.T

    @property
    def id(self) -> str:
        """Stable id: ``cam-`` + first 8 hex digits of a hash of the model's numbers."""
        h = hashlib.sha256()
        for a in (self.K, self.dist, self.R_O_C, self.position_O_m):
            h.update(np.round(np.asarray(a, np.float64), 12).tobytes())
        h.update(repr(self.image_size_px).encode())
        return "cam-" + h.hexdigest()[:8]

    def pose_C_P(self, position_O_m: ArrayLike, R_O_P: ArrayLike) -> tuple[F64, F64]:
        """Platform pose in the camera frame: ``(R_C_P (3, 3), t_C_P (3,) m)`` from a pose in {O}."""
        R_C_P = self.R_C_O @ np.asarray(R_O_P, np.float64)
        t = self.R_C_O @ (np.asarray(position_O_m, np.float64) - self.position_O_m)
        return R_C_P, t

    def pose_O_from_C(self, R_C_P: ArrayLike, t_C_P: ArrayLike) -> tuple[F64, F64]:
        """Platform pose in {O}: ``(position_O_m (3,), R_O_P (3, 3))`` from one in {C}."""
        R_O_P = self.R_O_C @ np.asarray(R_C_P, np.float64)
        p = self.R_O_C @ np.asarray(t_C_P, np.float64) + self.position_O_m
        return p, R_O_P

    def with_extrinsics(
        self, R_O_C: ArrayLike, position_O_m: ArrayLike, info: dict[str, Any] | None = None
    ) -> CameraModel:
        """A copy with new extrinsics."""
        return CameraModel(
            self.K.copy(),
            self.dist.copy(),
            self.image_size_px,
            np.asarray(R_O_C, np.float64),
            np.asarray(position_O_m, np.float64),
            self.name,
            dict(self.calibration),
            dict(info or {}),
        )

    def scaled_to(self, width: int, height: int) -> CameraModel:
        """The same lens on a sensor resampled to ``width x height`` (K scaled, pixel-centre aware)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return CameraModel(
            K, self.dist.copy(), (width, height), self.R_O_C, self.position_O_m, self.name
        )

    # -- serialisation ----------------------------------------------------------------------
    def to_mapping(self) -> dict[str, Any]:
        """The JSON-ready mapping (see the module docstring)."""
        return {
            "id": self.id,
            "name": self.name,
            "model": "opencv-pinhole",
            "pixel_convention": "pixel centres at integer coordinates (OpenCV)",
            "image_size_px": list(self.image_size_px),
            "camera_matrix": self.K.tolist(),
            "dist_coeffs": self.dist.tolist(),
            "extrinsics": {
                "R_O_C": self.R_O_C.tolist(),
                "position_O_m": self.position_O_m.tolist(),
                **self.extrinsics_info,
            },
            "calibration": self.calibration,
        }

    def to_json(self) -> str:
        return json.dumps(_jsonable(self.to_mapping()), indent=2) + "\n"

    def opencv_entries(self) -> dict[str, Any]:
        """Entries of the OpenCV FileStorage YAML export (names as OpenCV's own samples use)."""
        R_C_O = self.R_C_O
        t_C_O = -R_C_O @ self.position_O_m
        return {
            "camera_id": self.id,
            "image_width": self.width,
            "image_height": self.height,
            "camera_matrix": self.K,
            "distortion_coefficients": self.dist.reshape(1, -1),
            "R_C_O": R_C_O,
            "t_C_O_m": t_C_O.reshape(3, 1),
            "avg_reprojection_error": float(self.calibration.get("rms_px", -1.0)),
        }


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def camera_from_mapping(data: dict[str, Any], source: str = "<camera>") -> CameraModel:
    """A :class:`CameraModel` from its JSON mapping, whose keys, types and shapes a schema has
    checked (:class:`cdpr.daq.vision_files.CameraFile`; ``load_camera`` does both); here what
    relates the numbers: the camera matrix's form, 4, 5 or 8 distortion terms, a rotation."""
    K = np.asarray(data["camera_matrix"], dtype=np.float64)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1 or K[1, 0] or K[2, 0] or K[2, 1]:
        raise ConfigError(
            source, "camera_matrix", "expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]], fx, fy > 0"
        )
    dist = np.asarray(data["dist_coeffs"], dtype=np.float64).reshape(-1)
    if dist.size not in (4, 5, 8):
        raise ConfigError(source, "dist_coeffs", f"expected 4, 5 or 8 numbers, got {dist.size}")
    width, height = data["image_size_px"]
    ext = dict(data.get("extrinsics") or {})
    R = np.asarray(ext.pop("R_O_C", np.eye(3)), dtype=np.float64)
    p = np.asarray(ext.pop("position_O_m", np.zeros(3)), dtype=np.float64)
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ConfigError(source, "extrinsics.R_O_C", "expected a rotation matrix")
    return CameraModel(
        K,
        dist,
        (int(width), int(height)),
        R,
        p,
        str(data.get("name", "camera")),
        dict(data.get("calibration") or {}),
        ext,
    )


def look_at(
    eye_O_m: ArrayLike, target_O_m: ArrayLike, up_O: ArrayLike = (0.0, 0.0, 1.0)
) -> tuple[F64, F64]:
    """Extrinsics of a camera at ``eye_O_m`` looking at ``target_O_m``: ``(R_O_C, position_O_m)``.

    Image "up" (-y_C) is as close as possible to ``up_O``.
    """
    eye = np.asarray(eye_O_m, np.float64)
    z = np.asarray(target_O_m, np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up_O, np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1), eye
