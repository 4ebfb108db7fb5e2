"""sliscan's decoder as plain numpy (before the compiled kernels of `sliscan.decode`).

The kernels must give exactly these results; `test_decode.py` compares them on rendered
captures.  Kept only as that reference.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sliscan.decode import (LEVEL_PIXELS_KEPT, LEVEL_RESIDUAL, ZERO_STRIPE_MIN_DC, Decoded, _zero_stripe,
                            agrees_with_neighbours, dark_level, two_means)
from sliscan.demodulate import Demodulated
from sliscan.patterns import bits_to_code, code_to_stripe, stripe_center, stripe_codes
from sliscan.types import PatternSpec


def _sample(mask: NDArray[np.bool_], limit: int = 200_000) -> NDArray[np.bool_]:
    """Thin a mask to at most about `limit` pixels on a regular grid (for level statistics)."""
    step = max(1, int(np.sqrt(mask.sum() / limit)))
    thin = np.zeros_like(mask)
    thin[::step, ::step] = mask[::step, ::step]
    return thin


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


def _refine_borders(stripe: NDArray[np.integer], valid: NDArray[np.bool_], levels: NDArray[np.float32],
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
           max_misfit: float = 0.25, zero_code_dc: float = ZERO_STRIPE_MIN_DC, neighbour_radius: int = 3,
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
    dc = np.maximum(demod.dc, np.float32(dark_level(demod.dc)))
    reference = demod.amplitude[bits] if spec.pilot is not None else dc
    ratio = demod.amplitude[:bits] / np.maximum(reference, 1e-6)[None]
    lit = _lit(demod, spec, dc, min_modulation, min_snr)
    explained = lit & (demod.residual <= LEVEL_RESIDUAL)  # the bits' levels from windows the model explains
    levels, spans = _levels(ratio, _sample(explained if explained.sum() >= LEVEL_PIXELS_KEPT * lit.sum() else lit))
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
        zero = _zero_stripe(np.where(valid, stripe, -1), demod.dc, spec, min_dc=zero_code_dc)
        lit, valid, stripe = lit | zero, valid | zero, np.where(zero, 0, stripe)
    if demod.misfit is not None:
        valid &= demod.misfit <= max_misfit
    if border_reach:
        stripe = _refine_borders(stripe, valid, levels, spec, reach=border_reach)
    if neighbour_radius:
        valid = agrees_with_neighbours(stripe, valid, radius=neighbour_radius)
    stripe = np.where(valid, stripe, -1).astype(np.int16)
    proj_map = stripe_center(stripe, spec).astype(np.float32)
    return Decoded(stripe=stripe, proj_map=proj_map, valid=valid, lit=lit,
                   confidence=np.where(lit, confidence, 0).astype(np.float32), levels=levels)
