"""The sphere fit that checks a scan against the thesis's 122.555 mm target."""

import numpy as np
import pytest

from sliscan import ScanResult, patterns, simulate
from sliscan.evaluate import fit_sphere, robust_sphere, sphere_fit


def _cap(rng, n, radius, noise_mm):
    """Points on the camera-facing half of a sphere at (20, -10, 800), with Gaussian noise."""
    d = rng.normal(size=(n, 3))
    d[:, 2] = -np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.array([20.0, -10.0, 800.0]) + (radius + rng.normal(0, noise_mm, n))[:, None] * d


def test_fit_sphere_on_a_noisy_half_sphere(rng):
    centre, radius, rms = fit_sphere(_cap(rng, 4000, 122.555, 0.5))
    # 4000 points with 0.5 mm noise: the radius's standard error is ~0.5 / sqrt(4000) * 2 (half
    # sphere) ~ 0.02 mm; 0.1 mm is five of them
    assert radius == pytest.approx(122.555, abs=0.1)
    np.testing.assert_allclose(centre, [20, -10, 800], atol=0.2)
    assert rms == pytest.approx(0.5, rel=0.05)


def test_sphere_fit_of_the_true_points_is_the_true_radius(small_rig):
    spec = patterns.thesis_spec((1024, 768))
    capture = simulate.render(small_rig, simulate.sphere_scene(), patterns.render_pattern(spec),
                              simulate.Conditions.ideal())
    truth = capture.truth
    valid = truth.surface.copy()
    result = ScanResult(points=truth.points, valid=valid, texture=np.zeros(valid.shape, np.float32),
                        proj_map=truth.proj[..., 1], stripe=np.zeros(valid.shape, np.int16),
                        confidence=valid.astype(np.float32))
    radius, rejected = sphere_fit(result, truth, (0, 0, 800), 122.555)
    assert radius == pytest.approx(122.555, abs=1e-3)  # float32 points
    assert rejected < 0.01
    assert np.isnan(sphere_fit(result, truth, (0, 0, 800), 50.0)[0])  # no points on that sphere


def test_robust_sphere_ignores_flying_points(rng):
    points = _cap(rng, 4000, 122.555, 0.5)
    flying = rng.choice(4000, 200, replace=False)
    points[flying, 2] -= rng.uniform(50, 300, 200)  # 5 % wrong codes, far in front
    assert abs(fit_sphere(points)[1] - 122.555) > 2  # a plain fit is dragged away
    _, radius, rms, inliers = robust_sphere(points)
    assert radius == pytest.approx(122.555, abs=0.1)
    assert not inliers[flying].any() and inliers.mean() > 0.94
