"""Decoding the stripes by the order they come in along the phase direction (`sliscan.stripe_order`)."""

import dataclasses

import numpy as np
import pytest

from sliscan import patterns, simulate
from sliscan.decode import decode
from sliscan.demodulate import demodulate
from sliscan.evaluate import accuracy
from sliscan.patterns import code_bits, stripe_codes
from sliscan.pipeline import Scanner
from sliscan.stripe_order import (OrderCosts, anchored_runs, decode_by_order, reversed_runs, rig_direction,
                                  stripe_direction)

from order_reference import decode_column, evidence, transitions

SPEC = patterns.default_spec((1024, 768))
ON = code_bits(stripe_codes(SPEC), SPEC.bits).astype(bool)  # (S, K), stripes in order


def ideal_levels(stripes, gain=1.0):
    """``(K, H, W)`` levels of the stripe map `stripes` ``(H, W)`` (-1: dark, all bits 0), times `gain`."""
    on = np.vstack([ON, np.zeros((1, SPEC.bits), bool)])[stripes]  # (H, W, K); -1 picks the dark row
    return np.moveaxis(on.astype(np.float32) * np.float32(gain), -1, 0).copy()


def staircase(h=150, w=8, first=2, height=20):
    """Stripes first, first + 1, ... down every column, `height` rows each."""
    return np.broadcast_to((first + np.arange(h) // height)[:, None], (h, w)).astype(np.int16).copy()


SPAN = np.full(SPEC.bits, 0.3)


def test_kernels_equal_the_dense_reference(rng):
    """Stripes, margins and own misfits are the max-marginals of an explicit transition matrix
    over the evidence written out in numpy (`order_reference`), on noisy levels with dim, dark,
    corrupted and non-finite pixels, a depth jump, and a width that leaves a partial block."""
    truth = staircase(h=120, w=45)
    truth[50:58] = 11  # a depth edge: a jump and back
    truth[90:100, 5:20] = -1  # a shadow
    levels = ideal_levels(truth) * rng.uniform(0.2, 1.2, truth.shape).astype(np.float32)
    levels += rng.normal(0, 0.15, levels.shape).astype(np.float32)
    levels[:, 30, 3] = np.nan
    noise = rng.uniform(0.0, 0.05, truth.shape).astype(np.float32)
    noise[7, 7] = np.inf
    lit = (truth >= 0) ^ (rng.random(truth.shape) < 0.05)
    costs = OrderCosts()
    stripe, margin, misfit = decode_by_order(levels, noise, SPAN, lit, SPEC, 1, costs)
    cost = evidence(levels, noise, SPAN, lit, ON, costs)
    t = transitions(len(ON), costs, costs.step, costs.back)
    for x in range(truth.shape[1]):
        label, ref_margin, ref_misfit = decode_column(cost[:, x], t)
        sure = ref_margin > 1e-2  # ties may break either way in float32
        expected = np.where(label == len(ON), -1, label)
        np.testing.assert_array_equal(stripe[sure, x], expected[sure], err_msg=f"column {x}")
        np.testing.assert_allclose(margin[:, x], ref_margin, atol=2e-3, rtol=1e-4, err_msg=f"column {x}")
        np.testing.assert_allclose(misfit[sure, x], ref_misfit[sure], atol=1e-3, rtol=1e-4, err_msg=f"column {x}")


def test_bit_gains_divide_each_bits_noise(rng):
    """Envelopes divided by per-bit gains (`decode`'s `follow_blur`) carry their noise divided
    by the same gains: with gains constant per bit that is each bit's span times its gain (bit
    `n`'s noise is ``noise / (span[n] gain[n])``), so both decode the same, margins within
    float32's rounding; the rows orientation and its transpose alike."""
    truth = staircase(h=120, w=45)
    levels = ideal_levels(truth, gain=0.6) + rng.normal(0, 0.1, (SPEC.bits, *truth.shape)).astype(np.float32)
    noise = rng.uniform(0.01, 0.05, truth.shape).astype(np.float32)
    lit = np.ones(truth.shape, bool)
    gain = np.array([0.3, 0.5, 0.8, 1.0])
    gains = np.broadcast_to(gain[:, None, None], levels.shape).astype(np.float32)
    for spec, frame in ((SPEC, lambda a: a), (SPEC.with_(orientation="columns"),
                                              lambda a: np.swapaxes(a, -1, -2).copy())):
        divided = decode_by_order(frame(levels), frame(noise), SPAN, frame(lit), spec, 1, bit_gains=frame(gains))
        spans = decode_by_order(frame(levels), frame(noise), SPAN * gain, frame(lit), spec, 1)
        np.testing.assert_array_equal(divided[0], spans[0])
        np.testing.assert_allclose(divided[1], spans[1], atol=1e-3)
        plain = decode_by_order(frame(levels), frame(noise), SPAN, frame(lit), spec, 1)
        assert np.abs(plain[1] - spans[1]).max() > 1  # the gains do change the margins


def test_a_lost_bit_is_no_evidence_and_the_order_decides(rng):
    """The most significant bit read off everywhere (each stripe of the lower half reads as its
    mirror): decided with that bit, the columns come out mirrored (the per-pixel evidence
    outweighs the order); with its gain 0 (`decode`'s lost bit) the bit counts for nothing, and
    the order alone tells each stripe from its mirror: every pixel right but where the lost bit
    is the only one that changes (stripes 6 and 7, rows 80-119: the border between them is
    anywhere in that pair, a stripe off at most)."""
    truth = staircase(h=150, w=20)
    levels = ideal_levels(truth, gain=0.8) + rng.normal(0, 0.03, (SPEC.bits, *truth.shape)).astype(np.float32)
    levels[0] = rng.normal(0.1, 0.03, truth.shape)  # the lost bit: read off
    noise = np.full(truth.shape, 0.01, np.float32)
    lit = np.ones(truth.shape, bool)
    gains = np.ones(levels.shape, np.float32)
    with_bit, _, _ = decode_by_order(levels, noise, SPAN, lit, SPEC, 1, bit_gains=gains)
    gains[0] = 0
    without, margin, _ = decode_by_order(levels, noise, SPAN, lit, SPEC, 1, bit_gains=gains)
    assert (with_bit != truth).mean() > 0.3
    wrong = without != truth
    assert np.abs(without - truth).max() <= 1 and not wrong[:80].any() and not wrong[120:].any()


def test_a_dim_surface_decodes_by_its_code_not_its_level(rng):
    """A surface turning away from the projector: every level is 0.3 of its on level (the
    ambient part of the DC stays), so a 0.5 threshold reads every bit off, but the code's
    pattern is clear: every pixel gets its stripe, with a wide margin."""
    truth = staircase()
    levels = ideal_levels(truth, gain=0.3) + rng.normal(0, 0.02, (SPEC.bits, *truth.shape)).astype(np.float32)
    noise = np.full(truth.shape, 0.006, np.float32)  # 0.02 in level units
    stripe, margin, misfit = decode_by_order(levels, noise, SPAN, np.ones(truth.shape, bool), SPEC, 1)
    assert np.array_equal(stripe, truth)
    assert np.median(margin) > 5 and np.percentile(misfit, 95) < 3


def test_context_outvotes_a_corrupted_run_and_the_order_has_no_far_stripes(rng):
    """Six rows inside stripe 4 (code 0111) whose most significant bit reads 0.6 (light leaking
    from a neighbour): a 0.5 threshold makes them stripe 9 (1111), half the depth range away.
    Their evidence for 9 is ~3 nats a row better, the two jumps there and back cost 30: they
    take their stripe again, and no pixel anywhere is more than one stripe off."""
    truth = staircase()
    levels = ideal_levels(truth) + rng.normal(0, 0.03, (SPEC.bits, *truth.shape)).astype(np.float32)
    assert np.all(truth[45:51] == 4) and ON[4].tolist() == [False, True, True, True]
    levels[0, 45:51] = 0.6
    noise = np.full(truth.shape, 0.03, np.float32)
    stripe, margin, _ = decode_by_order(levels, noise, SPAN, np.ones(truth.shape, bool), SPEC, 1)
    assert np.array_equal(stripe[45:51], truth[45:51])
    assert np.all(np.abs(stripe.astype(int) - truth) <= 1)


def test_dark_pixels_stay_dark_and_unusable_pixels_give_no_evidence(rng):
    truth = staircase()
    truth[60:80] = -1
    levels = ideal_levels(truth) + rng.normal(0, 0.05, (SPEC.bits, *truth.shape)).astype(np.float32)
    levels[:, 30, 2] = np.nan
    noise = np.full(truth.shape, 0.03, np.float32)
    stripe, margin, misfit = decode_by_order(levels, noise, SPAN, truth >= 0, SPEC, 1)
    assert np.all(stripe[61:79] == -1)
    assert misfit[30, 2] == 0 and stripe[30, 2] == truth[30, 2]  # its column's context decides it
    assert np.array_equal(stripe[truth >= 0], truth[truth >= 0])


def test_direction_and_orientation(rng):
    truth = staircase()
    valid = np.ones(truth.shape, bool)
    assert stripe_direction(truth, valid, SPEC) == 1
    assert stripe_direction(truth[::-1], valid, SPEC) == -1
    assert stripe_direction(np.full(truth.shape, 3), valid, SPEC) == 0
    columns = SPEC.with_(orientation="columns")
    assert stripe_direction(truth.T, valid.T, columns) == 1
    levels = ideal_levels(truth) + rng.normal(0, 0.05, (SPEC.bits, *truth.shape)).astype(np.float32)
    noise = np.full(truth.shape, 0.03, np.float32)
    rows = decode_by_order(levels, noise, SPAN, valid, SPEC, 1)
    flipped = decode_by_order(levels[:, ::-1], noise[::-1], SPAN, valid, SPEC, -1)
    turned = decode_by_order(np.swapaxes(levels, 1, 2), noise.T, SPAN, valid.T, columns, 1)
    assert np.array_equal(rows[0], truth) and np.array_equal(flipped[0], truth[::-1])
    for a, b in zip(rows, turned):
        np.testing.assert_array_equal(a, b.T)


def realistic(seed):
    return simulate.Conditions(albedo=simulate.SmoothAlbedo(low=0.15, high=1.0, seed=seed), ambient=0.1,
                               projector_gamma=2.2, seed=seed, supersample=2)


def test_order_decodes_more_of_the_sphere_than_per_pixel_decisions(small_rig):
    """The virtual sphere under issue 2's conditions (640x480, smooth albedo 0.15-1, ambient
    10 %, gamma 2.2, blur, noise, 8 bits; seed 3, not one the defaults were chosen on).
    Measured when written: stripes right on 81.0 % of the lit pixels against 63.9 % per pixel (a
    stripe is only ~30 rows here, so many pixels see a border in their window), completeness 83.0 %
    against 65.6 %, stripes more than one off 0.07 % against 0.05 % (fifty-fourth session, with
    everything since: 89.7 against 78.4 %, 92.3 against 81.1 %, 0.22 against 0.20 %); at 1296x972 (seeds 0, 1)
    92.8-93.0 % against 90.8-90.9 %.  Asserted with room for other renders: at least 1.5
    points more of both, far stripes under 0.5 %."""
    spec = patterns.default_spec((1024, 768))
    capture = simulate.render(small_rig, simulate.sphere_scene(), patterns.render_pattern(spec), realistic(3))
    results = {name: accuracy(Scanner(spec, small_rig.calibration, decode_options=dict(order=order)).scan(capture.image),
                              capture.truth, spec, small_rig.calibration)
               for name, order in (("order", True), ("pixel", False))}
    order, pixel = results["order"], results["pixel"]
    assert order.stripe_accuracy >= pixel.stripe_accuracy + 0.015, results
    assert order.completeness >= pixel.completeness + 0.015, results
    assert order.far_stripe <= 0.005, results
    assert order.median_mm <= 1.1 * order.oracle_median_mm


def test_decode_by_order_is_the_default_for_the_thesis_pattern_too(small_rig):
    """Every single-shot pattern is decided by order unless asked otherwise, the thesis's too
    (its lit zero stripe, which looks like shadow, is added after the order by `_zero_stripe`).
    The thesis's pattern on the sphere under issue 2's conditions (640x480, seed 3): measured
    78.6 % of the lit pixels on the right stripe against 67.6 % per pixel, completeness 81.1 %
    against 69.7 %, more than one stripe off 0.14 % both (seeds 1, 2 and the steps: +6 to +10
    points).  Asserted with room for other renders: at least 5 points more of both, far
    stripes under 0.5 %."""
    capture = simulate.render(small_rig, simulate.plane_scene(), patterns.render_pattern(SPEC), realistic(1))
    demod, _ = demodulate(capture.image, SPEC)
    default, forced = decode(demod, SPEC), decode(demod, SPEC, order=True)
    assert np.array_equal(default.stripe, forced.stripe) and np.array_equal(default.valid, forced.valid)
    thesis = patterns.thesis_spec((1024, 768))
    capture = simulate.render(small_rig, simulate.sphere_scene(), patterns.render_pattern(thesis), realistic(3))
    results = {name: accuracy(Scanner(thesis, small_rig.calibration, decode_options=options).scan(capture.image),
                              capture.truth, thesis, small_rig.calibration)
               for name, options in (("default", {}), ("pixel", dict(order=False)))}
    default, pixel = results["default"], results["pixel"]
    assert default.stripe_accuracy >= pixel.stripe_accuracy + 0.05, results
    assert default.completeness >= pixel.completeness + 0.05, results
    assert default.far_stripe <= 0.005, results


def test_anchored_runs_keep_the_runs_their_own_pixels_vouch_for():
    """A run (one stripe's pixels in a row down a column) is kept when at least the share asked
    of its pixels got that stripe per pixel, or may be it (`alternates`: a lost bit); dark runs
    never."""
    stripe = np.array([[3, 3, 3, 3, 4, 4, 4, 4, -1, -1]], dtype=np.int16).T
    anchors = np.array([[3, -1, -1, -1, -1, 5, -1, 4, -1, -1]], dtype=np.int16).T
    np.testing.assert_array_equal(anchored_runs(stripe, anchors, SPEC)[:, 0], [1, 1, 1, 1, 1, 1, 1, 1, 0, 0])
    np.testing.assert_array_equal(anchored_runs(stripe, anchors, SPEC, min_share=0.3)[:, 0], [0] * 10)
    anchors[1, 0] = 3
    np.testing.assert_array_equal(anchored_runs(stripe, anchors, SPEC, min_share=0.3)[:, 0], [1, 1, 1, 1] + [0] * 6)
    columns = SPEC.with_(orientation="columns")
    np.testing.assert_array_equal(anchored_runs(stripe.T, anchors.T, columns, min_share=0.3),
                                  anchored_runs(stripe, anchors, SPEC, min_share=0.3).T)
    alternates = np.array([[-1, -1, -1, -1, 4, -1, 4, -1, -1, -1]], dtype=np.int16).T  # the stripes they may be too
    np.testing.assert_array_equal(anchored_runs(stripe, anchors, SPEC, min_share=0.3, alternates=alternates)[:, 0],
                                  [1] * 8 + [0] * 2)


def column(*runs):
    """A column ``(H, 1)`` of stripes from ``(stripe, pixels)`` runs."""
    return np.concatenate([np.full(n, s, np.int16) for s, n in runs])[:, None]


def test_reversed_runs_drop_a_mirrored_chain_but_not_one_step_back():
    """Down a column the stripes come in order; a chain of steps back (a lost bit read as its
    mirror: 5, 4, 3 after 0-3 and 6) is found on every run entered going back, the gaps between
    them skipped, and the chain's head (6, entered going forward) is left alone; the most
    significant bit set again reads it 8, 9, 10 (mirror 13 - s of the 15 stripes), forward from
    its head, and no other bit does, so those are its restored stripes.  One step back alone (a
    thin object before a wall) stays, and so do runs shorter than a quarter of a stripe's mean
    height (3 pixels at least, here) that step back, a border read early or late, and a wrong
    excursion (a jump, a step back, a jump back: no chain of small steps back, so the right run
    after it is not blamed); a chain that no one bit turns forward (4, 3 after 6: 9 is three
    stripes on) is found but not restored; the column upside down with direction -1 gives the
    same upside down; columns are the transpose."""
    def runs(stripe, spec=SPEC, direction=1):
        reverse, restored = reversed_runs(stripe, spec, direction)
        np.testing.assert_array_equal(restored >= 0, reverse & (restored >= 0))  # restored only where reversed
        return reverse, restored

    chain = column((-1, 1), (0, 8), (1, 8), (2, 8), (-1, 2), (3, 8), (6, 8), (5, 8), (-1, 2), (4, 8), (3, 8), (-1, 53))
    expected = np.zeros(chain.shape, bool)
    expected[43:69] = chain[43:69] >= 0
    reverse, restored = runs(chain)
    np.testing.assert_array_equal(reverse, expected)
    np.testing.assert_array_equal(restored, np.where(expected, 13 - chain, -1))
    reverse, restored = runs(chain[::-1].copy(), direction=-1)  # the stripes numbered up the column
    np.testing.assert_array_equal(reverse, expected[::-1])
    np.testing.assert_array_equal(restored, np.where(expected, 13 - chain, -1)[::-1])
    unrestorable = column((0, 20), (1, 20), (2, 20), (6, 20), (4, 20), (3, 20))
    reverse, restored = runs(unrestorable)
    assert reverse[80:].all() and not reverse[:80].any() and (restored == -1).all()
    edge = column((0, 20), (1, 20), (5, 20), (2, 20), (3, 20), (4, 20))
    jitter = column((9, 20), (10, 20), (11, 2), (10, 1), (11, 30), (12, 2), (11, 30), (9, 1), (12, 14))
    excursion = column((4, 20), (11, 20), (10, 20), (5, 20), (6, 20), (7, 20))  # 11 and 10 wrong, 5 right
    for stripe, direction in ((edge, 1), (jitter, 1), (excursion, 1), (chain, 0)):
        reverse, restored = runs(stripe, direction=direction)
        assert not reverse.any() and (restored == -1).all()
    columns = SPEC.with_(orientation="columns")
    both = np.hstack([chain, chain]).astype(np.int16)
    for by_rows, by_columns in zip(runs(both), runs(both.T.copy(), columns)):
        np.testing.assert_array_equal(by_columns, by_rows.T)


def test_rig_direction_follows_the_camera_and_the_pattern():
    """The virtual rig (projector above the camera) numbers the stripes down the camera's rows,
    as the ground truth of a capture shows; a camera turned upside down (its rows read bottom
    up) reverses it, and so does a mirrored one for a pattern in columns."""
    rig = simulate.virtual_rig(camera_size=(320, 240), projector_size=(256, 192))
    spec = patterns.default_spec((256, 192))
    capture = simulate.render(rig, simulate.plane_scene(), patterns.render_pattern(spec), simulate.Conditions(seed=0))
    truth = np.where(capture.truth.lit, patterns.stripe_of_line(np.nan_to_num(capture.truth.proj[..., 1], nan=-1), spec),
                     -1)
    assert rig_direction(rig.calibration, spec) == stripe_direction(truth, truth >= 0, spec) == 1
    width, height = rig.calibration.camera.size
    camera = rig.calibration.camera
    upside_down = np.array([[1.0, 0, 0], [0, -1, height], [0, 0, 1]]) @ camera.matrix
    mirrored = np.array([[-1.0, 0, 0], [0, 1, 0], [0, 0, 1]]) @ camera.matrix + np.outer([width, 0, 0], camera.matrix[2])
    turned = dataclasses.replace(rig.calibration, camera=dataclasses.replace(camera, matrix=upside_down))
    assert rig_direction(turned, spec) == -1
    columns = spec.with_(orientation="columns")
    flipped = dataclasses.replace(rig.calibration, camera=dataclasses.replace(camera, matrix=mirrored))
    assert rig_direction(flipped, columns) == -rig_direction(rig.calibration, columns) != 0
