"""Moving scenes of the virtual rig (issue 9): poses, moved surfaces, textures that move with the
object, and ``sliscan simulate --motion``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sliscan import motion, patterns, simulate
from sliscan._validate import InputError
from test_cli import PROJECTOR, listing, ok, sliscan

CAMERA = (160, 120)


@pytest.fixture(scope="module")
def tiny() -> tuple[simulate.Rig, np.ndarray]:
    rig = simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR)
    return rig, patterns.render_pattern(patterns.default_spec(PROJECTOR))


def test_pose_is_a_rotation_centred_on_the_middle_frame() -> None:
    m = motion.Motion(5, velocity_mm=(1.0, 2.0, -3.0), spin_deg=10.0, axis=(1.0, 1.0, 0.0))
    rotation, translation = m.pose(2)
    np.testing.assert_allclose(rotation, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(translation, 0.0, atol=1e-15)
    rotation, translation = m.pose(4)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    assert np.degrees(np.arccos((np.trace(rotation) - 1) / 2)) == pytest.approx(20.0)
    np.testing.assert_allclose(rotation @ np.array([1.0, 1.0, 0.0]), [1.0, 1.0, 0.0], atol=1e-12)  # the axis stays
    np.testing.assert_allclose(translation, [2.0, 4.0, -6.0])


@pytest.mark.parametrize("kwargs", [{"frames": 0}, {"frames": 3, "axis": (0.0, 0.0, 0.0)},
                                    {"frames": 3, "velocity_mm": (1.0, float("nan"), 0.0)}])
def test_bad_motion_is_an_input_error(kwargs: dict) -> None:
    with pytest.raises(InputError):
        motion.Motion(**kwargs)


def test_a_still_motion_renders_what_render_renders(tiny: tuple[simulate.Rig, np.ndarray]) -> None:
    rig, projected = tiny
    conditions = simulate.Conditions(supersample=1, seed=3, albedo=simulate.CheckerAlbedo())
    frames = list(motion.render_motion(rig, simulate.sphere_scene(), projected,
                                       motion.Motion(3, velocity_mm=(0.0, 0.0, 0.0), spin_deg=0.0), conditions))
    alone = simulate.render(rig, simulate.sphere_scene(), projected, conditions.with_(seed=5))
    np.testing.assert_array_equal(frames[2].image, alone.image)  # frame k has seed + k
    np.testing.assert_array_equal(frames[2].truth.points, alone.truth.points)


def interior(points: np.ndarray, square_mm: float) -> np.ndarray:
    """Points farther than a pixel's footprint here (under 10 mm) from every face of a `CheckerAlbedo`'s cubes."""
    return np.abs(np.abs(np.modf(points / square_mm + 0.5)[0]) - 0.5).max(axis=1) < 0.5 - 10.0 / square_mm


def test_the_sphere_moves_the_wall_stays_and_the_texture_rides_along(tiny: tuple[simulate.Rig, np.ndarray]) -> None:
    rig, projected = tiny
    checker = simulate.CheckerAlbedo()
    m = motion.Motion(3, velocity_mm=(20.0, -10.0, 15.0), spin_deg=25.0)
    scene = simulate.sphere_scene()
    sphere, wall = scene.surfaces
    for k, capture in enumerate(motion.render_motion(rig, scene, projected, m,
                                                     simulate.Conditions(supersample=1, albedo=checker))):
        rotation, translation = m.pose(k)
        truth = capture.truth
        on_wall = np.abs(truth.points[..., 2] - wall.point[2]) < 1e-3
        on_sphere = truth.surface & ~on_wall
        centre = np.array(sphere.center) + translation  # the pivot is the working point: the centre
        radius = np.linalg.norm(truth.points[on_sphere] - centre, axis=1)
        np.testing.assert_allclose(radius, sphere.radius, atol=1e-3)  # float32 points at 800 mm
        moved = motion.Moved(sphere, rotation, translation, rig.working_point)
        object_points = moved.to_object(truth.points[on_sphere].astype(np.float64))
        # away from the cubes' faces (a pixel's footprint there mixes both albedos, by area)
        points = truth.points[on_sphere].astype(np.float64)
        facing = -np.einsum("nk,nk->n", (points - centre) / sphere.radius, points / np.linalg.norm(points, axis=1,
                                                                                                   keepdims=True))
        inside = interior(object_points, checker.square_mm) & (facing > 0.5)  # not the limb's long footprints
        np.testing.assert_array_equal(truth.albedo[on_sphere][inside], checker(object_points)[inside])
        wall_points = truth.points[on_wall].astype(np.float64)
        away = interior(wall_points, checker.square_mm)
        np.testing.assert_array_equal(truth.albedo[on_wall][away], checker(wall_points)[away])
        assert on_wall.sum() > 0.2 * on_wall.size and on_sphere.sum() > 0.2 * on_sphere.size


def test_split_background_keeps_planes_still() -> None:
    sphere = simulate.Sphere((0.0, 0.0, 800.0), 50.0)
    plane = simulate.Plane.at_z(1000.0)
    assert motion.split_background(simulate.Union(sphere, plane)) == (sphere, (plane,))
    assert motion.split_background(plane) == (plane, ())
    assert motion.split_background(simulate.Union(plane, simulate.Plane.at_z(900.0)))[1] == ()


def test_simulate_motion_writes_a_frame_and_a_truth_per_frame(tmp_path: Path) -> None:
    ok("pattern", "composite", "--projector", "1024x768", "-o", "cp.png", cwd=tmp_path)
    result = ok("simulate", "--pattern", "cp.json", "--camera", "160x120", "--supersample", "1", "--motion", "3",
                "--velocity", "5,0,0", "--spin", "2", "--truth", "t/truth.npz", "-o", "t/f.png", cwd=tmp_path)
    assert "3 160x120 captures of the moving sphere scene" in result.stdout
    names = sorted(p.name for p in (tmp_path / "t").iterdir())
    assert names == ["f_00.png", "f_01.png", "f_02.png", "truth_00.npz", "truth_01.npz", "truth_02.npz"]
    first, last = (np.load(tmp_path / f"t/truth_0{k}.npz")["points"] for k in (0, 2))
    shift = np.nanmedian(last[..., 0] - first[..., 0])  # wall pixels do not move, sphere pixels by 10 mm
    assert shift == 0 and np.nanmax(np.abs(last[..., 0] - first[..., 0])) > 5


@pytest.mark.parametrize("args, message", [
    (("--motion", "2", "--velocity", "1,2"), "--velocity takes 3 numbers"),
    (("--motion", "2", "--camera-view", "cv.png"), "--motion renders a single-shot pattern"),
    (("--motion", "0"), "0 is not in the range"),
])
def test_bad_motion_options_are_one_line_and_write_nothing(tmp_path: Path, args: tuple[str, ...],
                                                           message: str) -> None:
    patterns.default_spec(PROJECTOR).with_(image="cp.png").save(tmp_path / "cp.json")
    before = listing(tmp_path)
    result = sliscan("simulate", "--pattern", "cp.json", "--camera", "160x120", *args, "-o", "f.png", cwd=tmp_path)
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1 and message in result.stderr, result.stderr
    assert listing(tmp_path) == before
