"""Lens distortion end to end on the virtual rig (issue 5): scanning through distorted lenses with
the true calibration, and calibrating them from poses of OpenCV's asymmetric circle grid, in
Python and through the command line (calibrate-board -> scan, simulate -> scan).

The rig (as benchmarks/distortion.py): a 480x360 camera and a 512x384 projector 200 mm above it,
camera lens (-0.1, 0.05, 1e-3, -5e-4, 0), projector lens (0.08, -0.03, -8e-4, 1e-3, 0) in
OpenCV's k1, k2, p1, p2, k3: 3-5 px of distortion at the image corners.  Captures are
noise-free with one sample per pixel (the issue's "noise-free"; the benchmark adds realistic
ones).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sliscan import reconstruct, sequences, simulate
from sliscan._validate import write_images
from sliscan.calibrate import board_view, calibrate_board
from sliscan.cli import main
from sliscan.evaluate import clean_pixels, read_truth, rigid_alignment
from sliscan.pipeline import Scanner
from sliscan.targets import Board
from sliscan.types import Calibration, Device, PatternSpec

CAMERA, PROJECTOR = (480, 360), (512, 384)
CAMERA_LENS = (-0.1, 0.05, 1e-3, -5e-4, 0.0)
PROJECTOR_LENS = (0.08, -0.03, -8e-4, 1e-3, 0.0)
NOISE_FREE = dict(supersample=1, full_well_e=None, bit_depth=None)
#: The scan: PMP at 1, 8 and 32 fringes, 4 steps, both directions (the other direction
#: undistorts the projector exactly).
SCAN_SPEC = PatternSpec(kind="pmp", orientation="both", steps=4, frequencies=(1, 8, 32), b_p=0.5,
                        projector_size=PROJECTOR)
#: The board poses: 5 steps, so the uncorrected projector gamma (2.2) costs nothing (4 steps
#: alias its third harmonic: 0.08 px of phase error against 0.024 px).
BOARD_SPEC = PatternSpec(kind="pmp", orientation="both", steps=5, frequencies=(1, 8), b_p=0.5,
                         projector_size=PROJECTOR)
GRID = Board("asymmetric", (4, 11), 20.0, 5.0)
#: A symmetric grid that fills most of the view at 800 mm (300 x 220 mm).
FULL_VIEW = Board("symmetric", (15, 11), 20.0, 6.0)
SPHERE_CENTRE, SPHERE_RADIUS = np.array([0.0, 0.0, 800.0]), 122.555


def rms(d: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(d, dtype=np.float64) ** 2, axis=-1))))


def without_lenses(calibration: Calibration, *devices: str) -> Calibration:
    out = [Device(d.matrix, d.size, intrinsics=d.intrinsics, distortion=None if name in devices else d.distortion)
           for name, d in (("camera", calibration.camera), ("projector", calibration.projector))]
    return Calibration(*out)


def on_sphere(truth: simulate.GroundTruth) -> np.ndarray:
    """Clean pixels (`clean_pixels`) whose true point lies on the sphere, not on the wall."""
    distance = np.linalg.norm(truth.points.astype(np.float64) - SPHERE_CENTRE, axis=-1)
    return clean_pixels(truth) & (np.abs(distance - SPHERE_RADIUS) < 1.0)


@pytest.fixture(scope="module")
def lens_rig() -> simulate.Rig:
    return simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR, camera_distortion=CAMERA_LENS,
                                projector_distortion=PROJECTOR_LENS)


@pytest.fixture(scope="module")
def sphere(lens_rig) -> simulate.SequenceCapture:
    return simulate.render_sequence(lens_rig, simulate.sphere_scene(), sequences.render_frames(SCAN_SPEC),
                                    simulate.Conditions(**NOISE_FREE))


@pytest.fixture(scope="module")
def grid_poses(lens_rig) -> list[np.ndarray]:
    """The capture sequences of 8 poses of OpenCV's 4x11 grid (`simulate.calibration_poses`
    tilted by 35 degrees and moved around the image: the small grid stays inside the view)."""
    frames = sequences.render_frames(BOARD_SPEC)
    poses = []
    for tilt, offset in simulate.calibration_poses(8, tilt_deg=35.0, offset_mm=(70.0, 50.0)):
        scene, albedo, _ = simulate.circle_grid_scene(GRID, tilt_deg=tilt, offset_mm=offset)
        poses.append(simulate.render_sequence(lens_rig, scene, frames,
                                              simulate.Conditions(albedo=albedo, **NOISE_FREE)).images)
    return poses


@pytest.fixture(scope="module")
def estimated(lens_rig) -> Calibration:
    """The calibration from 12 poses of `FULL_VIEW` (`simulate.calibration_poses`' defaults),
    noise-free at 3x3 samples per pixel (the pixel's box aperture)."""
    frames = sequences.render_frames(BOARD_SPEC)
    views = []
    for tilt, offset in simulate.calibration_poses(12):
        scene, albedo, _ = simulate.circle_grid_scene(FULL_VIEW, tilt_deg=tilt, offset_mm=offset)
        images = simulate.render_sequence(lens_rig, scene, frames, simulate.Conditions(
            albedo=albedo, **{**NOISE_FREE, "supersample": 3})).images
        views.append(board_view(sequences.decode_frames(images, BOARD_SPEC), FULL_VIEW, interpolate=True))
    return calibrate_board(views, FULL_VIEW, CAMERA, PROJECTOR)


def test_scans_through_the_lenses_are_as_good_as_without(lens_rig, sphere):
    """With the true calibration, distortion included, the sphere scene (sphere and wall, clean
    pixels: `clean_pixels`) is scanned as well as on the same rig without lenses (measured
    0.074 mm RMS against 0.079 mm; the two rigs' pixels sample the scene differently: tolerance
    20 %); ignoring the projector's lens gives 2.53 mm, ignoring both 5.05 mm (34x and 68x;
    asserted: 10x and 20x)."""
    plain = simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR)
    reference = simulate.render_sequence(plain, simulate.sphere_scene(), sequences.render_frames(SCAN_SPEC),
                                         simulate.Conditions(**NOISE_FREE))
    errors = {}
    for name, rig_calibration, capture in (
            ("undistorted rig", plain.calibration, reference), ("true", lens_rig.calibration, sphere),
            ("no projector lens", without_lenses(lens_rig.calibration, "projector"), sphere),
            ("no lenses", without_lenses(lens_rig.calibration, "camera", "projector"), sphere)):
        result = Scanner(SCAN_SPEC, rig_calibration).scan(capture.images)
        ok = result.valid & clean_pixels(capture.truth)
        assert ok.sum() > 0.9 * clean_pixels(capture.truth).sum()
        errors[name] = rms(result.points[ok] - capture.truth.points[ok])
    assert errors["true"] < 1.2 * errors["undistorted rig"], errors
    assert errors["no projector lens"] > 10 * errors["true"] and errors["no lenses"] > 20 * errors["true"], errors


def test_board_calibration_recovers_the_lenses(lens_rig, sphere, estimated):
    """Issue 5's criteria for the planar workflow on the distorted rig, noise-free, absolute.

    A board calibration's world is its own estimate of the camera frame; the rig's true camera
    frame is its world (the camera sits at the origin), so the truth is compared with the
    estimate directly, with no fitted alignment.  That frame's orientation rests on the
    camera's principal point and the scale on its focal length, which a 30-degree lens pins
    down poorly: the absolute figures need the focal length within ~0.03 px (3e-5 of it; 0.2
    px is 0.18 mm at 800 mm) and the principal point within ~0.04 px, i.e. circle centres good
    to a few thousandths of a pixel, which the area-rendered discs and `outline_centroids`
    give (0.0026 px on this grid).  Measured with these 12 poses (benchmarks/distortion.py,
    ninth session): principal point 0.010 px off (OpenCV's std 0.011 px), focal lengths
    0.028 px; the true points reproject within 0.010 px (camera) and 0.012 px (projector), the
    issue's 0.1 px; the sphere's RMS error is 0.091 mm against the true calibration's 0.088
    mm (1.04 times; the issue asks at most 1.1, asserted).  After the best rigid alignment
    (`rigid_alignment`, shape only) the sphere is as good as the truth's (0.076 mm each).
    """
    maps = sequences.decode_frames(sphere.images, SCAN_SPEC)
    ok = on_sphere(sphere.truth)
    scans = {}
    for name, calibration in (("true", lens_rig.calibration), ("estimated", estimated)):
        points = reconstruct.triangulate(maps["rows"].coord, calibration, valid=maps["rows"].valid,
                                         other=maps["columns"].coord)
        ok &= np.isfinite(points[..., 0])
        scans[name] = points
    truth = sphere.truth.points[ok].astype(np.float64)
    np.testing.assert_array_equal(lens_rig.camera.R, np.eye(3))  # the true camera frame is the world
    np.testing.assert_array_equal(lens_rig.camera.t, np.zeros(3))
    errors = {}
    for name, points in scans.items():
        rotation, translation = rigid_alignment(points[ok], truth)
        errors[name] = (rms(points[ok] - truth), rms(points[ok] @ rotation.T + translation - truth))
    assert errors["estimated"][0] <= 1.1 * errors["true"][0], errors
    assert errors["estimated"][1] <= 1.1 * errors["true"][1], errors
    for device in ("camera", "projector"):
        seen = getattr(lens_rig.calibration, device).project(truth)
        assert rms(getattr(estimated, device).project(truth) - seen) < 0.05, device
    principal = estimated.camera.intrinsics[:2, 2] - lens_rig.calibration.camera.intrinsics[:2, 2]
    std = estimated.extra["intrinsics_std_px"]["camera"]
    assert np.hypot(*principal) < 0.05 and max(std["cx"], std["cy"]) < 0.05, (principal, std)
    assert estimated.extra["board"] == {"kind": "symmetric", "size": [15, 11], "spacing": 20.0, "radius": 6.0}
    # f r**2 sin(2 tilt) / (2 Z**2) = 0.023 px at 20 degrees and 800 mm, 6 mm circles
    assert 0.01 < estimated.extra["perspective_bias_px"] < 0.05


# --- the command line ------------------------------------------------------------------------


def run(args: list[str], capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exit_:
        main(args)
    out, err = capsys.readouterr()
    return exit_.value.code, out, err


def test_cli_calibrate_board_with_circles_then_simulate_and_scan(tmp_path: Path, lens_rig, grid_poses, sphere,
                                                                 capsys):
    """calibrate-board on PNG captures of the grid (8-bit: 1/255 quantisation), then sliscan
    simulate and sliscan scan with the calibration it wrote, lenses and all."""
    sequences.save_sequence(tmp_path / "pmp" / "pmp.json", BOARD_SPEC)
    poses = []
    for k, images in enumerate(grid_poses):
        poses.append(tmp_path / f"pose_{k}")
        write_images(sequences.indexed_paths(poses[-1] / "f.png", len(images)), images)
    code, out, err = run(["calibrate-board", *map(str, poses), "--pattern", str(tmp_path / "pmp" / "pmp.json"),
                          "--board", "4x11", "--circles", "asymmetric", "--spacing", "20", "--radius", "5",
                          "-o", str(tmp_path / "rig.json")], capsys)
    assert code == 0, err
    assert "8 of 8 poses, asymmetric circle grid of 4x11 circles (perspective bias" in out
    rig = json.loads((tmp_path / "rig.json").read_text())
    assert rig["board"]["kind"] == "asymmetric" and rig["board"]["radius"] == 5.0
    # 8-bit captures: measured 0.090 / 0.087 px RMS residuals, as from float captures (the local
    # fit of the projector coordinates at a circle averages the quantisation out)
    assert rig["residuals"]["camera"]["rms_px"] < 0.15 and rig["residuals"]["projector"]["rms_px"] < 0.15
    # The lenses are found: k1 within 0.03 of the truth (measured 0.014 and 0.011 off; k1 and k2
    # trade off against each other over a 30-degree view, k2 is 0.2 off).
    assert abs(rig["camera"]["distortion"][0] - CAMERA_LENS[0]) < 0.03
    assert abs(rig["projector"]["distortion"][0] - PROJECTOR_LENS[0]) < 0.03

    # A capture simulated with that calibration (both lenses), scanned with it: the truth back.
    sequences.save_sequence(tmp_path / "scan" / "scan.json", SCAN_SPEC)
    code, _, err = run(["simulate", "--pattern", str(tmp_path / "scan" / "scan.json"), "--scene", "sphere",
                        "--calibration", str(tmp_path / "rig.json"), "--supersample", "1", "--no-noise",
                        "--truth", str(tmp_path / "truth.npz"), "-o", str(tmp_path / "cap" / "scan.png")], capsys)
    assert code == 0, err
    code, out, err = run(["scan", str(tmp_path / "cap"), "--pattern", str(tmp_path / "scan" / "scan.json"),
                          "--calibration", str(tmp_path / "rig.json"), "--npz", str(tmp_path / "s.npz")], capsys)
    assert code == 0, err
    truth = read_truth(tmp_path / "truth.npz")
    points = np.load(tmp_path / "s.npz")["points"]
    ok = np.isfinite(points[..., 0]) & clean_pixels(truth)
    # 8-bit frames of the noise-free scene (sphere and wall): measured 0.094 mm RMS (0.074 mm from
    # float frames through the true lenses, test above); tolerance 0.2 mm.
    assert ok.sum() > 0.9 * clean_pixels(truth).sum() and rms(points[ok] - truth.points[ok]) < 0.2


@pytest.mark.parametrize(("args", "message"), [
    (["--board", "4x11", "--circles", "asymmetric", "--square", "20"],
     "a circle grid (--circles asymmetric) takes --spacing (the circle spacing), not --square"),
    (["--board", "9x7", "--spacing", "20"], "a chessboard (--board with no --circles) takes --square"),
    (["--board", "9x7", "--circles", "symmetric", "--spacing", "20", "--radius", "12"],
     "circle radius must be positive and less than half the distance between neighbouring circles (10)"),
])
def test_cli_calibrate_board_refuses_mixed_board_options(tmp_path, args, message, capsys):
    sequences.save_sequence(tmp_path / "pmp.json", BOARD_SPEC)
    (tmp_path / "pose").mkdir()
    code, _, err = run(["calibrate-board", str(tmp_path / "pose"), "--pattern", str(tmp_path / "pmp.json"), *args,
                        "-o", str(tmp_path / "rig.json")], capsys)
    assert code == 2 and message in err and not (tmp_path / "rig.json").exists()


@pytest.mark.parametrize(("args", "message"), [
    (["--calibration-board", "4x11", "--circles", "asymmetric"],
     "a circle grid (--circles asymmetric) takes --spacing"),
    (["--calibration-target", "t.json", "--square", "30"],
     "leave out --poses, and --square, --circles, --spacing and --radius (they describe a --calibration-board)"),
])
def test_cli_acquire_checks_the_board_options(tmp_path, args, message, capsys):
    sequences.save_sequence(tmp_path / "pmp.json", BOARD_SPEC)
    code, _, err = run(["acquire", "--pattern", str(tmp_path / "pmp.json"), "--camera", "virtual", "--screen",
                        "virtual", *args, "-o", str(tmp_path / "cal")], capsys)
    assert code == 2 and err.count("\n") == 1 and message in err and not (tmp_path / "cal").exists()


def test_cli_calibrate_points_to_the_image_workflows(tmp_path, capsys):
    """`sliscan calibrate` takes measured points (a G file); given captured images it says which
    command calibrates from images, in one line, whatever else is missing."""
    (tmp_path / "pose_0").mkdir()
    for args in ([str(tmp_path / "pose_0")], [str(tmp_path / "pose_0"), str(tmp_path / "pose_1")],
                 [str(tmp_path / "f.png"), "--camera-size", "640x480", "--projector", "512x384", "-o", "r.json"]):
        code, _, err = run(["calibrate", *args], capsys)
        assert code == 2 and err.count("\n") == 1, err
        assert "captured images, not a G file; calibrate from images with sliscan calibrate-board" in err
    code, _, err = run(["calibrate", str(tmp_path / "G.txt"), "-o", str(tmp_path / "r.json")], capsys)
    assert code == 2 and "Missing option '--camera-size'" in err
