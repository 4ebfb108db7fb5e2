"""OpenCV's lens model on pixels (`sliscan.lens`): against OpenCV itself, round trips, the
Jacobian against finite differences, Newton along lines."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sliscan import InputError, lens

K = np.array([[900.0, 0.0, 250.0], [0.0, 905.0, 180.0], [0.0, 0.0, 1.0]])
DISTORTION = np.array([-0.12, 0.05, 1e-3, -2e-3, 0.01])


@pytest.fixture
def pixels(rng) -> np.ndarray:
    """Ideal pixels over a 500x360 image and 50 px beyond it."""
    return rng.uniform([-50, -50], [550, 410], (2000, 2))


def test_distort_is_opencvs_model(pixels):
    """`cv2.projectPoints` of the normalised ideal points: equal to float64 rounding (1e-9 px)."""
    normalised = np.c_[(pixels - K[:2, 2]) / np.diag(K)[:2], np.ones(len(pixels))]
    expected = cv2.projectPoints(normalised, np.zeros(3), np.zeros(3), K, DISTORTION)[0][:, 0]
    np.testing.assert_allclose(lens.distort(pixels, K, DISTORTION), expected, rtol=0, atol=1e-9)


def test_undistort_inverts_distort(pixels):
    """OpenCV's iteration run to 1e-12 in normalised coordinates: ~1e-9 px; 1e-7 px leaves room
    for the slower convergence near the image corners."""
    skewed = K + [[0, 0.4, 0], [0, 0, 0], [0, 0, 0]]  # skew is honoured both ways
    for k in (K, skewed):
        np.testing.assert_allclose(lens.undistort(lens.distort(pixels, k, DISTORTION), k, DISTORTION), pixels,
                                   rtol=0, atol=1e-7)
    assert lens.undistort(np.empty((0, 2)), K, DISTORTION).shape == (0, 2)


def test_jacobian_matches_finite_differences(pixels):
    """Central differences with a 1e-4 px step are exact to ~1e-8 for this smooth polynomial."""
    _, jac = lens.distort(pixels, K, DISTORTION, jacobian=True)
    step = 1e-4
    numeric = np.stack([(lens.distort(pixels + d, K, DISTORTION) - lens.distort(pixels - d, K, DISTORTION)) / (2 * step)
                        for d in np.eye(2) * step], axis=-1)
    np.testing.assert_allclose(jac, numeric, rtol=0, atol=1e-6)


@given(along=st.floats(-40, 400), a=st.floats(-100, 600), b=st.floats(-0.3, 0.3), axis=st.sampled_from([0, 1]))
def test_solve_on_lines_inverts_one_coordinate(along, a, b, axis):
    """The ideal point on ``across = a + b along`` whose distorted coordinate is observed: back
    to 1e-6 px (`SOLVE_TOLERANCE_PX`), i.e. to 1e-5 px in the ideal coordinate here (the lens
    stretches by at most a few percent)."""
    point = np.array([[a + b * along, along]])[:, ::1 if axis == 1 else -1]
    observed = lens.distort(point, K, DISTORTION)[:, axis]
    t = lens.solve_on_lines(observed, axis, [[a, b]], K, DISTORTION)
    assert abs(t[0] - along) < 1e-5


def test_unreachable_coordinates_are_nan():
    """k1 = -0.6 folds the model back at y = 0.745 f below the centre (y_d at most 0.497 f = 450
    px): an observed row beyond that, or NaN, has no solution."""
    folding = np.array([-0.6, 0.0, 0.0, 0.0, 0.0])
    t = lens.solve_on_lines([180 + 300.0, 180 + 500.0, np.nan], 1, [[250.0, 0.0]] * 3, K, folding)
    assert np.isfinite(t[0]) and np.isnan(t[1]) and np.isnan(t[2])
    assert not lens.has_distortion(np.zeros(5)) and not lens.has_distortion(None) and lens.has_distortion(folding)


def test_bad_input():
    with pytest.raises(InputError, match=r"^distortion must have shape \(5,\), got \(4,\)$"):
        lens.distort([[0.0, 0.0]], K, [0.1, 0, 0, 0])
    with pytest.raises(InputError, match="intrinsics must be upper triangular with positive focal lengths"):
        lens.undistort([[0.0, 0.0]], -K, DISTORTION)
    with pytest.raises(InputError, match=r"^xy must have shape \(\.\.\., 2\) \(x, y\), got \(3,\)$"):
        lens.distort([1.0, 2.0, 3.0], K, DISTORTION)
    with pytest.raises(InputError, match=r"^axis must be 0 \(x\) or 1 \(y\), got 2$"):
        lens.solve_on_lines([1.0], 2, [[0.0, 0.0]], K, DISTORTION)
    with pytest.raises(InputError, match=r"^need one line per observed coordinate, got 2 lines for 1$"):
        lens.solve_on_lines([1.0], 1, [[0.0, 0.0]] * 2, K, DISTORTION)
