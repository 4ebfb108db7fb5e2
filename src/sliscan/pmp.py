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

import numpy as np
import scipy.stats
from numpy.typing import NDArray

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
    variances = []
    if steps > 3:
        residual = np.sum([fit.residual for fit in fits], axis=0)
        variances.append(float(np.median(residual)) / scipy.stats.chi2.ppf(0.5, len(fits) * (steps - 3)))
    if len(fits) > 1:
        dc = np.stack([fit.dc for fit in fits])
        spread = steps * np.sum((dc - dc.mean(axis=0)) ** 2, axis=0)
        variances.append(float(np.median(spread)) / scipy.stats.chi2.ppf(0.5, len(fits) - 1))
    return max(math.sqrt(min(variances)), QUANTISATION_NOISE) if variances else QUANTISATION_NOISE


def unit_coordinate(cycles: NDArray[np.float32], lines: int) -> NDArray[np.float32]:
    """Projector line of a unit-frequency phase (any real `cycles`, wrapped here) in
    ``[-0.5, lines - 0.5)``: the projector's extent, so the wrap falls between its two ends."""
    shifted = cycles + np.float32(0.5 / lines)
    return ((shifted - np.floor(shifted)) * np.float32(lines) - np.float32(0.5)).astype(np.float32)


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


def decode_pmp(frames: NDArray[np.float32], spec: PatternSpec, direction: str, *, min_snr: float = 5.0,
               max_ambiguity: float = 0.3) -> ProjectorMap:
    """Projector coordinate along `direction` of every camera pixel of a ``pmp`` capture.

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
    fits = fringe_fits(frames, spec, direction)
    sigma = noise_level(fits, spec.steps)
    lines = spec.lines(direction)
    freqs = spec.frequencies
    unit = fits[0].cycles if freqs[0] == 1 else fits[1].cycles - fits[0].cycles
    coord = unit_coordinate(unit, lines)
    order = np.zeros(coord.shape, dtype=np.int32)
    ambiguity = np.zeros(coord.shape, dtype=np.float32)
    for fit, f in zip(fits[1:], freqs[1:]):
        coord, order, distance = unwrap_step(coord, fit.cycles, lines / f)
        ambiguity = np.maximum(ambiguity, np.abs(distance))
    modulation = np.min([fit.modulation for fit in fits], axis=0)
    valid = ((modulation > modulation_threshold(sigma, spec.steps, min_snr)) & (ambiguity <= max_ambiguity)
             & (coord >= -0.5) & (coord < lines - 0.5))
    finest = fits[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        visibility = np.where(finest.dc > 0, finest.modulation / finest.dc, 0)
    return ProjectorMap(coord=np.where(valid, coord, np.nan).astype(np.float32), valid=valid,
                        index=np.where(valid, order, -1).astype(np.int32),
                        confidence=np.clip(visibility, 0, 1).astype(np.float32),
                        brightness=np.mean([fit.dc for fit in fits], axis=0).astype(np.float32))
