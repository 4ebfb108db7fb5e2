"""Scanner plumbing and the accuracy figures themselves."""

import numpy as np
import pytest

from sliscan import InputError, PatternSpec, Scanner, ScanResult, patterns, simulate
from sliscan.evaluate import accuracy, oracle_points, true_stripes
from sliscan.patterns import stripe_center
from sliscan.pipeline import baseline_direction, device_centre, inside_projector, triangulation_angle
from sliscan.sequences import decode_frames, render_frames


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
    assert inside_projector(points, small_rig.calibration, spec.orientation).tolist() == [[True, False, False, False]]


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


# ------------------------------------------------------------------------------------ multi-frame patterns


PMP = PatternSpec(kind="pmp", projector_size=(1024, 768), steps=3, frequencies=(1.0, 16.0), b_p=0.5, gamma=2.2)


@pytest.mark.parametrize("frames, message", [
    ([np.zeros((480, 640), np.uint8)] * 5, r"a pmp capture needs 6 frames \(1 direction x 2 frequencies x 3 steps\), "
                                          r"got 5"),
    (np.zeros((480, 640), np.uint8), "a pmp capture is a sequence of 6 frames .*, got one image"),
    ([np.zeros((480, 640), np.uint8)] * 5 + [np.zeros((480, 641), np.uint8)],
     r"frame 5 must have shape \(480, 640\) \(H, W\), got \(480, 641\)"),
    ([np.zeros((240, 320), np.uint8)] * 6, r"frame 0 must have shape \(480, 640\)"),
    ([np.zeros((480, 640), np.int32)] * 6, "frame 0 must be uint8, uint16 or float, got int32"),
])
def test_scanner_refuses_bad_sequences(small_rig, frames, message):
    with pytest.raises(InputError, match=message) as exc:
        Scanner(PMP, small_rig.calibration).scan(frames)
    assert "\n" not in str(exc.value)


def test_sequence_scan_takes_uint8_and_leaves_it_alone(small_rig):
    seq = simulate.render_sequence(small_rig, simulate.plane_scene(), render_frames(PMP),
                                   simulate.Conditions(supersample=1, seed=4))
    frames = [np.round(image * 255).astype(np.uint8) for image in seq.images]  # 8-bit captures: the same levels
    copies = [f.copy() for f in frames]
    scanner = Scanner(PMP, small_rig.calibration)
    as_uint8, as_float = scanner.scan(frames), scanner.scan(seq.images)
    assert all(np.array_equal(a, b) for a, b in zip(frames, copies))
    np.testing.assert_array_equal(as_uint8.valid, as_float.valid)
    np.testing.assert_array_equal(as_uint8.points, as_float.points)
    assert as_uint8.valid.sum() > 0.9 * seq.truth.lit.sum()
    assert set(as_uint8.timings) == {"decode", "triangulate", "total"}


def test_both_orientations_triangulate_along_the_baseline():
    """Gray code of columns and rows: the rig decides which one is triangulated; both stay available."""
    rig = simulate.virtual_rig(camera_size=(320, 240), projector_size=(256, 192), baseline_axis="horizontal")
    assert baseline_direction(rig.calibration) == "columns"
    assert baseline_direction(simulate.virtual_rig(camera_size=(320, 240), projector_size=(256, 192)).calibration) \
        == "rows"
    spec = PatternSpec(kind="graycode", projector_size=(256, 192), orientation="both")
    seq = simulate.render_sequence(rig, simulate.plane_scene(), render_frames(spec), simulate.Conditions.ideal())
    strict = dict(max_dropped_bits=0, border_bit=False)  # OpenCV's rule: whole codes only
    result = Scanner(spec, rig.calibration, decode_options=strict).scan(seq.images)
    truth_xp = seq.truth.proj[..., 0]
    np.testing.assert_array_equal(result.proj_map[result.valid], np.floor(truth_xp[result.valid] + 0.5))
    assert result.valid.sum() > 0.95 * seq.truth.lit.sum()
    # a column is about 1.8 mm wide at 800 mm: every point within one column's depth of the plane
    assert np.abs(result.points[result.valid][:, 2] - 800).max() < 10
    maps = decode_frames(seq.images, spec)
    assert set(maps) == {"columns", "rows"} and maps["rows"].valid.sum() > 0.95 * seq.truth.lit.sum()
