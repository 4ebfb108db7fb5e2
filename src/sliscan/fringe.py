"""The phase channel of a composite pattern: sub-stripe projector lines from one frame (issue 8).

A pattern with `PatternSpec.phase_carriers` puts, on each of N more carriers, one phase-shifted
copy of a fringe along the phase direction (the PMP composite pattern of the thesis's lab)::

    I_n(line) = (1 + cos(phi(line) - 2 pi n / N)) / 2,   phi = 2 pi (line + 0.5) / period

so the N envelopes of a pixel are N phase-shifted samples of the fringe, all seen through the
same albedo, ambient light and projector gain: their phase places the pixel inside a fringe
period whatever the surface's reflectance, and the Gray code stripe says which period.  With a
period of two stripes the stripe may be off by a quarter period (half a stripe) and the
unwrapping is still right, so the phase also repairs the Gray code's decisions along stripe
borders, where most of its errors are.

Stages, each its own function:

1. `channel_levels`: each phase carrier's gain (optical roll-off differs per carrier),
   offset and crosstalk, from the capture itself: the envelopes, averaged along the phase
   direction at sampled pixels (`level_samples`, so that noise does not bias the fit), are
   regressed on the fringe model at each sample's current phase and light share, until the
   levels settle (the scene's phases need not cover the circle evenly).  The crosstalk is a projector gamma's
   products of two carriers that land on a phase carrier (`crosstalk`): with the pixel's
   stripe known they are linear in its fringes and are taken out (`phasors`).  Given each
   pixel's depth (the Gray code's lines triangulated), the gains are then fitted as
   quadratics in the inverse depth and each pixel's envelopes read with its own
   (`relevelled`): a projector focused at one depth blurs its finest carriers more elsewhere.
2. `phasors`: per pixel the fringe's phasor ``sum_n I_n exp(i 2 pi n / N)``, unweighted
   (a DC weight would move each box's phase toward its brighter side), from the envelopes of
   `phase_envelopes`: away from edges those of the demodulator's two-period windows with a
   ramp per phase carrier, which follow a fringe that crosses the carriers' lines obliquely
   (the one-period fits leak its change along the window into each other); each less the bias
   its noise gives it (`debiased`), except in the fringe's sum, which the tests divide by.
3. `smooth_phasors`: the phasors summed over a box along both image axes, restricted to runs of
   valid pixels whose stripe changes by at most 1.5 stripes from pixel to pixel (so the box
   does not reach across depth edges).  Along the carriers the box is one demodulation window
   long: a carrier whose local frequency differs from the window's (perspective, slope) leaks
   into its neighbours with a beat of exactly the carrier spacing, which a box of one spacing
   period cancels; it is "twiced" (``2 B - B B``), which also cancels the box's bias on a
   curved surface.  Along the phase direction it is an eighth of a fringe period (the
   modulation keeps 97 % of its depth) and averages the noise; for the phase of the pixels
   the decisions below keep, runs along the phase direction go on across the rows the Gray
   code left undecided at stripe borders (`bridge_gaps`).  Each summed phasor then has
   its phase moved from the position its windows and box describe back to its pixel, where
   the fringe's slope along the carriers is measured (`recentre`).
4. `unwrap`: the fringe period nearest to the Gray code stripe's centre; pixels where the two
   disagree by more than `max_disagreement` stripes are unwrapped against their sure
   neighbours' mean line (`local_reference`) instead, or dropped, and so are pixels whose
   fringe modulation is weak (`refine`).
5. Pixels the Gray code left out are unwrapped against the mean line of the kept pixels
   around them (`neighbour_lines`), if those lie on one surface and the pixel's own phase
   carriers stand above the noise (`refine`'s `extend`).
6. Pixels next to a depth edge are dropped, within a small margin (`near_jumps`, `EDGE_MARGIN`):
   there the windows and boxes reach across it, and where its jump is close to a whole fringe
   period a wrong stripe goes unnoticed.
7. Within half a window of such a jump (across the undecoded gap that usually lies beside it),
   also the pixels whose demodulation window lies on a surface more than twice as bright or as
   dark as themselves (`window_contrast` above `NEAR_JUMP_CONTRAST`): a window reaching
   onto the other surface, where far from any jump the same contrast is an albedo edge; and
   the runs along the carriers shorter than an eighth of a window (`SHORT_RUN`), which no
   window lying on them describes, and those shorter than half a window whose window
   contrast is above 1.5 (`MID_RUN`).
8. Then the pixels at the ends of runs (down the phase direction, and along the carriers on the
   capture itself) whose light puts their centre on the shadow's side of a light edge
   (`sliscan.outliers.shadow_side`): blur, or a window ending at them, lends them the lit
   side's code.
9. Last, the ring of pixels next to any pixel not kept (`beside_gaps`, `GAP_RING`): whatever
   made that one fail reaches them a little less, and the error grows toward every gap.

Measured on the virtual rig: docs/accuracy.md, "Sub-stripe depth from one frame".
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from sliscan._threads import over_rows
from sliscan.decode import Decoded
from sliscan.demodulate import RAMPED_PERIODS, Carriers, Demodulated, along_carriers
from sliscan.outliers import inner_pixels, run_bounds, run_end, run_lengths, shadow_side
from sliscan.patterns import code_bits, fringe_line, fringe_phase, phase_shifts, stripe_codes, stripe_of_line
from sliscan.staircase import slope_along_carriers
from sliscan.types import PatternSpec


@dataclass(frozen=True)
class ChannelLevels:
    """Each phase carrier's response to its fringe: ``ratio_n = offset_n + gain_n * I_n``.

    Attributes
    ----------
    gain, offset : (N,) float64 arrays
        In units of the envelope's ratio to the local DC.
    crosstalk : (N,) float64 array
        Weight of the projector's second-order products on each phase carrier (`crosstalk`),
        relative to its own fringe: ``ratio_n = offset_n + gain_n (I_n + crosstalk_n P_n)``.
        About ``(gamma - 1) / 2 * b_p / a_p`` for an uncorrected gamma (0.086 for gamma 2.2 and
        the default pattern; measured 0.082-0.096); 0 for a linear projector.
    depth_gain : (N, 2) float64 array or None
        How each gain changes with depth: ``gain_n + a_n t + b_n t**2`` at ``t = (1 / z -
        centre) / scale`` (`depth_reference`), ``z`` the projector's depth (mm) of the pixel's
        surface (`gains`).  A projector focused at one depth blurs nearer and farther points
        more, and its finer carriers lose more of their modulation: through a Gaussian blur of
        variance ``sigma**2`` a carrier of frequency ``f`` keeps ``exp(-2 pi**2 sigma**2 f**2)``,
        and a thin lens's ``sigma**2`` is a quadratic in ``1 / z``.  (The log gain, exactly
        quadratic for that lens, fitted so: measured worse on in-focus captures, docs/accuracy.md.)
        None: one gain everywhere.
    depth_reference : (4,) float64 array or None
        ``(centre, scale, low, high)``: the inverse depths' reference and scale (1/mm), and the
        range of ``t`` the fit saw (`gains` holds ``t`` within it).
    """

    gain: NDArray[np.float64]
    offset: NDArray[np.float64]
    crosstalk: NDArray[np.float64]
    depth_gain: NDArray[np.float64] | None = None
    depth_reference: NDArray[np.float64] | None = None

    def gains(self, inverse_depth: NDArray[np.floating], dtype: type = np.float64) -> NDArray[np.floating]:
        """Each phase carrier's gain at pixels of `inverse_depth` (1/mm, any shape; NaN: the
        reference depth's): ``(N, *shape)`` of `dtype`, held within `MIN_GAIN_SHARE` of the
        reference depth's and its inverse."""
        depth = np.asarray(inverse_depth)
        out = np.empty((self.gain.size, *depth.shape), dtype=dtype)
        if self.depth_gain is None or self.depth_reference is None:
            out[:] = self.gain.reshape(-1, *[1] * depth.ndim)
            return out
        centre, scale, low, high = (dtype(v) for v in self.depth_reference)
        t = np.clip(np.nan_to_num((depth.astype(dtype) - centre) / scale), low, high)
        for k, (g, (a, b)) in enumerate(zip(self.gain.astype(dtype), self.depth_gain.astype(dtype))):
            np.clip(g + t * (a + b * t), dtype(MIN_GAIN_SHARE) * g, g / dtype(MIN_GAIN_SHARE), out=out[k])
        return out


def crosstalk(spec: PatternSpec) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """What a projector's nonlinearity adds to each phase carrier, per stripe: ``(C, c)``.

    A projector whose light is a curved function of its drive (an uncorrected gamma) squares
    the pattern's sum of carriers a little: every pair of carriers adds a term at their sum
    and at their difference frequency, in phase with a carrier there (all are cosines of the
    same projector coordinate, and blur and pixel apertures are symmetric).  With carriers on
    multiples of one spacing these land exactly on other carriers: on sliscan's phase
    pattern (spacings 1-4 the bits, 5-7 the fringe) carrier 5 receives bits 1 x 4 and 2 x 3,
    and fringes 6 x bit 1 and 7 x bit 2.  Relative to carrier n's own fringe ``I_n`` they add
    ``P_n = sum over pairs of w_a w_b / w_n * s_a s_b`` (``s`` = 0/1 for a bit, ``I_m`` for a
    fringe, 1 for the pilot; half for a carrier with itself), linear in the fringes once the
    stripe's bits are known: ``P = C[stripe] @ I + c[stripe]``.  Products of two fringes
    (not linear) never land on a phase carrier of these layouts and are left out.

    Returns
    -------
    C : (S, N, N) float64 array
    c : (S, N) float64 array
        For each stripe ``0 .. S - 1`` (its Gray code's bits), N phase carriers.
    """
    freqs = np.asarray(spec.all_carriers, dtype=np.float64)
    weights = np.asarray(spec.all_weights, dtype=np.float64)
    first, n = spec.bits, len(spec.phase_carriers)
    phase = np.zeros(freqs.size, bool)
    phase[first:first + n] = True
    bits = code_bits(stripe_codes(spec), spec.bits).astype(np.float64)  # (S, bits)
    fixed = np.ones((bits.shape[0], freqs.size))  # the bits' and the pilot's values per stripe
    fixed[:, :spec.bits] = bits
    tol = 1e-6 * freqs.max()
    big_c, small_c = np.zeros((bits.shape[0], n, n)), np.zeros((bits.shape[0], n))
    for k in range(n):
        target = freqs[first + k]
        for a in range(freqs.size):
            for b in range(a, freqs.size):
                share = ((0.5 if a == b else 1.0) * (abs(freqs[a] + freqs[b] - target) < tol)
                         + (a != b) * (abs(abs(freqs[a] - freqs[b]) - target) < tol))
                if share == 0 or (phase[a] and phase[b]):
                    continue
                coef = share * weights[a] * weights[b] / weights[first + k]
                if phase[a] or phase[b]:  # a fringe times a bit (or the pilot)
                    fringe_index, other = (a, b) if phase[a] else (b, a)
                    big_c[:, k, fringe_index - first] += coef * fixed[:, other]
                else:
                    small_c[:, k] += coef * fixed[:, a] * fixed[:, b]
    return big_c, small_c


def _unmixing(levels: ChannelLevels, big_c: NDArray[np.float64],
              small_c: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per stripe, the map from a pixel's levels ``(ratio - offset) / gain`` to its fringes:
    ``I = M[stripe] @ (level - v[stripe])``, inverting ``level = I + k (C I + c)`` (``C, c``
    from `crosstalk`); one more entry (index S) is the identity, for pixels without a stripe.
    ``(S + 1, N, N)``, ``(S + 1, N)``."""
    n = big_c.shape[1]
    kappa = levels.crosstalk[None, :, None]
    mix = np.linalg.inv(np.eye(n)[None] + kappa * big_c)
    return (np.concatenate([mix, np.eye(n)[None]]),
            np.concatenate([levels.crosstalk[None, :] * small_c, np.zeros((1, n))]))


#: Pixels `channel_levels` samples (about).
LEVEL_SAMPLES = 5_000
#: A phase carrier's gain at any depth is held within this share of its gain at the reference
#: depth and its inverse: where the fit says the projector's blur took more, the carrier is
#: mostly noise, which a larger gain would only amplify (a 16 mm aperture, the finest carrier
#: at 1 % of its modulation: RMS 57 -> 131 mm with a share of 0.1, docs/accuracy.md).
MIN_GAIN_SHARE = 0.5
#: `channel_levels` scales the samples' inverse depths by their spread, but by at least this
#: share of their median: over a shallower scene the gains' change with depth is noise.
MIN_DEPTH_SPREAD = 0.02


def sample_step(mask: NDArray[np.bool_], limit: int) -> int:
    """Stride of the regular grid that thins the pixels of `mask` to about `limit`."""
    return max(1, int(np.sqrt(max(int(mask.sum()), 1) / limit)))


def channel_levels(ratios: NDArray[np.float32], mask: NDArray[np.bool_], spec: PatternSpec, *,
                   stripes: NDArray[np.integer] | None = None, inverse_depth: NDArray[np.floating] | None = None,
                   limit: int = LEVEL_SAMPLES, tolerance: float = 1e-4, max_iterations: int = 200) -> ChannelLevels:
    """Gains, offsets and crosstalk of the phase carriers, estimated from the capture.

    Each pixel's ratios follow ``m (offset_n + gain_n (I_n(phi) + crosstalk_n P_n))``: `m`,
    the pixel's share of projector light in its DC (albedo against ambient light), and the
    phase are the pixel's; ``P_n`` the projector's products landing on the carrier, from the
    pixel's stripe and fringes (`crosstalk`); the levels are common to all pixels (in the
    units of the sampled pixels' ratios: `m` has a mean of 1 over them).  Starting from each
    ratio's 98th percentile as gain, no offset and no crosstalk, the fit alternates until the
    levels move by less than `tolerance` (relative): every sampled pixel's phase and `m` with
    the current levels; each carrier's least-squares fit of ``ratio_n / m`` on ``1, I_n,
    P_n``.  A scene whose phases cover the circle converges in a few tens of rounds, one that
    shows only part of it (a small object) in up to a few hundred, hence the small sample.
    With `inverse_depth`, once those levels settle (or after `max_iterations` rounds) the fit
    goes on with each gain a quadratic in the samples' scaled inverse depth and the crosstalk
    kept (`ChannelLevels.depth_gain`), for up to `max_iterations` more rounds.

    Parameters
    ----------
    ratios : (N, H, W) float32 array
        Phase carriers' envelopes over the local DC.
    mask : (H, W) bool array
        Pixels to learn from (decoded, lit), thinned to about `limit` on a regular grid.
    stripes : (H, W) int array, optional
        Each pixel's stripe (Gray code); without them the crosstalk is not fitted (0).
    inverse_depth : (H, W) array, optional
        Each pixel's inverse depth along the projector's axis (1/mm; NaN: unknown, not
        sampled): the gains are fitted as quadratics in it (`ChannelLevels.depth_gain`).
    """
    step = sample_step(mask, limit)
    grid = mask[::step, ::step]
    if inverse_depth is not None:
        grid = grid & np.isfinite(inverse_depth[::step, ::step])
    samples = ratios[:, ::step, ::step][:, grid].astype(np.float64)  # (N, M)
    n = samples.shape[0]
    if samples.shape[1] < 10 * n:
        return ChannelLevels(gain=np.ones(n), offset=np.zeros(n), crosstalk=np.zeros(n))
    big_c, small_c = crosstalk(spec)
    if stripes is None:
        big_c, small_c = np.zeros_like(big_c), np.zeros_like(small_c)
        stripe = np.zeros(samples.shape[1], np.intp)
    else:
        stripe = np.clip(stripes[::step, ::step][grid], 0, big_c.shape[0] - 1).astype(np.intp)
    shifts = phase_shifts(spec)
    levels = ChannelLevels(gain=np.maximum(np.percentile(samples, 98, axis=1), 1e-6), offset=np.zeros(n),
                           crosstalk=np.zeros(n))
    depth_terms, reference, u = np.zeros((0, samples.shape[1])), None, np.zeros(0)
    if inverse_depth is not None:
        u = inverse_depth[::step, ::step][grid].astype(np.float64)
        centre = float(np.median(u))
        scale = max(float(np.std(u)), MIN_DEPTH_SPREAD * abs(centre), 1e-12)
        t = (u - centre) / scale
        depth_terms = np.stack([t, t * t])
        reference = np.array([centre, scale, *np.percentile(t, [0.5, 99.5])])
    share = np.ones(samples.shape[1])
    with_depth, rounds = False, 0  # one gain per carrier until that fit settles, then its change with depth
    for _ in range(2 * max_iterations):
        rounds += 1
        gain, offset, kappa = levels.gain, levels.offset, levels.crosstalk
        mix, shift = _unmixing(levels, big_c, small_c)
        per_sample = levels.gains(u) if with_depth else gain[:, None]
        level = (samples / share - offset[:, None]) / per_sample
        c, s = _phasor_parts(np.einsum("mij,jm->im", mix[stripe], level - shift[stripe].T), shifts)
        fringe = 0.5 * (1 + np.cos(np.arctan2(s, c)[None, :] - shifts[:, None]))  # (N, M)
        products = np.einsum("mij,jm->im", big_c[stripe], fringe) + small_c[stripe].T  # (N, M)
        model = offset[:, None] + per_sample * (fringe + kappa[:, None] * products)
        share = np.maximum(np.sum(samples * model, axis=0) / np.maximum(np.sum(model * model, axis=0), 1e-12), 1e-6)
        share /= share.mean()
        scaled = samples / share
        if with_depth:  # the crosstalk kept: each carrier's gain a quadratic in the depth term
            response = fringe + kappa[:, None] * products
            fits = np.array([np.linalg.lstsq(np.stack([np.ones_like(f), f, *(f * depth_terms)], axis=1), r,
                                             rcond=None)[0] for f, r in zip(response, scaled)])
            new_offset, new_gain, depth_gain = fits[:, 0], np.maximum(fits[:, 1], 1e-6), fits[:, 2:]
            weighted = kappa * new_gain
        else:
            fits = np.array([np.linalg.lstsq(np.stack([np.ones_like(f), f, p], axis=1), r, rcond=None)[0]
                             for f, p, r in zip(fringe, products, scaled)])
            new_offset, new_gain, weighted, depth_gain = fits[:, 0], np.maximum(fits[:, 1], 1e-6), fits[:, 2], None
        moved = [new_gain - gain, new_offset - offset, weighted - kappa * gain]
        if with_depth:
            moved.append((depth_gain - levels.depth_gain).ravel())
        change = np.max(np.abs(np.concatenate(moved))) / np.max(new_gain)
        levels = ChannelLevels(gain=new_gain, offset=new_offset, crosstalk=weighted / new_gain, depth_gain=depth_gain,
                               depth_reference=reference if with_depth else None)
        if change < tolerance or rounds >= max_iterations:
            if with_depth or reference is None:
                break
            with_depth, rounds = True, 0
            levels = replace(levels, depth_gain=np.zeros((n, 2)), depth_reference=reference)
    return levels


def level_samples(demod: Demodulated, valid: NDArray[np.bool_], stripes: NDArray[np.integer], spec: PatternSpec,
                  step: int, length: int, envelopes: NDArray[np.float32] | None = None
                  ) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.int16]]:
    """What `channel_levels` learns from: the phase carriers' envelopes over the DC, each a mean
    along the phase direction, on a grid of every `step`-th pixel (carriers along axis 1).

    Each grid pixel takes the DC-weighted mean of its ratios over `length` pixels along the
    phase direction centred on it; it is usable where all of them are `valid` and their
    `stripes` differ by at most one (one surface).  Why: the fit regresses every ratio on the
    fringe at the pixel's phase, and that phase comes from the same ratios; a lone pixel's
    noise scatters it, which biases the levels (errors in variables; measured on a plane at
    1296x972 with realistic noise: the weakest carrier's gain 19 % high, and the phase bent by
    up to 3 projector lines within each fringe period).  The mean of `length` pixels has
    1 / `length` of the noise variance, and within an eighth of a fringe period every carrier
    keeps the same share (97 %) of its modulation, so the levels' ratios stay those of one pixel.
    `envelopes` ``(N, H, W)``: the phase carriers' envelopes (`phase_envelopes`), by default
    `demod`'s.

    Returns
    -------
    ratios : (N, h, w) float32 array
    usable : (h, w) bool array
    stripes : (h, w) int16 array
        The grid pixels' own stripes.
    """
    n = len(spec.phase_carriers)
    gather = functools.partial(sample_stretches, spec=spec, step=step, length=length)
    stripe = gather(stripes).astype(np.int32)
    usable = np.all(gather(valid), axis=0) & (stripe.max(axis=0) - stripe.min(axis=0) <= 1)
    dc = np.sum(gather(demod.dc), axis=0, dtype=np.float64)
    envelopes = demod.amplitude[spec.bits:spec.bits + n] if envelopes is None else envelopes
    ratios = np.stack([np.sum(gather(envelopes[k]), axis=0, dtype=np.float64)
                       / np.maximum(dc, 1e-12) for k in range(n)]).astype(np.float32)
    return ratios, usable, stripe[max(length // 2, 0)].astype(np.int16)


def sample_stretches(image: NDArray, *, spec: PatternSpec, step: int, length: int) -> NDArray:
    """The values of `image` ``(H, W)`` (camera orientation) over `length` pixels along the phase
    direction centred on every `step`-th pixel of `level_samples`' grid: ``(length | 1, h, w)``
    (carriers along axis 2)."""
    half = max(length // 2, 0)
    framed = along_carriers(image, spec)
    height, width = framed.shape
    rows = np.arange(half, height - half, step)
    around = rows[None, :, None] + np.arange(-half, half + 1)[:, None, None]  # (L, h, 1)
    return framed[around, np.arange(0, width, step)[None, None, :]]


def relevelled(envelopes: list[NDArray[np.float32]], dc: NDArray[np.float32], levels: ChannelLevels,
               inverse_depth: NDArray[np.floating]) -> list[NDArray[np.float32]]:
    """Sets of phase carriers' envelopes ``(N, H, W)`` changed so that `levels`' gains read them
    as their gains at each pixel's depth (`ChannelLevels.gains` of `inverse_depth` ``(H, W)``)
    read the originals: with ``d`` the DC, ``(E' / d - offset) / gain = (E / d - offset) /
    gain(z)``.  The envelopes themselves where the levels do not change with depth."""
    if levels.depth_gain is None or levels.depth_reference is None:
        return envelopes
    d = np.maximum(dc, np.float32(1e-6))
    out = [np.empty_like(e) for e in envelopes]
    for k, local in enumerate(levels.gains(inverse_depth, np.float32)):
        ratio = np.float32(levels.gain[k]) / local
        d_offset = d * np.float32(levels.offset[k])
        for source, target in zip(envelopes, out):
            np.subtract(source[k], d_offset, out=target[k])
            target[k] *= ratio
            target[k] += d_offset
    return out


def _phasor_parts(levels: NDArray[np.floating], shifts: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
    """``sum_n levels_n cos(shift_n)`` and ``sum_n levels_n sin(shift_n)`` over axis 0."""
    return np.tensordot(np.cos(shifts), levels, 1), np.tensordot(np.sin(shifts), levels, 1)


@numba.njit(cache=True, nogil=True)
def _phasor_rows(amplitude: NDArray[np.float32], totals: NDArray[np.float32], first: int, dc: NDArray[np.float32],
                 valid: NDArray[np.bool_], stripe: NDArray[np.int16], gain: NDArray[np.float64],
                 offset: NDArray[np.float64], mix: NDArray[np.float64], shift: NDArray[np.float64],
                 cos_shift: NDArray[np.float64], sin_shift: NDArray[np.float64], weighted: bool,
                 rows: NDArray[np.intp], out: NDArray[np.float32]) -> None:
    """`phasors` on the given `rows`: `amplitude` and `totals` ``(C, H, W)`` with the phase
    carriers from index `first`; `mix`, `shift` from `_unmixing`; `out` ``(3, H, W)``, times
    the DC if `weighted`."""
    n = gain.size
    identity = mix.shape[0] - 1
    level, total = np.empty(n), np.empty(n)
    for r in rows:
        for x in range(dc.shape[1]):
            if not valid[r, x]:
                out[0, r, x] = out[1, r, x] = out[2, r, x] = 0.0
                continue
            d = max(dc[r, x], 1e-6)
            st = stripe[r, x] if 0 <= stripe[r, x] < identity else identity
            for k in range(n):
                level[k] = (amplitude[first + k, r, x] / d - offset[k]) / gain[k] - shift[st, k]
                total[k] = (totals[first + k, r, x] / d - offset[k]) / gain[k] - shift[st, k]
            c = s = t = 0.0
            for k in range(n):
                fringe = unmixed = 0.0
                for j in range(n):
                    fringe += mix[st, k, j] * level[j]
                    unmixed += mix[st, k, j] * total[j]
                c += fringe * cos_shift[k]
                s += fringe * sin_shift[k]
                t += unmixed
            w = dc[r, x] if weighted else 1.0
            out[0, r, x], out[1, r, x], out[2, r, x] = c * w, s * w, t * w


def phasors(demod: Demodulated, valid: NDArray[np.bool_], levels: ChannelLevels, spec: PatternSpec,
            stripes: NDArray[np.int16], *, weighted: bool = False, envelopes: NDArray[np.float32] | None = None,
            totals: NDArray[np.float32] | None = None) -> NDArray[np.float32]:
    """The fringe's phasor at every pixel: ``(3, H, W)`` float32 = (real, imaginary, sum of
    the fringes), 0 where not `valid`; each times the local DC if `weighted`.

    With ``level_n = (ratio_n - offset_n) / gain_n`` (``ratio_n`` the phase carrier's envelope
    over the DC) and the projector's products on it taken out with the pixel's stripe
    (`stripes`, -1: none taken out; `_unmixing`), ``I_n = m (1 + cos(phi - 2 pi n / N)) / 2``:
    ``sum_n I_n exp(i 2 pi n / N) = m (N / 4) exp(i phi)`` and ``sum_n I_n = m N / 2``, so
    ``|phasor| / (sum / 2)`` is the fringe's modulation depth (1 for a clean fringe).  A
    compiled kernel, rows in threads.

    Unweighted by default: the box sums of `smooth_phasors` then describe the middle of their
    box.  Weighted by the DC (brighter pixels are less noisy), a box describes the
    DC-weighted centroid of its pixels instead, off the middle where the albedo changes along
    the phase direction, and the fringe's phase there: on a 5 MP noise-free plane with the
    smooth albedo a bias of -0.33 / +0.40 projector lines where the log albedo falls / rises
    by more than 0.004 per pixel along the phase direction (unweighted: -0.01 / +0.08), and
    the median error 0.32 lines (unweighted 0.24; docs/accuracy.md, "Sub-stripe depth from one frame").

    `envelopes` ``(N, H, W)``: the phase carriers' envelopes to use (`phase_envelopes`,
    `debiased`), by default `demod`'s; `totals` ``(N, H, W)``: the envelopes the sum is taken
    from, by default the same (`refine` gives the debiased envelopes for the phasor and the
    envelopes as they are for the sum, so that its modulation tests keep their meaning).
    """
    shifts = phase_shifts(spec)
    mix, shift = _unmixing(levels, *crosstalk(spec))
    out = np.empty((3, *demod.dc.shape), dtype=np.float32)
    amplitude, first = (demod.amplitude, spec.bits) if envelopes is None else (envelopes, 0)
    totals = amplitude if totals is None else totals
    args = (np.ascontiguousarray(amplitude), np.ascontiguousarray(totals), first, np.ascontiguousarray(demod.dc),
            np.ascontiguousarray(valid), np.ascontiguousarray(stripes, dtype=np.int16), levels.gain.astype(np.float64),
            levels.offset.astype(np.float64), mix, shift, np.cos(shifts), np.sin(shifts), weighted)
    over_rows(lambda rows: _phasor_rows(*args, rows, out), out.shape[1])
    return out


@numba.njit(cache=True, inline="always")
def _clipped_box(cum: NDArray[np.float64], x: int, start: int, end: int, width: int, radius: int,
                 clamped: int) -> float:
    """The sum over pixel `x`'s box in `_segment_box_rows` from the run's prefix sums `cum`
    (``cum[i]``: the sum of the run's first `i` values), for the run ``start .. end - 1``."""
    length = 2 * radius + 1
    lo, hi = max(x - radius, start), min(x + radius + 1, end)
    if start == 0 and lo < clamped and end >= clamped + length:
        lo, hi = clamped, clamped + length
    elif end == width and hi > width - clamped and start <= width - clamped - length:
        lo, hi = width - clamped - length, width - clamped
    return cum[hi - start] - cum[lo - start]


@numba.njit(cache=True, nogil=True)
def _segment_box_rows(values: NDArray[np.float32], coarse: NDArray[np.float32], radius: int, max_jump: float,
                      clamped: int, rows: NDArray[np.intp], out: NDArray[np.float32]) -> None:
    """Box sums of `values` ``(K, H, W)`` over ``[x - radius, x + radius]`` along each row,
    clipped to the pixel's run: consecutive pixels with a finite `coarse` whose values differ by
    at most `max_jump`.  Pixels outside every run get 0.  A box that reaches into the first or
    last `clamped` pixels of a run at the frame's end is moved inward past them, keeping its
    length (see `_twiced_box`).  The boxes wholly inside their run take a loop of their own,
    which vectorises."""
    k_count, _, width = values.shape
    length = 2 * radius + 1
    cum = np.zeros((k_count, width + 1))
    for r in rows:
        start = 0
        while start < width:
            if not np.isfinite(coarse[r, start]):
                for k in range(k_count):
                    out[k, r, start] = 0.0
                start += 1
                continue
            end = run_end(coarse[r], start, max_jump)
            # the pixels whose box lies inside the run and is not moved at the frame's ends
            inner_lo, inner_hi = start + radius, end - radius
            if start == 0 and end >= clamped + length:
                inner_lo = max(inner_lo, clamped + radius)
            if end == width and start <= width - clamped - length:
                inner_hi = min(inner_hi, width - clamped - radius)
            inner_lo = min(inner_lo, end)
            inner_hi = max(inner_hi, inner_lo)
            for x in range(start, end):  # the channels' prefix sums side by side (independent chains)
                for k in range(k_count):
                    cum[k, x - start + 1] = cum[k, x - start] + values[k, r, x]
            for k in range(k_count):
                sums = cum[k]
                for x in range(start, inner_lo):
                    out[k, r, x] = _clipped_box(sums, x, start, end, width, radius, clamped)
                for x in range(inner_lo, inner_hi):
                    out[k, r, x] = sums[x - start + radius + 1] - sums[x - start - radius]
                for x in range(inner_hi, end):
                    out[k, r, x] = _clipped_box(sums, x, start, end, width, radius, clamped)
            start = end


def _segment_box(values: NDArray[np.float32], coarse: NDArray[np.float32], radius: int,
                 max_jump: float, axis: int = 2, clamped: int = 0) -> NDArray[np.float32]:
    """`_segment_box_rows` along every row (`axis` 2) or `_segment_box_columns` down every
    column (`axis` 1) of `values` ``(K, H, W)``, in threads: ``(K, H, W)`` float32."""
    values, coarse = np.ascontiguousarray(values, dtype=np.float32), np.ascontiguousarray(coarse, dtype=np.float32)
    out = np.empty_like(values)
    if axis == 2:
        over_rows(lambda rows: _segment_box_rows(values, coarse, radius, max_jump, clamped, rows, out),
                  values.shape[1])
    else:
        over_rows(lambda columns: _segment_box_columns(values, coarse, radius, max_jump, columns, out),
                  values.shape[2])
    return out


@numba.njit(cache=True, inline="always")
def _column_runs(coarse: NDArray[np.float32], max_jump: float, c0: int, n: int, start: NDArray[np.intp],
                 end: NDArray[np.intp]) -> None:
    """For columns ``c0 .. c0 + n - 1`` (index j): `start` ``[y, j]`` the first row of pixel
    ``(y, c0 + j)``'s run down its column (-1: in no run), `end` one past its last row."""
    height = coarse.shape[0]
    for y in range(height):
        for j in range(n):
            here = coarse[y, c0 + j]
            if not np.isfinite(here):
                start[y, j] = -1
            elif y > 0 and start[y - 1, j] >= 0 and abs(here - coarse[y - 1, c0 + j]) <= max_jump:
                start[y, j] = start[y - 1, j]
            else:
                start[y, j] = y
    for y in range(height - 1, -1, -1):
        for j in range(n):
            if start[y, j] < 0:
                end[y, j] = -1
            elif y < height - 1 and start[y + 1, j] == start[y, j]:
                end[y, j] = end[y + 1, j]
            else:
                end[y, j] = y + 1


@numba.njit(cache=True, nogil=True)
def _segment_box_columns(values: NDArray[np.float32], coarse: NDArray[np.float32], radius: int, max_jump: float,
                         columns: NDArray[np.intp], out: NDArray[np.float32], block: int = 256) -> None:
    """`_segment_box_rows` along axis 1 (down the columns) for the given `columns`, without a
    transpose: blocks of columns are walked row by row (loops along a row vectorise), each run's
    sums restarting at its first pixel, so every box sum is the same float64 sum as along a row."""
    if columns.size == 0:
        return
    k_count, height, _ = values.shape
    start, end = np.empty((height, block), np.intp), np.empty((height, block), np.intp)
    total = np.empty((height, block))
    for c0 in range(columns[0], columns[-1] + 1, block):
        n = min(c0 + block, columns[-1] + 1) - c0
        _column_runs(coarse, max_jump, c0, n, start, end)
        for k in range(k_count):
            for y in range(height):
                for j in range(n):
                    previous = total[y - 1, j] if y > 0 and start[y, j] == start[y - 1, j] and start[y, j] >= 0 else 0.0
                    total[y, j] = previous + values[k, y, c0 + j]
            for y in range(height):
                for j in range(n):
                    first = start[y, j]
                    if first < 0:
                        out[k, y, c0 + j] = 0.0
                        continue
                    lo, hi = max(y - radius, first), min(y + radius + 1, end[y, j])
                    out[k, y, c0 + j] = total[hi - 1, j] - (total[lo - 1, j] if lo > first else 0.0)


def _twiced_box(values: NDArray[np.float32], coarse: NDArray[np.float32], length: int,
                max_jump: float, frame_ends: bool = True) -> NDArray[np.float32]:
    """``2 B - B B`` of a box sum `B` of `length` along axis 2 within runs (`_segment_box`), in
    units of `B`: the box's bias on a curved profile (``f'' length^2 / 24``) cancels to second
    order ("twicing"), and so does any ripple of period `length`, which both boxes null.

    `length` is the demodulation window: at the frame's two ends, where it cannot be centred
    (`sliscan.demodulate._window_start` keeps it inside the line), the first and last
    ``length // 2`` pixels' values repeat those of the first and last centred window, and a
    box over them would hold one window's estimate many times over, its ripple and noise
    unaveraged (measured at 1296x972: a noise-free plane's line error 0.70 projector lines RMS
    within one window of the frame's sides against 0.33 inside; docs/accuracy.md, "Sub-stripe depth from
    one frame").  Those boxes are moved inward past them, keeping their length; the position
    channel of `with_positions` says where their sums lie, and `recentre` turns them back
    (`frame_ends`; if false, they are clipped like any run's end)."""
    clamped = length // 2 if frame_ends else 0
    once = _segment_box(values, coarse, length // 2, max_jump, clamped=clamped)
    twice = _segment_box(once, coarse, length // 2, max_jump, clamped=clamped)
    twice *= np.float32(1 / length)
    once *= np.float32(2)
    return np.subtract(once, twice, out=twice)  # in place: these are full frames


@numba.njit(cache=True, nogil=True)
def _bridge_columns(coarse: NDArray[np.float32], gap: int, max_jump: float, columns: NDArray[np.intp],
                    out: NDArray[np.float32]) -> None:
    """`bridge_gaps` for the given (consecutive) `columns`, walked row by row."""
    if columns.size == 0:
        return
    c0, n = columns[0], columns.size
    last = np.full(n, -1, np.intp)  # each column's last finite row so far
    for y in range(coarse.shape[0]):
        for j in range(n):
            value = coarse[y, c0 + j]
            out[y, c0 + j] = value
            if not np.isfinite(value):
                continue
            before = last[j]
            if before >= 0 and 1 < y - before <= gap + 1 and abs(value - coarse[before, c0 + j]) <= max_jump:
                for q in range(before + 1, y):
                    out[q, c0 + j] = 0.5 * (value + coarse[before, c0 + j])
            last[j] = y


def bridge_gaps(coarse: NDArray[np.float32], gap: int, max_jump: float) -> NDArray[np.float32]:
    """`coarse` ``(H, W)`` with every gap of at most `gap` NaN pixels down a column filled
    (with the mean of its two ends) where the finite pixels on either side differ by at most
    `max_jump`: one run of `smooth_phasors` goes on across it.

    The Gray code leaves a row or two undecided along every stripe border (its bit changes
    there); a box along the phase direction clipped at such a gap describes the fringe up to
    half a box away from its pixel, on the side away from the border.  Measured on a 5 MP
    noise-free plane: -1.5 and +2.0 projector lines next to a border, decaying over six lines
    (docs/accuracy.md, "Sub-stripe depth from one frame").  The gap's own pixels add nothing to the sums
    (their phasors are 0) and stay undecoded.

    >>> bridge_gaps(np.array([[1.0], [np.nan], [np.nan], [2.0], [np.nan], [90.0]], np.float32), 2, 5.0).ravel()
    array([ 1. ,  1.5,  1.5,  2. ,  nan, 90. ], dtype=float32)
    """
    coarse = np.ascontiguousarray(coarse, dtype=np.float32)
    out = np.empty_like(coarse)
    over_rows(lambda columns: _bridge_columns(coarse, gap, max_jump, columns, out), coarse.shape[1])
    return out


def smooth_phasors(phasor: NDArray[np.float32], coarse: NDArray[np.float32], *, along_carriers: int,
                   along_phase: int, max_jump: float, bridge: bool = False,
                   frame_ends: bool = True) -> NDArray[np.float32]:
    """Box sums of the phasors (in the carriers-along-axis-1 frame) within runs of one surface.

    Parameters
    ----------
    phasor : (K, H, W) float32 array
        From `phasors`, 0 where invalid.
    coarse : (H, W) float32 array
        The Gray code's projector line (stripe centre), NaN where invalid: runs break where it
        jumps by more than `max_jump` (projector lines) or is NaN.
    along_carriers, along_phase : int
        Box lengths in camera pixels along axis 1 and axis 0.
    bridge : bool
        Along axis 0, runs go on across gaps of up to half a box (`bridge_gaps`).
    frame_ends : bool
        Along axis 1, boxes at the frame's two ends skip the windows clamped there (`_twiced_box`).
    """
    rows = _twiced_box(phasor, coarse, along_carriers, max_jump, frame_ends)
    runs = bridge_gaps(coarse, along_phase // 2, max_jump) if bridge else coarse
    return _segment_box(rows, runs, along_phase // 2, max_jump, axis=1)


def with_positions(phasor: NDArray[np.float32], offset: NDArray[np.float32] | None) -> NDArray[np.float32]:
    """`phasor` ``(3, H, W)`` (carriers along axis 2) with a fourth channel for `recentre`: its
    third channel (the fringes' sum, the weight) times the position along the carriers that
    the pixel's envelopes describe, ``x + offset`` (`Demodulated.offset`, framed likewise).
    Box sums then carry, divided by the summed third channel, the position the summed phasor
    describes.  Unchanged without offsets."""
    if offset is None:
        return phasor
    position = np.arange(phasor.shape[2], dtype=np.float32)[None, :] + offset
    return np.concatenate([phasor, (phasor[2] * position)[None]])


@numba.njit(cache=True, inline="always")
def _slope(summed: NDArray[np.float32], ra: int, xa: int, rb: int, xb: int, min_span: float) -> float:
    """Phase change per pixel of position (channel 3 over channel 2) from summed phasor
    ``(ra, xa)`` to ``(rb, xb)``; NaN if either is empty or their positions lie less than
    `min_span` apart."""
    if summed[2, ra, xa] <= 0 or summed[2, rb, xb] <= 0:
        return np.nan
    span = summed[3, rb, xb] / summed[2, rb, xb] - summed[3, ra, xa] / summed[2, ra, xa]
    if span < min_span:
        return np.nan
    re = summed[0, rb, xb] * summed[0, ra, xa] + summed[1, rb, xb] * summed[1, ra, xa]
    im = summed[1, rb, xb] * summed[0, ra, xa] - summed[0, rb, xb] * summed[1, ra, xa]
    return np.arctan2(im, re) / span


@numba.njit(cache=True, nogil=True)
def _recentre_rows(summed: NDArray[np.float32], coarse: NDArray[np.float32], max_jump: float, reach: int,
                   min_slope: float, frame_ends: bool, also: NDArray[np.float32], turn_also: bool,
                   rows: NDArray[np.intp]) -> None:
    """`recentre` on the given `rows`, in place (and `also` if `turn_also`)."""
    width = coarse.shape[1]
    slope = np.zeros(width)
    for r in rows:
        start = 0
        while start < width:
            if not np.isfinite(coarse[r, start]):
                start += 1
                continue
            end = run_end(coarse[r], start, max_jump)
            for x in range(start, end):  # the phase's slope (radians per pixel) on either side, if they agree
                slope[x] = 0.0
                if summed[2, r, x] <= 0 or abs(summed[3, r, x] / summed[2, r, x] - x) < 0.5:
                    continue  # describes its own pixel: nothing to move
                at_start, at_end = start == 0 and x < 3 * reach, end == width and x >= width - 3 * reach
                if frame_ends and (at_start or at_end) and start + 6 * reach < end:
                    # the frame's end: from the position described to two reaches inward (see `recentre`)
                    inward = int(round(summed[3, r, x] / summed[2, r, x])) + (2 * reach if at_start else -2 * reach)
                    inward = min(max(inward, start), end - 1)
                    one = _slope(summed, r, x, r, inward, reach) if at_start else _slope(summed, r, inward, r, x, reach)
                    slope[x] = one if np.isfinite(one) and abs(one) >= min_slope else 0.0
                    continue
                a, b = max(x - reach, start), min(x + reach, end - 1)
                left, right = _slope(summed, r, a, r, x, 0.25 * reach), _slope(summed, r, x, r, b, 0.25 * reach)
                if np.isfinite(left) and np.isfinite(right) and abs(left - right) <= 0.3 * max(abs(left), abs(right)):
                    if abs(left + right) >= 2 * min_slope:
                        slope[x] = 0.5 * (left + right)
            for x in range(start, end):
                if slope[x] != 0.0:
                    turn = -slope[x] * (summed[3, r, x] / summed[2, r, x] - x)
                    c, s = np.cos(turn), np.sin(turn)
                    re, im = summed[0, r, x], summed[1, r, x]
                    summed[0, r, x], summed[1, r, x] = re * c - im * s, re * s + im * c
                    if turn_also:
                        re, im = also[0, r, x], also[1, r, x]
                        also[0, r, x], also[1, r, x] = re * c - im * s, re * s + im * c
            start = end


def recentre(summed: NDArray[np.float32], coarse: NDArray[np.float32], *, max_jump: float, reach: int,
             min_slope: float, also: NDArray[np.float32] | None = None, frame_ends: bool = True) -> None:
    """Move each summed phasor's phase from the position it describes back to its pixel, in place.

    A pixel's envelopes come from the window the demodulator chose for it, which starts or
    ends at the pixel where that fits better (next to an edge, and where oblique stripes
    cross a centred window: `Demodulated.offset`), and the box sums of `smooth_phasors` are
    clipped to the run: the summed phasor describes the fringe up to half a window away from
    the pixel (its position is channel 3 over channel 2, `with_positions`).  Where the phase
    changes along the carriers (stripes crossing the camera's lines obliquely, as toward a
    sphere's left and right limbs) that is a bias of the slope times the distance.  The slope
    is measured on each side of the pixel: the phase difference between its summed phasor
    and the one `reach` pixels away (within the run: consecutive pixels with a finite
    `coarse` that changes by at most `max_jump`), over the distance between the positions
    they describe (at least a quarter `reach`); where both sides agree within 30 % and their
    mean is at least `min_slope` (radians per pixel), the phasor is turned by minus that mean
    times its position's distance from the pixel.  Else it stays: at a run's end one side is
    missing, so the pixels nearest an edge keep their bias (filling their slope in from the
    nearest measured one bent flat surfaces, where error patches read as slopes: docs/accuracy.md), and
    a slope under `min_slope` is as likely the local error's as the fringe's.  Except at the
    frame's two ends (runs that start at its first pixel or end at its last), which are no
    edge: the surface goes on unseen, and within ``3 reach`` of them the (twiced) boxes
    describe a point up to ``1.5 reach`` inward (`_twiced_box`).  There the slope is the
    phase change from the position described to the box two `reach` inward of it (estimates a
    `reach` long on either side rarely agree within 30 % there), kept if at least `min_slope`.

    Measured on the 5 MP sphere (docs/accuracy.md, "Sub-stripe depth from one frame"): the fitted
    radius 123.86 -> 123.24 mm (122.555 true), median error 1.41 -> 1.34 mm.

    Parameters
    ----------
    summed : (4, H, W) float32 array
        Box-summed phasors with their positions (`with_positions`), carriers along axis 2.
    coarse : (H, W) float32 array
        The line the runs were cut by in `smooth_phasors` (NaN outside every run).
    also : (K, H, W) float32 array, optional
        Other sums of the same phasors, whose channels 0 and 1 (real, imaginary) are turned by
        the same angle per pixel.
    frame_ends : bool
        Measure the slope at the frame's two ends as above; if false, those pixels keep their
        bias like any run's end.
    """
    turn_also = also is not None
    also = also if turn_also else np.zeros((2, 1, 1), np.float32)
    over_rows(lambda rows: _recentre_rows(summed, coarse, max_jump, reach, min_slope, frame_ends, also, turn_also,
                                          rows), summed.shape[1])


@numba.njit(cache=True, nogil=True)
def _recentre_columns(sums: NDArray[np.float32], runs: NDArray[np.float32], max_jump: float, reach: int,
                      columns: NDArray[np.intp], block: int = 64) -> None:
    """`recentre_along_phase` for the given (consecutive) `columns`, in blocks walked row by row."""
    if columns.size == 0:
        return
    height = sums.shape[1]
    start, end = np.empty((height, block), np.intp), np.empty((height, block), np.intp)
    turn = np.zeros((height, block))
    for c0 in range(columns[0], columns[-1] + 1, block):
        n = min(c0 + block, columns[-1] + 1) - c0
        _column_runs(runs, max_jump, c0, n, start, end)
        for y in range(height):  # every turn first: the slopes read the phasors as summed
            for j in range(n):
                c, first = c0 + j, start[y, j]
                turn[y, j] = 0.0
                if first < 0 or sums[2, y, c] <= 0 or abs(sums[3, y, c] / sums[2, y, c] - y) < 0.5:
                    continue
                above = _slope(sums, max(y - reach, first), c, y, c, 0.25 * reach)
                below = _slope(sums, y, c, min(y + reach, end[y, j] - 1), c, 0.25 * reach)
                if np.isfinite(above) and np.isfinite(below):
                    agree = abs(above - below) <= 0.3 * max(abs(above), abs(below))
                    slope = 0.5 * (above + below) if agree else 0.0
                else:
                    slope = above if np.isfinite(above) else (below if np.isfinite(below) else 0.0)
                turn[y, j] = -slope * (sums[3, y, c] / sums[2, y, c] - y)
        for y in range(height):
            for j in range(n):
                if turn[y, j] != 0.0:
                    c = c0 + j
                    co, si = np.cos(turn[y, j]), np.sin(turn[y, j])
                    re, im = sums[0, y, c], sums[1, y, c]
                    sums[0, y, c], sums[1, y, c] = re * co - im * si, re * si + im * co


def recentre_along_phase(sums: NDArray[np.float32], runs: NDArray[np.float32], *, max_jump: float,
                         reach: int) -> None:
    """Move each summed phasor's phase from the row its box describes back to its pixel's row,
    in place (`recentre`'s counterpart along the phase direction).

    Where a run down a column ends (a depth or shadow edge, the projected area's border) the
    box of `smooth_phasors` along the phase direction is clipped to one side: it describes the
    fringe up to half a box away, where the fringe's phase differs by the slope times the
    distance (the projection's own slope along the phase direction, 2 pi per fringe period).
    Measured before this existed on the 5 MP virtual rig's sphere and steps (docs/accuracy.md, "Sub-stripe
    depth from one frame"): the 7 % of pixels within half a box of a run's end carried 45 % of
    the squared error left after the whole-period slips.  The slope is measured as in
    `recentre`, between the pixel's summed phasor and the one `reach` rows away on either side
    within the run, over the distance between the rows they describe; where one side is
    missing (the run ends) the other serves, since along the phase direction the slope is the
    fringe's own, large and steady, not an error patch's.

    Parameters
    ----------
    sums : (4, H, W) float32 array
        Box sums (real, imaginary, weight, weight times the row), phase direction along axis 1.
    runs : (H, W) float32 array
        The line the box sums' runs were cut by (NaN outside every run).
    """
    over_rows(lambda columns: _recentre_columns(sums, runs, max_jump, reach, columns), sums.shape[2])


@numba.njit(cache=True, inline="always")
def _unwrapped(phase: float, reference: float, period: float) -> float:
    """The projector line of wrapped `phase` in the fringe period nearest to line `reference`."""
    order = np.round(((reference + 0.5) * 2 * np.pi / period - phase) / (2 * np.pi))
    return (phase + 2 * np.pi * order) * period / (2 * np.pi) - 0.5


@numba.njit(cache=True, nogil=True)
def _unwrap_rows(summed: NDArray[np.float32], coarse: NDArray[np.float32], period: float, min_modulation: float,
                 max_disagreement: float, rows: NDArray[np.intp], line: NDArray[np.float32], strong: NDArray[np.bool_],
                 sure: NDArray[np.bool_]) -> None:
    """Per pixel of `rows`: the phase of the summed phasor unwrapped against `coarse` (`line`,
    NaN where `coarse` is), modulation at least `min_modulation` (`strong`), and the line within
    `max_disagreement` projector lines of `coarse` as well (`sure`)."""
    for r in rows:
        for x in range(coarse.shape[1]):
            centre = coarse[r, x]
            if not np.isfinite(centre):
                line[r, x], strong[r, x], sure[r, x] = np.nan, False, False
                continue
            re, im = summed[0, r, x], summed[1, r, x]
            value = _unwrapped(np.arctan2(im, re), centre, period)
            line[r, x] = value
            strong[r, x] = np.hypot(re, im) >= min_modulation * max(0.5 * summed[2, r, x], 1e-12)
            sure[r, x] = strong[r, x] and abs(value - centre) <= max_disagreement


@numba.njit(cache=True, nogil=True)
def _rescue_rows(summed: NDArray[np.float32], line: NDArray[np.float32], strong: NDArray[np.bool_],
                 sure: NDArray[np.bool_], reference: NDArray[np.float32], period: float, rescue: bool,
                 fine: NDArray[np.float32], use_fine: bool, stripes: int, lines: int, rows: NDArray[np.intp],
                 out: NDArray[np.float32], stripe: NDArray[np.int16]) -> None:
    """Per pixel of `rows`: the sure line, or a strong pixel's phase unwrapped against
    `reference` if it lands within a quarter period of it (and `rescue`), else NaN; if
    `use_fine`, a kept line is then replaced by the phase of `fine` ``(K, H, W)`` (channels 0
    and 1: real, imaginary) in the fringe period nearest to it; `stripe`: the line's stripe
    (`patterns.stripe_of_line`), -1 for NaN or beyond the projector."""
    for r in rows:
        for x in range(line.shape[1]):
            value = np.float32(np.nan)
            if sure[r, x]:
                value = line[r, x]
            elif rescue and strong[r, x] and np.isfinite(reference[r, x]):
                repaired = _unwrapped(np.arctan2(summed[1, r, x], summed[0, r, x]), reference[r, x], period)
                if abs(repaired - reference[r, x]) <= period / 4:
                    value = repaired
            if use_fine and np.isfinite(value):
                value = _unwrapped(np.arctan2(fine[1, r, x], fine[0, r, x]), value, period)
            out[r, x] = value
            nearest = np.floor(value + 0.5)
            stripe[r, x] = int(np.floor((nearest + 0.5) * stripes / lines)) if 0 <= nearest < lines else -1


def unwrap(phase: NDArray[np.floating], coarse: NDArray[np.floating], spec: PatternSpec) -> NDArray[np.float32]:
    """Projector line from the wrapped fringe phase and the Gray code's line, ``(H, W)`` float32.

    The fringe period chosen is the one whose line lies nearest to `coarse` (the stripe's
    centre), so the result is right whenever `coarse` is within half a period of the truth.
    `refine`'s kernels apply the same formula per pixel (`_unwrapped`; tested equal).

    >>> spec = PatternSpec(phase_carriers=(160, 192, 224))          # period 96 lines
    >>> unwrap(np.array([np.pi / 2]), np.array([130.0]), spec).round(3).tolist()   # 96 + 24
    [119.5]
    """
    period = fringe_phase(np.asarray(coarse, dtype=np.float64), spec) - phase
    order = np.round(period / (2 * np.pi))
    return fringe_line(phase + 2 * np.pi * order, spec).astype(np.float32)


def local_reference(line: NDArray[np.float32], sure: NDArray[np.bool_], coarse: NDArray[np.float32], *,
                    radius_carriers: int, radius_phase: int, max_jump: float,
                    min_share: float = 0.2) -> NDArray[np.float32]:
    """Mean of the `sure` pixels' lines in a box around each pixel, within runs of one surface
    (carriers along axis 1); NaN where under `min_share` of the box is sure.

    The reference against which `refine` unwraps the pixels whose own stripe is in doubt.
    """
    values = np.stack([np.where(sure, line, 0), sure]).astype(np.float32)
    rows = _segment_box(values, coarse, radius_carriers, max_jump)
    del values  # full frames: free each as soon as it is summed
    sums = _segment_box(rows, coarse, radius_phase, max_jump, axis=1)
    del rows
    enough = sums[1] >= min_share * (2 * radius_carriers + 1) * (2 * radius_phase + 1)
    return np.where(enough, sums[0] / np.maximum(sums[1], 1), np.nan).astype(np.float32)


def neighbour_lines(line: NDArray[np.float32], *, radius_carriers: int,
                    radius_phase: int) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """Share of finite pixels, their mean line and its standard deviation (projector lines) in
    a plain box of ``2 r + 1`` pixels along each axis around every pixel (carriers along axis
    1), each ``(H, W)`` float32; mean and deviation NaN where the box holds none.

    The reference of `extend`: unlike `local_reference` it needs no line at the pixel itself.
    """
    finite = np.isfinite(line)
    values = np.stack([finite, np.where(finite, line, 0), np.where(finite, line * line, 0)]).astype(np.float32)
    everywhere = np.zeros(line.shape, np.float32)  # one run per row: a plain box
    rows = _segment_box(values, everywhere, radius_carriers, 0.0)
    del values  # full frames: free each as soon as it is summed
    sums = _segment_box(rows, everywhere, radius_phase, 0.0, axis=1)
    del rows
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = sums[1] / sums[0]
        spread = np.sqrt(np.maximum(sums[2] / sums[0] - mean * mean, 0))
    return (sums[0] / ((2 * radius_carriers + 1) * (2 * radius_phase + 1))).astype(np.float32), mean, spread


@numba.njit(cache=True, nogil=True)
def _window_contrast_rows(dc: NDArray[np.float32], offset: NDArray[np.float32], windows: NDArray[np.intp],
                          rows: NDArray[np.intp], out: NDArray[np.float32]) -> None:
    """`window_contrast` on the given `rows`, into `out`."""
    width = dc.shape[1]
    running = np.zeros(width + 1)
    for r in rows:
        window = min(windows[r], width)
        for x in range(width):
            running[x + 1] = running[x] + dc[r, x]
        for x in range(width):
            start = int(np.floor(x + offset[r, x] - (window - 1) / 2 + 0.5))
            start = min(max(start, 0), width - window)
            mean = (running[start + window] - running[start]) / window
            out[r, x] = dc[r, x] / mean if mean > 0 else np.inf


def window_contrast(dc: NDArray[np.float32], offset: NDArray[np.float32],
                    windows: NDArray[np.intp]) -> NDArray[np.float32]:
    """Each pixel's DC over the mean DC of the pixels its demodulation window covers, ``(H, W)``
    float32 (carriers along axis 1; `Demodulated.dc`, `Demodulated.offset`, and each line's
    window length `Carriers.line_windows`, broadcast to ``(H,)``).

    About 1 where the window lies on the pixel's own surface under the same light, whatever
    the window's placement.  Far from 1 where a window that ends at the pixel reaches across
    into a surface several times brighter or darker: next to a depth edge the demodulator
    takes the window that fits best, and where the pixel's own side is dark (a sphere's limb
    under grazing light beside a bright wall) that is the window on the other surface; its
    envelopes, Gray code and fringe are that surface's, which `refine` cannot tell from the
    pixel's own when the depth edge's jump is close to a whole fringe period (`NEAR_JUMP_CONTRAST`).
    """
    out = np.empty(dc.shape, np.float32)
    windows = np.ascontiguousarray(np.broadcast_to(windows, dc.shape[:1]), dtype=np.intp)
    over_rows(lambda rows: _window_contrast_rows(dc, offset, windows, rows, out), dc.shape[0])
    return out


#: Smallest change of the fringe along the carriers that `recentre` acts on, in projector
#: lines per demodulation window (a slope of 0.1 lines per camera pixel at 1296x972, 0.05 at
#: 5 MP).  On the virtual rig's flat steps, whose true slope is 0, error patches read as up to
#: 10-15 lines per window at 1296x972; toward the sphere's left and right limbs the fringe
#: changes by 4-30 lines per window.
RECENTRE_MIN_CHANGE = 4.0

#: `phase_envelopes` takes the one-sided two-period ramped fits next to edges where the Gray
#: code's border-interpolated line changes by at least this many projector lines over a window
#: along the carriers (the fringe crosses them obliquely there).  Measured on 31 captures
#: (docs/accuracy.md, "Sub-stripe depth from one frame"): with it no capture's RMS rose by more than
#: 0.5 %; without it the checkered planes' rose by 7-8 %, 2 lines gained 0.1-0.6 % more on
#: the spheres for +0.4 % on one checkered plane.
ONE_SIDED_MIN_CHANGE = 4.0
#: The noise variance of a one-sided ramped envelope relative to the one-period fit's: the
#: end of a straight line fitted over two periods (four times its centre's variance, which is
#: half the one-period fit's).
ONE_SIDED_VARIANCE = 2.0

#: `refine` drops the pixels within this fraction of a demodulation window (a square of
#: ``2 r + 1`` pixels, ``r`` at least 1: 6 px at 5 MP, 3 px at 1296x972) of a jump of more than
#: half a fringe period in the kept lines (`near_jumps`): a depth edge, or a patch a whole fringe
#: period off beside one.  Those patches are where a window along the carriers, or a box along
#: the phase direction, described the surface across the edge, and where the edge's own jump is
#: close to a whole period the phase agrees with their wrong stripe.  Measured on the virtual
#: rig (docs/accuracy.md, "Sub-stripe depth from one frame"): RMS error 14-21 % lower on the smooth
#: spheres (5 MP seeds 0 and 7, 1296x972 seeds 1 and 2, an unseen 1920x1440 rig) for 0.2-0.7
#: points of completeness, the steps 3-10 % for 0.5-0.9 points; medians unchanged.  At 1/10
#: the 5 MP sphere's RMS falls further (5.4 -> 5.0 mm) for twice the completeness.
EDGE_MARGIN = 1 / 16

#: `refine` drops, within this fraction of a demodulation window (a square of ``2 r + 1``
#: pixels; 45 px at 5 MP) of a jump of more than half a fringe period between kept pixels, the
#: pixels whose `window_contrast` exceeds `NEAR_JUMP_CONTRAST` or is below its inverse: beside a
#: depth edge a window that reaches onto the other surface describes that surface (the
#: unwrapping cannot tell when the edge's jump is close to a whole period), while an albedo
#: edge on one surface, where the same contrast is harmless, has no jump.  The square bridges
#: the undecoded gap that usually separates such pixels from their own surface's kept ones.
#: Measured on the virtual rig (docs/accuracy.md, "Sub-stripe depth from one frame"): the 5 MP smooth
#: sphere's RMS error 3.7 -> 3.2 mm with the other tests on (its dark limb beside the wall),
#: for 0.3 points of completeness.
NEAR_JUMP_REACH = 0.5
NEAR_JUMP_CONTRAST = 2.0

#: `refine` also drops, within the same reach of such a jump, the runs of kept pixels along the
#: carriers (unbroken by an undecoded pixel or a jump) shorter than this fraction of a window:
#: every window that describes them lies mostly on pixels that could not be decoded or on
#: another surface, like the wall pixels beside a sphere's limb that carry the sphere's line
#: across the limb (at 5 MP an eighth of a window is 11 px).  Measured on the virtual rig
#: (docs/accuracy.md): the spheres' RMS error 2-19 % lower, the steps' 3-12 %, for 0.15-0.6 points of
#: completeness; a quarter of a window costs 1.6 times the completeness for 1.3 times the gain.
SHORT_RUN = 0.125

#: Within that reach, also the pixels of runs shorter than `MID_RUN` of a window whose window
#: contrast exceeds `MID_RUN_CONTRAST` (or is below its inverse): the longer runs of wall
#: pixels past a limb, whose windows lie on the sphere, where neither test alone takes them.
#: Measured on the virtual rig (docs/accuracy.md): the unseen 5 MP seed-13 sphere 5.28 -> 4.65 mm, the
#: other captures 0-1 % lower, for at most 0.09 points of completeness (at 1.25: 4.52 mm and
#: 0-4 %, for up to 0.23 points).
MID_RUN = 0.5
MID_RUN_CONTRAST = 1.5

#: `outliers.shadow_side` along the carriers, on the capture's own pixels (`refine`'s
#: `image`): their light carries the carriers' ripple, so it compares pixels a little farther
#: apart.
SHADOW_SIDE_REACH_CARRIERS = 3

#: `extend` defaults: a pixel the decoding left out joins when at least this share of its box
#: is decoded, their lines spread by at most this many stripes (one surface), and its own
#: phase carriers stand this far above the amplitude noise (sqrt of the summed squared
#: envelopes over `Demodulated.noise`).  Measured on the 1296x972 rig: shadowed pixels next
#: to lit ones reach a median of 3.3, lit pixels the Gray code rejected 6-9, decoded ones 10-12.
EXTEND_SHARE = 0.3
EXTEND_SPREAD = 0.25
EXTEND_SNR = 4.0
#: ... and lies within this many pixels (8-connected steps) of a pixel the first pass kept.
#: Without that limit the joins reached up to tens of pixels into the gaps, and the deeper
#: ones were the worse: on the virtual rig's 5 MP smooth sphere the joined pixels (3.3 % of
#: the lit ones) had 7.7 mm RMS error against 2.3 mm for the others, 3.5 mm next to a kept
#: pixel and 17 mm more than 12 px from one.  One pixel: RMS 0.1-11 % lower on each of 36
#: captures (three cameras, five seeds; 2-4 % on average; smooth 5 MP sphere 2.71 -> 2.48 mm),
#: medians 0-2 % lower, for 0-1.0 points of completeness (0.2-0.4 on average; docs/accuracy.md,
#: "The extension's reach").
EXTEND_REACH = 1

#: `refine` drops, last, the kept pixels within this many pixels (8-connected steps) of a pixel
#: it did not keep (`beside_gaps`).  Whatever made that pixel fail (a window or box reaching
#: across a depth edge or a shadow, a limb's light mixed with the wall's, a Gray code in doubt)
#: reaches its neighbours a little less: measured on the virtual rig's 5 MP sphere (docs/accuracy.md,
#: "Sub-stripe depth from one frame"), the pixels next to a gap are 1.1 % of the points and
#: carry 23 % of the squared error (RMS 14 mm against 1.9 mm for those 40 px or more inside).
#: One ring lowered the RMS error by 2-36 % on 23 captures (three rigs, six seeds) for 0.1-1.7
#: points of completeness at 5 MP, 1.2-1.4 at 1920x1440 and 0.5-3.5 at 1296x972 (with the
#: stretched drive of `patterns.PHASE_DRIVE`, which gives most of that back: RMS 1-38 % lower
#: than neither, -1.4 to +1.0 points); tests that looked for the bad ones among those pixels
#: (a plane fitted to the pixels farther in, the line's slope, only the gaps the phase channel
#: made) did no better for the completeness they cost.
GAP_RING = 1


def refine(decoded: Decoded, demod: Demodulated, carriers: Carriers, spec: PatternSpec, *,
           max_disagreement: float = 0.5, min_modulation: float = 0.5, smooth: bool = True,
           rescue: bool = True, extend: bool = True, unmix: bool = True, average_levels: bool = True,
           recentre_phase: bool = True, dc_weights: bool = False, bridge: bool = True, recentre_rows: bool = True,
           edge_margin: bool = True, near_jump_contrast: float = NEAR_JUMP_CONTRAST,
           short_run: float = SHORT_RUN, mid_run_contrast: float = MID_RUN_CONTRAST, shadow_sides: bool = True,
           ramped_windows: bool = True, gap_ring: int = GAP_RING, frame_ends: bool = True,
           one_sided_windows: bool = True, extend_reach: int = EXTEND_REACH, image: NDArray | None = None,
           border_line: NDArray | None = None, inverse_depth: NDArray | None = None) -> Decoded:
    """Sub-stripe projector lines from the phase channel; `decoded` unchanged without one.

    Each decoded pixel's fringe phase (`channel_levels`, `phasors`, `smooth_phasors`) is
    unwrapped against its stripe's centre.  Where the result lies more than
    `max_disagreement` stripes from that centre the stripe is in doubt (a Gray code off by
    one away from a stripe border, where the period nearest to the wrong centre is a coin
    toss): such a pixel is unwrapped instead against the mean line of the sure pixels around
    it (`local_reference`, a window along the carriers and a quarter fringe period along the
    phase direction), and kept only if it lands within a quarter period of it.

    Parameters
    ----------
    decoded : Decoded
        The Gray code decoding of the same capture.
    demod, carriers : Demodulated, Carriers
        The capture's envelopes and carriers (camera orientation).
    max_disagreement : float
        Stripes between the unwrapped line and its stripe's centre beyond which the stripe is
        in doubt.  Measured on the virtual rig's sphere (1296x972, smooth albedo): of the pixels
        past 0.6 stripes 70 % were more than 5 projector lines wrong, against 4 % below 0.5.
    min_modulation : float
        Drop pixels whose smoothed fringe modulation (1 for a clean fringe) is below this: a
        box that mixes two surfaces' phases, or noise (below 0.5: 70 % more than 5 lines off).
    smooth : bool
        Sum the phasors over the boxes of `smooth_phasors`; if false, each pixel's own phase
        (for the benchmark's record: see the tables of docs/accuracy.md).
    rescue : bool
        Unwrap the pixels whose stripe is in doubt against `local_reference`; if false, drop them.
    extend : bool
        Then unwrap the pixels the Gray code (or these checks) left out against the mean line of
        the kept pixels around them, where those lie on one surface and the pixel's own phase
        carriers are well above the noise (`EXTEND_SHARE`, `EXTEND_SPREAD`, `EXTEND_SNR`); kept
        on the same terms as a rescued pixel.  Needs the window demodulator's noise estimate
        (skipped without it).
    extend_reach : int
        How far (pixels, 8-connected steps) from the first pass's kept pixels `extend` may
        join pixels; 0: as far as the other tests let it (for the benchmark's record).
    unmix : bool
        Fit and take out the projector's carrier products on the phase carriers (`crosstalk`);
        if false, each phase carrier is taken for its fringe alone (for the benchmark's record).
    average_levels : bool
        Fit the levels to envelopes averaged along the phase direction (`level_samples`); if
        false, to single pixels (for the benchmark's record).
    recentre_phase : bool
        Move each summed phasor back to its pixel (`recentre`); if false, leave it where its
        windows and box describe the fringe (for the benchmark's record).
    dc_weights : bool
        Weight each pixel's phasor by its DC in the box sums (`phasors`; for the benchmark's record).
    bridge : bool
        Take each kept pixel's phase from box sums along the phase direction that go on across
        short gaps (`bridge_gaps`), in the fringe period the decisions chose; the decisions
        themselves (modulation, agreement with the stripe, rescue, extension) are made on boxes
        that stop at every undecoded pixel.  Bridged boxes for the decisions as well kept 0.1-0.2
        % more pixels, 10-15 % of them a fringe period off (docs/accuracy.md).  If false, the phase of the
        stopping boxes (for the benchmark's record).
    recentre_rows : bool
        Also move that phase from the row its box describes back to the pixel's
        (`recentre_along_phase`); if false, leave it (for the benchmark's record).
    edge_margin : bool
        Last, drop the pixels within `EDGE_MARGIN` of a window of a jump of more than half a
        fringe period between kept pixels (`near_jumps`); if false, keep them (for the
        benchmark's record).
    near_jump_contrast : float
        Then drop the pixels within `NEAR_JUMP_REACH` of a window of such a jump whose
        `window_contrast` exceeds this or is below its inverse (`NEAR_JUMP_CONTRAST`); ``inf``
        keeps them (for the benchmark's record).  Needs the window demodulator's offsets.
    short_run : float
        With it, drop the runs of kept pixels along the carriers shorter than this fraction of a
        window within that reach of a jump (`SHORT_RUN`, `run_lengths`); 0 keeps them (for the
        benchmark's record).
    mid_run_contrast : float
        With them, the runs shorter than `MID_RUN` of a window whose pixels' window contrast
        exceeds this or is below its inverse (`MID_RUN_CONTRAST`); ``inf`` keeps them (for the
        benchmark's record).  Needs the window demodulator's offsets.
    shadow_sides : bool
        Last, drop the pixels at the ends of runs down the phase direction whose DC puts their
        centre on the shadow's side of the edge (`sliscan.outliers.shadow_side`), and with
        `image` those at the ends of runs along the carriers whose own light does; if false,
        keep them (for the benchmark's record).
    ramped_windows : bool
        Take the phase carriers' envelopes from the demodulator's two-period windows with a ramp
        per carrier where those lie on one run of the Gray code's line (`phase_envelopes`); if
        false, from its one-period windows everywhere (for the benchmark's record).
    one_sided_windows : bool
        With them, next to edges where the fringe crosses the carriers obliquely (`border_line`
        changes by `ONE_SIDED_MIN_CHANGE` over a window), from the two-period windows with a
        ramp per carrier that start or end at the pixel (`Demodulated.sided`); if false, or
        without `border_line`, from the one-period windows there (for the benchmark's record).
    gap_ring : int
        Last, drop the kept pixels within this many pixels of one not kept (`GAP_RING`,
        `beside_gaps`); 0 keeps them (for the benchmark's record).
    frame_ends : bool
        The boxes at the frame's two ends skip the windows the demodulator clamped there, and
        their slope is measured inward (`_twiced_box`, `recentre`); if false, they are clipped
        like any run's end (for the benchmark's record).
    image : (H, W) array, optional
        The capture (camera orientation), for the test along the carriers.
    border_line : (H, W) array, optional
        The Gray code's lines between located stripe borders (`sliscan.staircase.
        interpolate_lines`, camera orientation), for `one_sided_windows`.
    inverse_depth : (H, W) array, optional
        Each pixel's inverse depth along the projector's axis (1/mm, camera orientation; NaN
        where unknown), from the Gray code's lines: the phase carriers' gains are fitted as
        quadratics in it (`channel_levels`) and each pixel's envelopes read with the gains of
        its depth (`relevelled`): a projector focused at one depth blurs the rest of the scene,
        its finest carriers most (docs/accuracy.md, "A lens's depth of field").  Without it
        one gain per carrier everywhere.

    Returns
    -------
    Decoded
        With `proj_map` the fringe's projector line, `stripe` its stripe, `valid` less the
        dropped pixels.
    """
    n = len(spec.phase_carriers)
    if n == 0:
        return decoded
    frame = lambda a: np.ascontiguousarray(along_carriers(a, spec))  # noqa: E731  (a transpose for columns)
    stripe_lines = spec.phase_lines / spec.stripes
    fringe_cam = spec.fringe_period / carriers.scale  # camera pixels per fringe period (about)
    max_jump = 1.5 * stripe_lines
    along_phase, radius_phase = max(1, int(round(fringe_cam / 8))) | 1, max(1, int(round(fringe_cam / 4)))
    min_slope = RECENTRE_MIN_CHANGE / carriers.window * 2 * np.pi / spec.fringe_period  # radians per camera pixel
    coarse = frame(np.where(decoded.valid, decoded.proj_map, np.float32(np.nan)))
    oblique = None
    if border_line is not None and one_sided_windows:
        with np.errstate(invalid="ignore"):  # NaN compares false
            change = np.abs(slope_along_carriers(frame(border_line), carriers.window)) * carriers.window
            oblique = change >= ONE_SIDED_MIN_CHANGE
    envelopes, variance, offset = phase_envelopes(demod, coarse, spec, carriers, max_jump=max_jump,
                                                  ramped=ramped_windows, oblique=oblique)
    unbiased = debiased(envelopes, variance)
    del variance
    step, length = sample_step(decoded.valid, LEVEL_SAMPLES), along_phase if average_levels else 1
    sample, usable, sample_stripes = level_samples(demod, decoded.valid, decoded.stripe, spec, step, length, unbiased)
    sample_depth = None if inverse_depth is None else np.mean(
        sample_stretches(inverse_depth, spec=spec, step=step, length=length), axis=0)
    levels = channel_levels(sample, usable, spec, stripes=sample_stripes if unmix else None,
                            inverse_depth=sample_depth)
    if inverse_depth is not None:
        unbiased, envelopes = relevelled([unbiased, envelopes], demod.dc, levels, inverse_depth)
    phasor = phasors(demod, decoded.valid, levels, spec, decoded.stripe, weighted=dc_weights, envelopes=unbiased,
                     totals=envelopes)
    phasor = np.stack([frame(p) for p in phasor]) if spec.orientation != "rows" else phasor
    offset = None if offset is None or not recentre_phase else frame(offset)
    phasor = with_positions(phasor, offset)
    # the kept pixels' phase: boxes across the Gray code's gaps (`bridge_gaps`), moved back to
    # their pixel's row (`recentre_along_phase`); the decisions use the plain boxes
    use_fine = smooth and (bridge or recentre_rows)
    fine, runs = np.zeros((4, 1, 1), np.float32), coarse
    if smooth:
        rows = _twiced_box(phasor, coarse, carriers.window, max_jump, frame_ends)
        if use_fine:
            runs = bridge_gaps(coarse, along_phase // 2, max_jump) if bridge else coarse
            fine = np.empty((4, *coarse.shape), np.float32)
            fine[:3] = rows[:3]
            np.multiply(rows[2], np.arange(coarse.shape[0], dtype=np.float32)[:, None], out=fine[3])
            fine = _segment_box(fine, runs, along_phase // 2, max_jump, axis=1)
        summed = _segment_box(rows, coarse, along_phase // 2, max_jump, axis=1)
        del rows
    else:
        summed = phasor.copy()
    if offset is not None:
        recentre(summed, coarse, max_jump=max_jump, reach=carriers.window // 2, min_slope=min_slope,
                 also=fine if use_fine else None, frame_ends=frame_ends)
    if use_fine and recentre_rows:
        recentre_along_phase(fine, runs, max_jump=max_jump, reach=along_phase)
    del runs
    shape = coarse.shape
    line, strong, sure = np.empty(shape, np.float32), np.empty(shape, bool), np.empty(shape, bool)
    period = float(spec.fringe_period)
    over_rows(lambda rows: _unwrap_rows(summed, coarse, period, min_modulation, max_disagreement * stripe_lines,
                                        rows, line, strong, sure), shape[0])
    reference = local_reference(line, sure, coarse, radius_carriers=carriers.window, radius_phase=radius_phase,
                                max_jump=max_jump)
    out, stripe = np.empty(shape, np.float32), np.empty(shape, np.int16)
    over_rows(lambda rows: _rescue_rows(summed, line, strong, sure, reference, period, rescue, fine, use_fine,
                                        spec.stripes, spec.phase_lines, rows, out, stripe), shape[0])
    del fine
    if extend and demod.noise is not None:
        del reference, summed, coarse  # the first pass's, no longer needed: memory for the second
        kept = np.isfinite(out)
        share, mean, spread = neighbour_lines(out, radius_carriers=carriers.window // 2, radius_phase=along_phase)
        snr = np.sqrt(np.sum(np.square(demod.amplitude[spec.bits:spec.bits + n]), axis=0)) / np.maximum(demod.noise, 1e-12)
        joins = (~kept & (share >= EXTEND_SHARE) & (spread <= EXTEND_SPREAD * stripe_lines)
                 & frame(snr >= EXTEND_SNR))
        if extend_reach > 0:
            joins &= within(kept, extend_reach)
        del share, spread, snr
        new = frame(joins) & ~decoded.valid  # the others have their phasors already
        stripes = np.full(new.shape, -1, np.int16)
        stripes[new] = stripe_of_line(frame(mean)[new], spec)
        extra = phasors(demod, new, levels, spec, stripes, weighted=dc_weights, envelopes=unbiased, totals=envelopes)
        extra = np.stack([frame(p) for p in extra]) if spec.orientation != "rows" else extra
        phasor += with_positions(extra, offset)
        del extra
        around = np.where(kept, out, np.where(joins, mean, np.float32(np.nan))).astype(np.float32)
        summed = (smooth_phasors(phasor, around, along_carriers=carriers.window, along_phase=along_phase,
                                 max_jump=max_jump, frame_ends=frame_ends) if smooth else phasor.copy())
        if offset is not None:
            recentre(summed, around, max_jump=max_jump, reach=carriers.window // 2, min_slope=min_slope,
                     frame_ends=frame_ends)
        over_rows(lambda rows: _unwrap_rows(summed, around, period, min_modulation, 0.0, rows, line, strong, sure),
                  shape[0])
        previous, candidates = out.copy(), strong & joins
        reference = np.where(joins, mean, np.float32(np.nan))
        over_rows(lambda rows: _rescue_rows(summed, previous, candidates, kept, reference, period, True,
                                            np.zeros((2, 1, 1), np.float32), False, spec.stripes, spec.phase_lines,
                                            rows, out, stripe), shape[0])
    contrast = (window_contrast(frame(demod.dc), frame(demod.offset), carriers.line_windows())
                if demod.offset is not None else None)

    def beyond(limit: float) -> NDArray[np.bool_] | None:
        """Where the window contrast exceeds `limit` or is below its inverse (None: no test)."""
        if contrast is None or not np.isfinite(limit):
            return None
        return (contrast > limit) | (contrast < 1 / limit)

    if edge_margin:
        near = near_jumps(out, radius=max(1, int(round(EDGE_MARGIN * carriers.window))), jump=0.5 * period)
        out[near], stripe[near] = np.nan, -1
    across, mid_across = beyond(near_jump_contrast), beyond(mid_run_contrast)
    if across is not None or mid_across is not None or short_run > 0:
        drop = np.zeros(shape, bool) if across is None else across
        if short_run > 0 or mid_across is not None:
            runs = run_lengths(out, jump=0.5 * period)
            drop |= runs < short_run * carriers.window
            if mid_across is not None:
                drop |= (runs < MID_RUN * carriers.window) & mid_across
            del runs
        drop &= near_jumps(out, radius=max(1, int(round(NEAR_JUMP_REACH * carriers.window))), jump=0.5 * period)
        out[drop], stripe[drop] = np.nan, -1
    if shadow_sides:
        dark = shadow_side(out, frame(demod.dc), jump=0.5 * period)
        if image is not None:
            dark |= shadow_side(out, frame(np.asarray(image, dtype=np.float32)), jump=0.5 * period, axis=1,
                                reach=SHADOW_SIDE_REACH_CARRIERS)
        out[dark], stripe[dark] = np.nan, -1
    if gap_ring > 0:
        ring = beside_gaps(np.isfinite(out), gap_ring)
        out[ring], stripe[ring] = np.nan, -1
    out, stripe = frame(out), frame(stripe)
    return replace(decoded, proj_map=out, stripe=stripe, valid=np.isfinite(out))


def within(mask: NDArray[np.bool_], steps: int) -> NDArray[np.bool_]:
    """The pixels at most `steps` 8-connected steps from a pixel of `mask` ``(H, W)``, the
    mask's own included (a dilation by a square of side ``2 steps + 1``).

    >>> mask = np.zeros((5, 5), bool); mask[2, 2] = True
    >>> int(within(mask, 1).sum()), bool(within(mask, 2).all())
    (9, True)
    """
    square = np.ones((2 * steps + 1, 2 * steps + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), square).astype(bool)


def beside_gaps(kept: NDArray[np.bool_], rings: int) -> NDArray[np.bool_]:
    """The kept pixels within `rings` pixels (8-connected steps) of a pixel that is not kept.

    The image's own border is not a gap.

    >>> kept = np.ones((5, 7), bool); kept[2, 3] = False
    >>> int(beside_gaps(kept, 1).sum()), int(beside_gaps(kept, 2).sum())
    (8, 24)
    >>> bool(beside_gaps(np.ones((3, 3), bool), 1).any())
    False
    """
    return kept & within(~kept, rings)


def phase_envelopes(demod: Demodulated, coarse: NDArray[np.float32], spec: PatternSpec, carriers: Carriers, *,
                    max_jump: float, ramped: bool = True, oblique: NDArray[np.bool_] | None = None
                    ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None, NDArray[np.float32] | None]:
    """The phase carriers' envelopes ``(N, H, W)``, the noise variance of each of their two
    components ``(H, W)`` (None if `demod` has no noise) and the window offsets ``(H, W)``
    (camera orientation) that `refine` decodes: `Demodulated.ramped` where its window of two
    spacing periods lies on one run of `coarse` (the Gray code's line, carriers along axis 1;
    runs as in `run_lengths` with `max_jump`); within half that window of an edge (a run's end
    that is not the frame's), where the pixel's chosen one-period window lies on the run's
    side and `oblique` ``(H, W)`` (carriers along axis 1, as `coarse`), `Demodulated.sided`
    where its two periods lie on the run; the one-period fit's elsewhere (everywhere if not
    `ramped`).

    Where the fringe crosses the carriers' lines obliquely (a surface turned about the
    phase direction: a sphere's left and right sides), each phase carrier's envelope changes
    within the window, and a one-period fit, which takes it for constant, leaks that change
    into the neighbouring carriers' fits: on a plane turned 60 degrees about the vertical
    (0.3 projector lines per camera pixel) the line came out 1.9 lines RMS off on a noise-free
    render (docs/accuracy.md, "Sub-stripe depth from one frame").  The ramped fit takes the change in, and
    its envelopes describe the pixel itself (offset 0).  Next to an edge a centred longer
    window would reach across; the one on the run's side, evaluated at its end, takes the
    change in there too (offset 0), where the fringe does change (`oblique`: on flat fringes
    its end value only adds noise, and a longer window more albedo edges; without `oblique`
    the one-period windows stay next to edges).  The variance is the one-period fit's
    (`Demodulated.noise` squared); over the ramped window, `RAMPED_PERIODS` times as long,
    that divided by `RAMPED_PERIODS` at its centre (its extra ramps barely widen it there), and
    `ONE_SIDED_VARIANCE` times it at its end (a straight line fitted over a window is four times
    as uncertain at its ends as at its centre)."""
    n = len(spec.phase_carriers)
    own = demod.amplitude[spec.bits:spec.bits + n]
    variance = None if demod.noise is None else np.square(demod.noise)
    if demod.ramped is None or not ramped:
        return own, variance, demod.offset
    frame = lambda a: along_carriers(a, spec)  # noqa: E731
    length = int(round(np.max(carriers.line_windows()) * RAMPED_PERIODS))
    reach = length // 2
    first, end = run_bounds(coarse, jump=max_jump)
    inner = frame(inner_pixels(first, end, reach)) & np.all(np.isfinite(demod.ramped), axis=0)
    envelopes = np.where(inner[None], demod.ramped, own)
    sided = np.zeros(inner.shape, bool)
    if oblique is not None and demod.sided is not None and demod.offset is not None:
        x = np.arange(coarse.shape[1], dtype=np.int32)[None, :]
        chosen = frame(demod.offset)
        after = (chosen > 0.5) & (first > 0) & (x - first < reach) & (x + length <= end)  # after an edge
        before = (chosen < -0.5) & (end < coarse.shape[1]) & (end - 1 - x < reach) & (x - length + 1 >= first)
        sided = frame((after | before) & oblique) & ~inner & np.all(np.isfinite(demod.sided), axis=0)
        envelopes = np.where(sided[None], demod.sided, envelopes)
    if variance is not None:
        variance = np.where(inner, variance / np.float32(RAMPED_PERIODS),
                            np.where(sided, variance * np.float32(ONE_SIDED_VARIANCE), variance))
    offset = None if demod.offset is None else np.where(inner | sided, np.float32(0), demod.offset)
    return envelopes, variance, offset


def debiased(envelopes: NDArray[np.float32], variance: NDArray[np.float32] | None) -> NDArray[np.float32]:
    """Envelopes less the bias their noise gives them: ``sqrt(max(E^2 - 2 var, 0))``.

    An envelope is the magnitude of a fitted complex amplitude whose two components each carry
    noise of variance `var` ``(H, W)`` (image units squared, like ``envelopes ** 2``, ``(N, H,
    W)``), so its square is ``A^2 + 2 var`` on average: a weak carrier reads high (a Rician
    bias), most where the fringe puts it near zero, which pulls the fringe's phase toward the
    others (`refine` takes the fringe's phase and levels from these, its modulation tests from
    the envelopes as they are).  With the phase carriers' envelopes a median 4-5 noise
    deviations high on the virtual rig's 1296x972 spheres, this lowered the phase channel's RMS
    error on 26 of 29 captures, by up to 12 % (docs/accuracy.md, "Sub-stripe depth from one frame").
    None: returned as they are.
    """
    if variance is None:
        return envelopes
    return np.sqrt(np.maximum(np.square(envelopes) - 2 * variance[None], 0)).astype(np.float32, copy=False)


def near_jumps(line: NDArray[np.float32], *, radius: int, jump: float) -> NDArray[np.bool_]:
    """The finite pixels of `line` ``(H, W)`` with a finite pixel within `radius` pixels (a
    square of side ``2 radius + 1``) whose line differs from theirs by more than `jump`, ``(H, W)``
    bool.  A dilation and an erosion by a square (OpenCV's, about 15 ms each at 5 MP; scipy.ndimage's
    running extrema took 200).

    >>> line = np.full((5, 9), 10.0, np.float32)
    >>> line[:, 6:] = 90.0                       # an edge between columns 5 and 6
    >>> line[0, 0] = np.nan
    >>> near_jumps(line, radius=1, jump=40.0)[2].astype(int)
    array([0, 0, 0, 0, 0, 1, 1, 0, 0])
    """
    finite = np.isfinite(line)
    square = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    def filled(value: float) -> NDArray[np.float32]:
        return np.where(finite, line, np.float32(value)).astype(np.float32, copy=False)

    with np.errstate(invalid="ignore"):  # one filled copy at a time
        near = cv2.dilate(filled(-np.inf), square) - line > jump
        near |= line - cv2.erode(filled(np.inf), square) > jump
    return near & finite
