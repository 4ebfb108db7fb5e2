"""Classic Gray code in OpenCV's order: the sequence, exact decoding (OpenCV's rule and sliscan's graceful one), the
hybrid with phase, and real captures."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from sliscan import InputError, PatternSpec, simulate
from sliscan._validate import read_image
from sliscan.graycode import BLACK_THRESHOLD, WHITE_THRESHOLD, code_planes, decode_graycode, pattern_frames
from sliscan.patterns import bits_to_code, gray_decode
from sliscan.sequences import decode_frames, render_frames

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "procam-chessboard-graycode"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"real captures not found at {DATA}")

OPENCV = PatternSpec(kind="graycode", projector_size=(1024, 768), orientation="both")
STRICT = dict(max_dropped_bits=0, border_bit=False)  # OpenCV's rule: every bit must be reliable


def test_frame_count_and_json_round_trip(tmp_path):
    assert OPENCV.frame_count == 42  # 10 column bits and 10 row bits (768 rows need 10), pairs, white, black
    assert OPENCV.with_(projector_size=(1280, 800)).frame_count == 2 * (11 + 10) + 2
    hybrid = OPENCV.with_(steps=4, code_width=8, b_p=0.5, orientation="rows")
    assert hybrid.frame_count == 2 * 7 + 2 + 4  # 96 codes of 8 rows: 7 bits
    hybrid.save(tmp_path / "gc.json")
    assert PatternSpec.load(tmp_path / "gc.json") == hybrid


@pytest.mark.parametrize("changes, message", [
    (dict(code_width=3), "power of two"),
    (dict(steps=4, b_p=0.5), "code_width >= 2"),
    (dict(steps=2, code_width=8), "steps >= 3"),
    (dict(steps=4, code_width=8), "a_p \\+/- b_p"),  # the default b_p = 0.125 is fine; 0.6 is not
])
def test_spec_refuses(changes, message):
    if "b_p" not in changes and changes.get("steps"):
        changes["b_p"] = 0.6
    with pytest.raises(InputError, match=message):
        OPENCV.with_(**changes)


def test_code_planes_are_a_gray_code():
    planes = code_planes(OPENCV, "rows").astype(int)
    assert planes.shape == (10, 768)
    # adjacent rows differ in exactly one bit, and the bits read MSB first give gray(row)
    assert (np.abs(np.diff(planes, axis=1)).sum(axis=0) == 1).all()
    values = (planes * (1 << np.arange(9, -1, -1))[:, None]).sum(axis=0)
    assert values.tolist() == (np.arange(768) ^ (np.arange(768) >> 1)).tolist()


@needs_data
def test_sequence_is_opencvs_bit_for_bit():
    files = sorted((DATA / "graycode_pattern").glob("pattern_*.png"))
    reference = np.stack([cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in files])
    frames = pattern_frames(OPENCV)
    np.testing.assert_array_equal(np.round(frames * 255).astype(np.uint8), reference)


@pytest.fixture(scope="module")
def ideal_tilted(small_rig):
    return simulate.render_sequence(small_rig, simulate.tilted_plane_scene(20), render_frames(OPENCV),
                                    simulate.Conditions.ideal())


def test_noise_free_capture_decodes_exactly(ideal_tilted):
    """Under OpenCV's rule every decoded pixel has its exact projector column and row; every lit pixel is decoded
    except where the pixel centre sees the border of two projector lines so closely that the pattern and its inverse
    differ by less than OpenCV's whiteThreshold: with bilinear light a fraction t past the border they differ by
    (1 - 2 t)(white - black), so that band is WHITE_THRESHOLD / (2 (white - black)) wide (about 0.01 px).  sliscan's
    default decodes the same pixels identically and the band too: a weak finest bit is dropped (the pixel gets the
    centre of its two lines, block 2), a weak coarser bit is decided by its sign (its line or the neighbour)."""
    frames, truth = ideal_tilted.images, ideal_tilted.truth
    strict_maps, maps = decode_frames(frames, OPENCV, **STRICT), decode_frames(frames, OPENCV)
    span = np.maximum(frames[40] - frames[41], 1e-6)  # 0 off the projector, where nothing is lit
    band = WHITE_THRESHOLD / (2 * span) + 1e-4
    for axis, direction in enumerate(("columns", "rows")):
        strict, decoded = strict_maps[direction], maps[direction]
        coord = truth.proj[..., axis]
        assert not (strict.valid & ~truth.lit).any()
        np.testing.assert_array_equal(strict.coord[strict.valid], np.floor(coord[strict.valid] + 0.5))
        ambiguous = np.abs(coord - np.floor(coord) - 0.5) < band
        assert (strict.valid | ~truth.lit | ambiguous).all()
        assert (truth.lit & ~strict.valid).sum() < 0.03 * truth.lit.sum()
        assert (decoded.valid == truth.lit).all() and (strict.valid <= decoded.valid).all()
        np.testing.assert_array_equal(decoded.coord[strict.valid], strict.coord[strict.valid])
        assert (decoded.block[strict.valid] == 1).all()
        added = decoded.valid & ~strict.valid
        assert (np.abs(decoded.coord - coord)[added] <= decoded.block[added] / 2 + band[added]).all()


@pytest.fixture(scope="module")
def blurred_tilted(small_rig):
    """Rows of OpenCV's sequence on a realistic rig: projector and camera blur 1 px, noise, ambient, gamma."""
    spec = OPENCV.with_(orientation="rows")
    conditions = simulate.Conditions(albedo=simulate.SmoothAlbedo(seed=2), seed=2, supersample=1)
    return spec, simulate.render_sequence(small_rig, simulate.tilted_plane_scene(20), render_frames(spec), conditions)


def test_blurred_capture_decodes_coarser_blocks_where_fine_bits_wash_out(blurred_tilted):
    """The 640x480 camera sees ~1.6 projector rows per pixel, blurred by 1 px in both optics: the finest bit
    (2-row stripes) washes out nearly everywhere, so OpenCV's rule decodes only ~11 % of the lit pixels (measured
    11.2 %); dropping it (and, where needed, the next) decodes 93.6 %, mostly in blocks of 2 rows.

    Every decoded row lies in its reported block, up to the camera pixel's footprint: the truth is the row at the
    pixel CENTRE while the bits come from the light over the whole blurred pixel, so a pixel whose centre lies just
    past a code or block border may take the neighbour's side (as OpenCV's rule does: it puts 1.5 % of its pixels
    outside their 1-row code, by up to 1.1 rows).  Measured: 1.1 % outside the block, 0.3 % by more than half a
    row, none by more than 1.13 rows."""
    spec, capture = blurred_tilted
    lit, truth = capture.truth.lit, capture.truth.proj[..., 1]
    strict = decode_graycode(capture.images, spec, "rows", **STRICT)
    decoded = decode_graycode(capture.images, spec, "rows")
    assert (strict.valid & lit).sum() < 0.15 * lit.sum()
    assert (decoded.valid & lit).sum() > 0.9 * lit.sum()
    inside = decoded.valid & lit
    outside = np.abs(decoded.coord - truth)[inside] - decoded.block[inside] / 2
    assert (outside > 0).mean() < 0.02 and (outside > 0.5).mean() < 0.005 and outside.max() < 1.5
    assert set(np.unique(decoded.block[inside])) <= {1, 2, 4, 8}  # at most 3 bits dropped by default
    assert (decoded.block[~decoded.valid] == 0).all()


def test_strict_option_is_opencvs_rule_exactly(blurred_tilted):
    """`max_dropped_bits=0, border_bit=False` is OpenCV's decode, written out here: lit where white - black exceeds
    blackThreshold, every |pattern - inverse| at least whiteThreshold, the Gray code of the bits' signs."""
    spec, capture = blurred_tilted
    frames = capture.images
    difference = frames[0:20:2] - frames[1:20:2]
    span = frames[20] - frames[21]
    valid = (span > BLACK_THRESHOLD) & (np.abs(difference) >= WHITE_THRESHOLD).all(axis=0)
    code = gray_decode(bits_to_code(difference > 0))
    decoded = decode_graycode(frames, spec, "rows", **STRICT)
    np.testing.assert_array_equal(decoded.valid, valid)
    np.testing.assert_array_equal(decoded.coord, np.where(valid, code, np.nan).astype(np.float32))
    np.testing.assert_array_equal(decoded.index, np.where(valid, code, -1))
    np.testing.assert_array_equal(decoded.block, valid.astype(np.int32))
    contrast = np.abs(difference).min(axis=0) / np.where(span > 0, span, np.inf)
    np.testing.assert_array_equal(decoded.confidence, np.clip(contrast, 0, 1).astype(np.float32))


@pytest.mark.parametrize("weak, options, expected", [
    ((), STRICT, (682, 1)),
    ((9,), STRICT, None),  # OpenCV: any weak bit rejects the pixel
    ((3,), STRICT, None),
    ((9,), {}, (682.5, 2)),  # the finest bit dropped: codes 682-683
    ((7, 8, 9), {}, (683.5, 8)),  # three dropped: codes 680-687
    ((6, 7, 8, 9), {}, None),  # four would exceed the default limit...
    ((6, 7, 8, 9), dict(max_dropped_bits=4), (679.5, 16)),  # ...unless allowed: codes 672-687
    ((3,), {}, (682, 1)),  # a border bit, decided by its sign
    ((3,), dict(border_bit=False), None),
    ((3, 9), {}, (682.5, 2)),  # a border bit and a dropped one
    ((2, 5), {}, None),  # two weak bits before reliable ones: not a border
    ((3, 8), {}, None),  # bit 8 is weak but bit 9 is not: not trailing
])
def test_weak_bits_rule(weak, options, expected):
    """Every Gray bit 1 (code 0b1010101010 = 682) with some bits weak: pattern brighter than its inverse by half
    OpenCV's whiteThreshold."""
    frames = np.full((42, 4, 4), 0.3, np.float32)
    frames[40] += 0.5
    frames[0:20:2] += 0.3
    for bit in weak:
        frames[2 * bit] = frames[2 * bit + 1] + WHITE_THRESHOLD / 2
    decoded = decode_graycode(frames, OPENCV, "columns", **options)
    if expected is None:
        assert not decoded.valid.any() and (decoded.block == 0).all()
    else:
        assert decoded.valid.all() and (decoded.coord == expected[0]).all() and (decoded.block == expected[1]).all()


def test_max_dropped_bits_must_not_be_negative(ideal_tilted):
    with pytest.raises(InputError, match="max_dropped_bits must be >= 0"):
        decode_frames(ideal_tilted.images, OPENCV, max_dropped_bits=-1)


def test_hybrid_gives_subpixel_rows_without_period_jumps(small_rig):
    spec = PatternSpec(kind="graycode", projector_size=(1024, 768), orientation="rows", steps=4, code_width=8, b_p=0.5)
    ideal = simulate.render_sequence(small_rig, simulate.tilted_plane_scene(20), render_frames(spec),
                                     simulate.Conditions.ideal())
    decoded = decode_graycode(ideal.images, spec, "rows")
    lit = ideal.truth.lit
    err = (decoded.coord - ideal.truth.proj[..., 1])[decoded.valid & lit]
    # as in plain Gray code the pixels within ~0.01 px of a code border are left out (96 borders here)
    assert (decoded.valid & lit).sum() > 0.995 * lit.sum()
    assert np.sqrt(np.mean(err**2)) < 0.05  # the phase, not the 8-row codes
    # with realistic noise and blur no pixel off an edge is a period (16 rows) off, also among those that a weak Gray
    # bit decided by its sign adds (a border bit: one code off, which the unwrapping absorbs); no bit is dropped
    noisy = simulate.render_sequence(small_rig, simulate.tilted_plane_scene(20), render_frames(spec),
                                     simulate.Conditions(albedo=simulate.SmoothAlbedo(seed=2), seed=2, supersample=1))
    decoded = decode_graycode(noisy.images, spec, "rows", black_threshold=0.02)
    strict = decode_graycode(noisy.images, spec, "rows", black_threshold=0.02, **STRICT)
    assert (strict.valid <= decoded.valid).all() and (decoded.valid & ~strict.valid).any()
    assert (decoded.block[decoded.valid] == 8).all()
    inner = decoded.valid & noisy.truth.lit & ~noisy.truth.edge
    assert inner.sum() > 0.9 * noisy.truth.lit.sum()
    assert np.abs(decoded.coord - noisy.truth.proj[..., 1])[inner].max() < 4


def test_white_darker_than_black_is_refused(ideal_tilted):
    frames = ideal_tilted.images.copy()
    frames[[40, 41]] = frames[[41, 40]]
    with pytest.raises(InputError, match=r"out of order: the white frame \(40\) is darker than the black frame \(41\)"):
        decode_frames(frames, OPENCV)


def test_contrast_and_shadow_thresholds(rng):
    frames = (0.3 + rng.normal(0, 0.002, (42, 20, 20))).astype(np.float32)
    frames[40] += 0.5  # lit, but no pattern differs from its inverse by OpenCV's whiteThreshold (5/255)
    assert not decode_frames(frames, OPENCV)["columns"].valid.any()
    frames[0:40:2] += 0.3  # every pattern now brighter than its inverse: all Gray bits 1, code 0b1010101010
    decoded = decode_frames(frames, OPENCV)["columns"]
    assert decoded.valid.all() and (decoded.coord == 682).all()
    frames[40] = frames[41] + 0.1  # white - black below OpenCV's blackThreshold (40/255): a shadow
    assert not decode_frames(frames, OPENCV)["columns"].valid.any()


@needs_data
def test_real_capture_of_a_planar_board_maps_by_a_homography():
    """capture_0: a printed chessboard under OpenCV's sequence (1280x1024 camera, 1024x768 projector).  On the plane
    of the board the camera -> projector map is a homography, so decoded (xp, yp) inside the board's detected corners
    must fit one; Gray code quantisation alone leaves residuals of at most 0.71 px (half a line on each axis)."""
    frames = [read_image(f) for f in sorted((DATA / "capture_0").glob("*.png"))]
    maps = decode_frames(frames, OPENCV)
    white = np.round(frames[40] * 255).astype(np.uint8)
    found, corners = cv2.findChessboardCorners(white, (9, 7))
    assert found
    board = np.zeros(white.shape, np.uint8)
    cv2.fillConvexPoly(board, cv2.convexHull(corners.reshape(-1, 2)).astype(np.int32), 1)
    decoded = maps["columns"].valid & maps["rows"].valid & (board > 0)
    assert decoded.sum() > 0.3 * board.sum()  # the dark squares fall under OpenCV's blackThreshold
    ys, xs = np.nonzero(decoded)
    camera = np.stack([xs, ys], axis=1).astype(np.float64)
    projector = np.stack([maps["columns"].coord[decoded], maps["rows"].coord[decoded]], axis=1).astype(np.float64)
    homography, inliers = cv2.findHomography(camera, projector, cv2.RANSAC, 1.0)
    assert inliers.mean() > 0.99  # measured 99.7 %
    residual = np.linalg.norm(cv2.perspectiveTransform(camera[None], homography)[0] - projector, axis=1)
    assert np.median(residual) < 0.5
