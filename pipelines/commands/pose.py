"""``cdpr pose``: platform poses from images, a video or a run's recorded camera frames.

``cdpr pose IMAGES_OR_FOLDERS... --camera camera.json --markers layout.toml --out poses.csv``
estimates the pose of {P} in {O} in every image (each acquired from scratch: unrelated snapshots);
``cdpr pose VIDEO --camera ... --markers ... --out poses.csv`` does it for every frame of a video
(tracked from frame to frame, ``--no-track`` to acquire each from scratch); ``cdpr pose RUN.mcap
...`` re-estimates the poses from the run's recorded camera frames (the ``foxglove.CompressedImage``
channel, ``--topic`` if there are several) when the live estimator could not keep up.

The CSV has one row per frame: ``source``, ``frame``, ``t_ns`` (the run's log time, the video
position, or empty for images), ``x_O_m, y_O_m, z_O_m``, ``qw, qx, qy, qz`` (scalar first),
``roll_rad, pitch_rad, yaw_rad`` (Z-Y-X), ``reprojection_px``, ``sigma_px`` (corner noise estimated
from the frame's residuals), ``n_points``, ``flags`` (bit field) and ``flag_names``, then the 6x6
covariance ``cov_00 .. cov_55`` row-major in the order ``[position_O_m, rotation_O_rad]``.  A frame
without a usable pose keeps its row (NaN pose, its flags).

Exit code: 0 when every frame has a usable pose; 3 when the CSV is written but some frames have none
(their count and flags are printed on stderr); 2 on bad input (one line naming the file and the
problem, nothing written): an unreadable image, an image whose size differs from the camera's, a run
without camera frames.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

EXIT_FLAGGED = 3


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "pose",
        help="platform poses (with covariance and flags) from images, a video or a run's frames",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("inputs", nargs="+", help="image files, folders of images, a video, or RUN.mcap")
    p.add_argument("--camera", required=True, help="camera model with extrinsics (JSON)")
    p.add_argument("--markers", required=True, help="marker layout (TOML)")
    p.add_argument("--out", required=True, help="output CSV")
    p.add_argument("--topic", help="image topic of a run file (default: its only image channel)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--track", dest="track", action="store_true", default=None, help="track")
    g.add_argument(
        "--no-track",
        dest="track",
        action="store_false",
        help="acquire every frame from scratch (default for images; videos and runs are tracked)",
    )
    p.add_argument(
        "--reference",
        nargs=6,
        type=float,
        metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"),
        help="nominal pose in {O} (m, rad) to acquire IR marks around (default: the camera's "
        "looks_at_O_m, level)",
    )
    p.set_defaults(func=run_pose)


def _frames(args: argparse.Namespace) -> tuple[Iterator[tuple[str, int, int | None, Any]], bool]:
    """(source, frame index, t_ns or None, gray image or None if unreadable) and the default
    tracking mode of the inputs."""
    from cdpr.analysis.errors import ConfigError
    from cdpr.calibration import cv

    paths = [Path(x) for x in args.inputs]
    for p in paths:
        if not p.exists():
            raise ConfigError(str(p), "", "file not found")
    runs = [p for p in paths if p.suffix.lower() == ".mcap"]
    videos = [
        p
        for p in paths
        if p.is_file() and p.suffix.lower() not in cv.IMAGE_EXTENSIONS and p.suffix != ".mcap"
    ]
    if (runs or videos) and len(paths) > 1:
        raise ConfigError(str(paths[0]), "", "give one video or one run file alone")
    if runs:
        return _run_frames(runs[0], args.topic), True
    if videos:
        return _video_frames(videos[0]), True
    files: list[Path] = []
    for p in paths:
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.suffix.lower() in cv.IMAGE_EXTENSIONS)
            if not found:
                raise ConfigError(str(p), "", "folder holds no image files")
            files += found
        else:
            files.append(p)
    return ((str(f), i, None, cv.read_image(f)) for i, f in enumerate(files)), False


def _video_frames(path: Path) -> Iterator[tuple[str, int, int | None, Any]]:
    from cdpr.analysis.errors import ConfigError
    from cdpr.calibration import cv

    cap = cv.VideoCapture(str(path))
    if not cap.is_opened():
        raise ConfigError(str(path), "", "not an image and not a video OpenCV can open")
    try:
        i = 0
        while True:
            frame = cap.read()
            if frame is None:
                break
            yield str(path), i, int(round(cap.position_ms() * 1e6)), cv.to_gray(frame)
            i += 1
        if i == 0:
            raise ConfigError(str(path), "", "video has no readable frames")
    finally:
        cap.release()


def _run_frames(path: Path, topic: str | None) -> Iterator[tuple[str, int, int | None, Any]]:
    """The camera frames of a run file, read through ``open_run`` (the one reader; a truncated or
    damaged file through its recovery, said on stderr) ten seconds of frames at a time."""
    from cdpr.analysis.errors import ConfigError
    from cdpr.calibration import cv
    from cdpr.daq.run_reader import open_run

    with open_run(path) as run:
        images = sorted(
            t for t, info in run.streams.items() if info.schema_name == "foxglove.CompressedImage"
        )
        if topic is not None:
            if topic not in images:
                raise ConfigError(str(path), topic, f"no image channel of that name (has {images})")
            images = [topic]
        if not images:
            raise ConfigError(str(path), "", "the run has no camera frames (no image channel)")
        if len(images) > 1:
            raise ConfigError(
                str(path), "", f"several image channels {images}: choose with --topic"
            )
        if not run.streams[images[0]].count:
            raise ConfigError(str(path), images[0], "the image channel holds no frames")
        if run.recovered:
            print(
                f"cdpr pose: warning: {path}: {run.warning}; "
                f"{run.streams[images[0]].count} frames read up to the damage",
                file=sys.stderr,
            )
        i = 0
        for df in run.iter_tables(images[0], 10 * 10**9, columns=["data"]):
            for t_ns, data in zip(df["t_ns"].tolist(), df["data"].tolist(), strict=True):
                # open_run gives the image bytes (the base64 of the JSON body decoded)
                data = data if isinstance(data, bytes) else b""
                yield f"{path}{images[0]}", i, int(t_ns), cv.decode_image(data) if data else None
                i += 1


def run_pose(args: argparse.Namespace) -> int:
    import numpy as np

    from cdpr.analysis.errors import ConfigError
    from cdpr.analysis.rotations import rotation_from_euler
    from cdpr.calibration.pose import BAD_FLAGS, flag_names
    from cdpr.daq.camera_source import FramePoseEstimator

    from ..config import atomic_output
    from ..vision_config import load_camera, load_marker_layout

    cam = load_camera(args.camera)
    layout = load_marker_layout(args.markers)
    if layout.frame != "P":
        raise ConfigError(args.markers, "frame", "expected a layout on the platform (frame = 'P')")
    frames, track_default = _frames(args)
    track = track_default if args.track is None else bool(args.track)
    reference = None
    if args.reference is not None:
        r = np.asarray(args.reference, np.float64)
        reference = (r[:3], rotation_from_euler(r[3:]))
    est = FramePoseEstimator(cam, layout, reference=reference, track=track)
    W, H = cam.image_size_px
    header = (
        "source,frame,t_ns,x_O_m,y_O_m,z_O_m,qw,qx,qy,qz,roll_rad,pitch_rad,yaw_rad,"
        "reprojection_px,sigma_px,n_points,flags,flag_names,"
        + ",".join(f"cov_{i}{j}" for i in range(6) for j in range(6))
    )
    rows = [header]
    n, bad = 0, 0
    bad_flags: dict[str, int] = {}
    for source, i, t_ns, gray in frames:
        where = source
        if gray is None:
            raise ConfigError(where, f"frame {i}", "cannot decode the image")
        if gray.shape != (H, W):
            raise ConfigError(
                where,
                f"frame {i}",
                f"image is {gray.shape[1]}x{gray.shape[0]} px, the camera model "
                f"{args.camera} is {W}x{H}: wrong camera or a resized image",
            )
        e = est.estimate(gray)
        n += 1
        if e.flags & BAD_FLAGS:
            bad += 1
            for name in flag_names(e.flags & BAD_FLAGS):
                bad_flags[name] = bad_flags.get(name, 0) + 1
        finite = bool(np.all(np.isfinite(e.R_O_P)))
        vals = [
            *e.position_O_m,
            *(e.q_wxyz if finite else np.full(4, np.nan)),
            *(e.euler_rad if finite else np.full(3, np.nan)),
            e.reprojection_rms_px,
            e.extra.get("sigma_px", float("nan")),
        ]
        cov = np.asarray(e.covariance, np.float64).reshape(-1)
        src = source.replace('"', '""')
        rows.append(
            f'"{src}",{i},{"" if t_ns is None else t_ns},'
            + ",".join(f"{v:.10g}" for v in vals)
            + f",{e.n_points},{e.flags},{'|'.join(flag_names(e.flags))},"
            + ",".join(f"{v:.6g}" for v in cov)
        )
    with atomic_output(args.out) as fh:
        fh.write("\n".join(rows) + "\n")
    print(
        f"cdpr pose: {n} frames ({'tracked' if track else 'each acquired from scratch'}), "
        f"{n - bad} usable poses; wrote {args.out}"
    )
    if bad:
        summary = ", ".join(f"{k} {v}" for k, v in sorted(bad_flags.items()))
        print(
            f"cdpr pose: warning: {bad} of {n} frames have no usable pose ({summary}); "
            "their rows carry the flags",
            file=sys.stderr,
        )
        return EXIT_FLAGGED
    return 0
