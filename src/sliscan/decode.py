"""Binarising and Gray decoding of demodulated envelopes (thesis section 3.5).

The thesis thresholds each envelope with one fixed value.  A real surface multiplies the
envelopes by its albedo and adds ambient light, so here each envelope is first normalised by
what the same window of the capture says about the light reaching that pixel:

* with a pilot carrier (on wherever the projector lights), by the pilot's envelope: the ratio
  is the bit itself, whatever the albedo, ambient light or optical roll-off;
* without one (the thesis's pattern), by the local DC, which still carries the ambient light.

Each bit's "off" and "on" levels are then estimated from the capture itself (two-means on the
lit pixels), so crosstalk and roll-off shift the threshold instead of flipping bits; pixels
between two stripes are re-decided at the changing bit's local midpoint (`refine_borders`),
and isolated decisions that disagree with their neighbours are dropped
(`agrees_with_neighbours`).

For patterns that never project the all-zero code, the stripes are then decided along the
phase direction as a whole, by the order they come in (`sliscan.stripe_order`): a pixel whose
own bits are unclear (a surface turning away from the projector, a blurred border) takes the
stripe its column's context leaves no doubt about, and one whose evidence contradicts it
badly is dropped.

The all-zero code projects no carrier at all: in one frame it looks like shadow.  Patterns with
``skip_zero_code`` never project it, so unmodulated pixels are shadow.  Otherwise (the
thesis's pattern) the lit zero stripe is found from the code's structure: it is the
neighbour of stripe 1 on the side away from stripe 2 (see `_zero_stripe`).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import cv2
import numba
import numpy as np
import scipy.ndimage
from numpy.typing import NDArray

from sliscan._threads import in_parallel, over_rows
from sliscan.demodulate import Demodulated
from sliscan.patterns import bits_to_code, code_to_stripe, stripe_center, stripe_codes
from sliscan.stripe_order import OrderCosts, anchored_runs, decode_by_order, reversed_runs, stripe_direction
from sliscan.types import PatternSpec


@dataclass(frozen=True, eq=False)
class Decoded:
    """Per-pixel decoding of one capture.

    Attributes
    ----------
    stripe : (H, W) int16 array
        Stripe index, -1 where invalid.
    proj_map : (H, W) float32 array
        Projector line (projector pixels), NaN where invalid: the stripe's centre from `decode`;
        between the stripe's borders after `sliscan.staircase.interpolate_lines`, the fringe's
        after `sliscan.fringe.refine`.
    valid : (H, W) bool array
    lit : (H, W) bool array
        Pixels the projector's light was detected on.
    confidence : (H, W) float32 array
        Smallest bit margin, in [0, 1]: 0 = a level exactly at its threshold.
    levels : (K, H, W) float32 array
        Normalised bit levels: 0 = the bit's off level, 1 = its on level.
    """

    stripe: NDArray[np.int16]
    proj_map: NDArray[np.float32]
    valid: NDArray[np.bool_]
    lit: NDArray[np.bool_]
    confidence: NDArray[np.float32]
    levels: NDArray[np.float32]

    @property
    def bit_confidence(self) -> NDArray[np.float32]:
        """``(K, H, W)`` float32: each bit decision's margin, in [0, 1] (0 = a level exactly at
        its threshold, 1 = at or beyond its off or on level); `confidence` is their minimum on
        lit pixels."""
        return np.clip(2 * np.abs(self.levels - np.float32(0.5)), 0, 1).astype(np.float32)


def two_means(values: NDArray[np.floating], *, iterations: int = 20) -> tuple[float, float]:
    """Centres of the low and high cluster of 1-D samples (Lloyd's algorithm, k = 2, with
    medians for centres: a carrier's ratio has a long upper tail where gamma sharpens the
    pattern's peaks, and a mean would follow it).

    >>> [round(m, 3) for m in two_means(np.array([0.0, 0.1, 0.0, 0.9, 1.0, 1.1]))]
    [0.0, 1.0]
    """
    v = np.asarray(values).ravel()
    # sorted once, by numpy (in the samples' own dtype: the conversion keeps the order)
    return _sorted_two_means(np.sort(v[np.isfinite(v)]).astype(np.float64), iterations)


#: `two_means`' clipping and starting percentiles (numpy's "linear" method).
_PERCENTILES = np.array([0.5, 5, 95, 99.5]) / 100


@numba.njit(cache=True, nogil=True)
def _sorted_two_means(v: NDArray[np.float64], iterations: int) -> tuple[float, float]:
    """`two_means` of sorted finite values, compiled (in place): each cluster is a slice and its
    median a middle element, and clipping keeps the order; the percentiles are numpy's (linear
    interpolation, same arithmetic), so the centres are ``np.percentile``'s and ``np.median``'s
    to the last bit."""
    n = v.size
    if n == 0:
        return 0.0, 1.0
    q = np.empty(4)
    for k in range(4):
        at = (n - 1) * _PERCENTILES[k]  # numpy's virtual index
        below = int(np.floor(at))
        if at >= n - 1:
            q[k] = v[n - 1]
            continue
        a, b, t = v[below], v[below + 1], at - below
        q[k] = b - (b - a) * (1 - t) if t >= 0.5 else a + (b - a) * t
    floor, lo, hi, top = q[0], q[1], q[2], q[3]
    for i in range(n):  # a few wild values cannot own a cluster
        v[i] = min(max(v[i], floor), top)
    for _ in range(iterations):
        split = np.searchsorted(v, 0.5 * (lo + hi))
        if split == 0 or split == n:
            break
        new_lo, new_hi = _sorted_median(v[:split]), _sorted_median(v[split:])
        if new_lo == lo and new_hi == hi:
            break
        lo, hi = new_lo, new_hi
    return lo, hi


@numba.njit(cache=True, inline="always")
def _sorted_median(a: NDArray[np.float64]) -> float:
    """Median of a sorted non-empty 1-D array (equal to ``np.median``)."""
    middle = a.size // 2
    return a[middle] if a.size % 2 else (a[middle - 1] + a[middle]) / 2


#: Samples per clustering from which `_Scale.of` clusters the carriers in threads.
PARALLEL_CLUSTERING = 50_000


@dataclass(frozen=True)
class _Scale:
    """Each carrier's off and on level of its ratio to a reference, from the capture itself:
    a level ``(ratio - off) / span`` is 0 off and 1 on.

    Attributes
    ----------
    off : (K,) float32 array
        The off cluster's centre (float32, as the ratios are).
    span : (K,) float64 array
        On minus off, at least 1e-6.
    """

    off: NDArray[np.float32]
    span: NDArray[np.float64]

    @classmethod
    def of(cls, amplitude: NDArray[np.float32], carriers: list[int], reference: NDArray[np.float32],
           mask: NDArray[np.bool_], limit: int = 200_000) -> _Scale:
        """Two-means levels of ``amplitude[n] / reference`` for each carrier `n`, over the pixels
        of `mask` thinned to at most about `limit` on a regular grid; the carriers in threads when
        there are `PARALLEL_CLUSTERING` samples or more."""
        step = max(1, int(np.sqrt(mask.sum() / limit)))
        grid = mask[::step, ::step]
        ref = reference[::step, ::step][grid]
        ratios = [amplitude[n, ::step, ::step][grid] / ref for n in carriers]
        # in threads the clusterings wait on each other's GIL (numpy's sorts hold it) until the
        # samples are many (4 of 8k samples: 1.0 ms in turn, 1.2 ms in two threads, measured when
        # two_means was all numpy calls; 4x faster since its loop is compiled)
        clusters = in_parallel(two_means, ratios, None if ref.size >= PARALLEL_CLUSTERING else 1)
        return cls(off=np.array([off for off, _ in clusters], dtype=np.float32),
                   span=np.array([max(on - off, 1e-6) for off, on in clusters]))


def dark_level(dc: NDArray[np.float32]) -> float:
    """2 % of the frame's bright DC level: the floor under the DC that `decode` divides by, so
    black pixels (outside the projector, no ambient light) do not look modulated by dividing
    noise by 0."""
    return 0.02 * float(np.percentile(dc[::4, ::4], 99)) + 1e-6


@numba.njit(cache=True, nogil=True)
def _lit_rows(amplitude: NDArray[np.float32], carriers: NDArray[np.intp], dc: NDArray[np.float32],
              scale_off: NDArray[np.float32], inv_span: NDArray[np.float64], min_modulation: np.float32,
              noise: NDArray[np.float32], bit_gains: NDArray[np.float32], snr_factor: np.float32,
              rows: NDArray[np.intp], lit: NDArray[np.bool_]) -> None:
    """`_lit` for the given rows (`inv_span`: one over the scale's spans); `noise` of shape
    (0, 0) when there is none, `bit_gains` of shape (0, 0, 0).  Carriers outside, columns
    inside, so the column loops vectorise (1.8x faster than pixel by pixel, the same mask)."""
    with_noise = noise.shape[0] > 0
    strongest, top = np.empty(dc.shape[1], np.float32), np.empty(dc.shape[1], np.float32)
    for y in rows:
        strongest[:], top[:] = -np.inf, -np.inf
        for i in range(carriers.size):
            a, off, gain = amplitude[carriers[i], y], scale_off[i], inv_span[i]
            divided = carriers[i] < bit_gains.shape[0]
            for x in range(dc.shape[1]):  # decode's arithmetic: the ratio less the off level in float32
                strongest[x] = max(strongest[x], np.float32(np.float64(a[x] / dc[y, x] - off) * gain))
                # against the noise, the envelope as it was before a division by its gain
                top[x] = max(top[x], a[x] * bit_gains[carriers[i], y, x] if divided else a[x])
        for x in range(dc.shape[1]):
            lit[y, x] = strongest[x] >= min_modulation and (not with_noise or top[x] >= snr_factor * noise[y, x])


#: `level_pixels`: the bits' levels are learned from the lit pixels whose windows leave at most
#: this fraction of their AC energy unexplained (`Demodulated.residual`), if those are at least
#: `LEVEL_PIXELS_KEPT` of the lit ones.
LEVEL_RESIDUAL = 0.3
LEVEL_PIXELS_KEPT = 0.5


def level_pixels(demod: Demodulated, lit: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The lit pixels the bits' off and on levels are learned from: those whose window the
    demodulator's model explains (`LEVEL_RESIDUAL`).

    Where it does not, an envelope can be many times its carrier's true level: on a plane turned
    60 degrees about the vertical (960x720, the pattern with a phase channel) the DC changes
    16-fold along a line on its dim receding side, the lowest carrier's envelope there reached
    1.5-6 times the DC on 1-5 % of the lit pixels, and `two_means` took that tail for the "on"
    cluster (bits 2 and 3 spans 1.09 and 1.42 instead of 0.11-0.12): 17 % of the stripes
    decoded right.  Without the pixels above `LEVEL_RESIDUAL` (5 % of the lit ones there) the
    spans are 0.11-0.12 (docs/accuracy.md, "Sub-stripe depth from one frame").  Demodulators without a
    residual (the baseband path's zeros) learn from every lit pixel."""
    explained = lit & (demod.residual <= LEVEL_RESIDUAL)
    return explained if explained.sum() >= LEVEL_PIXELS_KEPT * lit.sum() else lit


@dataclass(frozen=True, eq=False)
class FrameLevels:
    """What `decode` reads from the whole frame before it decides any pixel.

    Attributes
    ----------
    dc : (H, W) float32 array
        The DC floored at its `dark_level` (``floor``).
    floor : float
    reference : (H, W) float32 array
        What each bit's envelope is divided by: the pilot's envelope, or the floored DC.
    lit_carriers : (M,) intp array
        The carriers that say a pixel is lit: the pilot, or every bit.
    lit_scale : _Scale
        Their off and on levels over the DC (`_lit`).
    lit : (H, W) bool array
        Pixels whose carriers stand clear of the noise (`_lit`).
    bits : _Scale
        Each bit's off and on level over the reference, on the lit pixels whose windows the
        demodulator explains (`level_pixels`).
    """

    dc: NDArray[np.float32]
    floor: float
    reference: NDArray[np.float32]
    lit_carriers: NDArray[np.intp]
    lit_scale: _Scale
    lit: NDArray[np.bool_]
    bits: _Scale

    @classmethod
    def of(cls, demod: Demodulated, spec: PatternSpec, *, min_modulation: float, min_snr: float,
           limit: int = 200_000, bit_gains: NDArray[np.float32] | None = None) -> FrameLevels:
        """The levels of one demodulated frame (`decode`'s `min_modulation` and `min_snr`), each
        from about `limit` pixels at most (`_Scale.of`); `bit_gains` as in `_lit`."""
        floor = dark_level(demod.dc)
        dc = np.maximum(demod.dc, np.float32(floor))
        reference = np.maximum(demod.amplitude[spec.pilot_index] if spec.pilot is not None else dc, np.float32(1e-6))
        carriers = np.array([spec.pilot_index] if spec.pilot is not None else range(spec.bits), dtype=np.intp)
        lit_scale = _Scale.of(demod.amplitude, list(carriers), dc, np.isfinite(demod.amplitude[carriers[0]] / dc),
                              limit)
        lit = _lit(demod, dc, carriers, lit_scale, min_modulation, min_snr, bit_gains)
        bits = _Scale.of(demod.amplitude, list(range(spec.bits)), reference, level_pixels(demod, lit), limit)
        return cls(dc=dc, floor=floor, reference=reference, lit_carriers=carriers, lit_scale=lit_scale, lit=lit,
                   bits=bits)


def _lit(demod: Demodulated, dc: NDArray[np.float32], carriers: NDArray[np.intp], scale: _Scale,
         min_modulation: float, min_snr: float, bit_gains: NDArray[np.float32] | None = None) -> NDArray[np.bool_]:
    """Pixels whose carriers stand clear of the noise.

    Each carrier's envelope over the DC is put on its own 0 (off) .. 1 (on) scale over the
    whole frame (`scale`), so a code whose only bit rides on the most attenuated carrier
    counts as much as any other.  A pixel is lit when its strongest of `carriers` (the pilot,
    if any) reaches `min_modulation` on that scale and one of them stands `2 * min_snr` of its
    noise deviations above zero (`bit_gains` ``(K, H, W)``: what the bits' envelopes were
    divided by, and so their noise; see `decode`).
    """
    lit = np.empty(dc.shape, dtype=bool)
    noise = np.zeros((0, 0), np.float32) if demod.noise is None else demod.noise
    gains = np.zeros((0, 0, 0), np.float32) if bit_gains is None else bit_gains
    inv_span = 1 / scale.span
    over_rows(lambda rows: _lit_rows(demod.amplitude, carriers, dc, scale.off, inv_span, np.float32(min_modulation),
                                     noise, gains, np.float32(2 * min_snr), rows, lit), dc.shape[0])
    return lit


@numba.njit(cache=True, inline="always")
def is_settled(code: int, unclear: int, first_unclear: int, stripe_of_code: NDArray[np.int64],
               stripe_borders: bool) -> bool:
    """Whether a pixel's Gray `code` decides its stripe: every bit clear, or, with
    `stripe_borders`, one unclear bit (the `first_unclear`, 0 = most significant) whose flip
    gives the neighbouring stripe: a pixel on a stripe border (Gray code neighbours differ in
    one bit), off by at most one stripe either way."""
    if unclear == 0:
        return True
    if not stripe_borders or unclear > 1:
        return False
    bits = int(np.log2(stripe_of_code.size))
    s, other = stripe_of_code[code], stripe_of_code[code ^ (1 << (bits - 1 - first_unclear))]
    return other >= 0 and abs(other - s) == 1


@numba.njit(cache=True, nogil=True)
def _decode_rows(amplitude: NDArray[np.float32], reference: NDArray[np.float32], scale_off: NDArray[np.float32],
                 scale_span: NDArray[np.float64], stripe_of_code: NDArray[np.int64], lit: NDArray[np.bool_],
                 residual: NDArray[np.float32], noise: NDArray[np.float32], bit_gains: NDArray[np.float32],
                 half_confidence: np.float32, min_snr: np.float32, max_residual: np.float32, stripe_borders: bool,
                 rows: NDArray[np.intp], levels: NDArray[np.float32], stripe: NDArray[np.int16],
                 confidence: NDArray[np.float32], valid: NDArray[np.bool_], unclear_bits: NDArray[np.uint16]) -> None:
    """Bit levels, Gray decoding and the per-pixel validity tests of `decode`, for the given
    rows (see `decode` for the tests; `noise` of shape (0, 0) when there is none; bit `n`'s
    noise is ``noise / bit_gains[n]``, or `noise` where `bit_gains` has shape (0, 0, 0)).
    `unclear_bits`: the unclear bits of a lit pixel the model explains, as a mask of its code's
    bits (0 elsewhere)."""
    bits = scale_off.size
    with_noise = noise.shape[0] > 0
    divided = bit_gains.shape[0] > 0
    for y in rows:
        for x in range(reference.shape[1]):
            ref = reference[y, x]
            code, unclear, first_unclear, any_on, mask = 0, 0, -1, False, 0
            least = np.float32(np.inf)
            for n in range(bits):
                level = np.float32(np.float64(amplitude[n, y, x] / ref - scale_off[n]) / scale_span[n])
                levels[n, y, x] = level
                on = level >= 0.5
                code <<= 1
                if on:
                    code |= 1
                    any_on = True
                margin = abs(level - np.float32(0.5))
                if margin < least or np.isnan(margin):  # NaN sticks, as in a numpy min
                    least = margin
                clear = margin >= half_confidence
                if with_noise:
                    sd = noise[y, x] / bit_gains[n, y, x] if divided else noise[y, x]
                    clear = clear and np.float64(margin) * scale_span[n] * np.float64(ref) >= min_snr * sd
                if not clear:
                    unclear += 1
                    mask |= 1 << (bits - 1 - n)
                    if first_unclear < 0:
                        first_unclear = n
            s = stripe_of_code[code]
            settled = is_settled(code, unclear, first_unclear, stripe_of_code, stripe_borders)
            modelled = residual[y, x] <= max_residual or not any_on
            stripe[y, x] = s
            c = np.float32(2) * least
            confidence[y, x] = np.float32(0) if c < 0 else (np.float32(1) if c > 1 else c)
            valid[y, x] = lit[y, x] and s >= 0 and modelled and settled
            unclear_bits[y, x] = mask if lit[y, x] and modelled else 0


#: The lit zero stripe's walk from stripe 1 (`_zero_stripe`) stops where the DC falls below
#: this fraction of the brightest DC of the quarter stripe walked just before: leaving the
#: projector's light or entering a cast shadow divides the DC by (projected + ambient) / ambient
#: within a few pixels (about 3 on the virtual rig: 10 % ambient, a mid-grey pattern), while a
#: smooth albedo changes it far less over a quarter stripe.
ZERO_STRIPE_DROP = 0.5
#: The walk's DC is closed (a running maximum, then minimum) over this share of a quarter
#: stripe along the line: one-sided windows' DC flips from line to line where the albedo
#: curves (a window's DC is its own side's), and a dip of a few lines stopped the walk.
ZERO_STRIPE_GAP = 1 / 3
#: ... and the walk also stops where that DC falls below this fraction of its brightest over
#: the same reach before it: the edge of the light within the blur's few lines, even where a dim
#: surface leaves less than a 2:1 drop to the ambient light behind it (a smooth albedo changes
#: far less over those lines).  Measured on the thesis's pattern (docs/design.md, "The all-zero
#: code"): the zero stripe found 67.6 -> 91.3 % on the 1296x972 checkered plane (5 MP 71.7 ->
#: 95.1 %), within 0.2 points elsewhere or better, and the pixels beyond the light taken as
#: stripe 0 from 0.05-0.10 % of the lit ones to 0.00-0.02 %.
ZERO_STRIPE_EDGE = 2 / 3
#: ... and, a floor only, where the DC falls below this fraction of the adjacent stripe 1's
#: mean (`decode`'s `zero_code_dc`), for the walk and for the runs along the carriers alike:
#: the drop and edge tests above find the light's edge, and a run joins only where the walk
#: reached a share of it; the floor only keeps both off surfaces far darker than the stripe they
#: start from.  At 0.35 for the walk and 0.6 for the runs (before) they stopped wherever the
#: albedo above stripe 1 was a third of stripe 1's, which a smooth albedo reaches within a
#: stripe's height, and at a checker's dark squares: zero stripe found on the 1296x972 steps
#: 88.2 -> 99.9 %, checkered steps 55 -> 100 %, checkered sphere 36 -> 99 % (docs/design.md, "The
#: all-zero code").
ZERO_STRIPE_MIN_DC = 0.15
#: ... and pixels without a stripe join the zero stripe along the carriers (`_zero_stripe`) in
#: runs the walk reached for at least this share of their pixels.
ZERO_STRIPE_SPREAD_SHARE = 0.25


def _zero_stripe(stripe: NDArray[np.integer], dc: NDArray[np.float32], spec: PatternSpec, *,
                 min_dc: float) -> NDArray[np.bool_]:
    """Pixels of the lit all-zero stripe, found next to stripe 1 along the phase direction.

    Stripe 0 carries no carrier, so a single frame cannot tell it from shadow pixel by
    pixel.  Two structural facts can: stripe 0 is the only neighbour of stripe 1 besides
    stripe 2, and on a continuous surface the stripes follow each other monotonically along
    every camera line in the phase direction.  So:

    1. Along each such line, walking from the end of stripe 1 away from stripe 2, the pixels
       without a stripe are stripe 0 for at most 1.2 times stripe 1's own length there, as
       long as their DC (with dips of a few lines closed: `ZERO_STRIPE_GAP`) is at least
       `min_dc` times stripe 1's mean DC, at least `ZERO_STRIPE_DROP` times the brightest DC
       of the quarter stripe walked before them, and at least `ZERO_STRIPE_EDGE` times the
       brightest of the few lines before them.  The walk stops at the first pixel that fails.
    2. Along the carriers, a run of pixels without a stripe whose DC is at least `min_dc`
       times stripe 1's (the nearest lines' where a line has none) joins the zero stripe if
       the walk reached at least `ZERO_STRIPE_SPREAD_SHARE` of it: stripe 0 goes on behind an
       object that hides the stripe 1 below it.

    Measured on the 5 MP virtual rig, thesis pattern, smooth albedo (a walk against stripe 1's
    DC alone at 0.6, before): right stripes on the sphere 88.1 -> 90.2 %, steps 93.3 -> 94.6 %,
    tilted plane 97.1 -> 98.1 %, with fewer pixels beyond the projector's light taken as
    stripe 0 (docs/design.md, "The all-zero code").

    Parameters
    ----------
    stripe : (H, W) int array
        Stripes decoded from the modulated pixels, -1 where undecided or unmodulated: the
        candidates, with the pixels already decoded as stripe 0.
    dc : (H, W) float array
        Local mean intensity.
    """
    if spec.orientation == "columns":
        return _zero_stripe(stripe.T, dc.T, spec.with_(orientation="rows"), min_dc=min_dc).T
    h = stripe.shape[0]
    rows = np.arange(h)[:, None]
    one, two = stripe == 1, stripe == 2
    if not one.any():
        return np.zeros(stripe.shape, dtype=bool)
    # which way stripe numbers grow along the columns: compare where stripes 1 and 2 lie
    down = not two.any() or np.median(np.nonzero(two)[0]) >= np.median(np.nonzero(one)[0])
    if not down:
        return _zero_stripe(stripe[::-1], dc[::-1], spec, min_dc=min_dc)[::-1]
    top = np.where(one, rows, h).min(axis=0)  # first stripe-1 row of each column
    length = one.sum(axis=0)
    reference = np.where(one, dc, 0).sum(axis=0) / np.maximum(length, 1)  # mean DC of stripe 1
    near = (rows < top) & (rows >= top - 1.2 * length)
    quarter = max(3, int(round(0.25 * np.median(length[length > 0]))))
    # the DC the walk looks at, with the dips of a few lines closed (`ZERO_STRIPE_GAP`), only on
    # the lines the walk can reach (no other line's runs can join the zero stripe)
    columns = np.nonzero(length)[0]
    first = max(0, int(np.floor(np.min(top[columns] - 1.2 * length[columns]))) - quarter)
    last = min(h, int(np.max(top[columns])) + quarter)
    reach = max(2, int(ZERO_STRIPE_GAP * quarter))
    level = np.array(dc, dtype=np.float32)
    level[first:last] = scipy.ndimage.grey_closing(dc[first:last], size=(reach, 1), mode="nearest")

    def brightest_before(values: NDArray[np.float32], lines: int) -> NDArray[np.float32]:
        after = np.concatenate([values[1:], values[-1:]])  # each row's next row, toward stripe 1
        return scipy.ndimage.maximum_filter1d(after, lines, axis=0, origin=-(lines // 2), mode="nearest")

    candidate = stripe <= 0  # undecided, unmodulated, or decoded as stripe 0 already (a border with stripe 1)
    passable = (near & candidate & (level >= min_dc * reference)
                & (level >= ZERO_STRIPE_DROP * brightest_before(dc, quarter))
                & (level >= ZERO_STRIPE_EDGE * brightest_before(level, reach)))
    blocked = np.where(near & ~passable, rows, -1).max(axis=0)  # nearest failing row above stripe 1
    walked = passable & (rows > blocked)
    spread = np.interp(np.arange(stripe.shape[1]), columns, reference[columns])
    along_carriers = np.array([[0, 0, 0], [1, 1, 1], [0, 0, 0]])  # runs within a line
    runs, _ = scipy.ndimage.label(candidate & (level >= min_dc * spread), along_carriers)
    walked_share = np.bincount(runs[walked], minlength=runs.max() + 1) / np.maximum(np.bincount(runs.ravel()), 1)
    joined = walked_share >= ZERO_STRIPE_SPREAD_SHARE
    joined[0] = False
    return walked | joined[runs]


@numba.njit(cache=True, nogil=True)
def _agreeing_rows(stripe: NDArray[np.integer], valid: NDArray[np.bool_], radius: int, min_share: float,
                   rows: NDArray[np.intp], out: NDArray[np.bool_]) -> None:
    """`agrees_with_neighbours` for the given rows.

    Most boxes hold only stripes within one of their pixel's own, so that every valid pixel
    agrees: the box's smallest and largest valid stripe (a column's over the box's rows,
    then over the box's columns) tell, and only the other pixels count their box."""
    h, w = stripe.shape
    low, high = np.empty(w, np.int64), np.empty(w, np.int64)
    box_low, box_high = np.empty(w, np.int64), np.empty(w, np.int64)
    for y in rows:
        top, bottom = max(y - radius, 0), min(y + radius + 1, h)
        low[:], high[:] = np.iinfo(np.int64).max, np.iinfo(np.int64).min
        for yy in range(top, bottom):
            for x in range(w):
                s = np.int64(stripe[yy, x])
                counted = valid[yy, x] & (s >= 0)
                low[x] = min(low[x], s) if counted else low[x]
                high[x] = max(high[x], s) if counted else high[x]
        box_low[:], box_high[:] = low, high
        for shift in range(1, radius + 1):  # the columns `shift` to the right, then to the left
            for x in range(w - shift):
                box_low[x], box_high[x] = min(box_low[x], low[x + shift]), max(box_high[x], high[x + shift])
            for x in range(shift, w):
                box_low[x], box_high[x] = min(box_low[x], low[x - shift]), max(box_high[x], high[x - shift])
        for x in range(w):
            if not valid[y, x]:
                out[y, x] = False
                continue
            own = np.int64(stripe[y, x])
            left, right = max(x - radius, 0), min(x + radius + 1, w)
            if min_share <= 1 and own - 1 <= box_low[x] and box_high[x] <= own + 1:
                out[y, x] = True  # every counted stripe agrees (or none is counted: 0 >= 0)
                continue
            agree = total = 0
            for yy in range(top, bottom):
                for xx in range(left, right):
                    s = np.int64(stripe[yy, xx])
                    if valid[yy, xx] and s >= 0:
                        total += 1
                        agree += abs(s - own) <= 1
            out[y, x] = agree >= min_share * total


def agrees_with_neighbours(stripe: NDArray[np.integer], valid: NDArray[np.bool_], *, radius: int = 3,
                           min_share: float = 0.5) -> NDArray[np.bool_]:
    """Valid pixels whose stripe matches (within one) most valid pixels around them.

    On any surface the stripe index varies slowly across the camera image, except at depth
    edges, where each side still agrees with itself; an isolated decision that disagrees with
    at least `min_share` of the valid pixels (with a stripe >= 0) in its ``(2 radius + 1)**2``
    box is a decoding error (a flipped high bit), and would be a point far off the surface.
    The boxes are counted by a compiled kernel, rows in parallel threads.

    Parameters
    ----------
    stripe : (H, W) int array
    valid : (H, W) bool array
    """
    s = np.ascontiguousarray(stripe)
    if s.dtype.kind not in "iu":
        s = s.astype(np.int64)
    out = np.empty(s.shape, dtype=bool)
    mask = np.ascontiguousarray(valid)
    over_rows(lambda rows: _agreeing_rows(s, mask, radius, float(min_share), rows, out), s.shape[0])
    return out


@numba.njit(cache=True, nogil=True)
def _refine_rows(stripe: NDArray[np.integer], valid: NDArray[np.bool_], levels: NDArray[np.float32],
                 codes: NDArray[np.int64], dy: int, dx: int, rows: NDArray[np.intp], out: NDArray[np.integer]) -> None:
    """`refine_borders` for the given rows; the pixels compared are ``(y -+ dy, x -+ dx)``."""
    h, w = stripe.shape
    bits = levels.shape[0]
    for y in rows:
        for x in range(w):
            out[y, x] = stripe[y, x]
            if not valid[y, x]:
                continue
            yb, xb, ya, xa = y - dy, x - dx, y + dy, x + dx
            if yb < 0 or xb < 0 or ya >= h or xa >= w or not (valid[yb, xb] and valid[ya, xa]):
                continue
            own, before, after = stripe[y, x], stripe[yb, xb], stripe[ya, xa]
            if before < 0 or after < 0 or abs(before - after) != 1 or (own != before and own != after):
                continue
            changed, high = codes[before] ^ codes[after], 0
            while changed > 1:
                changed >>= 1
                high += 1
            bit = min(max(bits - 1 - high, 0), bits - 1)
            level, level_before, level_after = levels[bit, y, x], levels[bit, yb, xb], levels[bit, ya, xa]
            if np.isfinite(level_before) and np.isfinite(level_after):
                out[y, x] = before if abs(level - level_before) <= abs(level - level_after) else after


def refine_borders(stripe: NDArray[np.integer], valid: NDArray[np.bool_], levels: NDArray[np.float32],
                   spec: PatternSpec, *, reach: int) -> NDArray[np.integer]:
    """Re-decide the pixels between two neighbouring stripes at their local midpoint.

    Along the phase direction a pixel `reach` lines before and one `reach` lines after it
    show the two stripes of a border and the level the changing bit has on each side, right
    there; the pixel belongs to the side whose level its own is nearer to.  The frame-wide
    0.5 threshold moves the border by several pixels where the local levels differ from the
    frame's (ambient light, roll-off); this puts it back where the blurred step is half way.

    Parameters
    ----------
    stripe : (H, W) int array
    valid : (H, W) bool array
    levels : (K, H, W) float32 array
        Bit levels (`Decoded.levels`).

    Returns
    -------
    (H, W) array
        The stripes, of `stripe`'s integer dtype (int64 for any other).
    """
    dy, dx = (reach, 0) if spec.orientation == "rows" else (0, reach)
    stripe = np.ascontiguousarray(stripe)
    if stripe.dtype.kind not in "iu":
        stripe = stripe.astype(np.int64)
    out = np.empty_like(stripe)
    mask, bit_levels, codes = np.ascontiguousarray(valid), np.ascontiguousarray(levels), stripe_codes(spec)
    over_rows(lambda rows: _refine_rows(stripe, mask, bit_levels, codes, dy, dx, rows, out), stripe.shape[0])
    return out


@numba.njit(cache=True, nogil=True)
def _output_rows(valid: NDArray[np.bool_], lit: NDArray[np.bool_], centres: NDArray[np.float32], rows: NDArray[np.intp],
                 stripe: NDArray[np.int16], confidence: NDArray[np.float32], proj_map: NDArray[np.float32]) -> None:
    """`decode`'s outputs for the given rows, in place: `stripe` -1 where not `valid`,
    `confidence` 0 where not `lit`, and `proj_map` the stripe's centre line `centres`
    ``(stripes,)`` (NaN for -1)."""
    for y in rows:
        for x in range(valid.shape[1]):
            if not valid[y, x]:
                stripe[y, x] = -1
            s = stripe[y, x]
            proj_map[y, x] = centres[s] if s >= 0 else np.nan
            if not lit[y, x]:
                confidence[y, x] = 0


def _stripe_of_code(spec: PatternSpec) -> NDArray[np.int64]:
    """Stripe index of every ``spec.bits``-bit code, -1 for the codes never projected."""
    return code_to_stripe(np.arange(1 << spec.bits), spec).astype(np.int64)


def decode(demod: Demodulated, spec: PatternSpec, *, min_modulation: float = 0.3,
           min_confidence: float | None = None, min_snr: float | None = None, stripe_borders: bool = True,
           max_residual: float = 0.6, max_misfit: float = 0.25, zero_code_dc: float = ZERO_STRIPE_MIN_DC,
           neighbour_radius: int = 3, border_reach: int = 10, order: OrderCosts | bool = True,
           min_margin: float = 1.0, max_order_misfit: float = 8.0, min_anchored: float = 0.25,
           drop_reversed: bool = True, restore_reversed: bool = True, direction: int | None = None,
           follow_blur: bool = True) -> Decoded:
    """Binarise the envelopes and Gray-decode them into stripes and projector lines.

    Parameters
    ----------
    demod : Demodulated
        From `sliscan.demodulate.demodulate`, camera orientation.
    spec : PatternSpec
        The projected pattern.
    min_modulation : float
        A pixel is lit when its strongest carrier reaches this fraction of the way from the
        carrier's off level to its on level (see `_lit`).
    min_confidence : float, optional
        A bit is clear when its level is at least half this far from 0.5 ...
    min_snr : float, optional
        ... and at least this many noise standard deviations (`Demodulated.noise`) from its
        threshold.  Defaults: 0.1 and 3; with a phase channel (`PatternSpec.phase_carriers`)
        0.05 and 1.5, since `sliscan.fringe.refine` then drops or repairs the pixels whose
        stripe disagrees with their fringe phase (measured on the virtual rig's sphere: 85 %
        -> 92 % of the lit pixels decoded, 86 % kept after the phase's checks, against 83 %).  A pixel is valid when every bit is clear, or, with `stripe_borders`,
        when only one is not and flipping it gives the neighbouring stripe (a pixel on a
        stripe border, where either answer is off by at most one stripe).
    max_residual : float
        Pixels whose window the carrier model explains worse than this are invalid (except
        those with every bit off: the residual is relative to the AC energy, which the lit
        all-zero stripe does not have).
    max_misfit : float
        Pixels whose own neighbourhood the window's model mispredicts by more than this
        fraction of the DC are invalid (see `Demodulated.misfit`).
    zero_code_dc : float
        For patterns that project the all-zero code: the smallest DC, relative to the
        adjacent stripe 1, of a pixel taken as the lit zero stripe by the walk from stripe 1
        (a floor, `ZERO_STRIPE_MIN_DC`: the walk stops where the DC drops sharply; see
        `_zero_stripe`).
    border_reach : int
        Lines before and after a pixel that `refine_borders` compares it with; 0 skips it.
    neighbour_radius : int
        Drop valid pixels that disagree with most valid pixels within this many pixels
        (`agrees_with_neighbours`); 0 keeps them.
    order : OrderCosts or bool
        Decide the stripes along the phase direction by the order they come in
        (`sliscan.stripe_order.decode_by_order`) instead of pixel by pixel: True (default) or
        an `OrderCosts` (True: the default costs), False: per pixel.  Also for the thesis's
        pattern, whose lit zero stripe looks like shadow (the order then decides the other
        stripes; `_zero_stripe` adds the zero one): measured on 30 of its captures (1296x972
        seeds 0-3 and 5 MP seed 0; docs/design.md, the order of the stripes) right
        stripes +1.2 points on average (+2.2 to +3.5 on the spheres), for gross outliers
        0.015 -> 0.024 % on average (at most 0.20 %, a frame's edge on the 5 MP checkered steps).
    min_margin, max_order_misfit : float
        Decided by order, a pixel is valid when the best labelling with another label at the
        pixel costs at least `min_margin` nats more, and its own evidence against its label
        is at most `max_order_misfit` nats (about one bit fully wrong and another half wrong;
        `sliscan.stripe_order.emission`).  The per-pixel tests above (bit clearness,
        `stripe_borders`) then do not apply; the others do.
    min_anchored : float
        Decided by order, a pixel is valid only if at least this share of its run (the
        pixels of its stripe in a row along the phase direction) got the same stripe from the
        per-pixel decisions (`sliscan.stripe_order.anchored_runs`): the order fills in where
        the stripe's own pixels vouch for it, it does not invent a stripe (a blurred capture:
        0.24 % of the frame decoded with 0.25, 2.4 % with 0.1, mostly wrong, none per pixel).
        In the pass that follows the blur, a pixel whose one unclear bit is lost around it
        vouches for both stripes it may be, and the order decides without that bit
        (`lost_bit_alternates`, `LOST_BIT_SHARE`).
    drop_reversed : bool
        Decided by order, drop the runs that come in reverse order along the phase direction
        (`sliscan.stripe_order.reversed_runs`): a bit lost where every stripe has it on, read
        as its mirror image all the way down a column (a projector focused on near objects
        before a far wall: 3-4 % of the lit pixels more than three stripes off; under 0.01 %
        with those runs dropped).
    restore_reversed : bool
        With `drop_reversed`, give such runs the stripes they read with the lost bit set again
        where exactly one bit turns their chain forward from the run before it, instead of
        dropping them (the same wall: 5-11 points more of the lit pixels on the right stripe).
    direction : {1, -1, 0} or None
        Decided by order, whether the stripe numbers grow (+1) or fall (-1) with the camera
        coordinate along the phase direction: the rig's (`sliscan.stripe_order.rig_direction`,
        as `Scanner` passes it); None reads it from the per-pixel decisions
        (`sliscan.stripe_order.stripe_direction`), which a lost bit can make undecided (0: the
        previous stripe as cheap as the next, nothing dropped as reversed) where it reads a large
        part of the frame in reverse.
    follow_blur : bool
        Where fewer than `FOLLOW_BLUR_BELOW` of the lit pixels decode, decode again with each
        bit carrier's envelope divided by its gain there relative to the frame's
        (`blur_gains`): a projector focused at one depth blurs the rest of the scene, and its
        highest carriers lose most of their modulation there, below the levels learned from
        the whole frame.  Unless `min_snr` is given or `order` is False, that pass judges
        the bits at `FOLLOW_BLUR_MIN_SNR` noise deviations (a frame that decodes poorly is
        blurred or noisy: the decisions by order guard the bits), if it then decodes at least
        `RELAXED_MIN_DECODED` of the lit pixels and `RELAXED_MIN_GAIN` of them more than at
        the default.

    Returns
    -------
    Decoded
    """
    options = dict(min_modulation=min_modulation, min_confidence=min_confidence, min_snr=min_snr,
                   stripe_borders=stripe_borders, max_residual=max_residual, max_misfit=max_misfit,
                   zero_code_dc=zero_code_dc, neighbour_radius=neighbour_radius, border_reach=border_reach,
                   order=order, min_margin=min_margin, max_order_misfit=max_order_misfit, min_anchored=min_anchored,
                   drop_reversed=drop_reversed, restore_reversed=restore_reversed, direction=direction)
    first = _decode_once(demod, spec, **options)
    lit = int(first.lit.sum())
    if not follow_blur or spec.bits < 2 or not lit or first.valid.sum() >= FOLLOW_BLUR_BELOW * lit:
        return first
    gains = blur_gains(first.levels, first.lit, spec.carriers, scale_px=BLUR_GAIN_SCALE * demod.dc.shape[1])
    amplitude = demod.amplitude.copy()
    amplitude[: spec.bits] /= gains
    # each envelope so divided carries its noise with it: every bit is judged by its own light
    blurred = dataclasses.replace(demod, amplitude=amplitude)
    # the frame's levels: the same for both thresholds of the bits (the lit test keeps its own)
    frame = FrameLevels.of(blurred, spec, min_modulation=min_modulation,
                           min_snr=_default_min_snr(spec) if min_snr is None else min_snr, bit_gains=gains)
    followed = functools.partial(_decode_once, blurred, spec, bit_gains=gains, lost_bit_share=LOST_BIT_SHARE,
                                 frame=frame)
    strict = followed(**options)
    if min_snr is not None or order is False or _default_min_snr(spec) <= FOLLOW_BLUR_MIN_SNR:
        return strict  # a threshold asked for, no order to guard the bits, or nothing to relax
    relaxed = followed(bit_snr=FOLLOW_BLUR_MIN_SNR, **options)
    lit_pixels = int(relaxed.lit.sum())
    wanted = max(RELAXED_MIN_DECODED * lit_pixels, strict.valid.sum() + RELAXED_MIN_GAIN * lit_pixels)
    return relaxed if relaxed.valid.sum() >= wanted else strict


def _default_min_snr(spec: PatternSpec) -> float:
    """`decode`'s default `min_snr`: 1.5 with a phase channel, else 3."""
    return 1.5 if spec.phase_carriers else 3.0


#: `decode`'s `follow_blur` decodes a frame again with the bits' gains that follow the blur
#: where fewer than this share of its lit pixels decode.  A frame in focus decodes 87-98 % of
#: them on the virtual rig's scenes (the lowest on the objects), a projector aperture of 16 mm
#: focused on the working point 80-83 % of the sphere's.  Decoding every frame twice changed the
#: frames in focus by -0.2 to +0.2 points of completeness (1296x972 sphere and objects): the
#: share only spares them the second pass's time (a 5 MP decode: 1.3 s).
FOLLOW_BLUR_BELOW = 0.85
#: ... and in that pass an undecided pixel whose one unclear bit leaves at least this share of
#: the lit pixels around it undecided (every other bit under half of it) vouches for both
#: stripes it may be, and the decisions by order leave that bit out there
#: (`lost_bit_alternates`): the 960x720 rig blurred by 2 px, sliscan's pattern 23.8 -> 53.0 %
#: complete (docs/design.md, "A bit lost over a whole region").  Over 1: none.
LOST_BIT_SHARE = 0.5
#: ... and that pass judges a bit clear at this many noise deviations from its threshold instead
#: of `decode`'s default `min_snr` of 3 (unless one is given; the lit test keeps it: at 1.5 it took
#: shadows for lit): a frame that decodes poorly is noisy or blurred, and the decisions by order
#: (their margin, their misfit, the runs' anchors) then guard the bits the noise test alone would
#: leave undecided ...
FOLLOW_BLUR_MIN_SNR = 1.5
#: ... if that decodes at least this share of the lit pixels (two bits lost to blur: their
#: decisions at 1.5 deviations are chance, and the few runs they anchor are a few percent gross
#: outliers) ...
RELAXED_MIN_DECODED = 1 / 3
#: ... and this share of them more than the default does; else the pass keeps the default.  A
#: frame that the noise held back gains tens of points (960x720 sphere, 600 e- full well: 15 ->
#: 51 %); one whose undecided pixels the demodulator's model misfits gains a few, a quarter to
#: a half of them gross outliers (a plane turned 60 degrees about the vertical, the thesis's pattern:
#: +2.6 points, gross outliers 5.6 -> 7.7 %; under half the projector's white as ambient light
#: +1.6 points, 0.35 -> 0.89 %).
RELAXED_MIN_GAIN = 0.05
#: `blur_gains` fits a blur over neighbourhoods of this share of the frame's width (a
#: Gaussian's sigma).  Measured with the prototype (every frame decoded twice; docs/design.md,
#: "Bit levels that follow the blur") on the 960x720 and 1296x972 spheres: under a 16 mm
#: projector aperture 0.03 recovered 1-2 points more than 0.06, but lost 0.3-0.7 points where
#: the blur barely varies (an 8 mm aperture), 0.06 within 0.1 point of nothing.
BLUR_GAIN_SCALE = 0.05
#: ... from the carriers whose clear "on" pixels make up at least this share of the
#: neighbourhood (by the Gaussian's weights) ...
BLUR_GAIN_SUPPORT = 0.02
#: ... and divides no envelope by less than this gain.
BLUR_GAIN_FLOOR = 0.25


def blur_gains(levels: NDArray[np.float32], lit: NDArray[np.bool_], carriers: tuple[float, ...], *,
               scale_px: float) -> NDArray[np.float32]:
    """Each bit carrier's gain at every pixel relative to the frame's, as a Gaussian blur's
    transfer fitted to the bits' clear "on" levels around it: ``exp(-b (f_n^2 - f_0^2))``.

    A blur of sigma `s` passes a carrier of frequency `f` as ``exp(-2 pi^2 s^2 f^2)``.  The
    levels (`Decoded.levels`: 1 = the carrier's on level learned from the whole frame) of the
    clearly-on bits are averaged per carrier over a Gaussian neighbourhood of sigma `scale_px`,
    and ``log mean = a - b f^2`` is fitted by weighted least squares across the carriers with
    enough support (`BLUR_GAIN_SUPPORT`; `a`, the light's gain, is common to all).  So the
    highest carrier's gain comes from the lower ones where its own bit is unclear.  Gains are
    relative to the lowest carrier and at most 1: a neighbourhood blurrier than the frame
    boosts its higher carriers, a sharper one is left as it is; none below `BLUR_GAIN_FLOOR`.
    The averages are taken on a grid a quarter of `scale_px` apart and interpolated back.

    Parameters
    ----------
    levels : (K, H, W) float32 array
        Bit levels, NaN allowed (`Decoded.levels`).
    lit : (H, W) bool array
        Pixels with carriers (`Decoded.lit`).
    carriers : tuple of float
        The bits' carrier frequencies, in any one unit (`PatternSpec.carriers`).
    scale_px : float
        The neighbourhood's sigma, camera pixels.

    Returns
    -------
    (K, H, W) float32 array in [`BLUR_GAIN_FLOOR`, 1]
    """
    height, width = lit.shape
    step = max(1, int(scale_px // 4))
    rows, cols = -(-height // step), -(-width // step)

    def smoothed(sums: NDArray[np.float64]) -> NDArray[np.float64]:
        """Sums on the `step` grid smoothed by the neighbourhood's Gaussian."""
        return scipy.ndimage.gaussian_filter(sums, scale_px / step, mode="constant")

    def coarse(a: NDArray[np.float32]) -> NDArray[np.float64]:
        """`smoothed` block sums of `a` ``(H, W)``."""
        padded = np.zeros((rows * step, cols * step), np.float32)
        padded[:height, :width] = a
        return smoothed(padded.reshape(rows, step, cols, step).sum(axis=(1, 3), dtype=np.float64))

    f2 = (np.asarray(carriers, np.float64) / max(carriers)) ** 2
    block_rows = np.minimum(step, height - step * np.arange(rows))  # the frame's pixels in each block
    block_cols = np.minimum(step, width - step * np.arange(cols))
    area = smoothed(np.outer(block_rows, block_cols).astype(np.float64))
    sw = swx = swy = swxx = swxy = np.zeros((rows, cols))
    for n, x in enumerate(f2):
        on = lit & (levels[n] > 0.5)  # NaN is not on
        support = coarse(on.astype(np.float32))
        mean = coarse(np.where(on, levels[n], 0).astype(np.float32)) / np.maximum(support, 1e-6)
        w = np.where(support >= BLUR_GAIN_SUPPORT * area, support, 0.0)
        y = np.log(np.clip(mean, 0.05, 5.0))
        sw, swx, swy, swxx, swxy = sw + w, swx + w * x, swy + w * y, swxx + w * x * x, swxy + w * x * y
    det = sw * swxx - swx * swx
    fitted = det > 1e-9 * sw * sw  # two carriers or more with support
    slope = np.where(fitted, (sw * swxy - swx * swy) / np.where(fitted, det, 1.0), 0.0).astype(np.float32)
    slope = cv2.resize(slope, (cols * step, rows * step), interpolation=cv2.INTER_LINEAR)[:height, :width]
    gains = np.exp(slope[None] * (f2 - f2.min()).astype(np.float32)[:, None, None])
    return np.clip(gains, BLUR_GAIN_FLOOR, 1.0).astype(np.float32)


def lost_bit_alternates(levels: NDArray[np.float32], unclear: NDArray[np.uint16], lit: NDArray[np.bool_],
                        stripe_of_code: NDArray[np.int64], *, share: float, scale_px: float,
                        ) -> tuple[NDArray[np.int16], NDArray[np.bool_]]:
    """The other stripe a pixel may be where its one unclear bit is lost around it (-1
    elsewhere), and where each bit is so lost.

    A bit is lost around a pixel when it is unclear on at least `share` of the lit pixels in a
    Gaussian neighbourhood of sigma `scale_px` (the frame blurred beyond its carrier: a 2 px blur
    on both sides of a 960x720 rig leaves the highest carrier a tenth of its modulation), and
    every other bit on under half that share (two bits lost leave the order too little to go on:
    a 640x480 rig blurred by 2 px decoded 10 % of its lit pixels that way, a quarter of them
    gross outliers).  Such a pixel cannot tell its stripe from the one with that bit flipped,
    but the order down the column can.  A pixel with no clear bit on is left out: it may be a
    shadow a neighbour's light leaks into (the thesis's pattern projects the all-zero code).

    Parameters
    ----------
    levels : (K, H, W) float32 array
        Bit levels (`Decoded.levels`), read as on at 0.5 and above.
    unclear : (H, W) uint16 array
        Each pixel's unclear bits as a mask of its code's bits (0: none, or not considered).
    lit : (H, W) bool array
    stripe_of_code : (2**K,) int array
        Stripe of every code, -1 for those never projected.
    share, scale_px : float

    Returns
    -------
    alternates : (H, W) int16 array
    lost : (K, H, W) bool array
        Where bit `k` is lost (the decisions by order then leave its level out).
    """
    bits = levels.shape[0]
    height, width = lit.shape
    step = max(1, int(scale_px // 4))
    small = (max(1, width // step), max(1, height // step))

    def around(mask: NDArray[np.bool_]) -> NDArray[np.float32]:
        """The neighbourhood's mean of `mask`, on a grid `step` apart and back."""
        coarse = cv2.resize(mask.astype(np.float32), small, interpolation=cv2.INTER_AREA)
        return cv2.resize(cv2.GaussianBlur(coarse, (0, 0), scale_px / step), (width, height),
                          interpolation=cv2.INTER_LINEAR)

    lit_around = np.maximum(around(lit), np.float32(1e-6))
    masks = [np.uint16(1 << (bits - 1 - n)) for n in range(bits)]
    shares = [around(lit & ((unclear & bit) != 0)) / lit_around for bit in masks]
    lost = np.stack([(shares[n] >= share) & np.all([shares[m] < share / 2 for m in range(bits) if m != n], axis=0)
                     for n in range(bits)])
    vouch = np.zeros(lit.shape, bool)
    for n, bit in enumerate(masks):
        vouch |= (unclear == bit) & lost[n]  # the pixel's one unclear bit, and lost
    code = bits_to_code(levels >= 0.5)
    vouch &= (code & ~unclear.astype(np.int64)) != 0  # one clear bit on at least: light leaking into a shadow has none
    return np.where(vouch, stripe_of_code[code ^ unclear], -1).astype(np.int16), lost


def _decode_once(demod: Demodulated, spec: PatternSpec, *, min_modulation: float, min_confidence: float | None,
                 min_snr: float | None, stripe_borders: bool, max_residual: float, max_misfit: float,
                 zero_code_dc: float, neighbour_radius: int, border_reach: int, order: OrderCosts | bool,
                 min_margin: float, max_order_misfit: float, min_anchored: float, drop_reversed: bool,
                 restore_reversed: bool, direction: int | None, bit_gains: NDArray[np.float32] | None = None,
                 lost_bit_share: float = 2.0, bit_snr: float | None = None,
                 frame: FrameLevels | None = None) -> Decoded:
    """`decode`'s one pass over the envelopes as they are (see `decode` for the parameters;
    `bit_gains` ``(K, H, W)``: what the bits' envelopes were divided by, so bit `n`'s noise is
    ``demod.noise / bit_gains[n]``; `bit_snr`: the bits' `min_snr` where it is not the lit
    test's; `frame`: the frame's levels if already read, with the same `min_modulation`,
    `min_snr` and `bit_gains`)."""
    bits = spec.bits
    phase_channel = bool(spec.phase_carriers)
    min_confidence = (0.05 if phase_channel else 0.1) if min_confidence is None else min_confidence
    min_snr = _default_min_snr(spec) if min_snr is None else min_snr
    if frame is None:
        frame = FrameLevels.of(demod, spec, min_modulation=min_modulation, min_snr=min_snr, bit_gains=bit_gains)
    dc, reference, lit, scale = frame.dc, frame.reference, frame.lit, frame.bits
    levels = np.empty((bits, *dc.shape), dtype=np.float32)
    stripe = np.empty(dc.shape, dtype=np.int16)
    confidence = np.empty(dc.shape, dtype=np.float32)
    valid = np.empty(dc.shape, dtype=bool)
    unclear = np.empty(dc.shape, dtype=np.uint16)
    noise = np.zeros((0, 0), np.float32) if demod.noise is None else demod.noise
    gains = np.zeros((0, 0, 0), np.float32) if bit_gains is None else bit_gains
    stripe_of_code = _stripe_of_code(spec)
    over_rows(lambda rows: _decode_rows(
        demod.amplitude, reference, scale.off, scale.span, stripe_of_code, lit, demod.residual, noise, gains,
        np.float32(0.5 * min_confidence), np.float32(min_snr if bit_snr is None else bit_snr),
        np.float32(max_residual), stripe_borders, rows, levels, stripe, confidence, valid, unclear), dc.shape[0])
    if order is not False:
        costs = order if isinstance(order, OrderCosts) else OrderCosts()
        noise = np.zeros(dc.shape, np.float32) if demod.noise is None else demod.noise / reference
        anchors = np.where(valid, stripe, np.int16(-1))
        alternate = None
        if lost_bit_share <= 1:
            # a pixel whose one unclear bit is lost around it vouches for both stripes it may be;
            # the decided pixels neither vouch so nor count toward a bit's loss
            alternate, lost = lost_bit_alternates(levels, np.where(valid, 0, unclear).astype(np.uint16), lit,
                                                  stripe_of_code, share=lost_bit_share,
                                                  scale_px=BLUR_GAIN_SCALE * dc.shape[1])
            anchors = np.where(alternate >= 0, stripe, anchors)
            if bit_gains is not None and lost.any():
                bit_gains = np.where(lost, np.float32(0), bit_gains)  # a lost bit's level is no evidence
        if direction is None:
            direction = stripe_direction(stripe, valid, spec)
        stripe, margin, misfit = decode_by_order(levels, noise, scale.span, lit, spec, direction, costs,
                                                 bit_gains=bit_gains)
        valid = (stripe >= 0) & (margin >= min_margin) & (misfit <= max_order_misfit)
        valid &= (demod.residual <= max_residual) | ~lit
        valid &= anchored_runs(stripe, anchors, spec, min_share=min_anchored, alternates=alternate)
        if drop_reversed:
            reverse, restored = reversed_runs(np.where(valid, stripe, np.int16(-1)), spec, direction)
            if restore_reversed:
                stripe = np.where(restored >= 0, restored, stripe)
                reverse &= restored < 0
            valid &= ~reverse
    if spec.pilot is None and not spec.skip_zero_code:
        # Modulated pixels have at least one bit on; add the lit all-zero stripe.
        zero = _zero_stripe(np.where(valid, stripe, -1), demod.dc, spec, min_dc=zero_code_dc)
        lit, valid, stripe = lit | zero, valid | zero, np.where(zero, 0, stripe)
    if demod.misfit is not None:
        valid &= demod.misfit <= max_misfit
    if border_reach:
        stripe = refine_borders(stripe, valid, levels, spec, reach=border_reach)
    if neighbour_radius:
        valid = agrees_with_neighbours(stripe, valid, radius=neighbour_radius)
    centres = stripe_center(np.arange(spec.stripes), spec).astype(np.float32)
    proj_map = np.empty(dc.shape, dtype=np.float32)
    over_rows(lambda rows: _output_rows(valid, lit, centres, rows, stripe, confidence, proj_map), dc.shape[0])
    return Decoded(stripe=stripe, proj_map=proj_map, valid=valid, lit=lit, confidence=confidence, levels=levels)
