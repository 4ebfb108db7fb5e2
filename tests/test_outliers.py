"""The 3D filters on the projector map: wrong-code patches and the mixed pixels along depth edges go,
real surfaces stay."""

import cv2
import numpy as np
import pytest
from scipy.special import erf

from sliscan._validate import InputError
from sliscan.outliers import (default_min_region, remove_jump_edges, remove_narrow_runs, remove_run_ends,
                              remove_speckles, shadow_side)


def _two_surfaces(rng):
    """A 200x300 map: two smooth ramps meeting at a real depth step (column 150)."""
    yy, xx = np.mgrid[0:200, 0:300].astype(np.float32)
    proj = 0.5 * yy + 0.01 * xx
    proj[:, 150:] += 120  # an object edge: both sides are large regions
    return proj + rng.normal(0, 0.2, proj.shape).astype(np.float32)


def test_keeps_large_regions_across_a_real_step(rng):
    proj = _two_surfaces(rng)
    keep = remove_speckles(proj, np.ones(proj.shape, bool), lines=768, max_jump=4)
    assert keep.all()


def test_drops_wrong_code_patches_of_any_jump_sign(rng):
    proj = _two_surfaces(rng)
    truth = np.ones(proj.shape, bool)
    for (r, c), jump in zip([(20, 20), (100, 60), (150, 200), (50, 250)], (48, -48, 384, -96)):
        proj[r:r + 5, c:c + 6] += jump  # 30-pixel patches, under min_region_px=40
        truth[r:r + 5, c:c + 6] = False
    keep = remove_speckles(proj, np.ones(proj.shape, bool), lines=768, max_jump=4, min_region_px=40)
    np.testing.assert_array_equal(keep, truth)


def test_invalid_and_nan_pixels_stay_invalid_and_split_regions(rng):
    proj = _two_surfaces(rng)
    valid = np.ones(proj.shape, bool)
    valid[:, 100] = False          # a cut line: the 3-pixel-wide strip beside it is isolated
    valid[:, 104] = False
    proj[0, 0] = np.nan
    keep = remove_speckles(proj, valid, lines=768, max_jump=4, min_region_px=700)
    assert not keep[:, 100].any() and not keep[0, 0]
    assert not keep[:, 101:104].any()          # 600 pixels < 700
    assert keep[:, :100].sum() == 200 * 100 - 1


def _remove_speckles_reference(proj, valid, lines, max_jump, size):
    """The numpy form of `remove_speckles`' quantisation (before the compiled kernel)."""
    scale = 32000 / (lines + 1)
    inside = valid & np.isfinite(proj)
    quantised = np.full(proj.shape, -1, dtype=np.int16)
    quantised[inside] = np.clip(np.rint((proj[inside] + 1) * scale), 0, 32000)
    cv2.filterSpeckles(quantised, -1, size, max(1, int(max_jump * scale)))
    return inside & (quantised != -1)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int32])
def test_speckle_kernel_equals_the_numpy_form(rng, dtype):
    """Values beyond the map's range (clipped), NaN, invalid pixels; float32 arithmetic on a
    float32 map, as numpy's, so the same values round the same way."""
    proj = (rng.random((120, 160)) * 900 - 60).round(1)
    proj[rng.random(proj.shape) < 0.05] = np.nan
    proj = (np.nan_to_num(proj, nan=-7) if dtype == np.int32 else proj).astype(dtype)
    proj = np.repeat(proj, 2, axis=0)  # regions of a few pixels, some kept
    valid = rng.random(proj.shape) < 0.9
    keep = remove_speckles(proj, valid, lines=768, max_jump=30, min_region_px=3)
    np.testing.assert_array_equal(keep, _remove_speckles_reference(proj, valid, 768, 30, 3))
    assert 0.05 < keep.mean() < 0.95


def test_default_region_scales_with_the_image():
    assert default_min_region((972, 1296)) == 252
    assert default_min_region((10, 10)) == 25


@pytest.mark.parametrize("kwargs", [dict(lines=0, max_jump=1), dict(lines=768, max_jump=0)])
def test_bad_parameters_are_refused(kwargs):
    with pytest.raises(InputError):
        remove_speckles(np.zeros((4, 4)), np.ones((4, 4), bool), **kwargs)


def test_shape_mismatch_is_refused():
    with pytest.raises(InputError, match="same shape"):
        remove_speckles(np.zeros((4, 4)), np.ones((4, 5), bool), lines=768, max_jump=1)


def _edge_with_a_sliver(rng):
    """A 40x400 map: two surfaces meeting at a depth edge (column 200), and between them a
    30-pixel sliver of a wrong code (as a window straddling the edge decodes it)."""
    proj = np.tile(np.where(np.arange(400) < 200, 100.0, 160.0), (40, 1)).astype(np.float32)
    proj += rng.normal(0, 0.3, proj.shape).astype(np.float32)
    proj[:, 185:215] = 400
    return proj


def test_narrow_runs_across_a_depth_edge_are_dropped(rng):
    proj = _edge_with_a_sliver(rng)
    keep = remove_narrow_runs(proj, np.ones(proj.shape, bool), max_jump=10, window=60)
    assert not keep[:, 185:215].any() and keep[:, :185].all() and keep[:, 215:].all()


def test_narrow_runs_that_agree_with_a_side_or_are_wide_or_alone_are_kept(rng):
    proj = _edge_with_a_sliver(rng)
    valid = np.ones(proj.shape, bool)
    proj[:10, 185:215] = 100           # rows 0-9: the sliver continues the left surface
    kept = remove_narrow_runs(proj, valid, max_jump=10, window=30)   # a window of 30: not narrower
    assert kept.all()
    valid[20:30, 140:185] = valid[20:30, 215:260] = False             # rows 20-29: nothing within a window
    keep = remove_narrow_runs(proj, valid, max_jump=10, window=40)
    assert keep[:10].all() and keep[20:30, 185:215].all() and not keep[30:, 185:215].any()


def test_narrow_runs_along_columns_are_the_transpose(rng):
    proj = _edge_with_a_sliver(rng)
    valid = rng.random(proj.shape) < 0.97
    rows = remove_narrow_runs(proj, valid, max_jump=10, window=60)
    np.testing.assert_array_equal(remove_narrow_runs(proj.T, valid.T, max_jump=10, window=60, axis=0), rows.T)


@pytest.mark.parametrize("kwargs", [dict(max_jump=0, window=10), dict(max_jump=1, window=0),
                                    dict(max_jump=1, window=10, axis=2)])
def test_narrow_runs_bad_parameters_are_refused(kwargs):
    with pytest.raises(InputError):
        remove_narrow_runs(np.zeros((4, 4)), np.ones((4, 4), bool), **kwargs)


# ------------------------------------------------------------------------------------ run ends

def _distance_to_run_end(proj, valid, max_jump):
    """Per valid pixel, the pixels to the nearest end of its run along the rows, by walking."""
    h, w = proj.shape
    out = np.full((h, w), -1)
    for y in range(h):
        for x in range(w):
            if not valid[y, x]:
                continue
            left = right = 0
            while x - left - 1 >= 0 and valid[y, x - left - 1] and abs(proj[y, x - left - 1] - proj[y, x - left]) <= max_jump:
                left += 1
            while x + right + 1 < w and valid[y, x + right + 1] and abs(proj[y, x + right + 1] - proj[y, x + right]) <= max_jump:
                right += 1
            out[y, x] = min(left, right)
    return out


@pytest.mark.parametrize("margin", [0, 1, 4, 12])
def test_run_ends_drop_exactly_the_pixels_within_the_margin(rng, margin):
    """Against a walk to each run's ends: gaps, jumps (real steps and wrong-code slivers) and
    the frame's edges all end a run; a run shorter than twice the margin goes entirely."""
    proj = _edge_with_a_sliver(rng)
    valid = rng.random(proj.shape) < 0.97
    valid[:, 60:63] = False
    keep = remove_run_ends(proj, valid, margin=margin, max_jump=10)
    distance = _distance_to_run_end(proj, valid, 10)
    np.testing.assert_array_equal(keep, valid & (distance >= margin))
    assert not keep[~valid].any()


def test_run_ends_along_columns_are_the_transpose(rng):
    proj = _edge_with_a_sliver(rng)
    valid = rng.random(proj.shape) < 0.97
    rows = remove_run_ends(proj, valid, margin=5, max_jump=10)
    np.testing.assert_array_equal(remove_run_ends(proj.T, valid.T, margin=5, max_jump=10, axis=0), rows.T)


@pytest.mark.parametrize("kwargs", [dict(margin=-1, max_jump=10), dict(margin=2, max_jump=0),
                                    dict(margin=2, max_jump=10, axis=2)])
def test_run_ends_bad_parameters_are_refused(kwargs):
    with pytest.raises(InputError):
        remove_run_ends(np.zeros((4, 4)), np.ones((4, 4), bool), **kwargs)


# ------------------------------------------------------------------------------------ jump edges


def test_jump_edges_drop_both_sides_of_a_step_and_nothing_else(rng):
    proj = _two_surfaces(rng)   # neighbours of one surface differ by at most about 1.5 rows
    keep = remove_jump_edges(proj, np.ones(proj.shape, bool), max_jump=4)
    expected = np.ones(proj.shape, bool)
    expected[:, 149:151] = False
    np.testing.assert_array_equal(keep, expected)


@pytest.mark.parametrize("gap, reach, dropped", [(5, 16, [144, 150]), (5, 5, []), (15, 16, [134, 150])])
def test_jump_edges_look_across_a_gap_as_far_as_reach(rng, gap, reach, dropped):
    """The first pixel on each side of an undecoded gap goes when the other side is within
    `reach` (Chebyshev distance: gap + 1) and more than max_jump per pixel away; a surface's
    own steep slope (a ramp of 3 rows per pixel across the gap) is never cut."""
    proj = _two_surfaces(rng)
    valid = np.ones(proj.shape, bool)
    valid[:, 150 - gap:150] = False
    keep = remove_jump_edges(proj, valid, max_jump=4, reach=reach)
    assert (valid & ~keep).any(axis=0).nonzero()[0].tolist() == dropped
    assert (valid & ~keep)[:, dropped].all()
    ramp = np.tile(3.0 * np.arange(300, dtype=np.float32), (200, 1))
    assert (remove_jump_edges(ramp, valid, max_jump=4, reach=reach) == valid).all()


def test_jump_edges_ignore_invalid_and_nan_neighbours():
    proj = np.full((20, 20), 100.0)
    proj[:, 10:] = 300.0
    valid = np.ones(proj.shape, bool)
    valid[:, 10:] = False                          # the other surface undecoded: no jump, no gap across
    assert (remove_jump_edges(proj, valid, max_jump=4) == valid).all()
    proj[:, 10:] = np.nan
    assert (remove_jump_edges(proj, np.ones(proj.shape, bool), max_jump=4)[:, :10]).all()


@pytest.mark.parametrize("kwargs", [dict(max_jump=0), dict(max_jump=4, reach=0)])
def test_jump_edges_bad_parameters_are_refused(kwargs):
    with pytest.raises(InputError):
        remove_jump_edges(np.zeros((4, 4)), np.ones((4, 4), bool), **kwargs)


# ------------------------------------------------------------------------------------ shadow sides


def test_shadow_side_takes_the_run_ends_darker_than_halfway_to_the_shadow():
    # a lit surface (DC 1) whose shadow (DC 0.1) begins at row 20.5, blurred by a Gaussian of
    # sigma 1.5 rows: the light is halfway at row 20.5, so rows 21 and on lie in the shadow
    rows = np.arange(40)
    dc = (0.1 + 0.9 * 0.5 * (1 - erf((rows - 20.5) / (1.5 * np.sqrt(2))))).astype(np.float32)[:, None]
    line = np.full((40, 1), 300.0, np.float32)
    for last in (21, 22, 23):  # the decoder kept rows up to `last`: the shadow-side ones go, at most 3
        line[:] = 300.0
        line[last + 1:] = np.nan
        dark = shadow_side(line, dc, jump=50.0)[:, 0]
        assert np.nonzero(dark)[0].tolist() == list(range(21, last + 1))
    line[:] = 300.0
    line[25:] = np.nan  # four rows into the shadow: the walk stops after SHADOW_SIDE_STEPS
    assert np.nonzero(shadow_side(line, dc, jump=50.0)[:, 0])[0].tolist() == [22, 23, 24]
    # rows up to 20 (the lit side of the halfway point) stay, at a gap or at a jump
    line[:] = 300.0
    line[21:] = np.nan
    assert not shadow_side(line, dc, jump=50.0).any()
    line[21:] = 420.0  # another surface beyond a jump, kept too: only row 20's side is tested
    assert np.nonzero(shadow_side(line, dc, jump=50.0)[:, 0])[0].tolist() == []
    # not at a run end (a dark dip inside a run), or the outside brighter (a shadow ending): kept
    line[:] = 300.0
    assert not shadow_side(line, dc, jump=50.0).any()
    line[:21] = np.nan
    assert not shadow_side(line, dc, jump=50.0).any()


def test_jump_edges_search_equals_their_definition(rng):
    """The pruned search (bands of rings flagged by dilations, then a compiled ring search)
    drops exactly what the definition drops, on random maps with steps, gaps and NaNs."""
    for trial in range(40):
        height, width = rng.integers(5, 60, 2)
        proj = np.cumsum(rng.normal(0, rng.choice([0.5, 3.0, 8.0]), (height, width)), axis=1)
        proj[rng.random(proj.shape) < 0.05] += 200
        proj[rng.random(proj.shape) < 0.02] = np.nan
        valid = rng.random(proj.shape) < rng.choice([0.5, 0.8, 0.95])
        for max_jump, reach in ((2.0, 1), (2.0, 5), (6.0, 16)):
            inside = valid & np.isfinite(proj)
            values = np.where(inside, proj, 0.0)
            pad = reach + 1
            padded, there = np.pad(values, pad), np.pad(inside, pad, constant_values=False)
            frame = np.pad(np.ones(proj.shape, bool), pad, constant_values=False)
            near = np.zeros(proj.shape, bool)
            far = np.zeros(proj.shape, bool)
            gap = np.zeros(proj.shape, bool)
            for dy in range(-reach, reach + 1):
                for dx in range(-reach, reach + 1):
                    d = max(abs(dy), abs(dx))
                    if d == 0:
                        continue
                    window = np.s_[pad + dy:pad + dy + height, pad + dx:pad + dx + width]
                    differs = there[window] & (np.abs(padded[window] - values) > max_jump * d)
                    near |= differs & (d == 1)
                    far |= differs
                    gap |= (d == 1) & frame[window] & ~there[window]
            expected = valid & ~(inside & (near | (gap & far)))
            np.testing.assert_array_equal(remove_jump_edges(proj, valid, max_jump=max_jump, reach=reach), expected)
