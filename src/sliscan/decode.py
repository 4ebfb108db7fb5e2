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

The all-zero code projects no carrier at all: in one frame it looks like shadow.  Patterns with
``skip_zero_code`` never project it, so unmodulated pixels are shadow.  Otherwise (the
thesis's pattern) the lit zero stripe is found from the code's structure: it is the
neighbour of stripe 1 on the side away from stripe 2 (see `_zero_stripe`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from sliscan.demodulate import Demodulated, default_workers
from sliscan.patterns import bits_to_code, code_to_stripe, stripe_center, stripe_codes
from sliscan.types import PatternSpec


@dataclass(frozen=True, eq=False)
class Decoded:
    """Per-pixel decoding of one capture.

    Attributes
    ----------
    stripe : (H, W) int16 array
        Stripe index, -1 where invalid.
    proj_map : (H, W) float32 array
        Projector line at the stripe centre (projector pixels), NaN where invalid.
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


def two_means(values: NDArray[np.floating], *, iterations: int = 20) -> tuple[float, float]:
    """Centres of the low and high cluster of 1-D samples (Lloyd's algorithm, k = 2, with
    medians for centres: a carrier's ratio has a long upper tail where gamma sharpens the
    pattern's peaks, and a mean would follow it).

    >>> [round(m, 3) for m in two_means(np.array([0.0, 0.1, 0.0, 0.9, 1.0, 1.1]))]
    [0.0, 1.0]
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = float(np.percentile(v, 5)), float(np.percentile(v, 95))
    v = np.clip(v, float(np.percentile(v, 0.5)), float(np.percentile(v, 99.5)))  # a few wild values cannot own a cluster
    v.sort()  # each cluster is then a slice, and its median a middle element: no partition per iteration
    for _ in range(iterations):
        split = int(np.searchsorted(v, 0.5 * (lo + hi), side="left"))
        if split == 0 or split == v.size:
            break
        new = _sorted_median(v[:split]), _sorted_median(v[split:])
        if new == (lo, hi):
            break
        lo, hi = new
    return lo, hi


def _sorted_median(a: NDArray[np.float64]) -> float:
    """Median of a sorted non-empty 1-D array (equal to ``np.median``)."""
    middle = a.size // 2
    return float(a[middle]) if a.size % 2 else float((a[middle - 1] + a[middle]) / 2)


def _sample(mask: NDArray[np.bool_], limit: int = 200_000) -> NDArray[np.bool_]:
    """Thin a mask to at most about `limit` pixels on a regular grid (for level statistics)."""
    step = max(1, int(np.sqrt(mask.sum() / limit)))
    thin = np.zeros_like(mask)
    thin[::step, ::step] = mask[::step, ::step]
    return thin


def _dc_floor(dc: NDArray[np.float32]) -> NDArray[np.float32]:
    """The DC floored at 2 % of the frame's bright level, so black pixels (outside the
    projector, no ambient light) do not look modulated by dividing noise by 0."""
    return np.maximum(dc, 0.02 * float(np.percentile(dc[::4, ::4], 99)) + 1e-6)


def _levels(ratio: NDArray[np.floating], sample: NDArray[np.bool_]) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Per-carrier ratios mapped to 0 (off cluster) .. 1 (on cluster) of `sample`; also the spans."""
    levels = np.empty(ratio.shape, dtype=np.float32)
    spans = np.empty(ratio.shape[0])
    for n in range(ratio.shape[0]):
        off, on = two_means(ratio[n][sample])
        spans[n] = max(on - off, 1e-6)
        levels[n] = (ratio[n] - off) / spans[n]
    return levels, spans


def _lit(demod: Demodulated, spec: PatternSpec, dc: NDArray[np.float32], min_modulation: float,
         min_snr: float) -> NDArray[np.bool_]:
    """Pixels whose carriers stand clear of the noise.

    Each carrier's envelope over the DC is put on its own 0 (off) .. 1 (on) scale over the
    whole frame, so a code whose only bit rides on the most attenuated carrier counts as
    much as any other.  A pixel is lit when its strongest carrier (the pilot, if any) reaches
    `min_modulation` on that scale and stands `2 * min_snr` noise deviations above zero.
    """
    carriers = [spec.bits] if spec.pilot is not None else list(range(spec.bits))
    ratio = demod.amplitude[carriers] / dc[None]
    levels, _ = _levels(ratio, _sample(np.isfinite(ratio[0])))
    lit = levels.max(axis=0) >= min_modulation
    if demod.noise is not None:
        lit &= demod.amplitude[carriers].max(axis=0) >= 2 * min_snr * demod.noise
    return lit


def _zero_stripe(stripe: NDArray[np.int64], unmodulated: NDArray[np.bool_], dc: NDArray[np.float32], spec: PatternSpec,
                 *, min_dc: float) -> NDArray[np.bool_]:
    """Pixels of the lit all-zero stripe, found next to stripe 1 along the phase direction.

    Stripe 0 carries no carrier, so a single frame cannot tell it from shadow pixel by
    pixel.  Two structural facts can: stripe 0 is the only neighbour of stripe 1 besides
    stripe 2, and on a continuous surface the stripes follow each other monotonically along
    every camera line in the phase direction.  So along each such line, walking from the end
    of stripe 1 away from stripe 2, the unmodulated pixels are stripe 0 for at most about
    stripe 1's own length there, as long as their DC stays at least `min_dc` times stripe 1's
    (the same surface, lit).  The walk stops at the first pixel that fails.

    Parameters
    ----------
    stripe : (H, W) int array
        Stripes decoded from the modulated pixels, -1 where undecided or unmodulated.
    unmodulated : (H, W) bool array
        Pixels without a carrier: candidates.
    dc : (H, W) float array
        Local mean intensity.
    """
    if spec.orientation == "columns":
        return _zero_stripe(stripe.T, unmodulated.T, dc.T, spec.with_(orientation="rows"), min_dc=min_dc).T
    h = stripe.shape[0]
    rows = np.arange(h)[:, None]
    one, two = stripe == 1, stripe == 2
    if not one.any():
        return np.zeros_like(unmodulated)
    # which way stripe numbers grow along the columns: compare where stripes 1 and 2 lie
    down = not two.any() or np.median(np.nonzero(two)[0]) >= np.median(np.nonzero(one)[0])
    if not down:
        return _zero_stripe(stripe[::-1], unmodulated[::-1], dc[::-1], spec, min_dc=min_dc)[::-1]
    top = np.where(one, rows, h).min(axis=0)  # first stripe-1 row of each column
    length = one.sum(axis=0)
    reference = np.where(one, dc, 0).sum(axis=0) / np.maximum(length, 1)  # mean DC of stripe 1
    near = (rows < top) & (rows >= top - 1.2 * length)
    # undecided or already-zero pixels (a blurred border with stripe 1) do not stop the walk
    passable = near & (unmodulated | (stripe <= 0)) & (dc >= min_dc * reference)
    blocked = np.where(near & ~passable, rows, -1).max(axis=0)  # nearest failing row above stripe 1
    return passable & unmodulated & (rows > blocked)


@numba.njit(cache=True, nogil=True)
def _neighbour_agreement(stripe: NDArray[np.int32], radius: int, rows: NDArray[np.intp], agree: NDArray[np.int32],
                         total: NDArray[np.int32]) -> None:
    """For the given rows: valid pixels (stripe >= 0) in each pixel's ``(2 radius + 1)**2`` box
    (`total`), and how many of them are within one stripe of the pixel's own (`agree`)."""
    h, w = stripe.shape
    for y in rows:
        for x in range(w):
            own, n_agree, n_total = stripe[y, x], 0, 0
            for yy in range(max(y - radius, 0), min(y + radius + 1, h)):
                for xx in range(max(x - radius, 0), min(x + radius + 1, w)):
                    other = stripe[yy, xx]
                    if other >= 0:
                        n_total += 1
                        n_agree += abs(other - own) <= 1
            agree[y, x], total[y, x] = n_agree, n_total


def agrees_with_neighbours(stripe: NDArray[np.integer], valid: NDArray[np.bool_], *, radius: int = 3,
                           min_share: float = 0.5) -> NDArray[np.bool_]:
    """Valid pixels whose stripe matches (within one) most valid pixels around them.

    On any surface the stripe index varies slowly across the camera image, except at depth
    edges, where each side still agrees with itself; an isolated decision that disagrees with
    at least `min_share` of the valid pixels in its ``(2 radius + 1)**2`` box is a decoding
    error (a flipped high bit), and would be a point far off the surface.  The boxes are
    counted by a compiled kernel, rows in parallel threads.

    Parameters
    ----------
    stripe : (H, W) int array
    valid : (H, W) bool array
    """
    s = np.where(valid, stripe, -10).astype(np.int32)
    agree, total = np.empty(s.shape, dtype=np.int32), np.empty(s.shape, dtype=np.int32)
    workers = default_workers()
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(lambda rows: _neighbour_agreement(s, radius, rows, agree, total),
                      np.array_split(np.arange(s.shape[0]), 4 * workers)))
    return valid & (agree >= min_share * total)


def _shift(a: NDArray, offset: int, axis: int, fill: object) -> NDArray:
    """`a` moved by `offset` along `axis` (out[i] = a[i + offset]), `fill` where it runs out."""
    out = np.full_like(a, fill)
    src = [slice(None)] * a.ndim
    dst = [slice(None)] * a.ndim
    n = a.shape[axis]
    if offset >= 0:
        src[axis], dst[axis] = slice(offset, n), slice(0, n - offset)
    else:
        src[axis], dst[axis] = slice(0, n + offset), slice(-offset, n)
    out[tuple(dst)] = a[tuple(src)]
    return out


def refine_borders(stripe: NDArray[np.integer], valid: NDArray[np.bool_], levels: NDArray[np.float32],
                   spec: PatternSpec, *, reach: int) -> NDArray[np.int64]:
    """Re-decide the pixels between two neighbouring stripes at their local midpoint.

    Along the phase direction a pixel `reach` lines before and one `reach` lines after it
    show the two stripes of a border and the level the changing bit has on each side, right
    there; the pixel belongs to the side whose level its own is nearer to.  The frame-wide
    0.5 threshold moves the border by several pixels where the local levels differ from the
    frame's (ambient light, roll-off); this puts it back where the blurred step is half way.
    """
    axis = 0 if spec.orientation == "rows" else 1
    s = np.where(valid, stripe, -10).astype(np.int64)
    before, after = _shift(s, -reach, axis, -10), _shift(s, reach, axis, -10)
    border = valid & (before >= 0) & (after >= 0) & (np.abs(before - after) == 1) & ((s == before) | (s == after))
    if not border.any():
        return stripe.astype(np.int64)
    codes = stripe_codes(spec)
    changed = codes[np.clip(before, 0, None)] ^ codes[np.clip(after, 0, None)]
    bit = spec.bits - 1 - np.floor(np.log2(np.maximum(changed, 1))).astype(np.int64)
    bit = np.clip(bit, 0, spec.bits - 1)
    own = np.take_along_axis(levels, bit[None], axis=0)[0]
    level_before = np.take_along_axis(_shift(levels, -reach, axis + 1, np.nan), bit[None], axis=0)[0]
    level_after = np.take_along_axis(_shift(levels, reach, axis + 1, np.nan), bit[None], axis=0)[0]
    nearer_before = np.abs(own - level_before) <= np.abs(own - level_after)
    decided = border & np.isfinite(level_before) & np.isfinite(level_after)
    return np.where(decided, np.where(nearer_before, before, after), stripe).astype(np.int64)


def _flip_is_adjacent(code: NDArray[np.int64], stripe: NDArray[np.int64], unclear: NDArray[np.bool_],
                      spec: PatternSpec) -> NDArray[np.bool_]:
    """True where exactly one bit is unclear and flipping it gives an adjacent stripe.

    Such a pixel sits on the border of two neighbouring stripes (Gray code neighbours differ
    in one bit), so either decision is off by at most one stripe: keep it.  A single unclear
    bit whose flip jumps further is a real ambiguity: drop the pixel.
    """
    single = unclear.sum(axis=0) == 1
    which = np.argmax(unclear, axis=0)
    flipped = code ^ (1 << (spec.bits - 1 - which))
    other = code_to_stripe(flipped, spec)
    return single & (other >= 0) & (np.abs(other - stripe) == 1)


def decode(demod: Demodulated, spec: PatternSpec, *, min_modulation: float = 0.3,
           min_confidence: float = 0.1, min_snr: float = 3.0, stripe_borders: bool = True, max_residual: float = 0.6,
           max_misfit: float = 0.25, zero_code_dc: float = 0.6, neighbour_radius: int = 3,
           border_reach: int = 10) -> Decoded:
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
    min_confidence : float
        A bit is clear when its level is at least half this far from 0.5 ...
    min_snr : float
        ... and at least this many noise standard deviations (`Demodulated.noise`) from its
        threshold.  A pixel is valid when every bit is clear, or, with `stripe_borders`,
        when only one is not and flipping it gives the neighbouring stripe (a pixel on a
        stripe border, where either answer is off by at most one stripe).
    max_residual : float
        Pixels whose window the carrier model explains worse than this are invalid.
    max_misfit : float
        Pixels whose own neighbourhood the window's model mispredicts by more than this
        fraction of the DC are invalid (see `Demodulated.misfit`).
    zero_code_dc : float
        For patterns that project the all-zero code: the smallest DC, relative to the
        adjacent stripe 1, of a pixel taken as the lit zero stripe (see `_zero_stripe`).
    border_reach : int
        Lines before and after a pixel that `refine_borders` compares it with; 0 skips it.
    neighbour_radius : int
        Drop valid pixels that disagree with most valid pixels within this many pixels
        (`agrees_with_neighbours`); 0 keeps them.

    Returns
    -------
    Decoded
    """
    bits = spec.bits
    dc = _dc_floor(demod.dc)
    reference = demod.amplitude[bits] if spec.pilot is not None else dc
    ratio = demod.amplitude[:bits] / np.maximum(reference, 1e-6)[None]
    lit = _lit(demod, spec, dc, min_modulation, min_snr)
    levels, spans = _levels(ratio, _sample(lit))
    on_bits = levels >= 0.5
    code = bits_to_code(on_bits)
    stripe = code_to_stripe(code, spec)
    margin = np.abs(levels - 0.5)
    confidence = np.clip(2 * margin.min(axis=0), 0, 1).astype(np.float32)
    clear = margin >= 0.5 * min_confidence
    if demod.noise is not None:
        clear &= margin * spans[:, None, None] * np.maximum(reference, 1e-6) >= min_snr * demod.noise
    unclear = (~clear).sum(axis=0)
    # The residual is relative to the AC energy, which the lit all-zero stripe does not have.
    modelled = (demod.residual <= max_residual) | ~on_bits.any(axis=0)
    settled = unclear == 0
    if stripe_borders:
        settled |= _flip_is_adjacent(code, stripe, ~clear, spec)
    valid = lit & (stripe >= 0) & modelled & settled
    if spec.pilot is None and not spec.skip_zero_code:
        # Modulated pixels have at least one bit on; add the lit all-zero stripe.
        zero = _zero_stripe(np.where(valid, stripe, -1), ~lit, demod.dc, spec, min_dc=zero_code_dc)
        lit, valid, stripe = lit | zero, valid | zero, np.where(zero, 0, stripe)
    if demod.misfit is not None:
        valid &= demod.misfit <= max_misfit
    if border_reach:
        stripe = refine_borders(stripe, valid, levels, spec, reach=border_reach)
    if neighbour_radius:
        valid = agrees_with_neighbours(stripe, valid, radius=neighbour_radius)
    stripe = np.where(valid, stripe, -1).astype(np.int16)
    proj_map = stripe_center(stripe, spec).astype(np.float32)
    return Decoded(stripe=stripe, proj_map=proj_map, valid=valid, lit=lit,
                   confidence=np.where(lit, confidence, 0).astype(np.float32), levels=levels)
