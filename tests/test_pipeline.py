"""Scanner plumbing and the accuracy figures themselves."""

import numpy as np
import pytest

from sliscan import ScanResult, patterns, simulate
from sliscan.evaluate import accuracy, oracle_points, true_stripes
from sliscan.patterns import stripe_center
from sliscan.pipeline import device_centre, inside_projector, triangulation_angle


def test_device_centres_and_triangulation_angle(small_rig):
    camera = device_centre(small_rig.calibration.camera.matrix)
    projector = device_centre(small_rig.calibration.projector.matrix)
    np.testing.assert_allclose(camera, [0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(projector, [0, -200, 0], atol=1e-6)  # 200 mm above (y down)
    point = np.array([[[0.0, 0.0, 800.0]]])
    # closed form: the rays from (0, 0, 0) and (0, -200, 0) meet at atan(200 / 800)
    assert triangulation_angle(point, small_rig.calibration)[0, 0] == pytest.approx(np.degrees(np.arctan(0.25)))


def test_inside_projector(small_rig):
    spec = patterns.thesis_spec((1024, 768))
    points = np.array([[[0.0, 0.0, 800.0], [0.0, 0.0, -800.0], [5000.0, 0.0, 800.0], [np.nan, 0, 0]]])
    assert inside_projector(points, small_rig.calibration, spec).tolist() == [[True, False, False, False]]


def _perfect_result(truth, spec, calibration):
    """A scan that decoded every lit pixel's true stripe."""
    stripes = true_stripes(truth, spec)
    points = oracle_points(truth, spec, calibration)
    valid = stripes >= 0
    return ScanResult(points=points, valid=valid, texture=np.zeros(valid.shape, np.float32),
                      proj_map=stripe_center(stripes, spec).astype(np.float32), stripe=stripes.astype(np.int16),
                      confidence=valid.astype(np.float32))


def test_accuracy_of_a_perfect_decoder_is_the_oracle(small_rig):
    spec = patterns.thesis_spec((1024, 768))
    capture = simulate.render(small_rig, simulate.sphere_scene(), patterns.render_pattern(spec),
                              simulate.Conditions(supersample=1, seed=0))
    perfect = _perfect_result(capture.truth, spec, small_rig.calibration)
    acc = accuracy(perfect, capture.truth, spec, small_rig.calibration)
    assert acc.stripe_accuracy == 1.0 and acc.completeness == 1.0 and acc.wrong_stripe == 0.0
    assert acc.outliers == 0.0
    assert acc.median_mm == acc.oracle_median_mm and acc.rms_mm == acc.oracle_rms_mm
    # the staircase of 16 stripes: the error is at most about half a stripe's depth
    assert 5 < acc.oracle_median_mm < 60


def test_accuracy_counts_a_shifted_stripe_as_wrong(small_rig):
    spec = patterns.thesis_spec((1024, 768))
    capture = simulate.render(small_rig, simulate.plane_scene(), patterns.render_pattern(spec),
                              simulate.Conditions(supersample=1, seed=0))
    perfect = _perfect_result(capture.truth, spec, small_rig.calibration)
    stripe = np.where(perfect.stripe >= 3, perfect.stripe - 3, -1).astype(np.int16)  # 3 stripes off
    valid = stripe >= 0
    from sliscan.reconstruct import triangulate
    points = triangulate(stripe_center(stripe, spec), small_rig.calibration, valid=valid)
    shifted = ScanResult(points=points, valid=valid, texture=perfect.texture, proj_map=perfect.proj_map,
                         stripe=stripe, confidence=perfect.confidence)
    acc = accuracy(shifted, capture.truth, spec, small_rig.calibration)
    assert acc.stripe_accuracy == 0.0 and acc.wrong_stripe == 1.0
    assert acc.outliers > 0.99  # three stripes off is farther than one stripe's depth
