"""Lens distortion on the virtual rig (issue 5): scanning through distorted lenses, and
calibrating them from board poses.

The rig: a 480x360 camera (30 degrees across) and a 512x384 projector 200 mm above it, both
with realistic lenses (OpenCV's k1, k2, p1, p2, k3): camera (-0.1, 0.05, 1e-3, -5e-4, 0),
projector (0.08, -0.03, -8e-4, 1e-3, 0), 3-5 px of distortion at the image corners.

1. Scan: the thesis's sphere (PMP 1, 8, 32 x 4 steps in both directions), noise-free (one
   sample per pixel) and realistic (shot and read noise, 8 bits, 2x2 samples), `Scanner.scan`
   with the undistorted rig (the reference), the distorted rig's true calibration, and that
   calibration without the projector's lens or without both.  RMS and median 3D error over the
   sphere's clean pixels (`sliscan.evaluate.clean_pixels`, true point on the sphere) and over
   the whole view's (the wall behind the sphere reaches the image corners, where the lenses
   distort most).
2. Board calibration (`calibrate_board`): 12 poses (`simulate.calibration_poses`: tilted by 20
   degrees in 12 directions, moved a little around the image), each under 5-step PMP (1, 8) in
   both directions; a 9x7 chessboard (25 mm), OpenCV's 4x11 asymmetric circle grid (20 mm,
   radius 5) and a 15x11 symmetric grid (20 mm, radius 6) that fills most of the view; noise-free
   at 1 and 3 samples per pixel (3: the pixel's box aperture, `Conditions`' default), and the
   15x11 grid also from realistic captures (two noise seeds) and on a second rig (projector
   below, other lenses).  Per calibration: residual RMS; the camera's principal point and focal
   length against the truth and OpenCV's standard deviation of the principal point
   (`calibrate_board`'s ``intrinsics_std_px``); the sphere's RMS error triangulated from the same
   decoded maps with the estimate and with the truth, absolute and after the best rigid
   alignment (`sliscan.evaluate.rigid_alignment`); the reprojection of the sphere's true points,
   absolute and aligned.  Absolute: the estimate's world is its own camera frame, so the truth
   is taken into the TRUE camera frame by the rig's known camera pose (no fitting; the identity
   on these rigs, whose camera sits at the world origin) and compared there.
3. Circle centres: OpenCV's blob centres (`cv2.findCirclesGrid`) and sliscan's refined ones
   (`sliscan.targets.detect_circle_grid`) against the projected true centres.
4. Speed: `Triangulator` on a 1296x972 plane with and without the projector's lens (median of
   5 calls; camera lens in both).

    python benchmarks/distortion.py --json benchmarks/distortion.json
    python benchmarks/distortion.py --quick        # the view-filling grid at 3 samples per pixel only
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
import platform
import time

import cv2
import numpy as np

from sliscan import __version__, reconstruct, sequences, simulate
from sliscan.calibrate import board_view, calibrate_board
from sliscan.evaluate import clean_pixels, rigid_alignment
from sliscan.pipeline import Scanner
from sliscan.targets import Board
from sliscan.types import Calibration, Device, PatternSpec

CAMERA, PROJECTOR = (480, 360), (512, 384)
CAMERA_LENS = (-0.1, 0.05, 1e-3, -5e-4, 0.0)
PROJECTOR_LENS = (0.08, -0.03, -8e-4, 1e-3, 0.0)
SCAN_SPEC = PatternSpec(kind="pmp", orientation="both", steps=4, frequencies=(1, 8, 32), b_p=0.5,
                        projector_size=PROJECTOR)
BOARD_SPEC = PatternSpec(kind="pmp", orientation="both", steps=5, frequencies=(1, 8), b_p=0.5,
                         projector_size=PROJECTOR)
NOISE_FREE = dict(full_well_e=None, bit_depth=None)
BOARDS = {"chessboard 9x7": Board("chessboard", (9, 7), 25.0),
          "asymmetric 4x11": Board("asymmetric", (4, 11), 20.0, 5.0),
          "symmetric 15x11": Board("symmetric", (15, 11), 20.0, 6.0)}
#: The view-filling grid: the one calibrated from realistic captures and on the second rig.
FULL_VIEW = "symmetric 15x11"
POSES = 12
#: The second rig: the projector below the camera, other lenses.
RIG_B_LENSES = dict(camera_distortion=(-0.15, 0.08, -8e-4, 6e-4, 0.0),
                    projector_distortion=(0.05, -0.02, 5e-4, -1e-3, 0.0))
SPHERE_CENTRE, SPHERE_RADIUS = np.array([0.0, 0.0, 800.0]), 122.555


def lens_rig() -> simulate.Rig:
    return simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR, camera_distortion=CAMERA_LENS,
                                projector_distortion=PROJECTOR_LENS)


def rig_b() -> simulate.Rig:
    return simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR, projector_above=False, **RIG_B_LENSES)


def without_lenses(calibration: Calibration, *devices: str) -> Calibration:
    """The calibration with the named devices' distortion left out."""
    out = [Device(d.matrix, d.size, intrinsics=d.intrinsics, distortion=None if name in devices else d.distortion)
           for name, d in (("camera", calibration.camera), ("projector", calibration.projector))]
    return Calibration(*out)


def rms(d: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(d, dtype=np.float64) ** 2, axis=-1))))


def on_sphere(truth: simulate.GroundTruth) -> np.ndarray:
    """Clean pixels whose true point lies on the sphere (not the wall behind it)."""
    distance = np.linalg.norm(truth.points.astype(np.float64) - SPHERE_CENTRE, axis=-1)
    return clean_pixels(truth) & (np.abs(distance - SPHERE_RADIUS) < 1.0)


def scan_table() -> tuple[list[dict], dict]:
    rig, plain = lens_rig(), simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR)
    frames = sequences.render_frames(SCAN_SPEC)
    rows, captures = [], {}
    for condition, cond in (("noise-free", simulate.Conditions(supersample=1, **NOISE_FREE)),
                            ("realistic", simulate.Conditions(supersample=2, seed=1))):
        for name, render_rig, calib in (
                ("undistorted rig", plain, plain.calibration), ("true calibration", rig, rig.calibration),
                ("without the projector's lens", rig, without_lenses(rig.calibration, "projector")),
                ("without both lenses", rig, without_lenses(rig.calibration, "camera", "projector"))):
            key = (condition, render_rig is plain)
            if key not in captures:
                captures[key] = simulate.render_sequence(render_rig, simulate.sphere_scene(), frames, cond)
            capture = captures[key]
            result = Scanner(SCAN_SPEC, calib).scan(capture.images)
            row = {"conditions": condition, "calibration": name}
            for where, mask in (("sphere", on_sphere(capture.truth)), ("view", clean_pixels(capture.truth))):
                ok = result.valid & mask
                difference = result.points[ok] - capture.truth.points[ok]
                row.update({f"{where}_pixels": int(ok.sum()), f"{where}_rms_mm": rms(difference),
                            f"{where}_median_mm": float(np.median(np.linalg.norm(difference, axis=1)))})
            rows.append(row)
    return rows, {condition: captures[(condition, False)] for condition in ("noise-free", "realistic")}


def sphere_captures(rig: simulate.Rig) -> dict[str, simulate.SequenceCapture]:
    """The sphere scene on `rig`, noise-free (1 sample per pixel) and realistic (as `scan_table`)."""
    frames = sequences.render_frames(SCAN_SPEC)
    return {condition: simulate.render_sequence(rig, simulate.sphere_scene(), frames, cond)
            for condition, cond in (("noise-free", simulate.Conditions(supersample=1, **NOISE_FREE)),
                                    ("realistic", simulate.Conditions(supersample=2, seed=1)))}


def sphere_points(calibration: Calibration, capture: simulate.SequenceCapture) -> tuple[np.ndarray, np.ndarray]:
    """Scan points of the sphere from the capture's decoded maps, and their truth."""
    maps = sequences.decode_frames(capture.images, SCAN_SPEC)
    points = reconstruct.triangulate(maps["rows"].coord, calibration, valid=maps["rows"].valid,
                                     other=maps["columns"].coord)
    ok = on_sphere(capture.truth) & np.isfinite(points[..., 0])
    return points[ok].astype(np.float64), capture.truth.points[ok].astype(np.float64)


def in_camera_frame(points: np.ndarray, rig: simulate.Rig) -> np.ndarray:
    """World points (mm) in the rig's true camera frame, by its known pose (no fitting)."""
    return points @ rig.camera.R.T + rig.camera.t


def calibrate_poses(rig: simulate.Rig, board: Board, conditions: simulate.Conditions) -> Calibration:
    """`calibrate_board` from `POSES` poses of `board` rendered on `rig` under `conditions`."""
    frames = sequences.render_frames(BOARD_SPEC)
    views = []
    for k, (tilt, offset) in enumerate(simulate.calibration_poses(POSES)):
        if board.circles:
            scene, albedo, _ = simulate.circle_grid_scene(board, tilt_deg=tilt, offset_mm=offset)
        else:
            scene, albedo = simulate.board_scene(tilt_deg=tilt, offset_mm=offset, inner_corners=board.size,
                                                 square_mm=board.spacing)
        seed = None if conditions.seed is None else conditions.seed + k
        images = simulate.render_sequence(rig, scene, frames, replace(conditions, albedo=albedo, seed=seed)).images
        views.append(board_view(sequences.decode_frames(images, BOARD_SPEC), board, interpolate=True))
    return calibrate_board(views, board, CAMERA, PROJECTOR)


def compare(calib: Calibration, rig: simulate.Rig, spheres: dict) -> dict:
    """`calib` against the truth of `rig`: intrinsics, the sphere's errors and the reprojection
    of its true points, absolute (in the true camera frame) and aligned."""
    truth_calib = rig.calibration
    k, k_true = calib.camera.intrinsics, truth_calib.camera.intrinsics
    std = calib.extra["intrinsics_std_px"]["camera"]
    row = {"camera_residual_px": calib.extra["residuals"]["camera"]["rms_px"],
           "projector_residual_px": calib.extra["residuals"]["projector"]["rms_px"],
           "principal_point_error_px": float(np.hypot(*(k[:2, 2] - k_true[:2, 2]))),
           "principal_point_std_px": float(np.hypot(std["cx"], std["cy"])),
           "focal_error_px": float(np.mean(k[[0, 1], [0, 1]] - k_true[[0, 1], [0, 1]]))}
    for condition, capture in spheres.items():
        est, world = sphere_points(calib, capture)
        ref, ref_truth = sphere_points(truth_calib, capture)
        rotation, translation = rigid_alignment(ref, ref_truth)
        row[f"{condition}_true_mm"] = rms(ref - ref_truth)
        row[f"{condition}_true_aligned_mm"] = rms(ref @ rotation.T + translation - ref_truth)
        truth = in_camera_frame(world, rig)
        rotation, translation = rigid_alignment(est, truth)
        row[f"{condition}_estimated_mm"] = rms(est - truth)
        row[f"{condition}_estimated_aligned_mm"] = rms(est @ rotation.T + translation - truth)
    in_estimate = (truth - translation) @ rotation  # true points (camera frame) in the estimate's frame
    for device in ("camera", "projector"):
        seen = getattr(truth_calib, device).project(world)
        row[f"{device}_reprojection_px"] = rms(getattr(calib, device).project(truth) - seen)
        row[f"{device}_reprojection_aligned_px"] = rms(getattr(calib, device).project(in_estimate) - seen)
    return row


def board_table(spheres: dict, boards: dict[str, Board], supersamples: tuple[int, ...], *,
                quick: bool = False) -> list[dict]:
    rig = lens_rig()
    runs = [(name, board, "noise-free", ss, rig, spheres) for ss in supersamples for name, board in boards.items()]
    if not quick:
        runs += [(FULL_VIEW, BOARDS[FULL_VIEW], f"realistic, seed {seed}", seed, rig, spheres) for seed in (1, 2)]
        other = rig_b()
        runs.append((FULL_VIEW, BOARDS[FULL_VIEW], "noise-free, rig B", 3, other, sphere_captures(other)))
    rows = []
    for name, board, condition, value, render_rig, captures in runs:
        t0 = time.perf_counter()
        conditions = simulate.Conditions(supersample=value, **NOISE_FREE) if condition.startswith("noise-free") \
            else simulate.Conditions(supersample=3, seed=100 * value)
        calib = calibrate_poses(render_rig, board, conditions)
        row = {"board": name, "captures": condition, "supersample": conditions.supersample,
               "seconds": time.perf_counter() - t0, **compare(calib, render_rig, captures)}
        rows.append(row)
        print(f"  {name}, {condition}, {conditions.supersample} sample(s)/px: {row['seconds']:.1f} s", flush=True)
    return rows


def centre_table(supersamples: tuple[int, ...]) -> list[dict]:
    rig = lens_rig()
    board = BOARDS["asymmetric 4x11"]
    rows = []
    for ss in supersamples:
        errors = {"opencv": [], "sliscan": []}
        for tilt, offset in simulate.calibration_poses(8):
            scene, albedo, centres = simulate.circle_grid_scene(board, tilt_deg=tilt, offset_mm=offset)
            image = simulate.render(rig, scene, np.ones(rig.projector.shape),
                                    simulate.Conditions(albedo=albedo, supersample=ss, **NOISE_FREE)).image
            truth = rig.calibration.camera.project(centres)
            u8 = np.round(image / np.percentile(image, 99.5) * 255).clip(0, 255).astype(np.uint8)
            _, coarse = cv2.findCirclesGrid(u8, board.size, flags=cv2.CALIB_CB_ASYMMETRIC_GRID)
            for key, found in (("opencv", coarse.reshape(-1, 2)), ("sliscan", board.detect(image))):
                d = found - truth
                errors[key].append(d if np.abs(d).max() < 5 else found[::-1] - truth)
        rows.append({"supersample": ss, **{f"{k}_rms_px": rms(np.concatenate(v)) for k, v in errors.items()}})
    return rows


def speed_table() -> list[dict]:
    rig = simulate.virtual_rig(camera_size=(1296, 972), projector_size=(1024, 768), camera_distortion=CAMERA_LENS,
                               projector_distortion=PROJECTOR_LENS)
    yp = simulate.projector_rows(rig, simulate.plane_scene())
    rows = []
    for name, calib in (("camera lens only", without_lenses(rig.calibration, "projector")),
                        ("camera and projector lens", rig.calibration)):
        t0 = time.perf_counter()
        triangulator = reconstruct.Triangulator(calib, "rows")
        built = time.perf_counter() - t0
        triangulator(yp)
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            triangulator(yp)
            times.append(time.perf_counter() - t0)
        rows.append({"calibration": name, "build_s": built, "call_median_s": float(np.median(times)),
                     "pixels": int(np.isfinite(yp).sum())})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="the view-filling grid at 3 samples per pixel only")
    parser.add_argument("--json", help="write the tables here")
    args = parser.parse_args()
    print("scan of the sphere through the lenses (RMS over its clean pixels; and over the whole view's, the wall "
          "behind reaching the image corners):")
    scans, spheres = scan_table()
    for r in scans:
        print(f"  {r['conditions']:10s} {r['calibration']:30s} sphere RMS {r['sphere_rms_mm']:.3f} mm, median "
              f"{r['sphere_median_mm']:.3f} mm; whole view RMS {r['view_rms_mm']:.3f} mm, median "
              f"{r['view_median_mm']:.3f} mm")
    boards = {k: BOARDS[k] for k in ([FULL_VIEW] if args.quick else BOARDS)}
    print(f"board calibrations ({POSES} poses):")
    calibrations = board_table(spheres, boards, (3,) if args.quick else (1, 3), quick=args.quick)
    for r in calibrations:
        print(f"  {r['board']:16s} {r['captures']:18s} {r['supersample']} s/px: residuals {r['camera_residual_px']:.3f} / "
              f"{r['projector_residual_px']:.3f} px; principal point off {r['principal_point_error_px']:.3f} px "
              f"(OpenCV's std {r['principal_point_std_px']:.3f} px), focal length off {r['focal_error_px']:.3f} px; "
              f"sphere RMS, absolute / aligned: noise-free scan {r['noise-free_estimated_mm']:.3f} / "
              f"{r['noise-free_estimated_aligned_mm']:.3f} mm (truth {r['noise-free_true_mm']:.3f} / "
              f"{r['noise-free_true_aligned_mm']:.3f}), realistic scan {r['realistic_estimated_mm']:.3f} / "
              f"{r['realistic_estimated_aligned_mm']:.3f} mm (truth {r['realistic_true_mm']:.3f} / "
              f"{r['realistic_true_aligned_mm']:.3f}); reprojection of true points, absolute / aligned: camera "
              f"{r['camera_reprojection_px']:.3f} / {r['camera_reprojection_aligned_px']:.3f} px, projector "
              f"{r['projector_reprojection_px']:.3f} / {r['projector_reprojection_aligned_px']:.3f} px")
    centres = centre_table((1,) if args.quick else (1, 2, 3))
    print("circle centres of the 4x11 asymmetric grid against the truth (8 poses of calibration_poses):")
    for r in centres:
        print(f"  {r['supersample']} sample(s)/px: OpenCV {r['opencv_rms_px']:.3f} px RMS, "
              f"sliscan {r['sliscan_rms_px']:.3f} px RMS")
    speed = speed_table()
    print("Triangulator, 1296x972 plane (median of 5 calls):")
    for r in speed:
        print(f"  {r['calibration']:28s} build {r['build_s']:.3f} s, call {r['call_median_s']:.3f} s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scan": scans, "calibration": calibrations, "centres": centres, "speed": speed,
                       "versions": {"sliscan": __version__, "numpy": np.__version__, "opencv": cv2.__version__,
                                    "python": platform.python_version()}}, f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    main()
