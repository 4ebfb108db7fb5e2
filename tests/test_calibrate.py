"""DLT calibration (thesis 4.3-4.4) on synthetic rigs built from K [R | t]."""

from __future__ import annotations

import numpy as np
import pytest

from sliscan import Device, InputError
from sliscan.calibrate import (calibrate_points, dlt_least_squares, dlt_svd, reprojection_residuals,
                               summarize_residuals)
from sliscan.formats.premat5 import pixel_to_phase

CAMERA_SIZE = (640, 480)
PROJECTOR_SIZE = (256, 192)
WORKING_DISTANCE_MM = 800.0


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """3x4 [R | t] of a device at `centre` looking at `target`, image x along world +X."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    r = np.stack([x, np.cross(z, x), z])
    return np.c_[r, -r @ centre]


def make_rig(baseline_mm: tuple[float, float, float] = (0.0, -200.0, 0.0)) -> tuple[Device, Device]:
    """Camera at the origin looking along +Z (640x480); projector (256x192) at `baseline_mm`
    (default 200 mm above: y points down) aimed at the point 800 mm in front of the camera."""
    k_cam = np.array([[800.0, 0, 319.5], [0, 800, 239.5], [0, 0, 1]])
    k_proj = np.array([[400.0, 0, 127.5], [0, 400, 95.5], [0, 0, 1]])
    camera = Device(k_cam @ np.eye(3, 4), CAMERA_SIZE, intrinsics=k_cam)
    target = np.array([0.0, 0.0, WORKING_DISTANCE_MM])
    projector = Device(k_proj @ look_at(np.asarray(baseline_mm, dtype=float), target), PROJECTOR_SIZE,
                       intrinsics=k_proj)
    return camera, projector


def volume_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """`n` world points (mm) filling a 300 x 200 x 200 mm box around the working distance."""
    return rng.uniform([-150, -100, WORKING_DISTANCE_MM - 100], [150, 100, WORKING_DISTANCE_MM + 100], size=(n, 3))


def unit_scale(matrix: np.ndarray) -> np.ndarray:
    """The normal form the DLT returns: unit viewing direction, positive depth in front."""
    return matrix / np.linalg.norm(matrix[2, :3])


DLTS = [dlt_svd, dlt_least_squares]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20070601)


@pytest.mark.parametrize("dlt", DLTS)
@pytest.mark.parametrize("device_index", [0, 1])
def test_exact_points_recover_the_matrix(dlt, device_index, rng):
    device = make_rig()[device_index]
    world = volume_points(rng, 200)
    pixels = device.project(world)
    matrix = dlt(world, pixels)
    # Noise-free float64 data: the only error is rounding, amplified by the conditioning of the
    # normalised 400x12 system: ~3e-13 relative is observed, so 1e-9 leaves a wide margin.
    truth = unit_scale(device.matrix)
    np.testing.assert_allclose(matrix, truth, rtol=0, atol=1e-9 * np.abs(truth).max())
    assert reprojection_residuals(matrix, world, pixels).max() < 1e-6


@pytest.mark.parametrize("dlt", DLTS)
def test_six_points_are_enough(dlt, rng):
    camera, _ = make_rig()
    world = volume_points(rng, 6)
    matrix = dlt(world, camera.project(world))
    assert reprojection_residuals(matrix, world, camera.project(world)).max() < 1e-6


@pytest.mark.parametrize("dlt", DLTS)
def test_noise_residual_matches_degrees_of_freedom(dlt, rng):
    camera, _ = make_rig()
    n, sigma = 200, 0.5
    world = volume_points(rng, n)
    pixels = camera.project(world) + rng.normal(0, sigma, size=(n, 2))
    summary = summarize_residuals(reprojection_residuals(dlt(world, pixels), world, pixels))
    # 2N coordinates minus 11 fitted parameters: E[sum r^2] = sigma^2 (2N - 11), so the RMS of
    # the N point distances is sigma sqrt((2N - 11) / N) (per coordinate: sigma sqrt((2N - 11) /
    # 2N), the same thing divided by sqrt 2).  The sample RMS of 389 degrees of
    # freedom varies by 1/sqrt(2*389) = 3.6 % (1 s.d.); 12 % allows > 3 s.d. (the algebraic
    # DLT is not exactly the geometric fit, a further < 1 % here).
    expected = sigma * np.sqrt((2 * n - 11) / n)
    assert summary["rms_px"] == pytest.approx(expected, rel=0.12)
    assert summary["rms_px"] < summary["max_px"] < 6 * sigma


def test_svd_and_least_squares_agree_under_noise(rng):
    camera, _ = make_rig()
    world = volume_points(rng, 200)
    pixels = camera.project(world) + rng.normal(0, 0.3, size=(200, 2))
    a, b = dlt_svd(world, pixels), dlt_least_squares(world, pixels)
    # Both minimise algebraic errors that differ only in the constraint (|m| = 1 vs m34 = 1);
    # with 0.3 px noise they land within a small fraction of a pixel of each other.
    diff = np.hypot(*(Device(a, CAMERA_SIZE).project(world) - Device(b, CAMERA_SIZE).project(world)).T)
    assert diff.max() < 0.05


def test_least_squares_works_with_the_world_origin_in_the_focal_plane(rng):
    # m34 = 0 in raw coordinates (the origin is the camera centre): the thesis's m34 = 1 would
    # fail, the normalised form does not.
    camera, _ = make_rig()
    world = volume_points(rng, 50)
    assert camera.matrix[2, 3] == 0
    matrix = dlt_least_squares(world, camera.project(world))
    np.testing.assert_allclose(matrix, unit_scale(camera.matrix), rtol=0, atol=1e-6)


@pytest.mark.parametrize("phases", [True, False])
@pytest.mark.parametrize("method", ["svd", "lstsq"])
def test_calibrate_points_from_g_rows(method, phases, rng):
    camera, projector = make_rig()
    world = volume_points(rng, 60)
    cam_px = camera.project(world)
    proj_px = projector.project(world)
    if phases:
        proj_px = np.c_[pixel_to_phase(proj_px[:, 0], PROJECTOR_SIZE[0]), pixel_to_phase(proj_px[:, 1], PROJECTOR_SIZE[1])]
    calibration = calibrate_points(np.c_[world, cam_px, proj_px], CAMERA_SIZE, PROJECTOR_SIZE, method=method,
                                   phases=phases)
    for solved, truth in ((calibration.camera, camera), (calibration.projector, projector)):
        assert solved.size == truth.size
        # Exact data, as in test_exact_points_recover_the_matrix.
        np.testing.assert_allclose(solved.matrix, unit_scale(truth.matrix), rtol=0, atol=1e-9 * 1000)
    assert calibration.extra["method"] == method
    assert calibration.extra["points"] == 60
    for name in ("camera", "projector"):
        assert set(calibration.extra["residuals"][name]) == {"rms_px", "max_px"}
        assert calibration.extra["residuals"][name]["max_px"] < 1e-6


def test_calibrate_points_result_round_trips_through_json(tmp_path, rng):
    camera, projector = make_rig()
    world = volume_points(rng, 20)
    rows = np.c_[world, camera.project(world), projector.project(world)]
    calibration = calibrate_points(rows, CAMERA_SIZE, PROJECTOR_SIZE, phases=False)
    calibration.save(tmp_path / "rig.json")
    loaded = type(calibration).load(tmp_path / "rig.json")
    np.testing.assert_array_equal(loaded.camera.matrix, calibration.camera.matrix)
    assert loaded.extra == calibration.extra


# ---------------------------------------------------------------------------------------- errors

@pytest.mark.parametrize("dlt", DLTS)
def test_too_few_points(dlt, rng):
    world = volume_points(rng, 4)
    with pytest.raises(InputError, match="need at least 6 calibration points, got 4"):
        dlt(world, make_rig()[0].project(world))


@pytest.mark.parametrize("dlt", DLTS)
def test_coplanar_points(dlt, rng):
    world = volume_points(rng, 30)
    world[:, 2] = 800.0
    with pytest.raises(InputError, match="world points are coplanar .* non-coplanar"):
        dlt(world, make_rig()[0].project(world))


@pytest.mark.parametrize("dlt", DLTS)
def test_tilted_coplanar_points(dlt, rng):
    world = volume_points(rng, 30)
    world[:, 2] = 800.0 + 0.3 * world[:, 0] - 0.2 * world[:, 1]
    with pytest.raises(InputError, match="coplanar"):
        dlt(world, make_rig()[0].project(world))


@pytest.mark.parametrize("dlt", DLTS)
@pytest.mark.parametrize(("which", "value"), [("world", np.nan), ("pixels", np.inf)])
def test_non_finite_input(dlt, which, value, rng):
    world = volume_points(rng, 10)
    pixels = make_rig()[0].project(world)
    (world if which == "world" else pixels)[3, 1] = value
    with pytest.raises(InputError, match=rf"{which} has non-finite values \(NaN or inf\) at point 3"):
        dlt(world, pixels)


@pytest.mark.parametrize("dlt", DLTS)
def test_shape_errors(dlt, rng):
    world = volume_points(rng, 10)
    with pytest.raises(InputError, match=r"pixels must have shape \(10, 2\) \(x, y\), got \(2, 10\)"):
        dlt(world, np.zeros((2, 10)))
    with pytest.raises(InputError, match=r"world must have shape \(N, 3\)"):
        dlt(world[:, :2], np.zeros((10, 2)))


@pytest.mark.parametrize("dlt", DLTS)
def test_degenerate_pixels(dlt, rng):
    world = volume_points(rng, 20)
    pixels = make_rig()[0].project(world)
    with pytest.raises(InputError, match="degenerate calibration: every point has the same pixel"):
        dlt(world, np.full_like(pixels, 7.0))
    # Every point on one image row: rows 2 and 3 of M become proportional (a singular camera).
    pixels[:, 1] = 240.0
    with pytest.raises(InputError, match="degenerate calibration"):
        dlt(world, pixels)


def test_calibrate_points_errors(rng):
    world = volume_points(rng, 10)
    rows = np.c_[world, np.zeros((10, 4))]
    with pytest.raises(InputError, match="method must be one of"):
        calibrate_points(rows, CAMERA_SIZE, PROJECTOR_SIZE, method="magic")
    with pytest.raises(InputError, match=r"G rows must have shape \(N, 7\)"):
        calibrate_points(rows[:, :6], CAMERA_SIZE, PROJECTOR_SIZE)
    rows[2, 6] = np.nan
    with pytest.raises(InputError, match=r"G rows: non-finite values \(NaN or inf\) in point 2"):
        calibrate_points(rows, CAMERA_SIZE, PROJECTOR_SIZE)
    with pytest.raises(InputError, match="^camera: need at least 6 calibration points, got 5$"):
        calibrate_points(rows[5:], CAMERA_SIZE, PROJECTOR_SIZE)


def test_summary_and_residual_shapes(rng):
    camera, _ = make_rig()
    world = volume_points(rng, 8)
    pixels = camera.project(world)
    pixels[0] += [3.0, 4.0]
    residuals = reprojection_residuals(camera.matrix, world, pixels)
    assert residuals.shape == (8,)
    assert residuals[0] == pytest.approx(5.0)
    assert summarize_residuals(residuals)["max_px"] == pytest.approx(5.0)
    with pytest.raises(InputError, match=r"matrix must have shape \(3, 4\)"):
        reprojection_residuals(np.eye(3), world, pixels)
