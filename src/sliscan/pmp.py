"""Phase measuring profilometry: N-step phase shifting at one or more frequencies (thesis 2.6).

Every frequency `f` (cycles per projector extent `L` along the coded direction: H for rows, W
for columns) is projected as `N` phase-shifted fringe images (eq. 2.1)::

    I_n(y_p) = A_p + B_p cos(2 pi f y_p / L - 2 pi n / N),        n = 0 .. N-1

with `y_p` the projector line (pixel centres at integers).  The camera sees
``I_n = A + B cos(phi - 2 pi n / N)`` (eq. 2.2), so for any ``N >= 3`` (eq. 2.3 generalised)::

    phi = atan2(sum_n I_n sin(2 pi n / N), sum_n I_n cos(2 pi n / N))
    B = (2 / N) |sum_n I_n exp(2 pi i n / N)|,        A = mean_n I_n

and ``y_p = phi L / (2 pi f)`` (eq. 2.4) once `phi` is unwrapped.  Unwrapping is temporal and
hierarchical (the Hassebrook lab's multi-frequency PMP): the unit frequency ``f = 1`` spans the
projector once and is unambiguous; each next frequency takes its fringe order from the previous
level's coordinate, ``k = round(y_prev f / L - phi / 2 pi)``.  ``(1, f)`` is the dual-frequency
case; a heterodyne pair ``(f, f + 1)`` gives the unit phase as the beat of its two phases.

A pixel is reliable where every frequency's modulation `B` stands clear of the camera noise
(estimated from the fit residuals, see `noise_level`) and where every unwrapping step is
unambiguous: the distance of ``y_prev f / L - phi / 2 pi`` from the nearest integer stays below
`max_ambiguity` (0.5 would be a coin toss).

Frame order: for each coded direction (columns first for ``"both"``), each frequency in the
order given, the steps ``n = 0 .. N-1``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
import scipy.stats
from numpy.typing import NDArray

from sliscan._threads import over_rows
from sliscan._validate import to_uint8
from sliscan.patterns import precorrect
from sliscan.types import PatternSpec

#: Noise floor (in [0, 1] units) of the noise estimate: the quantisation noise of an 8-bit camera,
#: also the estimate when the frames leave no residual degrees of freedom (3 steps, 1 frequency).
QUANTISATION_NOISE = 1.0 / (255.0 * math.sqrt(12.0))


@dataclass(frozen=True, eq=False)
class ProjectorMap:
    """One projector coordinate decoded per camera pixel from a frame sequence.

    Gray code decoding returns the subclass `sliscan.graycode.GrayCodeMap`, whose `block` adds
    the resolution reached per pixel (width in projector lines of the block of lines its code
    identifies: more than ``code_width`` where the finest bits were dropped).

    Attributes
    ----------
    coord : (H, W) float32 array
        Projector line (`xp` for columns, `yp` for rows) in projector pixels, pixel centres at
        integers; NaN where not valid.
    valid : (H, W) bool array
    index : (H, W) int32 array
        Fringe order of the finest frequency (PMP, Gray code with phase) or Gray code index
        (plain Gray code: the block's first code); -1 where not valid.
    confidence : (H, W) float32 array
        In [0, 1]: the fringe visibility ``B / A`` (PMP) or the weakest decided bit's contrast
        over ``white - black`` (Gray code).
    brightness : (H, W) float32 array
        The camera's image under uniform light: the DC `A` (PMP) or the white frame (Gray code).
    """

    coord: NDArray[np.float32]
    valid: NDArray[np.bool_]
    index: NDArray[np.int32]
    confidence: NDArray[np.float32]
    brightness: NDArray[np.float32]


@dataclass(frozen=True, eq=False)
class Fringes:
    """The N-step fit of one frequency per camera pixel (eq. 2.2); all ``(H, W)`` float32.

    Attributes
    ----------
    cycles : wrapped phase ``phi / 2 pi`` in [0, 1] (1 only by float32 rounding of 0)
    modulation : `B`, in image units
    dc : `A`, in image units
    residual : sum over the N frames of the squared misfit of the fitted cosine
    """

    cycles: NDArray[np.float32]
    modulation: NDArray[np.float32]
    dc: NDArray[np.float32]
    residual: NDArray[np.float32]


# --------------------------------------------------------------------------------------------
# Patterns
# --------------------------------------------------------------------------------------------


def fringe_profile(lines: int, frequency: float, step: int, steps: int, a_p: float, b_p: float) -> NDArray[np.float64]:
    """Eq. 2.1 along the coded direction, as linear light: ``(lines,)`` float64.

    >>> fringe_profile(4, 1, 0, 4, 0.5, 0.5).round(6).tolist()
    [1.0, 0.5, 0.0, 0.5]
    """
    y = np.arange(lines, dtype=np.float64)
    return a_p + b_p * np.cos(2 * np.pi * frequency * y / lines - 2 * np.pi * step / steps)


def line_image(profile: NDArray, direction: str, projector_size: tuple[int, int]) -> NDArray[np.float32]:
    """A projector image ``(H_p, W_p)`` float32 constant across `direction`'s lines: `profile`
    (one value per line) runs down the rows (``"rows"``) or along the columns (``"columns"``)."""
    w, h = projector_size
    profile = np.asarray(profile, dtype=np.float32)
    shaped = profile[:, None] if direction == "rows" else profile[None, :]
    return np.ascontiguousarray(np.broadcast_to(shaped, (h, w)))


def quantised_drive(linear: NDArray[np.floating], spec: PatternSpec) -> NDArray[np.float32]:
    """Projector drive of wanted linear light: pre-corrected (`patterns.precorrect`) and
    quantised to 8 bits, as float32 on the 1/255 grid (like `patterns.render_pattern`)."""
    return (to_uint8(precorrect(linear, spec)).astype(np.float32) / np.float32(255)).astype(np.float32)


def fringe_frames(spec: PatternSpec, direction: str, frequency: float) -> list[NDArray[np.float32]]:
    """The `spec.steps` fringe images of one frequency along `direction`, step 0 first."""
    lines = spec.lines(direction)
    return [line_image(quantised_drive(fringe_profile(lines, frequency, n, spec.steps, spec.a_p, spec.b_p), spec),
                       direction, spec.projector_size) for n in range(spec.steps)]


def pattern_frames(spec: PatternSpec) -> NDArray[np.float32]:
    """Every image of a ``pmp`` spec in projection order: ``(frame_count, H_p, W_p)`` float32."""
    return np.stack([frame for d in spec.directions for f in spec.frequencies for frame in fringe_frames(spec, d, f)])


# --------------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------------


def fit_fringes(frames: NDArray[np.float32]) -> Fringes:
    """Wrapped phase, modulation and DC of N phase-shifted frames (eq. 2.3 for any N >= 3).

    Parameters
    ----------
    frames : (N, H, W) float32 array
        Step ``n`` shifted by ``2 pi n / N``, step 0 first.

    Examples
    --------
    >>> y = np.arange(8.0)
    >>> frames = np.stack([0.4 + 0.2 * np.cos(2 * np.pi * y / 8 - 2 * np.pi * n / 4) for n in range(4)])
    >>> fit = fit_fringes(frames[:, None, :].astype(np.float32))
    >>> (fit.cycles * 8).round(4).tolist(), round(float(fit.modulation.mean()), 4), round(float(fit.dc.mean()), 4)
    ([[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]], 0.2, 0.4)
    """
    steps = frames.shape[0]
    delta = 2 * np.pi * np.arange(steps) / steps
    sin_sum = np.tensordot(np.sin(delta).astype(np.float32), frames, axes=1)
    cos_sum = np.tensordot(np.cos(delta).astype(np.float32), frames, axes=1)
    dc = frames.mean(axis=0, dtype=np.float32)
    scale = np.float32(2.0 / steps)
    fitted = dc + scale * (np.cos(delta).astype(np.float32)[:, None, None] * cos_sum
                           + np.sin(delta).astype(np.float32)[:, None, None] * sin_sum)
    residual = np.sum((frames - fitted) ** 2, axis=0, dtype=np.float32)
    cycles = np.arctan2(sin_sum, cos_sum) / np.float32(2 * np.pi)
    cycles += cycles < 0
    return Fringes(cycles=cycles.astype(np.float32), modulation=scale * np.hypot(sin_sum, cos_sum), dc=dc,
                   residual=residual)


def noise_level(fits: Sequence[Fringes], steps: int) -> float:
    """Camera noise (standard deviation per frame, image units) estimated from the fits.

    Two estimates, each pooled per pixel and taken as the median over the image scaled by the
    chi-square median (robust to the pixels where the model fails: edges, saturation): the
    residuals of the N-step fits (``N - 3`` degrees of freedom per frequency) and the spread of
    the DC between frequencies (one less than their number).  An uncorrected projector gamma
    inflates each by a different harmonic (the fit residual by the 2nd, the DC by the N-th), so
    the smaller is taken; never below `QUANTISATION_NOISE`, which is also the answer when the
    frames leave no degree of freedom (3 steps at one frequency).
    """
    dc = np.stack([fit.dc for fit in fits])
    return pooled_noise(np.sum([fit.residual for fit in fits], axis=0),
                        steps * np.sum((dc - dc.mean(axis=0)) ** 2, axis=0), len(fits), steps)


def pooled_noise(residual: NDArray[np.floating], spread: NDArray[np.floating], frequencies: int, steps: int) -> float:
    """`noise_level` from its two per-pixel maps (any shape): `residual`, the fits' squared
    misfits summed over the frequencies, and `spread`, ``steps`` times the squared deviations of
    each frequency's DC from their mean, summed."""
    variances = []
    if steps > 3:
        variances.append(float(np.median(residual)) / scipy.stats.chi2.ppf(0.5, frequencies * (steps - 3)))
    if frequencies > 1:
        variances.append(float(np.median(spread)) / scipy.stats.chi2.ppf(0.5, frequencies - 1))
    return max(math.sqrt(min(variances)), QUANTISATION_NOISE) if variances else QUANTISATION_NOISE


def unwrap_step(coarse: NDArray[np.float32], cycles: NDArray[np.float32],
                period: float) -> tuple[NDArray[np.float32], NDArray[np.int32], NDArray[np.float32]]:
    """Unwrap a wrapped phase of fringe `period` (projector lines) with a coarse coordinate.

    Parameters
    ----------
    coarse : (H, W) float32 array
        Coordinate (projector lines) from a coarser level; its error must stay under half a period.
    cycles : (H, W) float32 array
        Wrapped phase over 2 pi of the fringes, whose phase is ``2 pi y / period``.

    Returns
    -------
    coord : (H, W) float32
        ``(cycles + order) * period``.
    order : (H, W) int32
        Fringe order ``round(coarse / period - cycles)``.
    distance : (H, W) float32
        ``coarse / period - cycles - order`` in [-0.5, 0.5]: 0 when both levels agree, +-0.5
        when the order is a coin toss.

    >>> coord, order, d = unwrap_step(np.float32([[37.0]]), np.float32([[0.25]]), 16.0)
    >>> float(coord[0, 0]), int(order[0, 0]), float(d[0, 0].round(4))
    (36.0, 2, 0.0625)
    """
    target = coarse / np.float32(period) - cycles
    order = np.rint(target)
    return ((cycles + order) * np.float32(period)).astype(np.float32), order.astype(np.int32), \
        (target - order).astype(np.float32)


def _direction_frames(frames: NDArray[np.float32], spec: PatternSpec, direction: str) -> NDArray[np.float32]:
    """The frames of one direction as ``(frequencies, steps, H, W)``."""
    block = len(spec.frequencies) * spec.steps
    start = spec.directions.index(direction) * block
    return frames[start:start + block].reshape(len(spec.frequencies), spec.steps, *frames.shape[1:])


def fringe_fits(frames: NDArray[np.float32], spec: PatternSpec, direction: str) -> list[Fringes]:
    """The N-step fit (`fit_fringes`) of every frequency of one direction, coarsest first.

    Parameters
    ----------
    frames : (frame_count, H, W) float32 array
        The whole capture in the spec's order.
    """
    return [fit_fringes(level) for level in _direction_frames(frames, spec, direction)]


def modulation_threshold(sigma: float, steps: int, min_snr: float) -> float:
    """Smallest reliable modulation: `min_snr` times the spread ``sigma sqrt(2 / N)`` of `B`
    on pure noise (Rayleigh), so noise alone passes with probability ``exp(-min_snr**2 / 2)``
    and the phase noise at the threshold is about ``1 / min_snr`` radians."""
    return min_snr * sigma * math.sqrt(2.0 / steps)


#: `decode_pmp` estimates the noise on every `NOISE_STRIDE`-th pixel along both axes (a median
#: of 1/16 of the image; the median of the whole one cost a third of the decoding's time).
NOISE_STRIDE = 4


@numba.njit(cache=True, nogil=True, inline="always")
def _atan2_turns(y: float, x: float) -> float:
    """``atan2(y, x) / 2 pi`` wrapped to [0, 1), from a degree-11 odd minimax polynomial of
    atan on [0, 1] (error under 3e-7 turns, 2e-6 rad) and the octant's symmetries.  Plain
    arithmetic, so the row loop vectorises (``math.atan2`` is a library call per pixel)."""
    ax, ay = abs(x), abs(y)
    big, small = max(ax, ay), min(ax, ay)
    t = small / big if big > 0 else 0.0
    t2 = t * t
    angle = t * (0.99997726 + t2 * (-0.33262347 + t2 * (0.19354346 + t2 * (-0.11643287 + t2 * (0.05265332
                                                                                         - t2 * 0.01172120)))))
    angle = 0.5 * math.pi - angle if ay > ax else angle
    angle = math.pi - angle if x < 0 else angle
    turns = angle / (2 * math.pi)
    return 1.0 - turns if y < 0 and turns > 0 else turns


@numba.njit(cache=True, nogil=True)
def _pmp_rows(frames: NDArray, cos_step: NDArray[np.float64], sin_step: NDArray[np.float64],
              frequencies: NDArray[np.float64], lines: int, rows: NDArray[np.intp], coord: NDArray[np.float32],
              order: NDArray[np.int32], ambiguity: NDArray[np.float32], modulation: NDArray[np.float32],
              visibility: NDArray[np.float32], brightness: NDArray[np.float32], residual: NDArray[np.float32],
              spread: NDArray[np.float32]) -> None:
    """Every frequency's N-step fit (`fit_fringes`) and the hierarchical unwrapping (the unit
    frequency's phase, or a heterodyne pair's beat, placed on the projector's extent, then
    `unwrap_step` per frequency) of the given `rows`, so the frames are read once.  `frames`
    ``(F N, H, W)`` in the spec's order; outputs ``(H, W)``: the unwrapped coordinate and finest
    fringe order, the largest unwrapping distance, the smallest modulation, the finest
    frequency's visibility ``B / A`` clipped to [0, 1], the mean DC, and the two maps of
    `pooled_noise` (the fit's residual in closed form: the frames' energy less the fitted one,
    ``N A^2 + (2 / N) |sum_n I_n e^{i d_n}|^2``).  Each row is summed frame by frame along x
    first, then finished quantity by quantity (loops along x the compiler vectorises)."""
    n_freq, steps = frequencies.size, cos_step.size
    width = frames.shape[2]
    c, s, sums, turns = np.empty((n_freq, width)), np.empty((n_freq, width)), np.empty((n_freq, width)), \
        np.empty((n_freq, width))
    scratch = np.empty((8, width))  # the row's per-pixel quantities
    energy, weakest, mean_dc, fitted, deviation, line, fringe, worst = scratch
    for r in rows:
        c[:], s[:], sums[:], energy[:] = 0.0, 0.0, 0.0, 0.0
        for f in range(n_freq):
            for n in range(steps):
                plane = frames[f * steps + n, r]
                for x in range(width):
                    value = float(plane[x])
                    c[f, x] += cos_step[n] * value
                    s[f, x] += sin_step[n] * value
                    sums[f, x] += value
                    energy[x] += value * value
        weakest[:], mean_dc[:], fitted[:], deviation[:], worst[:] = np.inf, 0.0, 0.0, 0.0, 0.0
        for f in range(n_freq):
            for x in range(width):
                a = sums[f, x] / steps
                power = c[f, x] * c[f, x] + s[f, x] * s[f, x]
                weakest[x] = min(weakest[x], power)
                mean_dc[x] += a / n_freq
                fitted[x] += steps * a * a + 2.0 / steps * power
                turns[f, x] = _atan2_turns(s[f, x], c[f, x])
        for f in range(n_freq):
            for x in range(width):
                deviation[x] += (sums[f, x] / steps - mean_dc[x]) ** 2
        for x in range(width):
            unit = turns[0, x] if frequencies[0] == 1 else turns[1, x] - turns[0, x]
            shifted = unit + 0.5 / lines
            line[x] = (shifted - math.floor(shifted)) * lines - 0.5
        for f in range(1, n_freq):
            period = lines / frequencies[f]
            for x in range(width):
                target = line[x] / period - turns[f, x]
                fringe[x] = math.floor(target + 0.5)
                line[x] = (turns[f, x] + fringe[x]) * period
                worst[x] = max(worst[x], abs(target - fringe[x]))
        last = n_freq - 1
        for x in range(width):
            b_last = 2.0 / steps * math.sqrt(c[last, x] * c[last, x] + s[last, x] * s[last, x])
            a_last = sums[last, x] / steps
            visibility[r, x] = min(max(b_last / a_last, 0.0), 1.0) if a_last > 0 else 0.0
            coord[r, x], order[r, x], ambiguity[r, x] = line[x], int(fringe[x]), worst[x]
            modulation[r, x], brightness[r, x] = 2.0 / steps * math.sqrt(weakest[x]), mean_dc[x]
            residual[r, x], spread[r, x] = max(energy[x] - fitted[x], 0.0), steps * deviation[x]


@numba.njit(cache=True, nogil=True)
def _pmp_valid_rows(coord: NDArray[np.float32], order: NDArray[np.int32], ambiguity: NDArray[np.float32],
                    modulation: NDArray[np.float32], min_modulation: float, max_ambiguity: float, lines: int,
                    rows: NDArray[np.intp], valid: NDArray[np.bool_]) -> None:
    """`valid` for the given `rows`; `coord` NaN and `order` -1 elsewhere, in place."""
    for r in rows:
        for x in range(coord.shape[1]):
            ok = (modulation[r, x] > min_modulation and ambiguity[r, x] <= max_ambiguity
                  and -0.5 <= coord[r, x] < lines - 0.5)
            valid[r, x] = ok
            if not ok:
                coord[r, x], order[r, x] = np.nan, -1


def decode_pmp(frames: NDArray[np.float32], spec: PatternSpec, direction: str, *, min_snr: float = 5.0,
               max_ambiguity: float = 0.3) -> ProjectorMap:
    """Projector coordinate along `direction` of every camera pixel of a ``pmp`` capture.

    One compiled pass over the frames fits every frequency and unwraps (`_pmp_rows`); the
    noise (`pooled_noise`, on every `NOISE_STRIDE`-th pixel) then sets the modulation threshold
    of a second, short pass.  Equal to composing `fringe_fits`, `noise_level` and `unwrap_step`
    up to float32 rounding and the noise estimate's sample (tested against that composition).

    Parameters
    ----------
    frames : (frame_count, H, W) float32 array
        The whole capture in the spec's order (`sliscan.sequences.check_frames`).
    spec : PatternSpec
        A ``pmp`` spec.
    direction : {"rows", "columns"}
        One of ``spec.directions``.
    min_snr : float
        Every frequency's modulation must exceed `min_snr` times its noise spread
        (`modulation_threshold`).
    max_ambiguity : float
        Largest accepted unwrapping distance from an integer fringe order (see `unwrap_step`).

    Returns
    -------
    ProjectorMap
        `coord` with sub-pixel precision, `index` the fringe order of the finest frequency.
    """
    own = np.ascontiguousarray(_direction_frames(frames, spec, direction).reshape(-1, *frames.shape[1:]))
    shape = own.shape[1:]
    coord, ambiguity, modulation, visibility, brightness, residual, spread = (
        np.empty(shape, np.float32) for _ in range(7))
    order = np.empty(shape, np.int32)
    delta = 2 * np.pi * np.arange(spec.steps) / spec.steps
    lines = spec.lines(direction)
    over_rows(lambda rows: _pmp_rows(own, np.cos(delta), np.sin(delta), np.asarray(spec.frequencies, np.float64),
                                     lines, rows, coord, order, ambiguity, modulation, visibility, brightness,
                                     residual, spread), shape[0])
    sample = (slice(None, None, NOISE_STRIDE),) * 2
    sigma = pooled_noise(residual[sample], spread[sample], len(spec.frequencies), spec.steps)
    threshold = modulation_threshold(sigma, spec.steps, min_snr)
    valid = np.empty(shape, bool)
    over_rows(lambda rows: _pmp_valid_rows(coord, order, ambiguity, modulation, threshold, max_ambiguity, lines,
                                           rows, valid), shape[0])
    return ProjectorMap(coord=coord, valid=valid, index=order, confidence=visibility, brightness=brightness)
