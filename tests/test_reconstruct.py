"""Triangulation (thesis eqs. 4.13-4.22): project world points exactly, triangulate them back."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_calibrate import WORKING_DISTANCE_MM, make_rig

from sliscan import Calibration, Device, InputError
from sliscan.reconstruct import Triangulator, _solve, triangulate, triangulate_points

# The projector sits 200 mm above the camera for rows (vertical baseline, the thesis's rig) and
# 200 mm to its right for columns (horizontal baseline): each orientation needs its baseline
# across the coded projector lines.
BASELINES = {"rows": (0.0, -200.0, 0.0), "columns": (200.0, 0.0, 0.0)}
CODED = {"rows": 1, "columns": 0}  # which projector pixel coordinate the map holds

# float32 output: at ~1 m its spacing is 6e-5 mm, so 1e-3 mm (1e-6 of the working distance)
# bounds rounding with a wide margin; the float64 solve itself contributes < 1e-9 mm.
ATOL_FLOAT32_MM = 1e-3
# float64 output (triangulate_points): observed errors are ~1e-12 mm.
ATOL_FLOAT64_MM = 1e-7


def rig(orientation: str) -> Calibration:
    camera, projector = make_rig(BASELINES[orientation])
    return Calibration(camera, projector)


def sphere_scene(calibration: Calibration, *, centre=(0.0, 0.0, WORKING_DISTANCE_MM), radius=150.0):
    """World point seen by every camera pixel (NaN where the ray misses the sphere)."""
    k = calibration.camera.intrinsics
    h, w = calibration.camera.shape
    yc, xc = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([xc, yc, np.ones_like(xc)], axis=-1) @ np.linalg.inv(k).T
    centre = np.asarray(centre)
    # |t ray - centre|^2 = radius^2, nearest root.
    a = np.einsum("...i,...i", rays, rays)
    b = -2 * rays @ centre
    c = centre @ centre - radius**2
    disc = b**2 - 4 * a * c
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)
    return rays * t[..., None]


def coded_map(calibration: Calibration, xyz_w: np.ndarray, orientation: str) -> np.ndarray:
    return calibration.projector.project(xyz_w)[..., CODED[orientation]]


@pytest.mark.parametrize("orientation", ["rows", "columns"])
def test_sphere_round_trip(orientation):
    calibration = rig(orientation)
    truth = sphere_scene(calibration)
    hit = np.isfinite(truth[..., 0])
    assert 0.2 < hit.mean() < 0.9  # the sphere fills part of the view
    xyz_w = triangulate(coded_map(calibration, truth, orientation), calibration, orientation=orientation)
    assert xyz_w.dtype == np.float32 and xyz_w.shape == (480, 640, 3)
    np.testing.assert_array_equal(np.isfinite(xyz_w[..., 0]), hit)
    np.testing.assert_allclose(xyz_w[hit], truth[hit], rtol=0, atol=ATOL_FLOAT32_MM)


def test_plane_round_trip_with_valid_mask_and_chunks(rng):
    calibration = rig("rows")
    truth = sphere_scene(calibration, radius=1e7, centre=(0.0, 0.0, 1e7 + 900.0))  # ~ the plane Z = 900
    proj_map = coded_map(calibration, truth, "rows").astype(np.float32)
    valid = rng.random(proj_map.shape) < 0.7
    full = triangulate(proj_map, calibration, valid=valid)
    assert np.all(np.isnan(full[~valid]))
    # float32 input: yp is rounded to ~1e-5 px, i.e. ~1e-4 mm in depth at this geometry.
    np.testing.assert_allclose(full[valid], truth[valid], rtol=0, atol=0.01)
    for chunk_rows in (1, 37, 10_000):
        np.testing.assert_array_equal(triangulate(proj_map, calibration, valid=valid, chunk_rows=chunk_rows), full)


def test_triangulate_does_not_modify_its_input():
    calibration = rig("rows")
    proj_map = coded_map(calibration, sphere_scene(calibration), "rows")
    before = proj_map.copy()
    triangulate(proj_map, calibration)
    np.testing.assert_array_equal(proj_map, before)


def test_integer_map_and_empty_map():
    calibration = rig("rows")
    xyz_w = triangulate(np.full((480, 640), 96, dtype=np.int16), calibration)
    assert np.all(np.isfinite(xyz_w))
    assert np.all(np.isnan(triangulate(np.full((480, 640), np.nan), calibration)))


@settings(max_examples=200, deadline=None)
@given(x=st.floats(-150, 150), y=st.floats(-100, 100), z=st.floats(500, 1200),
       orientation=st.sampled_from(["rows", "columns"]))
def test_project_then_triangulate_returns_the_point(x, y, z, orientation):
    calibration = rig(orientation)
    point = np.array([[x, y, z]])
    xc, yc = calibration.camera.project(point).T
    got = triangulate_points(xc, yc, coded_map(calibration, point, orientation), calibration,
                             orientation=orientation)
    np.testing.assert_allclose(got, point, rtol=0, atol=ATOL_FLOAT64_MM)


def test_scattered_points_match_the_grid():
    calibration = rig("rows")
    proj_map = coded_map(calibration, sphere_scene(calibration), "rows")
    rows, cols = np.nonzero(np.isfinite(proj_map))
    points = triangulate_points(cols, rows, proj_map[rows, cols], calibration)
    assert points.dtype == np.float64
    # the grid's per-pixel coefficients (`Triangulator`): equal to float32 rounding
    np.testing.assert_allclose(triangulate(proj_map, calibration)[rows, cols], points, rtol=1e-6)


def test_nan_and_ill_conditioned_points_are_nan():
    calibration = rig("rows")
    got = triangulate_points([319.5, 100.0], [239.5, 100.0], [np.nan, 90.0], calibration)
    assert np.all(np.isnan(got[0])) and np.all(np.isfinite(got[1]))
    # Vertical baseline, columns coded: the projector's centre column is the plane X = 0, which
    # holds the camera centre, so the camera's centre-column rays lie in it (det C = 0).
    got = triangulate_points([319.5], [239.5], [127.5], calibration, orientation="columns")
    assert np.all(np.isnan(got))


def test_camera_distortion_is_undistorted(rng):
    camera, projector = make_rig()
    dist = np.array([-0.12, 0.05, 5e-4, -3e-4, 0.0])
    k = camera.intrinsics
    calibration = Calibration(Device(camera.matrix, camera.size, intrinsics=k, distortion=dist), projector)
    world = rng.uniform([-150, -100, 700], [150, 100, 900], size=(100, 3))
    observed, _ = cv2.projectPoints(world, np.zeros(3), np.zeros(3), k, dist)
    xc, yc = observed[:, 0].T
    yp = projector.project(world)[:, 1]
    got = triangulate_points(xc, yc, yp, calibration)
    # Iterative undistortion stops at 1e-10 px; 1e-6 mm is far above that mapped to depth.
    np.testing.assert_allclose(got, world, rtol=0, atol=1e-6)
    ignoring = triangulate_points(xc, yc, yp, Calibration(camera, projector))
    assert np.abs(ignoring - world).max() > 1.0  # the distortion matters at this strength
    # The grid path undistorts the same way.
    proj_map = np.full(camera.shape, np.nan)
    proj_map[::50, ::50] = 90.0
    rows, cols = np.nonzero(np.isfinite(proj_map))
    np.testing.assert_allclose(triangulate(proj_map, calibration)[rows, cols],
                               triangulate_points(cols, rows, proj_map[rows, cols], calibration), rtol=1e-6)


# ---------------------------------------------------------------------------------------- errors

def test_shape_errors():
    calibration = rig("rows")
    with pytest.raises(InputError, match=r"^proj_map must have shape \(480, 640\) \(H, W\), got \(640, 480\)$"):
        triangulate(np.zeros((640, 480)), calibration)
    with pytest.raises(InputError, match=r"valid must be a bool array of shape \(480, 640\)"):
        triangulate(np.zeros((480, 640)), calibration, valid=np.ones((480, 640), dtype=np.uint8))
    with pytest.raises(InputError, match="xc, yc and proj must be 1-D arrays of one length"):
        triangulate_points([1.0, 2.0], [1.0], [1.0, 2.0], calibration)


@pytest.mark.parametrize(("value", "message"), [
    (np.inf, r"proj_map has infinite values \(use NaN for undecoded pixels\)"),
    (True, "proj_map must be a real-valued"),
])
def test_bad_map_values(value, message):
    proj_map = np.zeros((480, 640), dtype=type(value))
    proj_map[5, 5] = value
    with pytest.raises(InputError, match=message):
        triangulate(proj_map, rig("rows"))


def test_bad_options():
    calibration = rig("rows")
    proj_map = np.zeros((480, 640))
    with pytest.raises(InputError, match="orientation must be one of"):
        triangulate(proj_map, calibration, orientation="diagonal")
    with pytest.raises(InputError, match="chunk_rows must be a positive integer, got 0"):
        triangulate(proj_map, calibration, chunk_rows=0)
    with pytest.raises(InputError, match="xc and yc must be finite"):
        triangulate_points([np.nan], [1.0], [1.0], calibration)


# Realistic lenses (OpenCV's k1, k2, p1, p2, k3): 3-15 px of distortion at the image corners.
CAMERA_LENS = np.array([-0.12, 0.05, 5e-4, -3e-4, 0.0])
PROJECTOR_LENS = np.array([0.09, -0.04, -8e-4, 6e-4, 0.0])


def with_lenses(calibration: Calibration, camera_lens=CAMERA_LENS, projector_lens=PROJECTOR_LENS) -> Calibration:
    devices = [Device(d.matrix, d.size, intrinsics=d.intrinsics, distortion=lens)
               for d, lens in ((calibration.camera, camera_lens), (calibration.projector, projector_lens))]
    return Calibration(*devices)


@pytest.mark.parametrize("orientation", ["rows", "columns"])
def test_projector_distortion_is_undistorted(orientation, rng):
    """Decoded projector coordinates are distorted pixels: with one coordinate the point is solved
    on the epipolar line (Newton, to 1e-6 px), with both it is undistorted exactly.  1e-6 px of
    projector coordinate moves a point by Z**2 / (f_p b) * 1e-6 = 900**2 / (400 * 200) * 1e-6 =
    1e-5 mm at most in this volume: tolerance 2e-5 mm."""
    calibration = with_lenses(rig(orientation))
    world = rng.uniform([-150, -100, 700], [150, 100, 900], size=(200, 3))
    observed = calibration.projector.project(world)
    rvec, _ = cv2.Rodrigues(np.linalg.solve(calibration.projector.intrinsics, calibration.projector.matrix)[:, :3])
    tvec = np.linalg.solve(calibration.projector.intrinsics, calibration.projector.matrix[:, 3])
    expected = cv2.projectPoints(world, rvec, tvec, calibration.projector.intrinsics, PROJECTOR_LENS)[0][:, 0]
    np.testing.assert_allclose(observed, expected, rtol=0, atol=1e-9)  # Device.project is OpenCV's model
    xc, yc = calibration.camera.project(world).T
    coded, other = observed[:, CODED[orientation]], observed[:, 1 - CODED[orientation]]
    got = triangulate_points(xc, yc, coded, calibration, orientation=orientation)
    np.testing.assert_allclose(got, world, rtol=0, atol=2e-5)
    exact = triangulate_points(xc, yc, coded, calibration, orientation=orientation, other=other)
    np.testing.assert_allclose(exact, world, rtol=0, atol=2e-5)
    pinhole_projector = with_lenses(rig(orientation), projector_lens=None)
    ignoring = triangulate_points(xc, yc, coded, pinhole_projector, orientation=orientation)
    # Ignoring the projector's lens (1-2 px at its corners) costs 0.5-0.8 mm RMS here: 1e4 x the tolerance.
    assert np.sqrt(np.mean(np.sum((ignoring - world) ** 2, axis=1))) > 0.2
    # The grid path (Triangulator) solves the same way, with or without the other coordinate.
    h, w = calibration.camera.shape
    yc, xc = np.mgrid[0:h:40, 0:w:40].reshape(2, -1).astype(float)
    ray = calibration.camera.intrinsics @ np.eye(3)
    depth = rng.uniform(700, 900, xc.size)
    points = np.linalg.solve(ray, np.stack([*lens_undistort(calibration, xc, yc), np.ones_like(xc)])).T * depth[:, None]
    proj = calibration.projector.project(points)
    proj_map, other_map = np.full((2, h, w), np.nan)
    proj_map[yc.astype(int), xc.astype(int)] = proj[:, CODED[orientation]]
    other_map[yc.astype(int), xc.astype(int)] = proj[:, 1 - CODED[orientation]]
    for other_arg in (None, other_map):
        grid = triangulate(proj_map, calibration, orientation=orientation, other=other_arg)
        # float32 output at 900 mm: 6e-5 mm spacing; ATOL_FLOAT32_MM bounds it.
        np.testing.assert_allclose(grid[yc.astype(int), xc.astype(int)], points, rtol=0, atol=ATOL_FLOAT32_MM)


def lens_undistort(calibration: Calibration, xc: np.ndarray, yc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ideal camera pixels of observed ones (OpenCV's own undistortPoints, P = K)."""
    k = calibration.camera.intrinsics
    ideal = cv2.undistortPoints(np.stack([xc, yc], -1).reshape(-1, 1, 2), k, calibration.camera.distortion, P=k,
                                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))[:, 0]
    return ideal[:, 0], ideal[:, 1]


def test_projector_points_beyond_the_lens_model_are_nan():
    """A decoded row that no point on the ray can produce (beyond where the projector's barrel
    model folds back) is not triangulated: NaN, not a wrong point."""
    calibration = with_lenses(rig("rows"), projector_lens=np.array([-0.6, 0, 0, 0, 0]))
    # The camera's central ray meets the projector's central column (u = 0), where with k1 = -0.6
    # y_d = y (1 - 0.6 y**2) peaks at y = 0.745 (normalised): y_d = 0.497 f = 199 px below the centre.
    got = triangulate_points([319.5, 319.5], [239.5, 239.5], [95.5 + 100.0, 95.5 + 230.0], calibration)
    assert np.all(np.isfinite(got[0])) and np.all(np.isnan(got[1]))


def test_distortion_needs_intrinsics():
    camera, projector = make_rig()
    for name, calibration in (
            ("camera", Calibration(Device(camera.matrix, camera.size, distortion=[0.1, 0, 0, 0, 0]), projector)),
            ("projector", Calibration(camera, Device(projector.matrix, projector.size, distortion=[0.1, 0, 0, 0, 0])))):
        with pytest.raises(InputError, match=f"^the {name} has lens distortion but no intrinsics"):
            triangulate_points([1.0], [1.0], [1.0], calibration)
        with pytest.raises(InputError, match=f"^the {name} has lens distortion but no intrinsics"):
            triangulate(np.zeros(camera.shape), calibration)
    with pytest.raises(InputError, match=r"^other must have shape \(480, 640\) \(H, W\), got \(4, 4\)$"):
        triangulate(np.zeros(camera.shape), with_lenses(Calibration(camera, projector)), other=np.zeros((4, 4)))
    with pytest.raises(InputError, match="xc, yc, proj and other must be 1-D arrays of one length"):
        triangulate_points([1.0], [1.0], [1.0], Calibration(camera, projector), other=[1.0, 2.0])


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(4_13_22)


@pytest.mark.parametrize("orientation", ["rows", "columns"])
def test_triangulator_coefficients_equal_the_3x3_solve(small_rig, orientation, rng):
    """The per-pixel rational coefficients give the 3x3 solve's points within 1e-3 mm over
    the working volume of the virtual rig (float32 rounding), and NaN at the same pixels."""
    calibration = small_rig.calibration
    h, w = calibration.camera.shape
    lines = calibration.projector.size[1 if orientation == "rows" else 0]
    proj_map = rng.uniform(-0.5, lines - 0.5, (h, w)).astype(np.float32)
    proj_map[rng.random((h, w)) < 0.1] = np.nan
    points = Triangulator(calibration, orientation)(proj_map)
    yc, xc = np.mgrid[0:h, 0:w]
    solved = _solve(xc.ravel().astype(float), yc.ravel().astype(float), proj_map.ravel().astype(float), calibration,
                    orientation).reshape(h, w, 3)
    np.testing.assert_array_equal(np.isnan(points[..., 0]), np.isnan(solved[..., 0]))
    near = np.linalg.norm(np.nan_to_num(solved, nan=1e9), axis=-1) < 2000  # the rig looks at 800 mm
    assert near.mean() > 0.5
    np.testing.assert_allclose(points[near], solved[near], rtol=0, atol=1e-3)
