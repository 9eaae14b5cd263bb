"""Camera sources: platform pose from marker images, and optionally the compressed frames.

:class:`CameraSource` reads ``cv2.VideoCapture`` (device index or video file, through the adapter
:mod:`cdpr.calibration.cv`) or a folder of images; :class:`VirtualCameraSource` renders frames at the
virtual rig's true pose (a ``pose_at(t_ns) -> (position_O_m, R_O_P)`` callable).  Both produce:

- ``"pose"`` readings (every frame): ``position_O_m`` (3,), ``quaternion_wxyz`` (4,) scalar first
  (the name the MCAP pose codec maps to Foxglove's orientation), ``euler_rad`` (3,) Z-Y-X,
  ``reprojection_px`` (RMS, px), ``covariance`` (36,) = the 6x6 ``[position_O_m, rotation_O_rad]``
  covariance row-major, ``flags`` (bits of :mod:`cdpr.calibration.pose` ``FLAG_*``), ``n_points``,
  ``frame_index``; status ``STATUS_BAD_FRAME`` when the pose is unusable (NaN or flagged).
- ``"image"`` readings (every ``image_every``-th frame, or at most ``image_rate_hz`` per second of
  frame time; 0 = never): ``data`` (JPEG/PNG bytes),
  ``format`` (``"jpeg"``/``"png"``), ``width``, ``height``, ``frame_index``, ``frame_id``.

Timestamps: device frames get the host time at grab; video files the open time plus the frame's
position in the file; image folders the open time plus ``index / fps``.  Dropped frames: for a device,
gaps of more than 1.5 frame periods (``fps`` known) count ``period``-sized losses in ``stats.lost``;
unreadable files in a folder count as lost.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import block_diag

from cdpr.analysis.errors import ConfigError
from cdpr.calibration import cv
from cdpr.calibration.camera_model import CameraModel
from cdpr.calibration.detect import (
    SATURATION_MAX_FRACTION,
    BlobSettings,
    FiducialDetector,
    PointMatcher,
    check_blob_shapes,
    check_frame,
    detect_blobs,
    edge_fit_corner_covariance,
    saturated_fraction,
)
from cdpr.calibration.markers import MarkerLayout
from cdpr.calibration.pose import (
    BAD_FLAGS,
    FLAG_NO_POSE,
    FLAG_OCCLUDED_MARK,
    FLAG_SATURATED,
    PoseEstimate,
    estimate_pose,
    estimate_pose_single_marker,
    failed_pose,
)
from cdpr.calibration.render import RenderSettings, VirtualCamera

from .pose_camera import pose_stream
from .schema import parse, plain
from .source import STATUS_BAD_FRAME, FieldDescription, Reading, Source, StreamDescription, now_ns
from .vision_files import BlobDetection, load_camera, load_marker_layout

PoseAt = Callable[[int], tuple[ArrayLike, ArrayLike]]


def _camera(camera: CameraModel | str) -> CameraModel:
    if isinstance(camera, CameraModel):
        return camera
    return load_camera(camera)


def _layout(layout: MarkerLayout | str) -> MarkerLayout:
    if isinstance(layout, MarkerLayout):
        return layout
    return load_marker_layout(layout)


class FramePoseEstimator:
    """Pose of {P} from one gray frame, for either layout kind, with frame-to-frame tracking.

    sigma_px: detector noise per image coordinate (px) used for the covariance; defaults are the
    values measured on rendered frames (docs/vision.md).  reference: the nominal pose used to
    acquire point markers (defaults to the camera's ``looks_at_O_m`` with R = I).  track: False
    for unrelated snapshots (a folder of photographs): every frame is then acquired from scratch,
    no search around the last pose.
    """

    def __init__(
        self,
        camera: CameraModel,
        layout: MarkerLayout,
        sigma_px: float | None = None,
        reference: tuple[ArrayLike, ArrayLike] | None = None,
        blob_settings: BlobSettings | None = None,
        track: bool = True,
    ) -> None:
        self.camera, self.layout = camera, layout
        self.track = bool(track)
        self._n_frames = 0
        if reference is None:
            p0 = camera.extrinsics_info.get("looks_at_O_m", [0.0, 0.0, 0.0])
            reference = (np.asarray(p0, np.float64), np.eye(3))
        ref = (np.asarray(reference[0], np.float64), np.asarray(reference[1], np.float64))
        if layout.kind == "fiducial":
            self.sigma_px = FIDUCIAL_SIGMA_PX if sigma_px is None else float(sigma_px)
            self._fid = FiducialDetector(layout, camera)
            self._pos = {int(m): k for k, m in enumerate(layout.ids)}
            self._corners = layout.fiducial_corners_m  # (M, 4, 3), cached
            self._last: PoseEstimate | None = None
            self._prev: PoseEstimate | None = None
            # corner noise measured on multi-marker frames (RSS, dof; forgetting beyond
            # NOISE_DOF_MAX): the prior of a single-marker pose's 2-dof noise estimate
            self._noise_rss_px2 = 0.0
            self._noise_dof = 0.0
        else:
            self.sigma_px = POINT_SIGMA_PX if sigma_px is None else float(sigma_px)
            self._pm = PointMatcher(layout, camera, ref, sigma_px=self.sigma_px)
            self._blob = blob_settings or BlobSettings()

    @property
    def blob_settings(self) -> BlobSettings | None:
        """The IR-mark detector's settings (None for a fiducial layout)."""
        return self._blob if self.layout.kind == "points" else None

    def _learn_noise(self, est: PoseEstimate) -> None:
        """Pool a good multi-marker frame's residuals into the running corner-noise estimate."""
        self._noise_rss_px2 += est.extra["sigma_px"] ** 2 * est.extra["dof"]
        self._noise_dof += est.extra["dof"]
        if self._noise_dof > NOISE_DOF_MAX:  # forget old frames (the noise may change)
            k = NOISE_DOF_MAX / self._noise_dof
            self._noise_rss_px2 *= k
            self._noise_dof *= k

    def _single_marker(
        self,
        obj: NDArray[np.float64],
        img: NDArray[np.float64],
        guess: Any,
        shape: Any,
        edge_noise: NDArray[np.float64],
    ) -> PoseEstimate:
        """One marker's pose (flagged ``single_marker``; ``ambiguous`` if the planar flip is not
        ruled out).  The 2-dof noise estimate is pooled with the corner noise measured on this
        camera's earlier multi-marker frames (up to ``SINGLE_PRIOR_DOF`` dof) when there are some,
        else with the corner noise its own edge samples show (``edge_noise`` ``[RSS, dof, rho]``
        of the samples about their lines and the correlation of neighbouring ones, through
        ``shape``, the corners' covariance per unit sample variance), else with the nominal
        ``sigma_px`` (``extra["sigma_prior_dof"]`` = 0)."""
        rss_e, dof_e, rho = (float(x) for x in np.asarray(edge_noise).reshape(3))
        # neighbouring edge samples err alike (pixel phase, blur): a line's offset and angle then
        # vary by (1 + rho) / (1 - rho) more than independent samples' would (AR(1) errors)
        rss_e *= (1.0 + rho) / (1.0 - rho)
        if self._noise_dof >= 10:
            prior_px = float(np.sqrt(self._noise_rss_px2 / self._noise_dof))
            prior_dof = min(self._noise_dof, SINGLE_PRIOR_DOF)
            est = estimate_pose_single_marker(
                obj, img, self.camera, prior_px, guess, prior_dof, noise_shape=shape
            )
        elif np.isfinite(rss_e) and dof_e >= 10:
            prior_px = float(np.sqrt(rss_e / dof_e * np.mean(np.diag(shape))))
            prior_dof = EDGE_PRIOR_DOF
            est = estimate_pose_single_marker(
                obj, img, self.camera, prior_px, guess, prior_dof, noise_shape=shape
            )
        else:
            prior_px, prior_dof = self.sigma_px, 0.0
            est = estimate_pose_single_marker(
                obj, img, self.camera, prior_px, guess, noise_shape=shape
            )
        est.extra["sigma_prior_px"] = prior_px
        est.extra["sigma_prior_dof"] = prior_dof
        return est

    def reset(self) -> None:
        """Forget the last poses: the next frame is acquired from scratch."""
        if self.layout.kind == "fiducial":
            self._last = self._prev = None
        else:
            self._pm.reset()

    def estimate(self, gray: NDArray[np.uint8], name: str | None = None) -> PoseEstimate:
        """The pose in this frame (flags say when it is not usable).

        Raises :class:`InputError` naming the frame (``name``, e.g. its file; default "frame N",
        N counted from 0 by this estimator) when it is not gray uint8 of the camera model's size
        (both marker kinds: a resized frame would give a pose far off, silently)."""
        self._n_frames += 1
        check_frame(gray, self.camera.image_size_px, name or f"frame {self._n_frames - 1}")
        if not self.track:  # unrelated snapshots: every frame acquired from scratch
            self.reset()
        if self.layout.kind == "fiducial":
            pred = None
            guess = None
            if self._last is not None:
                r, t = self._last.rvec_C, self._last.tvec_C_m
                if self._prev is not None:  # constant-velocity prediction from the last two poses
                    R1, R0 = cv.rodrigues(r), cv.rodrigues(self._prev.rvec_C)
                    r = cv.rotation_vector(R1 @ R0.T @ R1)
                    t = 2 * t - self._prev.tvec_C_m
                guess = (r, t)
                pred = cv.project_points(
                    self._corners.reshape(-1, 3), r, t, self.camera.K, self.camera.dist
                ).reshape(-1, 4, 2)
            ids, corners = self._fid.detect(gray, pred)
            if len(ids) == 0:
                self._last = self._prev = None
                return failed_pose()
            obj = self._corners[[self._pos[int(i)] for i in ids]].reshape(-1, 3)
            shape = block_diag(*edge_fit_corner_covariance(corners))
            if len(ids) == 1:
                est = self._single_marker(
                    obj, corners.reshape(-1, 2), guess, shape, self._fid.edge_noise[0]
                )
            else:
                est = estimate_pose(
                    obj,
                    corners.reshape(-1, 2),
                    self.camera,
                    self.sigma_px,
                    guess=guess,
                    noise_shape=shape,
                )
            sat = saturated_fraction(gray, corners)
            est.extra["saturated_fraction"] = float(sat.max())
            if np.any(sat > SATURATION_MAX_FRACTION):
                est.flags |= FLAG_SATURATED
            elif len(ids) > 1 and not (est.flags & BAD_FLAGS):
                self._learn_noise(est)
            self._prev = self._last
            self._last = est if not (est.flags & BAD_FLAGS) else None
            return est
        pred = None
        last = self._pm._last
        if last is not None:
            pred = cv.project_points(
                self.layout.point_centers_m, last[0], last[1], self.camera.K, self.camera.dist
            )
        blobs = detect_blobs(gray, self._blob, pred)
        if pred is not None and len(blobs) < len(self.layout.points):
            blobs = detect_blobs(gray, self._blob, None)
        res = self._pm.match(blobs)
        if self._blob.shape_check and not res.flags & FLAG_NO_POSE:
            # compare each blob with its mark's projected disk: the most damaged blob (a cable
            # across the mark) is dropped, the pose refitted and the others checked again at the
            # new pose, until none is damaged (a damaged blob drawn into the pose can push intact
            # marks off their outlines); a damaged or lost mark is flagged
            first, dropped = res, np.zeros(0, np.int64)
            while True:
                chk = check_blob_shapes(
                    gray,
                    self.layout,
                    self.camera,
                    res.pose.rvec_C,
                    res.pose.tvec_C_m,
                    first.labels,
                    self._blob,
                )
                worse = chk.damaged[~np.isin(chk.damaged, dropped)]
                if not len(worse) or res.flags & FLAG_NO_POSE:
                    break
                dropped = np.append(dropped, worse[0])
                res = self._pm.drop_marks(first, blobs, dropped)
            if len(dropped) or len(chk.lost):
                res.pose.flags |= FLAG_OCCLUDED_MARK
            for key, v in (("notch_max", np.abs(chk.notch_depth)), ("bias_max_px", chk.bias_px)):
                v = v[np.isfinite(v)]
                res.pose.extra[key] = float(v.max()) if v.size else float("nan")
            rim = chk.rim_residual_px[np.isfinite(chk.rim_residual_px)]
            res.pose.extra["rim_residual_max_px"] = float(rim.max()) if rim.size else float("nan")
            res.pose.extra["occluded_marks"] = float(len(dropped) + len(chk.lost))
        return res.pose


NOISE_DOF_MAX = 400.0
"""Degrees of freedom of the running corner-noise estimate (about 20 six-marker frames)."""

SINGLE_PRIOR_DOF = 60.0
"""At most this many prior degrees of freedom pooled into a single-marker pose's noise estimate."""

EDGE_PRIOR_DOF = 4.0
"""Degrees of freedom given to a lone marker's own edge-sample noise as the prior of its corner
noise (with the corners' 2 residual dof: 6, as ``pose.MIN_NOISE_DOF`` fills in).  Not the samples'
56: their scatter about straight lines misses what errs alike along a whole edge (the blur of a
neighbouring edge one cell away, pixel phase), which only the corners' own residuals can show;
weighted by 56 it made the covariance too small (on rendered markers at the scale of OpenCV's
tutorial photo, 80-83 % of NEES within the chi-square 99 % bound; with 4, 88-90 %)."""

FIDUCIAL_SIGMA_PX = 0.020
"""Effective corner noise (px) of the edge-refined fiducial corners on our rendered frames, the value
whose covariance matches the observed pose errors (NEES ~ 6; docs/vision.md)."""

POINT_SIGMA_PX = 0.020
"""Effective centroid noise (px) of IR blobs on our rendered frames (same calibration)."""


def pose_reading(t_ns: int, est: PoseEstimate, frame_index: int, stream: str = "pose") -> Reading:
    """A ``"pose"`` reading from a :class:`PoseEstimate`."""
    bad = bool(est.flags & BAD_FLAGS) or not np.all(np.isfinite(est.position_O_m))
    values = {
        "position_O_m": est.position_O_m.tolist(),
        "quaternion_wxyz": est.q_wxyz.tolist()
        if np.all(np.isfinite(est.R_O_P))
        else [float("nan")] * 4,
        "euler_rad": est.euler_rad.tolist()
        if np.all(np.isfinite(est.R_O_P))
        else [float("nan")] * 3,
        "reprojection_px": float(est.reprojection_rms_px),
        "covariance": np.asarray(est.covariance, np.float64).reshape(-1).tolist(),
        "flags": int(est.flags),
        "n_points": int(est.n_points),
        "frame_index": int(frame_index),
    }
    return Reading(stream, int(t_ns), values, STATUS_BAD_FRAME if bad else 0)


def _describe(
    rate_hz: float, image_every: int, image_rate_hz: float = 0.0
) -> dict[str, StreamDescription]:
    d = {
        "pose": pose_stream(
            rate_hz,
            "platform pose of {P} in {O} from the camera; covariance order [position_O_m, rotation_O_rad]",
        )
    }
    if image_every or image_rate_hz:
        d["image"] = StreamDescription(
            {
                "data": FieldDescription("", "bytes"),
                "format": FieldDescription("", "str"),
                "width": FieldDescription("px", "int64"),
                "height": FieldDescription("px", "int64"),
                "frame_index": FieldDescription("", "int64"),
                "frame_id": FieldDescription("", "str"),
            },
            image_rate_hz if image_rate_hz else rate_hz / image_every,
            "compressed camera frames (JPEG/PNG) at a reduced rate",
        )
    return d


class _PoseSourceBase(Source):
    def __init__(
        self,
        name: str,
        camera: CameraModel | str,
        layout: MarkerLayout | str,
        image_every: int = 0,
        image_rate_hz: float = 0.0,
        image_format: str = "jpeg",
        jpeg_quality: int = 85,
        sigma_px: float | None = None,
        reference: tuple[ArrayLike, ArrayLike] | None = None,
        track: bool = True,
        blobs: BlobSettings | Mapping[str, Any] | None = None,
        origin: str = "<config>",
    ) -> None:
        super().__init__(name)
        self.camera = _camera(camera)
        self.layout = _layout(layout)
        blob_settings = None
        if isinstance(blobs, BlobSettings):
            blob_settings = blobs
        elif blobs is not None:  # a config's table
            table = parse(BlobDetection, plain(blobs), origin, f"sources.{name}.blobs")
            blob_settings = table.settings()
        if blob_settings is not None and self.layout.kind != "points":
            raise ConfigError(
                origin,
                f"sources.{name}.blobs",
                f"the marker layout is {self.layout.kind}: the blob detector's settings apply "
                "to IR marks (a points layout)",
            )
        # image_format jpeg | png and the ranges: cdpr.daq.source_schema.CameraSettings
        self.image_every = int(image_every)
        self.image_rate_hz = float(image_rate_hz)
        self._last_image_t: int | None = None
        self.image_format = image_format
        self.jpeg_quality = int(jpeg_quality)
        self.estimator = FramePoseEstimator(
            self.camera, self.layout, sigma_px, reference, blob_settings, track=track
        )
        self.frame_index = 0

    def _blob_settings(self) -> dict[str, Any]:
        """``{"blobs": {...}}``, the IR-mark detector's settings in use (points layouts)."""
        blob = self.estimator.blob_settings
        return {} if blob is None else {"blobs": dataclasses.asdict(blob)}

    def _readings(self, t_ns: int, gray: NDArray[np.uint8]) -> list[Reading]:
        est = self.estimator.estimate(gray)
        out = [pose_reading(t_ns, est, self.frame_index)]
        if self.image_rate_hz > 0:
            due = (
                self._last_image_t is None or t_ns - self._last_image_t >= 1e9 / self.image_rate_hz
            )
        else:
            due = bool(self.image_every) and self.frame_index % self.image_every == 0
        if due:
            self._last_image_t = t_ns
            data = cv.encode_image(gray, self.image_format, self.jpeg_quality)
            out.append(
                Reading(
                    "image",
                    t_ns,
                    {
                        "data": data,
                        "format": self.image_format,
                        "width": int(gray.shape[1]),
                        "height": int(gray.shape[0]),
                        "frame_index": self.frame_index,
                        "frame_id": self.name,
                    },
                )
            )
        self.frame_index += 1
        return out


class CameraSource(_PoseSourceBase):
    """Pose (and frames) from a real camera (``device``), a video file or an image folder.

    Exactly one of ``device`` (int index), ``video`` (path) or ``folder`` (path) is given.
    ``fps``: nominal frame rate (for folders' timestamps and the drop counter; a device's or video's
    own rate is used if 0).  ``finished`` turns True at the end of a file or folder.
    ``realtime``: a folder or video is delivered at its frame rate, frame ``k`` not before the open
    time plus ``k / fps`` (a recording of a folder then lasts as long as the folder; default True);
    False delivers frames as fast as the pose estimator goes (post-hoc processing).
    ``blobs``: IR marks, the detector's settings (a :class:`BlobSettings`, or a config's
    ``[sources.<name>.blobs]`` table checked by :class:`cdpr.daq.vision_files.BlobDetection`).
    """

    kind = "camera"
    accepts_origin = True

    def __init__(
        self,
        name: str,
        camera: CameraModel | str,
        layout: MarkerLayout | str,
        device: int | None = None,
        video: str | None = None,
        folder: str | None = None,
        fps: float = 0.0,
        realtime: bool = True,
        origin: str = "<config>",
        **kwargs: Any,
    ) -> None:
        given = [x is not None for x in (device, video, folder)]
        if sum(given) != 1:
            raise ConfigError(
                origin, f"sources.{name}", "give exactly one of device, video, folder"
            )
        super().__init__(name, camera, layout, origin=origin, **kwargs)
        self.realtime = bool(realtime)
        self.device, self.video, self.folder = device, video, folder
        self.fps = float(fps)
        self.finished = False
        self._cap: cv.VideoCapture | None = None
        self._files: list[Path] = []
        self._t0 = 0
        self._last_t: int | None = None

    def settings(self) -> dict[str, Any]:
        return {
            "camera_id": self.camera.id,
            "device": self.device,
            "video": self.video,
            "folder": self.folder,
            "fps": self.fps,
            "image_every": self.image_every,
            "image_rate_hz": self.image_rate_hz,
            "image_format": self.image_format,
            "sigma_px": self.estimator.sigma_px,
            "track": self.estimator.track,
            "realtime": self.realtime,
            **self._blob_settings(),
        }

    @property
    def exhausted(self) -> bool:
        """The end of a video file or image folder (a device never ends)."""
        return self.finished

    def _not_due(self, t_ns: int, timeout_s: float) -> bool:
        """Realtime pacing of a file or folder: True (after sleeping up to ``timeout_s``) while the
        frame at ``t_ns`` is still in the future."""
        if not self.realtime:
            return False
        wait_s = (t_ns - now_ns()) / 1e9
        if wait_s <= 0:
            return False
        time.sleep(min(wait_s, timeout_s))
        return wait_s > timeout_s

    def describe(self) -> dict[str, StreamDescription]:
        return _describe(self.fps, self.image_every, self.image_rate_hz)

    def _open(self) -> None:
        self._t0 = now_ns()
        self.finished = False
        if self.folder is not None:
            p = Path(self.folder)
            if not p.is_dir():
                raise ConfigError(str(p), "", "image folder not found")
            self._files = sorted(f for f in p.iterdir() if f.suffix.lower() in cv.IMAGE_EXTENSIONS)
            if not self.fps:
                self.fps = 30.0
            return
        target: int | str = self.device if self.device is not None else str(self.video)
        if self.video is not None and not Path(self.video).exists():
            raise ConfigError(str(self.video), "", "video file not found")
        self._cap = cv.VideoCapture(target)
        if not self._cap.is_opened():
            raise ConfigError(str(target), "", "cv2.VideoCapture cannot open it")
        if not self.fps:
            self.fps = self._cap.fps() or 0.0

    def _close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def _read(self, timeout_s: float) -> list[Reading]:
        if self.finished:
            return []
        if self.folder is not None:
            while self.frame_index < len(self._files):
                i = self.frame_index
                t = self._t0 + int(round(i * 1e9 / self.fps))
                if self._not_due(t, timeout_s):
                    return []
                img = cv.read_image(self._files[i])
                if img is None:
                    self.stats.lost += 1
                    self.frame_index += 1
                    continue
                return self._readings(t, img)
            self.finished = True
            return []
        assert self._cap is not None
        frame = self._cap.read()
        t_host = now_ns()
        if frame is None:
            if self.video is not None:
                self.finished = True
            else:
                self.stats.errors += 1
            return []
        gray = cv.to_gray(frame)
        if self.video is not None:
            t = self._t0 + int(round(self._cap.position_ms() * 1e6))
            if self.realtime and t > now_ns():
                time.sleep((t - now_ns()) / 1e9)  # at most one frame period
        else:
            t = t_host
            if self._last_t is not None and self.fps > 0:
                period = 1e9 / self.fps
                gap = (t - self._last_t) / period
                if gap > 1.5:
                    self.stats.lost += int(round(gap)) - 1
            self._last_t = t
        return self._readings(t, gray)


class VirtualCameraSource(_PoseSourceBase):
    """Frames rendered at the true platform pose, measured like real ones.

    pose_at: ``pose_at(t_ns) -> (position_O_m (3,), R_O_P (3, 3))``, the virtual rig's truth (e.g.
    ``lambda t: rig.true_pose_at(t)``).  rate_hz: frame rate.  realtime: if True, ``read`` waits for
    the next frame time of the host clock; if False, every ``read`` returns the next frame at
    ``t_start_ns + k / rate_hz`` immediately (fast simulation).  truth_stream: also emit
    ``"pose_truth"`` readings (position_O_m, quaternion_wxyz, euler_rad at the frame time) for checks.
    """

    kind = "virtual_camera"

    def __init__(
        self,
        name: str,
        camera: CameraModel | str,
        layout: MarkerLayout | str,
        pose_at: PoseAt,
        rate_hz: float = 30.0,
        realtime: bool = True,
        t_start_ns: int | None = None,
        render: RenderSettings | None = None,
        seed: int | None = None,
        truth_stream: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(name, camera, layout, **kwargs)
        if rate_hz <= 0:
            raise ConfigError("<config>", f"sources.{name}.rate_hz", f"expected > 0, got {rate_hz}")
        self.pose_at = pose_at
        self.rate_hz = float(rate_hz)
        self.realtime = bool(realtime)
        self.t_start_ns = t_start_ns
        self.truth_stream = truth_stream
        self.vcam = VirtualCamera(self.camera, render)
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self._k = 0

    def settings(self) -> dict[str, Any]:
        return {
            "camera_id": self.camera.id,
            "layout": self.layout.name,
            "rate_hz": self.rate_hz,
            "realtime": self.realtime,
            "image_every": self.image_every,
            "image_rate_hz": self.image_rate_hz,
            "image_format": self.image_format,
            "sigma_px": self.estimator.sigma_px,
            "seed": self.seed,
            **self._blob_settings(),
        }

    def describe(self) -> dict[str, StreamDescription]:
        d = _describe(self.rate_hz, self.image_every, self.image_rate_hz)
        if self.truth_stream:
            d["pose_truth"] = StreamDescription(
                {
                    "position_O_m": FieldDescription("m", shape=(3,)),
                    "quaternion_wxyz": FieldDescription("", shape=(4,)),
                    "euler_rad": FieldDescription("rad", shape=(3,)),
                },
                self.rate_hz,
                "true pose at the frame time (virtual rig)",
            )
        return d

    def _open(self) -> None:
        if self.t_start_ns is None:
            self.t_start_ns = now_ns()
        self._k = 0

    def _close(self) -> None:
        pass

    def render(self, position_O_m: ArrayLike, R_O_P: ArrayLike) -> NDArray[np.uint8]:
        """One frame at a given pose."""
        if self.layout.kind == "fiducial":
            return self.vcam.render_fiducials(self.layout, position_O_m, R_O_P, self.rng)
        return self.vcam.render_points(self.layout, position_O_m, R_O_P, self.rng)

    def _read(self, timeout_s: float) -> list[Reading]:
        assert self.t_start_ns is not None
        t = self.t_start_ns + int(round(self._k * 1e9 / self.rate_hz))
        if self.realtime:
            wait = (t - now_ns()) / 1e9
            if wait > timeout_s:
                time.sleep(max(timeout_s, 0.0))
                return []
            if wait > 0:
                time.sleep(wait)
            elif -wait > 1.5 / self.rate_hz:  # late: skip the missed frames, count them as lost
                missed = int(-wait * self.rate_hz)
                self.stats.lost += missed
                self._k += missed
                t = self.t_start_ns + int(round(self._k * 1e9 / self.rate_hz))
        self._k += 1
        p, R = self.pose_at(t)
        p = np.asarray(p, np.float64)
        R = np.asarray(R, np.float64)
        out = self._readings(t, self.render(p, R))
        if self.truth_stream:
            from cdpr.analysis.rotations import euler_from_rotation, quaternion_from_rotation

            out.append(
                Reading(
                    "pose_truth",
                    t,
                    {
                        "position_O_m": p.tolist(),
                        "quaternion_wxyz": quaternion_from_rotation(R).tolist(),
                        "euler_rad": euler_from_rotation(R).tolist(),
                    },
                )
            )
        return out
