"""A camera that delivers the platform pose, not frames: what a motion-capture system (or a camera
with on-board marker tracking) sends, and the virtual rig's fast camera (200 Hz and more, where
rendering and measuring frames, :class:`cdpr.daq.camera_source.VirtualCameraSource`, takes tens of
ms a frame).

:class:`PoseCameraSource` samples ``pose_at(t_ns)`` (the virtual rig's
:meth:`~cdpr.daq.virtual_rig.VirtualRig.camera_pose_at`, which puts the camera's clock offset in)
at ``t_start + k / rate_hz`` of its own clock and adds white noise: ``position_sd_m`` on each axis
of the position and a small rotation of ``rotation_sd_rad`` on each axis in {O}
(``R = exp([dtheta]) R_true``).  Its ``"pose"`` readings carry the same fields as the camera's
(``position_O_m``, ``quaternion_wxyz``, ``euler_rad``, ``reprojection_px`` (NaN: no image),
``covariance`` the diagonal 6x6 of that noise in the order ``[position_O_m, rotation_O_rad]``,
``flags`` 0, ``n_points`` 0, ``frame_index``), stamped with the camera's clock.  In real time it
returns, at each read, every frame whose time has come (one batch, never a sleep per frame).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from cdpr.analysis.errors import ConfigError
from cdpr.analysis.rotations import euler_from_rotation, quaternion_from_rotation

from .source import FieldDescription, Reading, Source, StreamDescription, now_ns

PoseAt = Callable[[Any], tuple[ArrayLike, ArrayLike]]

MAX_BATCH = 10_000
"""Most frames one read returns (a reader far behind catches up over several reads)."""


def pose_stream(rate_hz: float, doc: str) -> StreamDescription:
    """The ``"pose"`` stream of a camera (its fields; both camera sources share them)."""
    return StreamDescription(
        {
            "position_O_m": FieldDescription("m", shape=(3,)),
            "quaternion_wxyz": FieldDescription("", shape=(4,)),
            "euler_rad": FieldDescription("rad", shape=(3,)),
            "reprojection_px": FieldDescription("px"),
            "covariance": FieldDescription("m, rad (6x6 row-major)", shape=(36,)),
            "flags": FieldDescription("", "int64"),
            "n_points": FieldDescription("", "int64"),
            "frame_index": FieldDescription("", "int64"),
        },
        rate_hz,
        doc,
    )


class PoseCameraSource(Source):
    """Poses at ``rate_hz`` from ``pose_at`` with white noise (see the module docstring).

    pose_at: ``pose_at(t_ns (n,)) -> (position_O_m (n, 3), R_O_P (n, 3, 3))``; realtime: frames
    when the host clock reaches them (else every read returns the next ``batch`` frames at once:
    a fast simulation); seed: the noise's.
    """

    kind = "pose_camera"

    def __init__(
        self,
        name: str,
        pose_at: PoseAt,
        rate_hz: float = 200.0,
        position_sd_m: float = 5.0e-5,
        rotation_sd_rad: float = 1.7453292519943295e-4,
        realtime: bool = True,
        seed: int | None = None,
        t_start_ns: int | None = None,
        batch: int = 100,
    ) -> None:
        super().__init__(name)
        for key, v in (("position_sd_m", position_sd_m), ("rotation_sd_rad", rotation_sd_rad)):
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError("<config>", f"sources.{name}.{key}", f"expected >= 0, got {v}")
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ConfigError("<config>", f"sources.{name}.rate_hz", f"expected > 0, got {rate_hz}")
        self.pose_at = pose_at
        self.rate_hz = float(rate_hz)
        self.position_sd_m = float(position_sd_m)
        self.rotation_sd_rad = float(rotation_sd_rad)
        self.realtime = bool(realtime)
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.t_start_ns = t_start_ns
        self.batch = int(batch)
        self._k = 0
        cov = np.diag([self.position_sd_m**2] * 3 + [self.rotation_sd_rad**2] * 3)
        self._covariance = cov.reshape(-1).tolist()

    def settings(self) -> dict[str, Any]:
        return {
            "rate_hz": self.rate_hz,
            "position_sd_m": self.position_sd_m,
            "rotation_sd_rad": self.rotation_sd_rad,
            "realtime": self.realtime,
            "seed": self.seed,
        }

    def describe(self) -> dict[str, StreamDescription]:
        return {
            "pose": pose_stream(
                self.rate_hz,
                "platform pose of {P} in {O} from a pose camera (no frames), stamped with the "
                "camera's clock; covariance order [position_O_m, rotation_O_rad]",
            )
        }

    def _open(self) -> None:
        if self.t_start_ns is None:
            self.t_start_ns = now_ns()
        self._k = 0

    def _close(self) -> None:
        pass

    def _frame_ns(self, k: np.ndarray) -> np.ndarray:
        assert self.t_start_ns is not None
        return self.t_start_ns + np.round(k * (1e9 / self.rate_hz)).astype(np.int64)

    def _read(self, timeout_s: float) -> list[Reading]:
        if self.realtime:
            k_next = np.array([self._k])
            wait = (int(self._frame_ns(k_next)[0]) - now_ns()) * 1e-9
            if wait > timeout_s:
                time.sleep(max(timeout_s, 0.0))
                return []
            if wait > 0:
                time.sleep(wait)
            assert self.t_start_ns is not None
            due = int((now_ns() - self.t_start_ns) * self.rate_hz // 1e9) + 1
            n = max(1, min(due - self._k, MAX_BATCH))
        else:
            n = self.batch
        k = np.arange(self._k, self._k + n)
        self._k += n
        t = self._frame_ns(k)
        p, R = self.pose_at(t)
        p = np.asarray(p, np.float64).reshape(n, 3)
        R = np.asarray(R, np.float64).reshape(n, 3, 3)
        p = p + self.position_sd_m * self.rng.standard_normal((n, 3))
        dR = Rotation.from_rotvec(self.rotation_sd_rad * self.rng.standard_normal((n, 3)))
        R = dR.as_matrix() @ R
        quat = quaternion_from_rotation(R)
        eul = euler_from_rotation(R)
        return [
            Reading(
                "pose",
                int(t[i]),
                {
                    "position_O_m": p[i].tolist(),
                    "quaternion_wxyz": quat[i].tolist(),
                    "euler_rad": eul[i].tolist(),
                    "reprojection_px": float("nan"),
                    "covariance": self._covariance,
                    "flags": 0,
                    "n_points": 0,
                    "frame_index": int(k[i]),
                },
            )
            for i in range(n)
        ]
