"""``cdpr calibrate``: camera intrinsics and extrinsics (camera pose in {O}).

``cdpr calibrate camera IMAGES_OR_VIDEO... --board board.toml --out camera.json`` reads image files,
folders of images or video files, finds the board (``[board] type``: ``"charuco"``,
``"chessboard"`` or ``"circles"``) in each, and fits the intrinsics.  Any bad
image (no board, too few corners, blurred, unreadable) is an error naming the files (exit 2, nothing
written) unless ``--skip-bad`` is given.  Writes ``camera.json`` (with an id), ``camera.yaml``
(OpenCV FileStorage), ``camera_coverage.png`` and ``camera_crossval.png`` beside it.

``cdpr calibrate extrinsics IMAGE --camera camera.json (--board board.toml | --markers layout.toml)
--out camera_O.json``: the camera pose in {O} from a board at the pose given in the board file's
``[pose_O]`` or from fiducials whose layout has ``frame = "O"``.

``cdpr calibrate render-views`` renders synthetic ChArUco views through a camera model (for tests
and demos); ``cdpr calibrate verify-pose`` renders frames at known platform poses, estimates the
poses and prints the errors against the truth.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "calibrate",
        help="calibration: camera intrinsics/extrinsics, load cells, balance check loads",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    cs = p.add_subparsers(dest="calibrate_command", metavar="ACTION")
    cs.required = True
    from ._calibrate_balance import register_actions  # loadcells, balance

    register_actions(cs)

    cam = cs.add_parser(
        "camera", help="intrinsics from ChArUco, chessboard or circle-grid images or videos"
    )
    cam.add_argument("inputs", nargs="+", help="image files, folders of images, or video files")
    cam.add_argument("--board", required=True, help="board file (TOML)")
    cam.add_argument("--out", required=True, help="output camera model (JSON)")
    cam.add_argument("--name", default="camera", help="camera name stored in the model")
    cam.add_argument("--skip-bad", action="store_true", help="drop bad images instead of failing")
    cam.add_argument(
        "--every", type=int, default=10, help="take every N-th video frame (default 10)"
    )
    cam.set_defaults(func=run_camera)

    ext = cs.add_parser(
        "extrinsics", help="camera pose in {O} from a board or fiducials at known poses"
    )
    ext.add_argument("image", help="image of the board / markers")
    ext.add_argument("--camera", required=True, help="camera model with intrinsics (JSON)")
    g = ext.add_mutually_exclusive_group(required=True)
    g.add_argument("--board", help="board file with a [pose_O] table")
    g.add_argument("--markers", help="fiducial layout with frame = 'O'")
    ext.add_argument(
        "--sigma-px",
        type=float,
        default=0.1,
        help="nominal corner noise (px): the outlier gate; the covariance takes the noise from the "
        "residuals (this value fills in only below 6 residual degrees of freedom)",
    )
    ext.add_argument("--out", required=True, help="output camera model (JSON)")
    ext.set_defaults(func=run_extrinsics)

    rv = cs.add_parser("render-views", help="render synthetic ChArUco views through a camera model")
    rv.add_argument("--camera", required=True, help="camera model (JSON)")
    rv.add_argument("--board", required=True, help="board file (TOML)")
    rv.add_argument("-n", type=int, default=20, help="number of views")
    rv.add_argument("--noise-dn", type=float, default=6.0, help="image noise (DN, 8 bit)")
    rv.add_argument("--seed", type=int, default=1)
    rv.add_argument("--out", required=True, help="output folder (PNG files)")
    rv.set_defaults(func=run_render_views)

    vp = cs.add_parser("verify-pose", help="render frames at known poses and print the pose errors")
    vp.add_argument("--camera", required=True, help="camera model with extrinsics (JSON)")
    vp.add_argument("--layout", required=True, help="marker layout (TOML)")
    vp.add_argument("--rig", help="rig file: its reference pose is the centre of the test poses")
    vp.add_argument("-n", type=int, default=5, help="number of poses")
    vp.add_argument("--seed", type=int, default=1)
    vp.add_argument("--out", help="optional folder for the rendered frames (PNG)")
    vp.set_defaults(func=run_verify_pose)


# ------------------------------------------------------------------------------------ inputs
def _frames(inputs: list[str], every: int) -> list[tuple[str, Any]]:
    """(name, gray image or None if unreadable) for every image / folder entry / video frame."""
    from cdpr.analysis.errors import ConfigError
    from cdpr.calibration import cv

    out: list[tuple[str, Any]] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            files = sorted(f for f in p.iterdir() if f.suffix.lower() in cv.IMAGE_EXTENSIONS)
            if not files:
                raise ConfigError(str(p), "", "folder holds no image files")
            out += [(str(f), cv.read_image(f)) for f in files]
        elif not p.exists():
            raise ConfigError(str(p), "", "file not found")
        elif p.suffix.lower() in cv.IMAGE_EXTENSIONS:
            out.append((str(p), cv.read_image(p)))
        else:
            cap = cv.VideoCapture(str(p))
            if not cap.is_opened():
                raise ConfigError(str(p), "", "not an image and not a video OpenCV can open")
            i = 0
            while True:
                frame = cap.read()
                if frame is None:
                    break
                if i % max(every, 1) == 0:
                    out.append((f"{p}#frame{i}", cv.to_gray(frame)))
                i += 1
            cap.release()
            if i == 0:
                raise ConfigError(str(p), "", "video has no readable frames")
    return out


def _write_outputs(out: Path, camera: Any, figures: dict[str, Any] | None = None) -> list[str]:
    """Write camera JSON + OpenCV YAML (+ figures, each ``fig(path)``): everything goes to temporary
    files first and is moved into place only when all succeeded (no partial outputs)."""
    from cdpr.calibration import cv

    from ..config import atomic_output

    out.parent.mkdir(parents=True, exist_ok=True)
    final = {out.with_suffix(".yaml"): out.parent / f".{out.stem}.yaml.part.yaml"}
    for suffix in figures or {}:
        final[out.parent / f"{out.stem}_{suffix}.png"] = (
            out.parent / f".{out.stem}_{suffix}.part.png"
        )
    try:
        cv.write_filestorage_yaml(final[out.with_suffix(".yaml")], camera.opencv_entries())
        for suffix, fig in (figures or {}).items():
            fig(str(final[out.parent / f"{out.stem}_{suffix}.png"]))
        with atomic_output(out) as fh:
            fh.write(camera.to_json())
        for dst, tmp in final.items():
            os.replace(tmp, dst)
    finally:
        for tmp in final.values():
            if tmp.exists():
                tmp.unlink()
    return [str(out), *(str(d) for d in final)]


# ------------------------------------------------------------------------------------ commands
def run_camera(args: argparse.Namespace) -> int:
    import sys

    from cdpr.analysis.errors import ConfigError, InputError
    from cdpr.calibration.intrinsics import (
        calibrate_intrinsics,
        coverage_figure,
        crossval_figure,
        detect_view,
    )

    from .. import __version__
    from ..config import file_sha256
    from ..vision_config import load_board

    spec, settings = load_board(args.board)
    board = spec.make()
    frames = _frames(args.inputs, args.every)
    views, bad = [], []
    size = None
    for name, img in frames:
        if img is None:
            bad.append((name, "cannot read the image"))
            continue
        wh = (img.shape[1], img.shape[0])
        if size is None:
            size = wh
        elif wh != size:
            bad.append((name, f"image size {wh[0]}x{wh[1]} differs from {size[0]}x{size[1]}"))
            continue
        v, why = detect_view(name, img, board, settings)
        if v is None:
            bad.append((name, why))
        else:
            views.append(v)
    listing = "; ".join(f"{n}: {w}" for n, w in bad)
    if bad and not args.skip_bad:
        raise ConfigError(
            f"{len(bad)} of {len(frames)} images",
            "",
            f"bad images (use --skip-bad to drop them): {listing}",
        )
    if len(views) < settings.min_views or size is None:
        raise ConfigError(
            args.board,
            "calibration.min_views",
            f"too few usable views: {len(views)} of {len(frames)} (need {settings.min_views})"
            + (f"; bad: {listing}" if bad else ""),
        )
    if bad:
        print(
            f"cdpr calibrate camera: warning: skipped {len(bad)} bad images: {listing}",
            file=sys.stderr,
        )
    try:
        res = calibrate_intrinsics(views, board, size, settings, name=args.name)
    except InputError as exc:
        raise ConfigError(args.board, "calibration", str(exc)) from None
    cam = res.camera
    cam.calibration["board"] = {
        "file": args.board,
        "sha256": file_sha256(args.board),
        **spec.description(),
    }
    cam.calibration["skipped_images"] = dict(bad)
    cam.calibration["software"] = f"cdpr {__version__}"

    written = _write_outputs(
        Path(args.out),
        cam,
        {
            "coverage": lambda path: coverage_figure(res, path),
            "crossval": lambda path: crossval_figure(res, path),
        },
    )
    K = cam.K
    print(
        f"cdpr calibrate camera: {len(res.views)} views ({len(res.rejected)} rejected as outliers), "
        f"RMS {res.rms_px:.4f} px"
    )
    print(
        f"  fx = {K[0, 0]:.3f} +- {res.std['fx']:.3f}  fy = {K[1, 1]:.3f} +- {res.std['fy']:.3f}  "
        f"cx = {K[0, 2]:.3f} +- {res.std['cx']:.3f}  cy = {K[1, 2]:.3f} +- {res.std['cy']:.3f} px"
    )
    print(f"  dist = {[round(float(x), 6) for x in cam.dist]}")
    print(f"  id {cam.id}; wrote {', '.join(written)}")
    return 0


def run_extrinsics(args: argparse.Namespace) -> int:
    import numpy as np

    from cdpr.analysis.errors import ConfigError, InputError
    from cdpr.calibration import cv
    from cdpr.calibration.intrinsics import extrinsics_from_board, extrinsics_from_fiducials

    from ..vision_config import load_board, load_camera, load_marker_layout

    cam = load_camera(args.camera)
    img = cv.read_image(args.image)
    if img is None:
        raise ConfigError(args.image, "", "cannot read the image")
    try:
        if args.board:
            spec, _ = load_board(args.board)
            if spec.R_O_B is None:
                raise ConfigError(
                    args.board, "pose_O", "missing: the board's pose in {O} is needed"
                )
            out = extrinsics_from_board(cam, spec, img, args.sigma_px)
        else:
            layout = load_marker_layout(args.markers)
            out = extrinsics_from_fiducials(cam, layout, img, args.sigma_px)
    except InputError as exc:
        raise ConfigError(args.image, "", str(exc)) from None
    written = _write_outputs(Path(args.out), out)
    info = out.extrinsics_info
    print(
        f"cdpr calibrate extrinsics: camera at {np.round(out.position_O_m, 5).tolist()} m in {{O}}, "
        f"RMS {info['rms_px']:.4f} px, "
        f"std position {np.round(np.array(info['std_position_O_m']) * 1e3, 3).tolist()} mm"
    )
    print(f"  id {out.id}; wrote {', '.join(written)}")
    return 0


def run_render_views(args: argparse.Namespace) -> int:
    import numpy as np

    from cdpr.calibration import cv
    from cdpr.calibration.render import RenderSettings, VirtualCamera, random_board_poses

    from ..vision_config import load_board, load_camera

    cam = load_camera(args.camera)
    spec, _ = load_board(args.board)
    board = spec.make()
    rng = np.random.default_rng(args.seed)
    vc = VirtualCamera(cam, RenderSettings(noise_sigma_dn=args.noise_dn))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for i, (R, t) in enumerate(random_board_poses(cam, board, args.n, rng)):
        cv.write_image(out / f"view_{i:03d}.png", vc.render_board(board, R, t, rng))
    print(
        f"cdpr calibrate render-views: {args.n} views of {args.board} through {args.camera} in {out}"
    )
    return 0


def run_verify_pose(args: argparse.Namespace) -> int:
    import numpy as np

    from cdpr.analysis.rotations import rotation_from_euler
    from cdpr.calibration import cv
    from cdpr.calibration.pose import flag_names, nees, pose_error
    from cdpr.calibration.render import VirtualCamera
    from cdpr.daq.camera_source import FramePoseEstimator

    from ..config import load_rig
    from ..vision_config import load_camera, load_marker_layout

    cam = load_camera(args.camera)
    layout = load_marker_layout(args.layout)
    if args.rig:
        rig = load_rig(args.rig)
        p0, R0 = rig.reference_position_O_m, rotation_from_euler(rig.reference_euler_rad)
    else:
        p0 = np.asarray(cam.extrinsics_info.get("looks_at_O_m", [0.5, 0.0, 0.36]), np.float64)
        R0 = np.eye(3)
    rng = np.random.default_rng(args.seed)
    vc = VirtualCamera(cam)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
    print(
        f"{'pose':>4s} {'dx_mm':>8s} {'dy_mm':>8s} {'dz_mm':>8s} {'rot_deg':>8s} "
        f"{'reproj_px':>9s} {'NEES':>6s}  flags"
    )
    errs = []
    for i in range(args.n):
        p = p0 + rng.uniform(-0.02, 0.02, 3)
        R = rotation_from_euler(np.deg2rad(rng.uniform(-5, 5, 3))) @ R0
        img = (
            vc.render_fiducials(layout, p, R, rng)
            if layout.kind == "fiducial"
            else vc.render_points(layout, p, R, rng)
        )
        est = FramePoseEstimator(cam, layout, reference=(p0, R0)).estimate(img)
        if args.out:
            cv.write_image(Path(args.out) / f"frame_{i:03d}.png", img)
        e = pose_error(est.position_O_m, est.R_O_P, p, R)
        errs.append(e)
        print(
            f"{i:4d} {e[0] * 1e3:8.4f} {e[1] * 1e3:8.4f} {e[2] * 1e3:8.4f} "
            f"{np.rad2deg(np.linalg.norm(e[3:])):8.5f} {est.reprojection_rms_px:9.4f} "
            f"{nees(e, est.covariance):6.2f}  {','.join(flag_names(est.flags)) or '-'}"
        )
    E = np.array(errs)
    print(
        f"RMS position error {1e3 * np.sqrt(np.mean(np.sum(E[:, :3] ** 2, 1))):.4f} mm, "
        f"RMS rotation error {np.rad2deg(np.sqrt(np.mean(np.sum(E[:, 3:] ** 2, 1)))):.5f} deg "
        f"over {args.n} poses"
    )
    return 0
