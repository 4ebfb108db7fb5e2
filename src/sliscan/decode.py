"""Binarising and Gray decoding of demodulated envelopes (thesis section 3.5).

The thesis thresholds each envelope with one fixed value.  A real surface multiplies the
envelopes by its albedo and adds ambient light, so here each envelope is first normalised by
what the same window of the capture says about the light reaching that pixel:

* with a pilot carrier (on wherever the projector lights), by the pilot's envelope: the ratio
  is the bit itself, whatever the albedo, ambient light or optical roll-off;
* without one (the thesis's pattern), by the local DC, which still carries the ambient light.

Each bit's "off" and "on" levels are then estimated from the capture itself (two-means on the
lit pixels), so crosstalk and roll-off shift the threshold instead of flipping bits.

The all-zero code projects no carrier at all: in one frame it looks like shadow.  Patterns with
``skip_zero_code`` never project it, so unmodulated pixels are shadow.  Otherwise (the
thesis's pattern) an unmodulated pixel is taken as the lit all-zero stripe when its DC is at
least `zero_code_dc` times the DC of the modulated pixels around it, and as shadow otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from sliscan.demodulate import Demodulated
from sliscan.patterns import bits_to_code, code_to_stripe, stripe_center
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
    """Means of the low and high cluster of 1-D samples (Lloyd's algorithm, k = 2).

    >>> two_means(np.array([0.0, 0.1, 0.0, 0.9, 1.0, 1.1]))
    (0.03333333333333333, 1.0)
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        return 0.0, 1.0
    lo, hi = float(np.percentile(v, 5)), float(np.percentile(v, 95))
    for _ in range(iterations):
        t = 0.5 * (lo + hi)
        low, high = v[v < t], v[v >= t]
        if low.size == 0 or high.size == 0:
            break
        new = float(low.mean()), float(high.mean())
        if new == (lo, hi):
            break
        lo, hi = new
    return lo, hi


def _sample(mask: NDArray[np.bool_], limit: int = 200_000) -> NDArray[np.bool_]:
    """Thin a mask to at most about `limit` pixels on a regular grid (for level statistics)."""
    step = max(1, int(np.sqrt(mask.sum() / limit)))
    thin = np.zeros_like(mask)
    thin[::step, ::step] = mask[::step, ::step]
    return thin


def modulation(demod: Demodulated, spec: PatternSpec) -> NDArray[np.float32]:
    """How strongly the projector's carriers show at each pixel, relative to the local DC.

    The pilot's envelope over the DC when there is a pilot, else the largest bit envelope
    over the DC.  The DC is floored at 2 % of the frame's bright level, so black pixels
    (outside the projector, no ambient light) do not look modulated by dividing noise by 0.
    """
    dc = np.maximum(demod.dc, 0.02 * float(np.percentile(demod.dc[::4, ::4], 99)) + 1e-6)
    if spec.pilot is not None:
        return demod.amplitude[spec.bits] / dc
    return demod.amplitude[: spec.bits].max(axis=0) / dc


def _lit_by_modulation(mod: NDArray[np.float32], demod: Demodulated, min_modulation: float | None) -> NDArray[np.bool_]:
    """Pixels whose carrier modulation stands above the noise floor."""
    if min_modulation is None:
        lo, hi = two_means(mod[_sample(np.isfinite(mod))])
        min_modulation = lo + 0.35 * (hi - lo)
    return (mod >= min_modulation) & (demod.dc > 0)


def _zero_code_pixels(lit: NDArray[np.bool_], demod: Demodulated, ratio: float, sigma: float) -> NDArray[np.bool_]:
    """Unmodulated pixels bright enough, next to modulated ones, to be the lit all-zero stripe."""
    weights = ndimage.gaussian_filter(lit.astype(np.float32), sigma)
    local = ndimage.gaussian_filter(np.where(lit, demod.dc, 0).astype(np.float32), sigma)
    reference = local / np.maximum(weights, 1e-6)
    return ~lit & (weights > 0.02) & (demod.dc >= ratio * reference)


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


def decode(demod: Demodulated, spec: PatternSpec, *, min_modulation: float | None = None,
           min_confidence: float = 0.1, min_snr: float = 3.0, max_residual: float = 0.6, max_misfit: float = 0.25, zero_code_dc: float = 0.55,
           window: int = 64) -> Decoded:
    """Binarise the envelopes and Gray-decode them into stripes and projector lines.

    Parameters
    ----------
    demod : Demodulated
        From `sliscan.demodulate.demodulate`, camera orientation.
    spec : PatternSpec
        The projected pattern.
    min_modulation : float, optional
        Carrier-to-DC ratio under which a pixel counts as unlit; default from the capture
        (a third of the way from the noise cluster to the lit cluster).
    min_confidence : float
        A bit is clear when its level is at least half this far from 0.5 ...
    min_snr : float
        ... and at least this many noise standard deviations (`Demodulated.noise`) from its
        threshold.  A pixel is valid when every bit is clear, or when only one is not and
        flipping it gives the neighbouring stripe (a pixel on a stripe border).
    max_residual : float
        Pixels whose window the carrier model explains worse than this are invalid.
    max_misfit : float
        Pixels whose own neighbourhood the window's model mispredicts by more than this
        fraction of the DC are invalid (see `Demodulated.misfit`).
    zero_code_dc : float
        For patterns that project the all-zero code: DC ratio to the surrounding lit pixels
        above which an unmodulated pixel is the lit zero stripe (see module docstring).
    window : int
        Scale (camera pixels) of the neighbourhood used for the zero-code DC reference.

    Returns
    -------
    Decoded
    """
    bits = spec.bits
    reference = demod.amplitude[bits] if spec.pilot is not None else demod.dc
    ratio = demod.amplitude[:bits] / np.maximum(reference, 1e-6)[None]
    mod = modulation(demod, spec)
    lit = _lit_by_modulation(mod, demod, min_modulation)
    stats = _sample(lit)
    levels = np.empty_like(ratio, dtype=np.float32)
    spans = np.empty(bits)
    for n in range(bits):
        off, on = two_means(ratio[n][stats])
        spans[n] = max(on - off, 1e-6)
        levels[n] = (ratio[n] - off) / spans[n]
    if spec.pilot is None:
        # Without a pilot the DC carries the ambient light, so a dimly lit pixel reads every
        # bit low.  A lit code has at least one bit on: rescale so the strongest bit reads 1.
        strongest = levels.max(axis=0)
        levels = np.where(strongest >= 0.6, levels / np.maximum(strongest, 1e-6), levels).astype(np.float32)
    if spec.pilot is None and not spec.skip_zero_code:
        # Modulated pixels have at least one bit on; add the lit all-zero stripe.
        lit = lit | _zero_code_pixels(lit, demod, zero_code_dc, sigma=window)
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
    valid = lit & (stripe >= 0) & modelled & ((unclear == 0) | _flip_is_adjacent(code, stripe, ~clear, spec))
    if demod.misfit is not None:
        valid &= demod.misfit <= max_misfit
    stripe = np.where(valid, stripe, -1).astype(np.int16)
    proj_map = stripe_center(stripe, spec).astype(np.float32)
    return Decoded(stripe=stripe, proj_map=proj_map, valid=valid, lit=lit,
                   confidence=np.where(lit, confidence, 0).astype(np.float32), levels=levels)
