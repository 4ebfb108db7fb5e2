"""Tests of the virtual rig: every check against a closed form or an independent computation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sliscan import InputError
from sliscan.simulate import (
    Box,
    CheckerAlbedo,
    Conditions,
    Cylinder,
    Mat5Surface,
    Pinhole,
    Plane,
    Rig,
    SmoothAlbedo,
    TracedScene,
    Sphere,
    UniformAlbedo,
    Union,
    _box_sum_cdf,
    board_scene,
    camera_view,
    circle_grid_scene,
    cylinder_scene,
    plane_scene,
    projector_rows,
    projector_view,
    render,
    render_sequence,
    sphere_scene,
    steps_scene,
    objects_scene,
    tilted_plane_scene,
    virtual_rig,
)
from sliscan.targets import Board
from sliscan.types import Calibration, Device

CAMERA = (160, 120)
PROJECTOR = (128, 96)
#: float32 storage of coordinates near 1000 mm is exact to 6e-5 mm; 1e-3 leaves room for that.
XYZ_ATOL = 1e-3
#: Images are float32 (relative rounding 6e-8); 1e-5 is far below any physical effect tested.
IMG_ATOL = 1e-5

NOISELESS = dict(full_well_e=None, bit_depth=None)


@pytest.fixture(scope="module")
def rig() -> Rig:
    return virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR)


@pytest.fixture(scope="module")
def sphere_capture(rig):
    return render(rig, sphere_scene(), np.ones(rig.projector.shape), Conditions.ideal())


def pixel_rays(rig: Rig, z: float) -> np.ndarray:
    """(H, W, 3) points at depth `z` on the camera's pixel-centre rays (closed form)."""
    h, w = rig.camera.shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    K = rig.calibration.camera.intrinsics
    return np.stack([(x - K[0, 2]) / K[0, 0] * z, (y - K[1, 2]) / K[1, 1] * z, np.full_like(x, z)], axis=-1)


def cos_incidence(rig: Rig, points: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """cos of the angle between `normal` and the direction to the projector centre."""
    to_p = rig.projector.centre - points
    return (to_p @ normal) / np.linalg.norm(to_p, axis=-1)


# ---------------------------------------------------------------------------------- the rig


def test_rig_geometry(rig):
    cal = rig.calibration
    # The projector sits baseline_mm above the camera (negative y); exact up to rounding.
    np.testing.assert_allclose(rig.projector.centre, [0, -200, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(rig.camera.centre, [0, 0, 0], rtol=0, atol=1e-12)
    # The camera axis point at the working distance is the centre of both images (exact by
    # construction, so 1e-6 px rather than the 1 px a real rig would be set up to).
    centre_p = (np.array(PROJECTOR) - 1) / 2
    np.testing.assert_allclose(cal.projector.project(np.array([0.0, 0.0, 800.0])), centre_p, rtol=0, atol=1e-6)
    np.testing.assert_allclose(cal.camera.project(np.array([0.0, 0.0, 800.0])), (np.array(CAMERA) - 1) / 2, atol=1e-9)
    # The projector covers the camera's whole view of the working plane (the outer corners of
    # its corner pixels), with exactly the 5 % margin on the tighter axis.
    K = cal.camera.intrinsics
    u, v = np.array([-0.5, CAMERA[0] - 0.5]), np.array([-0.5, CAMERA[1] - 0.5])
    corners = np.array([[(x - K[0, 2]) / K[0, 0] * 800, (y - K[1, 2]) / K[1, 1] * 800, 800] for x in u for y in v])
    reach = np.abs(cal.projector.project(corners) - centre_p).max(axis=0) / (np.array(PROJECTOR) / 2)
    assert reach.max() == pytest.approx(1 / 1.05, rel=1e-9)
    # Intrinsics are stored and consistent: matrix = K [R | t].
    for device, pin in ((cal.camera, rig.camera), (cal.projector, rig.projector)):
        np.testing.assert_allclose(device.intrinsics, pin.K, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(device.matrix, pin.matrix, rtol=1e-12, atol=1e-9)


def test_projector_below():
    rig = virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR, projector_above=False, baseline_mm=150)
    np.testing.assert_allclose(rig.projector.centre, [0, 150, 0], rtol=0, atol=1e-9)
    assert rig.working_distance_mm == 800.0


@pytest.mark.parametrize("roll", [-6.0, 3.0])
def test_a_rolled_projector_turns_its_rows_by_the_roll(roll):
    """Along the camera's middle row on the plane facing it at the working distance, the
    projector coordinates move at `roll` degrees to the projector's rows (clockwise as the camera
    sees it, as documented), and the projector's centre still lands on the camera's: a turn
    about the projector's own axis, nothing else (0.01 degrees: float64 rounding and the
    pitched projector's keystone, which is zero on the row through the principal point)."""
    rolled = virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR, projector_roll_deg=roll)
    plain = virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR)
    np.testing.assert_allclose(rolled.projector.centre, plain.projector.centre, atol=1e-9)
    np.testing.assert_allclose(rolled.projector.axis, plain.projector.axis, atol=1e-12)
    row = (CAMERA[1] - 1) / 2
    points = 800 * rolled.camera.rays(np.array([0.25, 0.75]) * (CAMERA[0] - 1), np.full(2, row))
    (xa, ya), (xb, yb) = rolled.calibration.projector.project(points)
    assert np.degrees(np.arctan2(ya - yb, xb - xa)) == pytest.approx(roll, abs=0.01)


def test_a_projector_moved_across_the_baseline_still_aims_at_the_working_point():
    """`projector_offset_mm` moves the projector's centre sideways (a vertical baseline) and
    keeps the working point in the middle of its image (1e-6 px, as the level rig)."""
    moved = virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR, projector_offset_mm=60.0)
    np.testing.assert_allclose(moved.projector.centre, [60, -200, 0], atol=1e-9)
    np.testing.assert_allclose(moved.calibration.projector.project(np.array([0.0, 0.0, 800.0])),
                               (np.array(PROJECTOR) - 1) / 2, atol=1e-6)


def test_rig_from_any_scaled_calibration(rig):
    # A DLT calibration has arbitrary scale and sign; the decomposition must not care.
    cal = rig.calibration
    scaled = Calibration(
        Device(-3.7 * cal.camera.matrix, cal.camera.size), Device(0.01 * cal.projector.matrix, cal.projector.size)
    )
    again = Rig(scaled)
    for a, b in ((again.camera, rig.camera), (again.projector, rig.projector)):
        np.testing.assert_allclose(a.K, b.K, rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(a.R, b.R, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, rtol=0, atol=1e-9)
    # Without a stated working distance it is where the optical axes cross.
    assert again.working_distance_mm == pytest.approx(800.0, rel=1e-12)


@settings(max_examples=50, deadline=None)
@given(
    quaternion=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
    focal=st.floats(100, 5000),
    skew=st.floats(-2, 2),
    translation=st.lists(st.floats(-500, 500), min_size=3, max_size=3),
    scale=st.floats(1e-3, 1e3).flatmap(lambda v: st.sampled_from([v, -v])),
)
def test_pinhole_decomposition_round_trip(quaternion, focal, skew, translation, scale):
    w, x, y, z = np.asarray(quaternion) / np.linalg.norm(quaternion)
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    K = np.array([[focal, skew, 320.0], [0.0, 1.1 * focal, 240.0], [0.0, 0.0, 1.0]])
    truth = Pinhole(K=K, R=R, t=translation, size=(640, 480))
    again = Pinhole.from_matrix(scale * truth.matrix, (640, 480))  # any scale, any sign
    np.testing.assert_allclose(again.K, K, rtol=1e-9, atol=1e-9 * focal)
    np.testing.assert_allclose(again.R, R, rtol=0, atol=1e-9)
    np.testing.assert_allclose(again.centre, truth.centre, rtol=0, atol=1e-7)
    # rays() and project() are inverse: a ray's point at parameter s projects back, depth s.
    xy = np.array([[0.0, 0.0], [639.0, 479.0], [100.5, 300.25]])
    points = again.centre + 750.0 * again.rays(xy[:, 0], xy[:, 1])
    back, depth = again.project(points)
    np.testing.assert_allclose(back, xy, rtol=0, atol=1e-7)
    np.testing.assert_allclose(depth, 750.0, rtol=1e-12)


def test_calibration_projects_truth_onto_pixels(rig, sphere_capture):
    truth = sphere_capture.truth
    h, w = rig.camera.shape
    y, x = np.mgrid[0:h, 0:w]
    ok = truth.surface
    # float32 points (6e-5 mm) times at most 0.4 px/mm: 1e-3 px is ample.
    cam_xy = rig.calibration.camera.project(truth.points[ok].astype(np.float64))
    np.testing.assert_allclose(cam_xy, np.stack([x[ok], y[ok]], -1), rtol=0, atol=1e-3)
    proj_xy = rig.calibration.projector.project(truth.points[ok].astype(np.float64))
    np.testing.assert_allclose(proj_xy, truth.proj[ok], rtol=0, atol=1e-3)


# ------------------------------------------------------------------------------- geometry


def test_plane_depth_is_analytic(rig):
    truth = render(rig, plane_scene(distance_mm=650.0), np.ones(rig.projector.shape), Conditions.ideal()).truth
    assert truth.surface.all()
    np.testing.assert_allclose(truth.points, pixel_rays(rig, 650.0), rtol=0, atol=XYZ_ATOL)


def test_tilted_plane_points_on_plane(rig):
    truth = render(rig, tilted_plane_scene(40.0), np.ones(rig.projector.shape), Conditions.ideal()).truth
    # Z = 800 - Y tan(40 deg): the plane's top recedes.
    p = truth.points.astype(np.float64)
    np.testing.assert_allclose(p[..., 2], 800 - p[..., 1] * np.tan(np.radians(40)), rtol=0, atol=XYZ_ATOL)
    assert not truth.edge.any()  # a smooth surface has no depth edges


def test_sphere_points_on_sphere(sphere_capture):
    p = sphere_capture.truth.points.astype(np.float64)
    on_sphere = p[..., 2] < 1000 - 1  # the wall is at 800 + 200 mm
    assert on_sphere.sum() > 0.3 * on_sphere.size
    r = np.linalg.norm(p[on_sphere] - [0, 0, 800], axis=-1)
    assert np.abs(r - 122.555).max() < XYZ_ATOL
    np.testing.assert_allclose(p[~on_sphere][:, 2], 1000.0, rtol=0, atol=XYZ_ATOL)


def test_sphere_shadow_matches_shadow_rays(rig, sphere_capture):
    truth = sphere_capture.truth
    wall = truth.surface & (truth.points[..., 2] > 999)
    inside = np.all((truth.proj > -0.5) & (truth.proj < np.array(PROJECTOR) - 0.5), axis=-1)
    X = truth.points[wall & inside].astype(np.float64)
    # Closed form: the segment X -> projector centre passes within R of the sphere's centre.
    c, C = np.array([0.0, 0.0, 800.0]), rig.projector.centre
    seg = C - X
    s = np.clip(((c - X) * seg).sum(1) / (seg * seg).sum(1), 0, 1)
    blocked = np.linalg.norm(X + s[:, None] * seg - c, axis=1) < 122.555
    assert blocked.sum() > 200  # a real shadow, visible to the camera
    np.testing.assert_array_equal(truth.lit[wall & inside], ~blocked)
    # The shadow falls below the sphere (the projector is above the camera).
    assert np.median(X[blocked][:, 1]) > 0


@pytest.mark.parametrize("axis", ["y", "x"])
def test_cylinder_hits_lie_on_its_surface_nearest_first(axis):
    rng = np.random.default_rng(3)
    centre, radius, height = np.array([10.0, -200.0, 800.0]), 90.0, 240.0  # the camera below its lower cap
    cyl = Cylinder(tuple(centre), radius, height, axis=axis)
    along = 0 if axis == "x" else 1
    across = [k for k in range(3) if k != along]
    dirs = np.column_stack([rng.uniform(-0.4, 0.2, 4000), rng.uniform(-0.4, 0.2, 4000), np.ones(4000)])
    t, normal = cyl.intersect(np.zeros_like(dirs), dirs)
    hit = np.isfinite(t)
    assert 0.1 < hit.mean() < 0.9  # some rays pass beside or beyond it
    rel = t[hit, None] * dirs[hit] - centre
    radial = np.linalg.norm(rel[:, across], axis=1)
    on_side = np.abs(radial - radius) < 1e-6
    on_cap = np.abs(np.abs(rel[:, along]) - height / 2) < 1e-6
    assert np.all((on_side & (np.abs(rel[:, along]) <= height / 2 + 1e-6)) | (on_cap & (radial <= radius + 1e-6)))
    assert on_side.sum() > 100 and (on_cap.sum() > 10) == (axis == "y")  # the camera sees the upright one's cap
    np.testing.assert_allclose(np.linalg.norm(normal[hit], axis=1), 1.0, atol=1e-12)
    assert np.all(np.sum(normal[hit] * dirs[hit], axis=1) <= 0)
    # the side's normal is radial, a cap's along the axis
    side_normal = np.zeros_like(rel[on_side])
    side_normal[:, across] = rel[on_side][:, across] / radius
    np.testing.assert_allclose(normal[hit][on_side], side_normal, atol=1e-9)
    # nearest first: a point a little before the hit lies outside, one a little after inside
    before, after = rel - 1e-3 * dirs[hit], rel + 1e-3 * dirs[hit]
    inside = lambda q: (np.linalg.norm(q[:, across], axis=1) < radius) & (np.abs(q[:, along]) < height / 2)  # noqa: E731
    assert not inside(before).any() and inside(after).all()
    # a ray through the axis meets the side face-on at the closed-form depth
    t0, _ = cyl.intersect([[0.0, 0.0, 0.0]], [list(centre)])
    assert abs(t0[0] - (1 - radius / np.linalg.norm(centre[across]))) < 1e-12


def test_cylinder_and_objects_scenes_render_with_shadows(rig):
    for scene in (cylinder_scene(), objects_scene()):
        truth = render(rig, scene, np.ones(rig.projector.shape), Conditions.ideal()).truth
        z = truth.points[..., 2][truth.surface]
        assert z.min() < 760 and np.isclose(z.max(), 1000.0, atol=XYZ_ATOL)  # objects before the wall
        assert (truth.surface & ~truth.lit).mean() > 0.005  # cast shadows the camera sees
        assert np.nanmax(np.abs(np.diff(truth.points[..., 2], axis=1))) > 50  # depth edges at the silhouettes


def test_steps_shadows_where_geometry_says(rig):
    count, step, height, distance, wall_z = 4, 40.0, 160.0, 800.0, 900.0
    truth = render(rig, steps_scene(), np.ones(rig.projector.shape), Conditions.ideal()).truth
    p = truth.points.astype(np.float64)
    on_wall = truth.surface & (np.abs(p[..., 2] - wall_z) < 1e-3) & (p[..., 1] > height / 2)
    for k in range(count):
        z_front = distance - k * step
        lo, hi = -count * 40.0 + 80.0 * k, -count * 40.0 + 80.0 * (k + 1)
        # Wall points whose path to the projector stays in box k's x range (x shrinks as z / wall_z)
        # over the depths of all boxes, so that no neighbouring box can block it.
        x_near = p[..., 0] * (distance - (count - 1) * step) / wall_z
        col = on_wall & (p[..., 0] > lo + 1) & (p[..., 0] < hi - 1) & (x_near > lo + 1) & (x_near < hi - 1)
        # The ray from wall point Y up to the projector (0, -200, 0) crosses the box's front
        # plane at y_f = -200 + (Y + 200) z_front / wall_z; it is blocked iff y_f <= height / 2.
        blocked = -200 + (p[..., 1] + 200) * z_front / wall_z <= height / 2
        assert col.sum() > 20
        np.testing.assert_array_equal(truth.lit[col], ~blocked[col])
        # The shadow's lower edge on the wall, within one pixel footprint (900 / 298.6 = 3 mm).
        edge = (height / 2 + 200) * wall_z / z_front - 200
        assert p[..., 1][col & ~truth.lit].max() == pytest.approx(edge, abs=wall_z / rig.camera.K[0, 0])


def test_ideal_reproduces_drive_times_cosine(rig):
    hp, wp = rig.projector.shape
    yp, xp = np.mgrid[0:hp, 0:wp].astype(float)
    drive = 0.1 + 0.5 * xp / (wp - 1) + 0.3 * yp / (hp - 1)  # linear: bilinear sampling is exact
    scene = tilted_plane_scene(25.0)
    cap = render(rig, scene, drive, Conditions.ideal())
    t = cap.truth
    X = t.points.astype(np.float64)
    xy = rig.calibration.projector.project(X)  # independent of the renderer's projection
    core = t.lit & np.all((xy >= 0) & (xy <= np.array([wp - 1, hp - 1])), axis=-1)
    assert core.mean() > 0.8
    drive_there = 0.1 + 0.5 * xy[..., 0] / (wp - 1) + 0.3 * xy[..., 1] / (hp - 1)
    expected = drive_there * cos_incidence(rig, X, np.array(scene.normal))
    np.testing.assert_allclose(cap.image[core], expected[core], rtol=0, atol=IMG_ATOL)
    # Ideal conditions: nothing outside the projector image, no ambient.
    assert np.all(cap.image[~t.surface | ~t.lit] == 0)


@pytest.mark.parametrize("inverse_square", [False, True])
def test_gamma_black_ambient_falloff(rig, inverse_square):
    d, gamma, black, ambient, exposure, albedo = 0.5, 2.2, 0.005, 0.1, 0.8, 0.6
    cond = Conditions(albedo=UniformAlbedo(albedo), ambient=ambient, projector_gamma=gamma, projector_black=black,
                      exposure=exposure, supersample=1, inverse_square=inverse_square, **NOISELESS)
    cap = render(rig, plane_scene(), np.full(rig.projector.shape, d), cond)
    X = cap.truth.points.astype(np.float64)
    r = np.linalg.norm(X - rig.projector.centre, axis=-1)
    falloff = (rig.projector_distance_mm / r) ** 2 if inverse_square else 1.0
    light = (black + (1 - black) * d**gamma) * cos_incidence(rig, X, np.array([0.0, 0.0, -1.0])) * falloff
    expected = exposure * albedo * (light + ambient)
    # Away from the frustum's blurred edge (4 sigma = 4 projector px = 10 camera px) and the
    # camera blur's border; the camera blur of this smooth field changes it by < 1e-6.
    core = np.s_[15:-15, 15:-15]
    np.testing.assert_allclose(cap.image[core], expected[core], rtol=0, atol=IMG_ATOL)


# ------------------------------------------------------------------------------- the sensor


@pytest.mark.parametrize("bit_depth", [None, 8])
def test_noise_matches_shot_and_read_model(rig, bit_depth):
    full_well, read = 10000.0, 8.0
    base = Conditions(supersample=1, bit_depth=None, full_well_e=None)
    scene, drive = plane_scene(), np.full(rig.projector.shape, 0.7)
    clean = render(rig, scene, drive, base).image.astype(np.float64)
    noisy_cond = base.with_(full_well_e=full_well, read_noise_e=read, bit_depth=bit_depth)
    noisy = render(rig, scene, drive, noisy_cond, rng=1).image
    variance = (clean * full_well + read**2) / full_well**2  # Poisson + Gaussian, in full-scale units
    if bit_depth is not None:
        variance += (1 / (2**bit_depth - 1)) ** 2 / 12  # uniform quantisation error
    z = (noisy - clean) / np.sqrt(variance)
    # 19200 samples estimate a std to 0.5 %; 10 % leaves room for the model's approximations.
    assert np.std(z) == pytest.approx(1.0, rel=0.1)
    assert abs(np.mean(z)) < 0.05


def test_quantisation_and_saturation(rig):
    img = render(rig, sphere_scene(), np.ones(rig.projector.shape), Conditions(supersample=1), rng=0).image
    np.testing.assert_allclose(img * 255, np.round(img * 255), rtol=0, atol=1e-4)  # the 1/255 grid
    hot_cond = Conditions(supersample=1, exposure=3.0)
    hot = render(rig, sphere_scene(), np.ones(rig.projector.shape), hot_cond, rng=0).image
    assert hot.max() == 1.0 and (hot == 1.0).mean() > 0.3 and hot.dtype == np.float32


def test_seeds_make_renders_reproducible(rig):
    drive = np.full(rig.projector.shape, 0.5)
    cond = Conditions(supersample=1)
    a, b, c = (render(rig, plane_scene(), drive, cond, rng=s).image for s in (7, 7, 8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    seeded = cond.with_(seed=7)
    np.testing.assert_array_equal(render(rig, plane_scene(), drive, seeded).image, a)


# --------------------------------------------------------------------------------- sampling


def test_supersampling_mixes_a_depth_edge(rig):
    s, z = 4, 700.0
    lo, hi = (-50.3, -30.7), (47.1, 35.9)
    box = Box((lo[0], lo[1], z), (hi[0], hi[1], z + 60))  # seen alone: around it, nothing
    cap = render(rig, box, np.ones(rig.projector.shape), Conditions.ideal().with_(supersample=s))
    K = rig.calibration.camera.intrinsics
    h, w = rig.camera.shape
    sub = (np.arange(s) + 0.5) / s - 0.5
    # Closed-form coverage: the fraction of the s x s sub-pixel rays that meet the front face.
    cover_x = ((np.arange(w)[:, None] + sub - K[0, 2]) / K[0, 0] * z)
    cover_y = ((np.arange(h)[:, None] + sub - K[1, 2]) / K[1, 1] * z)
    fx = ((cover_x >= lo[0]) & (cover_x <= hi[0])).mean(axis=1)
    fy = ((cover_y >= lo[1]) & (cover_y <= hi[1])).mean(axis=1)
    coverage = fy[:, None] * fx[None, :]
    centre_pts = pixel_rays(rig, z)
    lit_value = cos_incidence(rig, centre_pts, np.array([0.0, 0.0, -1.0]))
    mixed = (coverage > 0) & (coverage < 1)
    assert mixed.sum() > 50  # at least two of the four sides fall between sub-pixel rows
    # cos varies by < 1e-4 across one pixel, so coverage * cos(centre) is good to 1e-4.
    np.testing.assert_allclose(cap.image, coverage * lit_value, rtol=0, atol=1e-4)
    assert np.all((cap.image[mixed] > 0.02) & (cap.image[mixed] < 0.97 * lit_value[mixed]))
    np.testing.assert_array_equal(cap.truth.edge, mixed)


def test_edges_flag_steps(rig):
    truth = render(rig, steps_scene(), np.ones(rig.projector.shape), Conditions.ideal().with_(supersample=3)).truth
    assert truth.edge.sum() > 100
    flat = render(rig, plane_scene(), np.ones(rig.projector.shape), Conditions.ideal().with_(supersample=3)).truth
    assert not flat.edge.any()


def _sinusoid_gain(rig, blur: dict, freq: float, transfer=None) -> float:
    """Amplitude of a projected cosine along xp after `blur`, relative to no blur and to
    `transfer(truth)`, the ``(H, W)`` gain expected at each pixel (default 1)."""
    hp, wp = rig.projector.shape
    xp = np.arange(wp)[None, :] * np.ones((hp, 1))
    wave = 0.5 + 0.4 * np.cos(2 * np.pi * freq * xp)
    flat = np.full((hp, wp), 0.5)
    sharp_cond = Conditions.ideal()
    blur_cond = sharp_cond.with_(**blur)
    ac_sharp = render(rig, plane_scene(), wave, sharp_cond).image - render(rig, plane_scene(), flat, sharp_cond).image
    blurred = render(rig, plane_scene(), wave, blur_cond)
    ac_blur = blurred.image - render(rig, plane_scene(), flat, blur_cond).image
    if transfer is not None:
        ac_sharp = ac_sharp * transfer(blurred.truth)
    core = np.s_[20:-20, 20:-20]  # away from the frustum edge and the image border
    a, b = ac_sharp[core].ravel(), ac_blur[core].ravel()
    return float(a @ b / (a @ a))


def test_projector_blur_mtf(rig):
    sigma, f = 2.0, 1 / 16  # cycles per projector pixel
    gain = _sinusoid_gain(rig, {"projector_blur_px": sigma}, f)
    # Gaussian MTF: the sampled, truncated kernel's response differs by < 0.01 % at sigma = 2
    # and bilinear resampling scales blurred and sharp alike; 1 % leaves room for neither.
    assert gain == pytest.approx(np.exp(-2 * np.pi**2 * sigma**2 * f**2), rel=0.01)


def test_camera_blur_mtf():
    rig = virtual_rig(camera_size=(320, 240), projector_size=PROJECTOR)
    sigma, f_p = 2.0, 1 / 8
    # On the working plane xp is affine in xc along a row; its slope turns f_p into camera cycles.
    xp_row = render(rig, plane_scene(), np.ones(rig.projector.shape), Conditions.ideal()).truth.proj[120, :, 0]
    f_c = f_p * float(np.mean(np.diff(xp_row[100:220])))
    gain = _sinusoid_gain(rig, {"camera_blur_px": sigma}, f_p)
    # The fringes fan out slightly between rows, which the vertical blur mixes (0.2 % here).
    assert gain == pytest.approx(np.exp(-2 * np.pi**2 * sigma**2 * f_c**2), rel=0.01)


def test_projector_depth_of_field_mtf(rig):
    """Each point's light is blurred by the thin lens's circle of confusion at its own depth
    along the projector's axis (786-863 mm on the working plane, the projector pitched)."""
    focus, aperture, f = 500.0, 40.0, 1 / 16
    focal = rig.projector.K[0, 0]

    def transfer(truth):
        _, depth = rig.projector.project(truth.points.astype(np.float64))
        sigma = focal * aperture * np.abs(1 / depth - 1 / focus) / 4  # 1.6-1.9 px here
        return np.exp(-2 * np.pi**2 * sigma**2 * f**2)

    gain = _sinusoid_gain(rig, {"projector_focus_mm": focus, "projector_aperture_mm": aperture}, f, transfer)
    # as for test_projector_blur_mtf, with the blend between blurs 0.125 px apart (< 0.3 % here)
    assert gain == pytest.approx(1.0, rel=0.01)  # (in focus everywhere it would be 1.27)


def test_camera_depth_of_field_mtf():
    rig = virtual_rig(camera_size=(320, 240), projector_size=PROJECTOR)
    focus, aperture, f_p = 500.0, 20.0, 1 / 8
    xp_row = render(rig, plane_scene(), np.ones(rig.projector.shape), Conditions.ideal()).truth.proj[120, :, 0]
    f_c = f_p * float(np.mean(np.diff(xp_row[100:220])))
    # the working plane is 800 mm from the camera everywhere: one circle of confusion
    sigma = rig.camera.K[0, 0] * aperture * (1 / 500 - 1 / 800) / 4
    assert 1.5 < sigma < 2.5
    gain = _sinusoid_gain(rig, {"camera_focus_mm": focus, "camera_aperture_mm": aperture}, f_p)
    assert gain == pytest.approx(np.exp(-2 * np.pi**2 * sigma**2 * f_c**2), rel=0.01)


def test_a_traced_scene_renders_the_depth_of_field_as_render_does(rig):
    conditions = Conditions(projector_focus_mm=600.0, projector_aperture_mm=20.0, camera_focus_mm=700.0,
                            camera_aperture_mm=20.0, supersample=2, seed=3)
    drive = np.random.default_rng(0).random(rig.projector.shape)
    traced = TracedScene(rig, sphere_scene(), conditions)
    np.testing.assert_array_equal(traced.capture(drive), render(rig, sphere_scene(), drive, conditions).image)


def test_depth_of_field_conditions_are_checked():
    for bad in ({"projector_focus_mm": 0.0}, {"camera_focus_mm": -5.0}, {"projector_aperture_mm": 0.0},
                {"camera_aperture_mm": float("nan")}):
        with pytest.raises(InputError, match=next(iter(bad))):
            Conditions(**bad)


# ----------------------------------------------------------------------------- mat5 surface


@pytest.fixture(scope="module")
def sphere_mesh(sphere_capture):
    truth = sphere_capture.truth
    return Mat5Surface(truth.points, truth.surface)


def test_mat5_surface_reproduces_the_scene(rig, sphere_capture, sphere_mesh):
    truth = sphere_capture.truth
    cap = render(rig, sphere_mesh, np.ones(rig.projector.shape), Conditions.ideal())
    both = cap.truth.surface & truth.surface
    # Every pixel-centre ray passes through its own mesh vertex, so depths agree to float32;
    # only the outer border and a one-cell rim at depth jumps (curtains removed) are lost.
    assert both.sum() > 0.95 * truth.surface.sum()
    np.testing.assert_allclose(cap.truth.points[both], truth.points[both], rtol=0, atol=XYZ_ATOL)
    # Shadows come from shadow rays through the mesh: the wall's shadow matches the analytic one.
    wall = both & (truth.points[..., 2] > 999)
    assert (cap.truth.lit[wall] != truth.lit[wall]).mean() < 0.005


def test_mat5_surface_needs_concurrent_rays(sphere_mesh):
    origins = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    dirs = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    with pytest.raises(InputError, match="share one point"):
        sphere_mesh.intersect(origins, dirs)
    t, n = sphere_mesh.intersect(origins[:1], dirs[:1])  # one ray: its own common point
    assert t[0] == pytest.approx(800 - 122.555, abs=0.05) and n[0] @ dirs[0] < 0


def test_mat5_surface_drops_curtains():
    y, x = np.mgrid[0:20, 0:20].astype(float)
    z = np.where(x < 10, 800.0, 900.0)  # a 100 mm depth jump between columns 9 and 10
    mesh = Mat5Surface(np.stack([x, y, z], -1), np.ones((20, 20), bool))
    assert mesh.triangles.shape == (2 * 19 * 18, 3, 3)  # the 19 squares across the jump are gone
    assert np.ptp(mesh.triangles[..., 2], axis=1).max() == 0


# ------------------------------------------------------------------------- chapter 5 views


def test_projector_and_camera_views(rig):
    hp, wp = rig.projector.shape
    yp, xp = np.mgrid[0:hp, 0:wp]
    pattern = ((xp // 4 + yp // 3) % 2).astype(float) * 0.8 + 0.1
    points = pixel_rays(rig, 800.0)
    valid = np.ones(rig.camera.shape, bool)
    texture = np.full(rig.camera.shape, 0.5)
    # Closed form: every point carries texture * pattern at its nearest projector pixel.
    ij = np.floor(rig.calibration.projector.project(points) + 0.5).astype(int)
    expected_cam = 0.5 * pattern[ij[..., 1], ij[..., 0]]
    np.testing.assert_allclose(camera_view(rig, points, valid, texture, pattern), expected_cam, rtol=0, atol=1e-7)
    view = projector_view(rig, points, valid, texture, pattern)
    covered = view > 0
    assert covered.mean() > 0.75  # the camera sees the projector image less its margin and keystone
    np.testing.assert_allclose(view[covered], 0.5 * pattern[covered], rtol=0, atol=1e-7)


def test_camera_view_z_buffer(rig):
    # Two layers on the same camera rays, the near one first in the grid: MATLAB's last write
    # would show the far layer; the z-buffer must show the near one.
    points = np.concatenate([pixel_rays(rig, 700.0), pixel_rays(rig, 900.0)])
    texture = np.concatenate([np.full(rig.camera.shape, 0.9), np.full(rig.camera.shape, 0.2)])
    view = camera_view(rig, points, np.ones(points.shape[:2], bool), texture, np.ones(rig.projector.shape))
    lit_near = view > 0
    assert lit_near.mean() > 0.9
    np.testing.assert_allclose(view[lit_near], 0.9, rtol=0, atol=1e-7)


def test_projector_rows_matches_projection(rig):
    yp = projector_rows(rig, plane_scene())
    expected = rig.calibration.projector.project(pixel_rays(rig, 800.0))[..., 1]
    lit = np.isfinite(yp)
    assert lit.mean() > 0.99
    np.testing.assert_allclose(yp[lit], expected[lit], rtol=0, atol=1e-4)


# ---------------------------------------------------------------------------------- albedo


def test_albedo_fields():
    pts = np.random.default_rng(0).uniform(-300, 300, (5000, 3))
    a = SmoothAlbedo(seed=3)(pts)
    np.testing.assert_array_equal(a, SmoothAlbedo(seed=3)(pts))
    assert a.min() >= 0.15 and a.max() <= 1.0 and not np.array_equal(a, SmoothAlbedo(seed=4)(pts))
    # Spread roughly uniformly over [low, high]: std of U(0.15, 1) is 0.245.
    assert a.std() == pytest.approx(0.85 / np.sqrt(12), rel=0.25)
    checker = CheckerAlbedo(square_mm=40)(np.array([[0.0, 0.0, 800.0], [40.0, 0.0, 800.0], [40.0, 40.0, 800.0]]))
    np.testing.assert_array_equal(checker, np.float32([0.9, 0.25, 0.9]))


# ------------------------------------------------------------------------------ bad inputs


class PointSampled:
    """An albedo without `area_mean`: the renderer samples it at points."""

    def __init__(self, albedo):
        self.albedo = albedo

    def __call__(self, xyz):
        return self.albedo(xyz)


@pytest.mark.parametrize("scene_and_albedo, ratio, worst", [
    (lambda: board_scene(tilt_deg=(15.0, -20.0), inner_corners=(9, 7), square_mm=25.0), 0.25, 0.05),
    (lambda: circle_grid_scene(Board("symmetric", (7, 5), 30.0, 9.0), tilt_deg=(20.0, 10.0))[:2], 0.25, 0.05),
    (lambda: (sphere_scene(), CheckerAlbedo(square_mm=40.0)), 0.4, 0.15)], ids=["chessboard", "circles", "checker sphere"])
def test_sharp_albedo_edges_cover_pixels_by_area(rig, scene_and_albedo, ratio, worst):
    """One sample per pixel with the footprint's area coverage matches 8x8 point samples per
    pixel (whose own aliasing is at most 1/64 of the contrast per edge pixel): the edges do not
    alias, where one point sample per pixel is off by up to the whole contrast.  On the sphere
    the limb's long footprints and the cubes' corners (the axes taken as independent) are
    approximate: measured 0.33 of the point samples' RMS there, 0.12 at the 99.5th percentile."""
    scene, albedo = scene_and_albedo()
    plain = dict(full_well_e=None, bit_depth=None, camera_blur_px=0.0, projector_blur_px=0.0)
    white = np.ones(rig.projector.shape)

    def image(texture, supersample):
        return render(rig, scene, white, Conditions(albedo=texture, supersample=supersample, **plain)).image

    reference = image(PointSampled(albedo), 8)
    area = np.abs(image(albedo, 1) - reference)
    point = np.abs(image(PointSampled(albedo), 1) - reference)
    assert np.nanmax(point) > 0.2
    assert np.sqrt(np.nanmean(area**2)) < ratio * np.sqrt(np.nanmean(point**2))
    assert np.nanpercentile(area, 99.5) < worst


def test_footprint_coverage_of_one_edge_is_the_trapezoid():
    """`_box_sum_cdf` against the share of a sampled parallelogram on one side of an edge."""
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0.1, 2.0, 20), rng.uniform(0.0, 2.0, 20)
    z = rng.uniform(-2.0, 2.0, 20)
    s, t = np.meshgrid(np.linspace(-0.5, 0.5, 801), np.linspace(-0.5, 0.5, 801))
    sampled = [np.mean(ai * s + bi * t < zi) for ai, bi, zi in zip(a, b, z)]
    np.testing.assert_allclose(_box_sum_cdf(z, a, b), sampled, atol=3e-3)


def test_bad_projected_raises(rig):
    hp, wp = rig.projector.shape
    with pytest.raises(InputError, match=r"projected must have shape \(96, 128\) \(H, W\), got \(128, 96\)"):
        render(rig, plane_scene(), np.zeros((wp, hp)))
    nan = np.zeros((hp, wp))
    nan[3, 4] = np.nan
    with pytest.raises(InputError, match="projected has non-finite pixels"):
        render(rig, plane_scene(), nan)
    with pytest.raises(InputError, match=r"projected values must lie in \[0, 1\]"):
        render(rig, plane_scene(), np.full((hp, wp), 1.5))


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: Conditions(supersample=0), "Conditions.supersample"),
        (lambda: Conditions(ambient=-0.1), "Conditions.ambient"),
        (lambda: Conditions(bit_depth=0), "Conditions.bit_depth"),
        (lambda: Conditions(albedo=0.5), "albedo must be callable"),
        (lambda: UniformAlbedo(1.5), r"value must lie in \[0, 1\]"),
        (lambda: Plane((0, 0, 0), (0, 0, 0)), "normal must be non-zero"),
        (lambda: Sphere((0, 0, 800), -1.0), "radius must be positive"),
        (lambda: Box((0, 0, 0), (1, -1, 1)), "lo must be below hi"),
        (lambda: Cylinder((0, 0, 800), 50.0, 0.0), "radius and height must be positive"),
        (lambda: Cylinder((0, 0, 800), 50.0, 10.0, axis="z"), "axis must be 'x' or 'y'"),
        (lambda: Union(), "Union needs one or more surfaces"),
        (lambda: virtual_rig(distance_mm=-5.0), "distance_mm must be positive"),
        (lambda: virtual_rig(camera_fov_deg=190.0), r"camera_fov_deg must lie in \(0, 180\)"),
        (lambda: Mat5Surface(np.zeros((4, 4)), np.ones((4, 4), bool)), r"points must have shape \(H, W, 3\)"),
        (lambda: Mat5Surface(np.zeros((4, 4, 3)), np.ones((4, 5), bool)), r"valid must have shape \(4, 4\)"),
        (lambda: Mat5Surface(np.full((4, 4, 3), np.nan), np.ones((4, 4), bool)), "no triangle"),
        (lambda: Pinhole.from_matrix(np.zeros((3, 4)), (4, 4)), "not a pinhole projection"),
        (lambda: tilted_plane_scene(axis="z"), "axis must be 'x' or 'y'"),
    ],
)
def test_bad_parameters_raise(make, match):
    with pytest.raises(InputError, match=match):
        make()


def test_bad_albedo_values_raise(rig):
    cond = Conditions.ideal().with_(albedo=lambda xyz: np.full(len(xyz), 1.2))
    with pytest.raises(InputError, match=r"albedo values must lie in \[0, 1\], got \[1.2, 1.2\]"):
        render(rig, plane_scene(), np.ones(rig.projector.shape), cond)


def test_rig_rejects_bad_lenses_and_parallel_axes(rig):
    cam = rig.calibration.camera
    for intrinsics in (None, cam.intrinsics * [[1.01], [1], [1]]):
        distorted = Device(cam.matrix, cam.size, intrinsics=intrinsics, distortion=[0.1, 0, 0, 0, 0])
        with pytest.raises(InputError, match=r"^camera: lens distortion needs the intrinsics K it goes with"):
            Rig(Calibration(distorted, rig.calibration.projector))
    shifted = Device(cam.matrix + np.hstack([np.zeros((3, 3)), cam.intrinsics @ [[0], [-200.0], [0]]]), cam.size)
    with pytest.raises(InputError, match="optical axes are parallel; give working_distance_mm"):
        Rig(Calibration(cam, shifted))
    assert Rig(Calibration(cam, shifted), working_distance_mm=600.0).working_distance_mm == 600.0


# ---------------------------------------------------------------------------------- sequences


def test_render_sequence_matches_render_frame_by_frame(rig):
    """One trace shaded under each image gives, bit for bit, what `render` gives for that image alone."""
    drives = [np.full(rig.projector.shape, 0.3), np.tile(np.linspace(0, 1, PROJECTOR[0]), (PROJECTOR[1], 1))]
    cond = Conditions(supersample=2, albedo=SmoothAlbedo(seed=3)).with_(full_well_e=None)  # no noise: comparable
    seq = render_sequence(rig, sphere_scene(), drives, cond)
    assert seq.images.shape == (2, *rig.camera.shape) and seq.images.dtype == np.float32
    for drive, image in zip(drives, seq.images):
        single = render(rig, sphere_scene(), drive, cond)
        np.testing.assert_array_equal(image, single.image)
    for name in ("points", "proj", "lit", "surface", "albedo", "edge"):
        np.testing.assert_array_equal(getattr(seq.truth, name), getattr(single.truth, name))


def test_render_sequence_draws_noise_per_frame(rig):
    drive = np.full(rig.projector.shape, 0.6)
    cond = Conditions(supersample=1)
    seq = render_sequence(rig, plane_scene(), [drive, drive], cond, rng=5)
    # the first frame draws first from the same generator: exactly `render`'s frame for that seed
    np.testing.assert_array_equal(seq.images[0], render(rig, plane_scene(), drive, cond, rng=5).image)
    difference = seq.images[0].astype(np.float64) - seq.images[1]
    assert difference.std() > 0.002  # shot noise of ~0.4 full scale at 10000 e-: ~0.006 per frame
    assert abs(np.corrcoef(difference[:, :-1].ravel(), difference[:, 1:].ravel())[0, 1]) < 0.2  # no shared pattern


def test_render_sequence_refuses_bad_images(rig):
    with pytest.raises(InputError, match="at least one image"):
        render_sequence(rig, plane_scene(), [])
    with pytest.raises(InputError, match=r"projected\[1\] must have shape \(96, 128\)"):
        render_sequence(rig, plane_scene(), [np.ones(rig.projector.shape), np.ones((2, 2))])


# ---------------------------------------------------------------------------------- lenses

#: Realistic lenses (OpenCV's k1, k2, p1, p2, k3).
CAMERA_LENS = (-0.1, 0.05, 1e-3, -5e-4, 0.0)
PROJECTOR_LENS = (0.08, -0.03, -8e-4, 1e-3, 0.0)


@pytest.fixture(scope="module")
def lens_rig() -> Rig:
    return virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR, camera_distortion=CAMERA_LENS,
                       projector_distortion=PROJECTOR_LENS)


def test_lenses_bend_the_rays_and_the_projector_light(lens_rig):
    """Through the camera's lens every pixel centre's truth point reprojects onto that pixel; the
    projector lights each point from its distorted pixel (the truth's `proj`, what a decoder
    measures), checked by projecting a ramp along x: drive ``xp / (W - 1)`` over drive 1 reads
    ``xp`` back (bilinear sampling of a ramp is exact).  Tolerances: float32 truth points and
    images, 1e-4 px (a float32 image ratio times 127 px is good to 2e-5 px)."""
    ramp = np.tile(np.linspace(0, 1, PROJECTOR[0]), (PROJECTOR[1], 1))
    seq = render_sequence(lens_rig, plane_scene(), [np.ones(lens_rig.projector.shape), ramp],
                          Conditions.ideal().with_(projector_gamma=1.0))
    truth = seq.truth
    lit = truth.lit & ~truth.edge
    assert lit.mean() > 0.9
    h, w = lens_rig.camera.shape
    y, x = np.mgrid[0:h, 0:w]
    seen = lens_rig.calibration.camera.project(truth.points[lit].astype(np.float64))
    np.testing.assert_allclose(seen, np.c_[x[lit], y[lit]], rtol=0, atol=1e-4)
    proj = lens_rig.calibration.projector.project(truth.points[lit].astype(np.float64))
    np.testing.assert_allclose(truth.proj[lit], proj, rtol=0, atol=1e-4)
    xp = seq.images[1][lit] / seq.images[0][lit] * (PROJECTOR[0] - 1)
    np.testing.assert_allclose(xp, truth.proj[lit][:, 0], rtol=0, atol=1e-3)
    # ... and the lens matters: the pinhole projection is 0.6 px away at this small projector's
    # corners (100x the tolerance above).
    pinhole = Device(lens_rig.calibration.projector.matrix, PROJECTOR).project(truth.points[lit].astype(np.float64))
    assert np.abs(pinhole - proj).max() > 0.3


def test_zero_distortion_is_the_pinhole(rig):
    """All-zero coefficients are no lens: the rig's devices and its renders are the pinhole's, bit for bit."""
    zero = virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR, camera_distortion=np.zeros(5),
                       projector_distortion=np.zeros(5))
    assert zero.camera.distortion is None and zero.projector.distortion is None
    drive = np.full(rig.projector.shape, 0.7)
    assert np.array_equal(render(zero, sphere_scene(), drive, Conditions.ideal()).image,
                          render(rig, sphere_scene(), drive, Conditions.ideal()).image)
