"""Calibration from captured images (issue 5): the thesis's 3-D circle target and chessboard poses,
on the virtual rig (truth known) and on real captures (skipped when the data folder is absent)."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from sliscan import InputError, figures, reconstruct, sequences, simulate
from sliscan._validate import read_image, write_images
from sliscan.calibrate import (BoardView, Residuals, board_view, calibrate_board, calibrate_target,
                               ellipse_centres, match_circles, outline_centroids, triangulate_correspondences)
from sliscan.cli import main
from sliscan.formats.premat5 import read_g
from sliscan.pipeline import (MAX_BASELINE_ANGLE_DEG, MAX_STRIPE_TILT_DEG, Scanner, baseline_angle_deg,
                              baseline_direction, stripe_tilt_deg)
from sliscan.targets import Board, CircleTarget, bilinear, detect_circles, local_fit
from sliscan.types import Device, PatternSpec

REAL_DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "procam-chessboard-graycode"
NOISE_FREE = dict(supersample=1, full_well_e=None, bit_depth=None)
TARGET_SPEC = PatternSpec(kind="pmp", orientation="both", steps=4, frequencies=(1, 8, 64), b_p=0.5)
BOARD_PROJECTOR = (512, 384)
BOARD_SPEC = PatternSpec(kind="pmp", orientation="both", steps=4, frequencies=(1, 8), b_p=0.5,
                         projector_size=BOARD_PROJECTOR)
BOARD_TILTS = [(20, 0), (-20, 15), (0, 25), (15, -25)]
CHESSBOARD = Board("chessboard", (9, 7), 30.0)


def rms(d: np.ndarray) -> float:
    """RMS length of vectors (N, k), or RMS of values (N,)."""
    d = np.asarray(d, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum(d**2, axis=-1) if d.ndim > 1 else d**2)))


@pytest.fixture(scope="module")
def target_capture(small_rig):
    """18 dark circles on two faces at 90 degrees, 640x480 camera, 3 x 4 PMP in both directions."""
    scene, albedo, target = simulate.circle_target_scene()
    capture = simulate.render_sequence(small_rig, scene, sequences.render_frames(TARGET_SPEC),
                                       simulate.Conditions(albedo=albedo, **NOISE_FREE))
    return capture, sequences.decode_frames(capture.images, TARGET_SPEC), target


@pytest.fixture(scope="module")
def board_rig():
    return simulate.virtual_rig(camera_size=(480, 360), projector_size=BOARD_PROJECTOR)


@pytest.fixture(scope="module")
def board_captures(board_rig):
    """A 9x7-corner board of 30 mm squares in four poses, 2 x 4 PMP in both directions."""
    frames = sequences.render_frames(BOARD_SPEC)
    out = []
    for tilt in BOARD_TILTS:
        scene, albedo = simulate.board_scene(tilt_deg=tilt, square_mm=30.0)
        out.append(simulate.render_sequence(board_rig, scene, frames,
                                            simulate.Conditions(albedo=albedo, **NOISE_FREE)).images)
    return out


# --- the thesis's workflow -------------------------------------------------------------------


def test_target_calibration_reprojects_and_scans_like_the_truth(small_rig, target_capture):
    """Recovered matrices reproject the true target points within 0.1 px RMS (the issue's bound for
    noise-free captures), and a scan triangulated with them is as good as with the true ones.

    Tolerance of the scan: a projector reprojection error eps (px) moves a point by about
    Z**2 eps / (f_p b) in depth, a camera error by Z eps / f_c sideways; with eps = 0.1 px,
    Z = 710 mm, f_p = 1787 px, f_c = 1194 px, b = 200 mm that is 0.14 + 0.06 = 0.2 mm.
    Measured: 0.032 / 0.044 px, scans 0.029 mm apart, 0.159 mm RMS error against 0.157 mm.
    """
    capture, maps, target = target_capture
    calib, rows = calibrate_target(maps, target, small_rig.calibration.projector.size)
    for name in ("camera", "projector"):
        true = getattr(small_rig.calibration, name).project(target.centres)
        assert rms(getattr(calib, name).project(target.centres) - true) < 0.1, name
    assert rows.shape == (18, 7) and calib.extra["circles"] == 18
    assert 0.15 < calib.extra["perspective_bias_px"] < 0.4  # 10-20 px circles at 45 degrees
    ok = maps["rows"].valid & capture.truth.lit & ~capture.truth.edge
    est = reconstruct.triangulate(maps["rows"].coord, calib)[ok]
    true = reconstruct.triangulate(maps["rows"].coord, small_rig.calibration)[ok]
    truth = capture.truth.points[ok]
    z, fp, fc = float(np.mean(truth[:, 2])), small_rig.projector.K[0, 0], small_rig.camera.K[0, 0]
    assert rms(est - true) < z**2 * 0.1 / (fp * 200.0) + z * 0.1 / fc
    assert rms(est - truth) < 1.1 * rms(true - truth)


def test_without_normals_the_perspective_bias_stays(small_rig, target_capture):
    _, maps, target = target_capture
    calib, _ = calibrate_target(maps, CircleTarget(target.centres), small_rig.calibration.projector.size)
    true = small_rig.calibration.camera.project(target.centres)
    assert calib.extra["perspective_bias_px"] == 0
    assert rms(calib.camera.project(target.centres) - true) > 0.1


def test_circle_centres_are_the_ellipse_centres(small_rig, target_capture):
    """Detected centres sit on the image ellipses' centres (measured 0.045 px RMS, 0.1 px at most:
    one sample per pixel aliases the edges), not on the images of the circle centres (0.18-0.25
    px away, `ellipse_centres`)."""
    capture, maps, target = target_capture
    found = detect_circles(maps["rows"].brightness)
    matrix = small_rig.calibration.camera.matrix
    ellipses = ellipse_centres(matrix, target)
    nearest = np.linalg.norm(found[:, None] - ellipses[None], axis=2).min(axis=0)
    assert len(found) == 18 and rms(nearest) < 0.06 and nearest.max() < 0.15
    bias = np.linalg.norm(ellipses - small_rig.calibration.camera.project(target.centres), axis=1)
    assert 0.15 < bias.min() and bias.max() < 0.3


def test_outline_centroids_are_the_ellipse_centres_without_a_lens_and_move_with_one(small_rig):
    """Through a pinhole the centroid of a circle's image is its ellipse's centre; a barrel lens
    pulls an off-axis disc's centroid toward the image centre by more than it moves its centre's image."""
    _, _, target = simulate.circle_target_scene()
    camera = small_rig.calibration.camera
    n = target.normals[0]
    u = np.cross(n, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    axes = np.stack([u, np.cross(n, u)])
    face = np.all(np.isclose(target.normals, n, atol=1e-9), axis=1)
    centroids = outline_centroids(camera, target.centres[face], axes, target.radius_mm)
    np.testing.assert_allclose(centroids, ellipse_centres(camera.matrix, target)[face], atol=1e-4)
    k = camera.intrinsics
    barrel = Device(camera.matrix, camera.size, intrinsics=k, distortion=(-0.2, 0.0, 0.0, 0.0, 0.0))
    pulled = outline_centroids(barrel, target.centres[face], axes, target.radius_mm) - \
        (barrel.project(target.centres[face]) + centroids - camera.project(target.centres[face]))
    outward = barrel.project(target.centres[face]) - k[:2, 2]
    assert np.all(np.einsum("nk,nk->n", pulled, outward) < 0)


def test_ellipse_centres_fit_the_projected_outline(small_rig):
    _, _, target = simulate.circle_target_scene()
    matrix = small_rig.calibration.camera.matrix
    k, n = 3, target.normals[3]
    u = np.cross(n, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    angles = np.linspace(0, 2 * np.pi, 360, endpoint=False)[:, None]
    outline = target.centres[k] + target.radius_mm * (np.cos(angles) * u + np.sin(angles) * np.cross(n, u))
    (cx, cy), _, _ = cv2.fitEllipse(small_rig.calibration.camera.project(outline).astype(np.float32))
    assert np.allclose(ellipse_centres(matrix, target)[k], [cx, cy], atol=1e-3)


def test_match_circles_finds_the_order_and_refuses_symmetry(small_rig, rng):
    _, _, target = simulate.circle_target_scene()
    pixels = small_rig.calibration.camera.project(target.centres)
    shuffled = rng.permutation(len(pixels))
    assert np.array_equal(shuffled[match_circles(pixels[shuffled], target.centres)], np.arange(18))
    mirrored = target.centres.copy()
    left = mirrored[:, 0] < 0
    mirrored[~left] = mirrored[left] * [-1, 1, 1]  # the right face: the left one mirrored, a symmetric target
    with pytest.raises(InputError, match="ambiguous"):
        match_circles(small_rig.calibration.camera.project(mirrored), mirrored)
    with pytest.raises(InputError, match="found 17 circles, the target has 18"):
        match_circles(pixels[:17], target.centres)


def test_sampling_uses_only_valid_pixels():
    y, x = np.mgrid[0:40, 0:40].astype(np.float64)
    coord = 3.0 + 0.5 * x + 0.25 * y + 0.001 * x * y
    valid = np.ones_like(coord, dtype=bool)
    valid[15:25, 15:25] = False  # a dark circle that did not decode
    coord[~valid] = 1e6  # garbage where invalid must never leak in
    points = np.array([[5.3, 7.6], [20.0, 20.0]])
    direct = bilinear(coord, valid, points)
    assert direct[0] == pytest.approx(3 + 0.5 * 5.3 + 0.25 * 7.6 + 0.001 * 5.3 * 7.6, abs=1e-3) and np.isnan(direct[1])
    fitted = local_fit(coord, valid, points, half_window=10)
    assert fitted == pytest.approx([3 + 2.65 + 1.9 + 0.001 * 5.3 * 7.6, 3 + 10 + 5 + 0.4], abs=1e-6)


def test_target_file_round_trip_and_errors(tmp_path):
    _, _, target = simulate.circle_target_scene()
    target.save(tmp_path / "t.json")
    loaded = CircleTarget.load(tmp_path / "t.json")
    assert np.allclose(loaded.centres, target.centres) and loaded.radius_mm == target.radius_mm
    (tmp_path / "bad.json").write_text(json.dumps({"circles": [[0, 0, 0]], "normals": [[0, 0, 1]]}))
    with pytest.raises(InputError, match=r"bad\.json: give both normals and radius_mm"):
        CircleTarget.load(tmp_path / "bad.json")


# --- the planar workflow ---------------------------------------------------------------------


def test_board_calibration_recovers_the_virtual_rig(board_rig, board_captures):
    """Four noise-free poses at 480x360, one sample per pixel: the aliased edges leave the corners
    0.44 px RMS from the truth, which limits the focal lengths to about 1 % (measured 0.9 % for
    the camera, 0.4 % for the projector, 0.6-0.9 % with 8 poses or 2x2 samples): tolerance 2 %.
    The projector centre is 3.4 mm from the truth (baseline 200 mm; tolerance 5 mm), the board
    is flat and regular (the relative geometry is good), and exact pixel pairs triangulate 8.8 mm
    RMS from the truth: the 1 % scale error of the focal lengths at 800 mm (tolerance 2 %)."""
    views = [board_view(sequences.decode_frames(images, BOARD_SPEC), CHESSBOARD, interpolate=True)
             for images in board_captures]
    calib = calibrate_board(views, CHESSBOARD, board_rig.camera.size, BOARD_PROJECTOR, projector_distortion=False)
    assert calib.camera.intrinsics[0, 0] == pytest.approx(board_rig.camera.K[0, 0], rel=0.02)
    assert calib.projector.intrinsics[0, 0] == pytest.approx(board_rig.projector.K[0, 0], rel=0.02)
    extrinsic = np.linalg.solve(calib.projector.intrinsics, calib.projector.matrix)
    centre = -extrinsic[:, :3].T @ extrinsic[:, 3]
    assert np.linalg.norm(centre - board_rig.projector.centre) < 5.0
    assert not np.any(calib.projector.distortion)
    for device in ("camera", "projector"):
        assert calib.extra["residuals"][device]["rms_px"] < 0.5
    for view in calib.extra["views"]:
        assert view["planarity_rms"] < 0.5 and abs(view["spacing_error"]) < 0.005
    assert calib.extra["outlier_views"] == []
    scene, albedo = simulate.board_scene(tilt_deg=BOARD_TILTS[0], square_mm=30.0)
    cam, proj = (d.project(albedo.corners) for d in (board_rig.calibration.camera, board_rig.calibration.projector))
    assert rms(triangulate_correspondences(calib, cam, proj) - albedo.corners) < 0.02 * 800.0  # mm


def test_board_view_errors(board_captures):
    maps = sequences.decode_frames(board_captures[0], BOARD_SPEC)
    with pytest.raises(InputError, match="no chessboard of 8x7 inner corners found"):
        board_view(maps, Board("chessboard", (8, 7), 30.0))
    with pytest.raises(InputError, match="need at least 3 board views, got 1"):
        calibrate_board([board_view(maps, CHESSBOARD)], CHESSBOARD, (480, 360), BOARD_PROJECTOR)
    view = board_view(maps, CHESSBOARD)
    with pytest.raises(InputError, match=r"^view 0 has 63 points, the symmetric circle grid of 7x6 circles has 42$"):
        calibrate_board([view] * 3, Board("symmetric", (7, 6), 20.0), (480, 360), BOARD_PROJECTOR)


# --- circle grids ----------------------------------------------------------------------------


@pytest.mark.parametrize("board", [Board("asymmetric", (4, 11), 20.0, 5.0), Board("symmetric", (7, 6), 25.0, 7.0)])
def test_circle_grid_centres_are_the_ellipse_centres(board_rig, board):
    """On a grid tilted by 35 degrees (2x2 samples per pixel, noise-free) the centres come in
    OpenCV's order, at the image ellipses' centres to 0.05 px RMS (measured 0.03-0.04 px: the
    aliasing of the edges), where OpenCV's own blob centres are 0.07 px off."""
    tilt, offset = simulate.calibration_poses(8, tilt_deg=35.0, offset_mm=(70.0, 50.0))[1]
    scene, albedo, centres = simulate.circle_grid_scene(board, tilt_deg=tilt, offset_mm=offset)
    image = simulate.render(board_rig, scene, np.ones(board_rig.projector.shape),
                            simulate.Conditions(albedo=albedo, supersample=2, full_well_e=None, bit_depth=None)).image
    found = board.detect(image)
    normal = np.cross(centres[1] - centres[0], centres[board.size[0]] - centres[0])
    target = CircleTarget(centres, np.tile(normal, (len(centres), 1)), board.radius)
    ellipses = ellipse_centres(board_rig.calibration.camera.matrix, target)
    assert found.shape == (len(centres), 2) and rms(found - ellipses) < 0.05
    u8 = np.round(image / np.percentile(image, 99.5) * 255).clip(0, 255).astype(np.uint8)
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if board.kind == "asymmetric" else cv2.CALIB_CB_SYMMETRIC_GRID
    _, blobs = cv2.findCirclesGrid(u8, board.size, flags=flags)
    assert rms(found - ellipses) < 0.8 * rms(blobs.reshape(-1, 2) - ellipses)
    assert board.detect(np.full_like(image, 0.8)) is None


def test_perspective_bias_of_circle_grids_is_removed(board_rig, rng):
    """Exact synthetic views of big circles (radius 15 mm, 40 mm apart, tilted 40 degrees: a
    0.1-0.2 px perspective bias): the camera sees the image ellipses' centres and the projector
    is read where the camera sees them.  With the radius the calibration is exact (measured:
    focal length 2e-5 px off, points triangulated 1e-4 mm off); without, the bias hides in the
    parameters (residuals stay under 3e-4 px) and costs 0.37 px of focal length and 0.34 mm.
    For OpenCV's 4x11 grid of 5 mm circles the same comparison gives 0.04 mm (the bias is
    ~0.02 px)."""
    board = Board("symmetric", (6, 5), 40.0, 15.0)
    calibration = board_rig.calibration
    views = []
    for tilt, offset in simulate.calibration_poses(6, tilt_deg=40.0, offset_mm=(30.0, 20.0)):
        plane, _, centres = simulate.circle_grid_scene(board, tilt_deg=tilt, offset_mm=offset)
        target = CircleTarget(centres, np.tile(plane.normal, (len(centres), 1)), board.radius)
        camera = ellipse_centres(calibration.camera.matrix, target)
        rays = board_rig.camera.rays(camera[:, 0], camera[:, 1])
        depth, _ = plane.intersect(np.zeros_like(rays), rays)
        views.append(BoardView(camera, calibration.projector.project(rays * depth[:, None])))
    world = rng.uniform([-120, -100, 700], [120, 100, 900], (500, 3))
    pixels = [d.project(world) for d in (calibration.camera, calibration.projector)]
    errors = {}
    for name, layout in (("corrected", board), ("biased", replace(board, radius=None))):
        calib = calibrate_board(views, layout, board_rig.camera.size, BOARD_PROJECTOR)
        errors[name] = (abs(calib.camera.intrinsics[0, 0] - board_rig.camera.K[0, 0]),
                        rms(triangulate_correspondences(calib, *pixels) - world), calib.extra["perspective_bias_px"])
        assert calib.extra["residuals"]["projector"]["rms_px"] < 1e-3
    assert 0.1 < errors["corrected"][2] < 0.3 and errors["biased"][2] == 0
    assert errors["corrected"][0] < 0.01 and errors["corrected"][1] < 0.01  # px, mm
    assert errors["biased"][0] > 0.2 and errors["biased"][1] > 0.2


def test_board_descriptions_and_errors():
    assert Board("asymmetric", (4, 11), 20.0).describe() == "asymmetric circle grid of 4x11 circles"
    assert Board("chessboard", (9, 7), 25.0).to_dict() == {"kind": "chessboard", "size": [9, 7], "spacing": 25.0}
    assert len(Board("asymmetric", (4, 11), 20.0).neighbours()) == 70  # diagonal neighbours: 2 x 3 x 10 + 10
    for args, message in ((("hexagon", (4, 4), 1.0), "board kind must be one of"),
                          (("symmetric", (2, 5), 1.0), r"a symmetric board needs at least 3x3 points, got \(2, 5\)"),
                          (("chessboard", (9, 7), -1.0), "board spacing must be positive, got -1.0"),
                          (("chessboard", (9, 7), 25.0, 5.0), "a chessboard has no circle radius")):
        with pytest.raises(InputError, match=message):
            Board(*args)
    with pytest.raises(InputError, match="a circle grid scene needs a circle grid with its radius"):
        simulate.circle_grid_scene(Board("symmetric", (7, 6), 25.0))


def test_block_pixels_weigh_by_their_resolution():
    """A plain Gray code decoded gracefully: full codes (one line: the true line rounded, +-0.5)
    and, over half the window (from the point on), blocks of 8 lines whose centres here all lie
    0.6 line above the truth (within the 1-line floor of the outlier test, so nothing removes
    them; a block's centre may be up to 4 lines off).  Unweighted, they pull the fit at the
    point by half their offset (measured 0.28 line); weighted by 1/block**2 (a block's variance
    is block**2 / 12) by a quarter of that (measured 0.064 line: what is left is the quadratic
    model bending over the step)."""
    y, x = np.mgrid[0:41, 0:41].astype(np.float64)
    true = 100.0 + 0.8 * x + 0.3 * y
    coord, block = np.round(true), np.ones(true.shape, dtype=np.int32)
    blocks = x > 20
    coord[blocks] = true[blocks] + 0.6
    block[blocks] = 8
    valid = np.ones(true.shape, dtype=bool)
    point = np.array([[20.0, 20.0]])
    weighted = abs(local_fit(coord, valid, point, half_window=15, block=block)[0] - true[20, 20])
    plain = abs(local_fit(coord, valid, point, half_window=15)[0] - true[20, 20])
    assert weighted < 0.1 and plain > 0.2 and weighted < plain / 3


@pytest.fixture(scope="module")
def real_chessboard():
    """kamino410/procam-calibration's 3 poses (OpenCV Gray code order, 1280x1024, 1024x768): the
    spec, each pose's frames and board view, and the calibration from them."""
    if not REAL_DATA.is_dir():
        pytest.skip("real captures (shared/data) not available")
    spec = PatternSpec(kind="graycode", orientation="both", projector_size=(1024, 768))
    board = Board("chessboard", (9, 7), 75.0)
    poses = [[read_image(p) for p in sorted((REAL_DATA / f"capture_{k}").glob("*.png"))] for k in range(3)]
    views = [board_view(sequences.decode_frames(frames, spec), board) for frames in poses]
    return spec, poses, views, calibrate_board(views, board, (1280, 1024), (1024, 768))


def test_real_chessboard_calibrates(real_chessboard):
    """Measured: camera view RMS 0.20-0.45 px, projector 0.13-0.28 px; the corners triangulated
    with the result lie within 0.42-0.78 units RMS of a plane (the board is 750 x 600 units) and
    their mean spacing is within 0.4 % of 75."""
    calib = real_chessboard[3]
    for view in calib.extra["views"]:
        assert view["camera_rms_px"] < 1.0 and view["projector_rms_px"] < 1.0
        assert view["projector_corners"] == 63
        assert view["planarity_rms"] < 1.5 and abs(view["spacing_error"]) < 0.01


def test_real_rigs_geometry_for_single_shot_patterns(real_chessboard):
    """The real rig codes rows best (its camera mostly below the projector); its projector rows
    cross the camera's rows at 1.5 degrees (measured 1.53), under `MAX_STRIPE_TILT_DEG`, but its
    projector also sits to the side: the camera's epipolar lines turn up to 13.6 degrees from its
    columns (measured 13.60), over `MAX_BASELINE_ANGLE_DEG`, which a composite scan warns about.
    The bounds leave room for another OpenCV's calibration of the same views."""
    calib = real_chessboard[3]
    assert baseline_direction(calib) == "rows"
    assert 1.0 < stripe_tilt_deg(calib, "rows") < MAX_STRIPE_TILT_DEG
    assert MAX_BASELINE_ANGLE_DEG < baseline_angle_deg(calib, "rows") < 17.0


def test_real_chessboard_depth_edge_filters_keep_the_board(real_chessboard):
    """The multi-shot filters of the blur's mixed pixels on a real plane: the jump edges drop
    no pixel inside the board's corners, the shadow sides only white squares' borders with
    the black ones (2.8 % of the board's decoded pixels in this pose when this test was
    written; 4 % leaves room), and what is kept lies no farther from the board's plane (RMS
    2.800 -> 2.778 units)."""
    spec, poses, views, calib = real_chessboard
    hull = cv2.convexHull(views[0].camera.astype(np.float32)).astype(np.int32)
    board = np.zeros((1024, 1280), np.uint8)
    cv2.fillConvexPoly(board, hull, 1)
    board = board.astype(bool)
    scans = [Scanner(spec, calib, **options).scan(poses[0]) for options in
             (dict(remove_jump_edges=False, remove_shadow_sides=False), dict(remove_shadow_sides=False), {})]
    neither, jump_edges, both = (scan.valid & board for scan in scans)
    assert (jump_edges == neither).all()
    assert 0 < (neither & ~both).sum() < 0.04 * neither.sum()
    points = scans[0].points
    centre = points[neither].mean(axis=0)
    normal = np.linalg.svd(points[neither] - centre, full_matrices=False)[2][2]
    distance = np.abs((points - centre) @ normal)
    assert np.sqrt(np.mean(distance[both] ** 2)) <= np.sqrt(np.mean(distance[neither] ** 2))


# --- the command line ------------------------------------------------------------------------


def run(args: list[str], capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exit_:
        main(args)
    out, err = capsys.readouterr()
    return exit_.value.code, out, err


@pytest.fixture
def plotted(monkeypatch) -> list[list[dict]]:
    """The panels (view, device, RMS) of every residual plot the CLI draws."""
    pytest.importorskip("matplotlib")
    calls: list[list[dict]] = []
    real = figures.plot_residuals

    def spy(*args, **kwargs):
        calls.append(real(*args, **kwargs))
        return calls[-1]

    monkeypatch.setattr("sliscan.cli.plot_residuals", spy)
    return calls


def check_png(path: Path, rows: int) -> None:
    """A readable PNG of two 360-px panels per row (3.6 in at 100 dpi)."""
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.imread(str(path))
    assert image is not None and image.shape[1] == 720 and 360 * rows <= image.shape[0] <= 360 * rows + 60
    assert not list(path.parent.glob(f".{path.name}.*"))  # no temporary file left


def test_plot_without_matplotlib_says_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    residuals = Residuals(("v",), (np.zeros((3, 2)),), (np.zeros((3, 2)),))
    with pytest.raises(InputError, match=r"^plotting needs matplotlib: pip install 'sliscan\[plot\]'$"):
        figures.plot_residuals(tmp_path / "r.png", residuals)
    assert not list(tmp_path.iterdir())


def test_cli_calibrate_target(tmp_path, small_rig, target_capture, capsys, plotted):
    capture, _, target = target_capture
    sequences.save_sequence(tmp_path / "pmp" / "pmp.json", TARGET_SPEC)
    frames = sequences.indexed_paths(tmp_path / "cap" / "cap.png", len(capture.images))
    write_images(frames, capture.images)
    target.save(tmp_path / "target.json")
    base = ["calibrate-target", str(tmp_path / "cap"), "--pattern", str(tmp_path / "pmp" / "pmp.json")]
    code, out, err = run(base + ["--target", str(tmp_path / "target.json"), "-o", str(tmp_path / "rig.json"),
                                 "--g-file", str(tmp_path / "G.byt"), "--plot", str(tmp_path / "res.png")], capsys)
    assert code == 0, err
    assert "18 circles" in out and "rig.json" in out and "res.png" in out
    assert read_g(tmp_path / "G.byt").shape == (18, 7)
    rig = json.loads((tmp_path / "rig.json").read_text())
    assert rig["residuals"]["projector"]["rms_px"] < 0.2
    # The plot: one row (camera, projector) of the 18 circles, with the JSON's RMS values.
    check_png(tmp_path / "res.png", rows=1)
    [panels] = plotted
    assert [(p["device"], p["points"]) for p in panels] == [("camera", 18), ("projector", 18)]
    for p in panels:
        assert p["rms_px"] == pytest.approx(rig["residuals"][p["device"]]["rms_px"], rel=1e-9)
    code, _, err = run(base + ["--target", str(tmp_path / "target.json"), "-o", str(tmp_path / "rig2.json"),
                               "--plot", str(tmp_path / "res.png")], capsys)
    assert code == 2 and "res.png exists (use --overwrite)" in err and not (tmp_path / "rig2.json").exists()

    CircleTarget(np.vstack([target.centres, [[0.0, 0.0, 700.0]]])).save(tmp_path / "19.json")
    code, _, err = run(base + ["--target", str(tmp_path / "19.json"), "-o", str(tmp_path / "bad.json")], capsys)
    assert code == 2 and err.count("\n") == 1 and "found 18 circles, the target has 19" in err
    frames[-1].unlink()
    code, _, err = run(base + ["--target", str(tmp_path / "target.json"), "-o", str(tmp_path / "bad.json")], capsys)
    assert code == 2 and err.count("\n") == 1 and "needs 24 frames" in err and "cap_00.png" in err
    assert not (tmp_path / "bad.json").exists()


def test_cli_calibrate_board_skips_a_pose_without_a_board(tmp_path, board_captures, capsys, plotted):
    sequences.save_sequence(tmp_path / "pmp.json", BOARD_SPEC)
    poses = []
    for k, images in enumerate([*board_captures, np.zeros_like(board_captures[0])]):
        poses.append(tmp_path / f"pose_{k}")
        write_images(sequences.indexed_paths(poses[-1] / "f.png", len(images)), images)
    base = ["calibrate-board", "--pattern", str(tmp_path / "pmp.json"), "--board", "9x7", "--square", "30"]
    code, out, err = run(base + [*map(str, poses), "-o", str(tmp_path / "rig.json"),
                                 "--plot", str(tmp_path / "res.png")], capsys)
    assert code == 0, err
    assert "pose_4: no chessboard of 9x7 inner corners found; skipping this pose" in err
    assert "4 of 5 poses" in out and "res.png" in out
    rig = json.loads((tmp_path / "rig.json").read_text())
    assert len(rig["camera"]["distortion"]) == 5 and len(rig["views"]) == 4
    assert not any(isinstance(x, list) for v in rig["views"] for x in v.values())  # no residual vectors in it
    # The plot: a row per good pose, its camera and projector RMS those of the JSON.
    check_png(tmp_path / "res.png", rows=4)
    [panels] = plotted
    assert [p["view"] for p in panels] == [f"pose_{k}" for k in range(4) for _ in range(2)]
    for p in panels:
        view = rig["views"][int(p["view"][-1])]
        assert p["rms_px"] == view[f"{p['device']}_rms_px"]
        assert p["points"] == view["corners" if p["device"] == "camera" else "projector_corners"]

    code, _, err = run(base + [*map(str, poses[2:]), "-o", str(tmp_path / "bad.json")], capsys)
    assert code == 2 and "only 2 of 3 poses are usable" in err
    assert not (tmp_path / "bad.json").exists()


def test_cli_calibrate_board_refuses_poses_of_different_sizes(tmp_path, board_captures, capsys):
    sequences.save_sequence(tmp_path / "pmp.json", BOARD_SPEC)
    write_images(sequences.indexed_paths(tmp_path / "pose_0" / "f.png", len(board_captures[0])), board_captures[0])
    write_images([tmp_path / "small" / "f.png"], np.zeros((1, 80, 100), np.float32))
    code, _, err = run(["calibrate-board", str(tmp_path / "pose_0"), str(tmp_path / "small"), "--pattern",
                        str(tmp_path / "pmp.json"), "--board", "9x7", "--square", "30", "-o",
                        str(tmp_path / "rig.json")], capsys)
    assert code == 2 and err.count("\n") == 1 and "f.png: the frame is 100x80 but the first pose's are 480x360" in err
