"""Carrier detection and demodulation of a composite-pattern capture (thesis 3.3-3.4).

The capture of eq. 3.2 holds, along every camera line in the carrier direction, a sum of
cosine carriers whose amplitudes are the Gray code bit planes (times albedo and gain), on top
of a slowly varying DC.  Demodulation recovers, per pixel, the amplitude of each carrier.

Two demodulators share one output type, `Demodulated`:

* `demodulate_bandpass` is the thesis's: per carrier a Butterworth band-pass along the line
  with the other carriers notched, applied to the one-sided spectrum (the analytic signal,
  eqs. 3.3-3.4), whose magnitude is the envelope.
* `demodulate_window` (the default) divides the capture by the sharp steps of its albedo
  (`normalise_albedo`: where a line stops repeating itself one carrier period later), each
  line by its local mean (the smooth albedo), then fits a DC, a ramp and every carrier by
  least squares in a sliding window of one period of the carriers' common spacing (where
  the carriers are orthogonal), with every sum taken from cumulative sums.  Each pixel takes
  the window placement (ending at, centred on, or starting at the pixel) that the model
  explains best, so a window need not straddle a depth edge, a shadow border or an albedo
  edge when a clean one exists on either side: this is what keeps neighbours' light out of a
  pixel's envelopes.  Each line has its own carrier frequencies (`detect_carriers` measures
  them band by band) and a window of a whole number of periods.  Where the carriers' scale
  changes along the lines themselves (a surface turned steeply about the phase direction),
  the lines are fitted resampled along the scale the first fit measured (`along_scale`).  A
  phase channel's carriers are also fitted in two-period windows with a ramp per carrier
  (`_fit_ramped`), which follow a fringe that crosses the lines obliquely: centred on each
  pixel, and beside an edge on the side its chosen window lies (`Demodulated.sided`).  On
  request every pixel's centred window's envelopes are kept as well (`Demodulated.centred`):
  where a stripe border crosses the lines obliquely, they change across it smoothly where the
  chosen ones jump (`sliscan.staircase.prefer_centred` places such borders from them).

Frequencies are in cycles per camera pixel along the carrier direction (camera `x` for the
``rows`` orientation, camera `y` for ``columns``).
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace

import cv2
import numba
import numpy as np
import scipy.ndimage
from numpy.typing import NDArray

from sliscan._threads import default_workers, over_rows
from sliscan._validate import InputError, check_image
from sliscan.edge_blur import BLUR_HEIGHT, edge_blur
from sliscan.types import PatternSpec


@dataclass(frozen=True)
class Carriers:
    """Carrier frequencies found in a capture.

    Attributes
    ----------
    frequencies : (C,) float64 array
        Cycles per camera pixel along the carrier direction: bit carriers first (bit 0 =
        most significant), then the pilot, as in ``PatternSpec.all_carriers``.
    scale : float
        Projector pixels per camera pixel along the carrier direction (``f_cam = scale *
        f_proj / W_p``).
    window : int
        Demodulation window, camera pixels: one period of the carriers' common spacing.
    line_scale : (H,) float64 array or None
        The scale of each line (row for the ``rows`` orientation): a projector pitched toward
        the camera's axis magnifies its pattern differently at the top and the bottom of the
        frame (up to ~10 % on the virtual rig), enough to drift a carrier's phase by a fair part of a cycle
        across the window.  None: `scale` everywhere.
    """

    frequencies: NDArray[np.float64]
    scale: float
    window: int
    line_scale: NDArray[np.float64] | None = field(default=None, repr=False)

    def line_windows(self) -> NDArray[np.intp]:
        """Window of each line (camera pixels): one period of its carriers' common spacing."""
        if self.line_scale is None:
            return np.array([self.window])
        return np.maximum(np.round(self.window * self.scale / self.line_scale).astype(np.intp), 3)

    def line_frequencies(self, lines: slice | NDArray[np.intp]) -> NDArray[np.float64]:
        """Carrier frequencies of the given lines, ``(n_lines, C)`` cycles per camera pixel."""
        if self.line_scale is None:
            n = len(range(*lines.indices(10**9))) if isinstance(lines, slice) else len(lines)
            return np.broadcast_to(self.frequencies, (n, self.frequencies.size))
        return self.line_scale[lines, None] * (self.frequencies / self.scale)[None, :]


@dataclass(frozen=True, eq=False)
class Demodulated:
    """Per-pixel carrier amplitudes and local mean of a capture.

    Attributes
    ----------
    amplitude : (C, H, W) float32 array
        Envelope of each carrier (peak amplitude, same units as the image), ordered like
        `Carriers.frequencies`.
    dc : (H, W) float32 array
        Local mean intensity over the same window (the albedo-weighted DC of eq. 3.2).
    residual : (H, W) float32 array
        Fraction of the window's AC energy that the carrier model leaves unexplained, in
        [0, 1]: high at edges, in shadow and where the signal is noise.
    noise : (H, W) float32 array or None
        Standard deviation of each amplitude estimate (image units), from the part of the
        window the model leaves unexplained; None for demodulators that do not compute it.
    misfit : (H, W) float32 array or None
        How badly the window's fitted model predicts the pixel's own neighbourhood (the mean
        over the shortest carrier period next to it, on the side of its window), relative to
        the window's DC: large where the light next to the pixel is of another level than its
        window's DC and ramp describe (a shadow or another surface within that short window).
        None for demodulators that do not compute it.
    offset : (H, W) float32 array or None
        Where the window a pixel's envelopes come from is centred, relative to the pixel, along
        the carriers (camera pixels): 0 for a centred window, about half a window for one that
        starts or ends at the pixel (next to an edge, or where the code changes within a centred
        window).  The envelopes describe the light around that centre, not at the pixel
        (`sliscan.fringe.recentre`).  None for demodulators that do not compute it.
    ramped : (R, H, W) float32 array or None
        R carriers' envelopes (a phase channel's, after the bits') from a centred window of two
        spacing periods with a ramp per carrier (`demodulate_window`'s `ramped`), relative to the
        DC as `amplitude` is; NaN where that window leaves the line.  None unless asked for.
    sided : (R, H, W) float32 array or None
        The same carriers' envelopes from a window of two spacing periods with a ramp per
        carrier that starts at the pixel where its chosen one-period window lies after it
        (`offset` > 0), or ends at it where that window lies before it, evaluated at the pixel
        (the fitted ramps carry the envelopes to it: no `offset`); NaN where the chosen window is
        centred, where the two periods leave the line, or where an edge lies within them (as for
        `ramped`).  With `ramped`.
    centred : Demodulated or None
        The same fit with every pixel's envelopes and `offset` from its centred window (shifted
        inside the line at its ends), where `amplitude` may come from a one-sided one; its
        `dc`, `residual`, `misfit` and `noise` are the chosen window's (the same values).  Where
        a stripe border crosses the carriers obliquely, the centred window's levels change
        across it symmetrically, the one-sided ones' by jumps (`sliscan.staircase.
        prefer_centred`).  None unless asked for (`demodulate_window`'s `centred`).
    """

    amplitude: NDArray[np.float32]
    dc: NDArray[np.float32]
    residual: NDArray[np.float32]
    misfit: NDArray[np.float32] | None = None
    noise: NDArray[np.float32] | None = None
    offset: NDArray[np.float32] | None = None
    ramped: NDArray[np.float32] | None = None
    sided: NDArray[np.float32] | None = None
    centred: Demodulated | None = None

    def mapped(self, fn: Callable[[NDArray], NDArray]) -> Demodulated:
        """This demodulation with `fn` applied to every array (`centred`'s too), e.g. to
        transpose it."""
        def apply(value: NDArray | Demodulated | None) -> NDArray | Demodulated | None:
            if value is None:
                return None
            return value.mapped(fn) if isinstance(value, Demodulated) else fn(value)

        return Demodulated(**{f.name: apply(getattr(self, f.name)) for f in fields(self)})


def along_carriers(image: NDArray, spec: PatternSpec) -> NDArray:
    """View of `image` whose axis 1 runs along the carriers (a transpose for ``columns``)."""
    return image if spec.orientation == "rows" else image.T


def line_spectrum(image: NDArray[np.floating], *, max_lines: int = 256) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mean power spectrum of the image lines along axis 1 (fig. 3.19's first row).

    Uses at most `max_lines` evenly spaced lines, each with its mean removed and a Hann
    window.  Returns ``(frequencies in cycles per pixel, power)``, both ``(W // 2 + 1,)``.
    """
    h, w = image.shape
    lines = np.asarray(image[:: max(1, h // max_lines)], dtype=np.float64)
    lines = lines - lines.mean(axis=1, keepdims=True)
    power = np.abs(np.fft.rfft(lines * np.hanning(w), axis=1)) ** 2
    return np.fft.rfftfreq(w), power.mean(axis=0)


def _common_spacing(carriers: NDArray[np.float64]) -> float:
    """Largest spacing of which every carrier is (nearly) an integer multiple."""
    srt = np.sort(carriers)
    gap = float(np.min(np.diff(srt))) if srt.size > 1 else float(srt[0])
    gap = min(gap, float(srt[0]))
    for divisor in range(1, 9):
        d = gap / divisor
        if np.all(np.abs(carriers / d - np.round(carriers / d)) < 0.02):
            return d
    return gap


#: A carrier counts as found when its spectral peak stands this many times above the power
#: around it (the median within half a carrier spacing).  Clean captures reach e^5 ~ 150; a
#: textured or partly saturated one e^2 ~ 7; a capture without the carriers stays below 1.
MIN_PEAK_CONTRAST = 4.0


def _log_power(power: NDArray[np.float64]) -> NDArray[np.float64]:
    """Natural log of a power spectrum, floored 120 dB below its peak (no log of zero)."""
    return np.log(power + power.max() * 1e-12 + 1e-30)


def _locate_carriers(img: NDArray[np.float32], proj: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The spectral search of `detect_carriers` along axis 1 of `img`.

    Returns the refined peak position of each carrier (in rfft bins of a line) and its
    contrast: the peak's power over the median power within half a carrier spacing around it.
    """
    width = img.shape[1]
    freqs, power = line_spectrum(img)
    logp = _log_power(power)
    s_hi = 0.45 / proj.max()
    s_lo = 4.0 / (width * proj.min())
    if s_lo >= s_hi:
        raise InputError(f"capture is {width} px along the carriers: too short to resolve them")
    scales = np.exp(np.arange(np.log(s_lo), np.log(s_hi), 0.5 / (width * proj.max())))
    # Score: log power on the carriers minus log power half a spacing beside them, so a
    # scale that puts the carriers on peaks beats one that merely sits on a bright region.
    offset = 0.5 * _common_spacing(proj)
    at = np.interp(scales[:, None] * proj[None, :] * width, np.arange(freqs.size), logp)
    beside = np.interp(scales[:, None] * (proj[None, :] + offset) * width, np.arange(freqs.size), logp)
    scale = float(scales[np.argmax((at - beside).sum(axis=1))])

    return _peaks(logp, proj * scale * width, _common_spacing(proj) * scale * width)


def _peaks(logp: NDArray[np.float64], predicted: NDArray[np.float64], gap: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The spectral peak nearest each predicted carrier and how far it stands out.

    `logp` is a log power spectrum ``(B,)``, `predicted` the carriers' expected positions in
    its bins ``(C,)`` and `gap` their common spacing in bins.  Each peak is the maximum within
    0.3 gap of its prediction, refined by a parabola; its contrast is its power over the
    median power within half a gap around it (2 bins and more away).  Returns ``(refined
    positions, contrasts)``, both ``(C,)``.
    """
    bins = np.arange(logp.size)
    refined = np.empty(predicted.size)
    contrast = np.empty(predicted.size)
    for n, b in enumerate(predicted):
        lo, hi = max(1, int(np.floor(b - 0.3 * gap))), min(logp.size - 2, int(np.ceil(b + 0.3 * gap)))
        k = lo + int(np.argmax(logp[lo : hi + 1]))
        a, c, e = logp[k - 1], logp[k], logp[k + 1]
        den = a - 2 * c + e
        refined[n] = k + (0.5 * (a - e) / den if den < 0 else 0.0)
        around = (np.abs(bins - k) <= max(0.5 * gap, 4)) & (np.abs(bins - k) > 2) & (bins > 0)
        contrast[n] = np.exp(c - np.median(logp[around])) if around.any() else 0.0
    return refined, contrast


#: Tiles of `_depth_normalised_contrast`: this many bins between carriers (the tile's length
#: follows), this many lines, at most this many line blocks, and local scales searched within
#: this log span of the frame's.
TILE_BINS_PER_SPACING = 8
TILE_LINES = 8
TILE_BLOCKS = 128
TILE_SCALE_SPAN = 0.25


def _tile_spectra(img: NDArray[np.float32], length: int) -> NDArray[np.float64]:
    """Power spectra of tiles `length` px long (half overlapping) and `TILE_LINES` lines tall.

    Each tile's lines have their means removed and a Hann window; their power spectra are
    averaged.  At most `TILE_BLOCKS` evenly spaced blocks of lines are used.  Returns ``(T,
    length // 2 + 1)``, one row per tile.
    """
    h, w = img.shape
    starts = np.unique(np.r_[np.arange(0, w - length + 1, max(1, length // 2)), w - length])
    lines = min(TILE_LINES, h)
    first = np.arange(0, h - lines + 1, lines)
    first = first[np.unique(np.linspace(0, first.size - 1, min(first.size, TILE_BLOCKS)).astype(np.intp))]
    spectra = []
    for r0 in first:
        segs = np.asarray(img[r0 : r0 + lines], np.float64)[:, starts[:, None] + np.arange(length)]
        segs -= segs.mean(axis=2, keepdims=True)
        spectra.append((np.abs(np.fft.rfft(segs * np.hanning(length), axis=2)) ** 2).mean(axis=0))
    return np.concatenate(spectra, axis=0)


def _lerp(values: NDArray[np.float64], positions: NDArray[np.float64]) -> NDArray[np.float64]:
    """`values` ``(T, B)`` linearly interpolated at `positions` ``(T, ...)`` (bins; 0 beyond the last)."""
    last = values.shape[1] - 1
    at = np.clip(positions, 0, last)
    k = np.minimum(at.astype(np.intp), last - 1)
    frac = at - k
    rows = np.arange(values.shape[0]).reshape((-1,) + (1,) * (positions.ndim - 1))
    out = values[rows, k] * (1 - frac) + values[rows, k + 1] * frac
    return np.where(positions > last, 0.0, out)


def _depth_normalised_contrast(img: NDArray[np.float32], proj: NDArray[np.float64], scale: float,
                               which: NDArray[np.intp]) -> NDArray[np.float64]:
    """The peak contrast of the carriers `which` (indices into `proj`) in a spectrum that
    undoes the local scale of every tile.

    Where the baseline has a component along the carriers, depth changes their local
    frequency across the frame (by 10-20 % on a sphere 14-27 degrees off a straight rig), and
    the frame's mean spectrum smears the finest carriers into plateaus.  Here each short tile
    (`_tile_spectra`, `TILE_BINS_PER_SPACING` bins between carriers) gets its own scale, the
    one that puts the *other* carriers on peaks (log power on them against half a spacing
    beside them, as `_locate_carriers` scores the frame), its spectrum is resampled to the
    frame's `scale` (projector pixels per camera pixel, `Carriers.scale`), and the carrier's peak
    contrast is measured (`_peaks`) in the mean of the resampled spectra.  Leaving the carrier
    out of its own tiles' scales keeps noise from lining up on it: a carrier faded by blur or
    drowned in noise stays as low as in the frame's spectrum.  Returns one contrast per index
    of `which`.
    """
    spacing = _common_spacing(proj)
    length = int(min(img.shape[1], round(TILE_BINS_PER_SPACING / (spacing * scale))))
    power = _tile_spectra(img, length)
    logp = _log_power(power)
    trial = scale * np.exp(np.arange(-TILE_SCALE_SPAN, TILE_SCALE_SPAN, 0.25 / (length * proj.max() * scale)))
    on = _lerp(logp, np.broadcast_to(trial[:, None] * proj * length, (logp.shape[0], trial.size, proj.size)))
    beside = _lerp(logp, np.broadcast_to(trial[:, None] * (proj + 0.5 * spacing) * length,
                                         (logp.shape[0], trial.size, proj.size)))
    score = on - beside  # (tiles, trials, carriers)
    total = score.sum(axis=2)
    bins = np.arange(power.shape[1], dtype=np.float64)
    contrast = np.empty(len(which))
    for k, n in enumerate(which):
        tile_scale = trial[np.argmax(total - score[:, :, n], axis=1)]
        resampled = _lerp(power, bins * (tile_scale / scale)[:, None]).mean(axis=0)
        contrast[k] = _peaks(_log_power(resampled), proj[n : n + 1] * scale * length, spacing * scale * length)[1][0]
    return contrast


def _carriers_missing(img: NDArray[np.float32], spec: PatternSpec, found: NDArray[np.bool_]) -> str:
    """Why the carriers of `spec` are not (all) in the capture, as specifically as the spectrum tells."""
    carriers = np.asarray(spec.all_carriers)

    def listed(mask: NDArray[np.bool_]) -> str:
        return ", ".join(f"{f:g}" for f in carriers[mask])

    proj = carriers / spec.orthogonal_lines
    with contextlib.suppress(InputError):
        if np.all(_locate_carriers(np.ascontiguousarray(img.T), proj)[1] >= MIN_PEAK_CONTRAST):
            return (f"no carriers found along the camera's {'x' if spec.orientation == 'rows' else 'y'} but across it: "
                    f"is the capture rotated by 90 degrees (or the pattern's orientation wrong)?")
    if found.any():  # typically the finest carriers, faded by blur
        return (f"carriers near {listed(~found)} cycles/width not found (only {listed(found)}): is the capture out of "
                f"focus (or the camera too coarse for the finest carriers, or the pattern spec wrong)?")
    return f"no carriers found near {listed(~found)} cycles/width: is this a composite-pattern capture?"


def detect_carriers(image: NDArray[np.floating], spec: PatternSpec) -> Carriers:
    """Find the carriers of `spec` in a capture (thesis 3.3): detect, don't assume.

    Perspective scales every carrier by the same factor, so the search is over one scale:
    the one whose carriers all sit on spectral peaks (log power on each carrier against half
    a spacing beside it, summed), then refined by a parabolic fit on each peak and a
    least-squares common scale.  Every carrier's peak must stand `MIN_PEAK_CONTRAST` times
    above the spectrum around it.  A strongly pitched projector magnifies its pattern so
    differently from the top of the frame to the bottom that the frame's mean spectrum smears
    the finest carriers into plateaus; then each quarter of the lines is searched alone, and
    the quarter whose weakest carrier stands highest gives the scale (`_line_scales` then
    follows the magnification line by line).  A baseline with a component along the carriers
    (a projector beside as well as above the camera) smears the finest carriers too, by depth;
    then the carriers not found are looked for in a spectrum that undoes each tile's scale
    (`_depth_normalised_contrast`), and the scale is the one of the carriers found on the
    frame's spectrum.

    Raises
    ------
    InputError
        If the capture is too small for the carriers or some carrier peaks are not found (the
        message says which, and guesses why: another pattern, defocus, a rotated capture).
    """
    img = along_carriers(check_image("capture", image), spec)
    width = img.shape[1]
    proj = np.asarray(spec.all_carriers, dtype=np.float64) / spec.orthogonal_lines  # cycles / projector px
    refined, contrast = _locate_carriers(img, proj)
    if not np.all(contrast >= MIN_PEAK_CONTRAST):
        with contextlib.suppress(InputError):
            bands = [_locate_carriers(band, proj) for band in np.array_split(img, 4) if band.shape[0] >= 8]
            refined, contrast = max([(refined, contrast)] + bands, key=lambda found: float(found[1].min()))
    found = contrast >= MIN_PEAK_CONTRAST
    scale = float(np.sum((refined * proj)[found]) / np.sum(proj[found] ** 2) / width) if found.any() else 0.0
    if found.any() and not found.all():
        missing = np.flatnonzero(~found)
        found[missing] = _depth_normalised_contrast(img, proj, scale, missing) >= MIN_PEAK_CONTRAST
    if not found.all():
        raise InputError(_carriers_missing(img, spec, found))
    window = int(round(1.0 / (_common_spacing(proj) * scale)))
    if window > width:
        raise InputError(f"capture is {width} px along the carriers, shorter than one carrier spacing ({window} px)")
    return Carriers(frequencies=proj * scale, scale=scale, window=window, line_scale=_line_scales(img, proj, scale))


def _line_scales(img: NDArray[np.float32], proj: NDArray[np.float64], scale: float, *,
                 band: int = 48, span: float = 0.08) -> NDArray[np.float64]:
    """Scale per line: refined in bands of lines, then a weighted quadratic fit over lines.

    In each band the scale within `span` of the global one that puts the most power on the
    carriers wins (parabolic refinement); bands are weighted by that power, so dark bands
    (shadow, background beyond the projector) barely count.
    """
    h, width = img.shape
    centres, best, weights = [], [], []
    trial = scale * np.exp(np.linspace(-span, span, 161))
    for r0 in range(0, h - band // 2, band):
        freqs, power = line_spectrum(img[r0 : r0 + band], max_lines=16)
        on = np.interp(trial[:, None] * proj[None, :] * width, np.arange(freqs.size), power).sum(axis=1)
        k = int(np.clip(np.argmax(on), 1, trial.size - 2))
        a, c, e = on[k - 1], on[k], on[k + 1]
        den = a - 2 * c + e
        step = 0.5 * (a - e) / den if den < 0 else 0.0
        centres.append(r0 + min(band, h - r0) / 2)
        best.append(np.log(trial[k]) + step * (np.log(trial[1]) - np.log(trial[0])))
        weights.append(c)
    if len(best) < 4:
        return np.full(h, scale)
    x = np.asarray(centres) / h
    y, w = np.asarray(best), np.sqrt(np.asarray(weights))
    coef = np.polyfit(x, y, 2, w=w)
    keep = np.abs(np.polyval(coef, x) - y) < 0.02
    if keep.sum() >= 4:
        coef = np.polyfit(x[keep], y[keep], 2, w=w[keep])
    fitted = np.exp(np.polyval(coef, np.arange(h) / h))
    return np.clip(fitted, scale * np.exp(-span), scale * np.exp(span))


def _short_window(carriers: Carriers) -> int:
    """One period of the highest carrier, in camera pixels (at least 3)."""
    return max(3, int(round(1.0 / float(carriers.frequencies.max()))))


#: A one-sided window replaces the centred one where it leaves less than this fraction of
#: the centred window's unexplained energy.  0.7 since the thirteenth session (0.5 before):
#: on captures of two rigs and three seeds not used to choose it, 0.2-1.6 points more right
#: stripes with every pattern and scene, for up to 0.15 point more stripes off by more than
#: one (docs/design.md).
PLACEMENT_GAIN = 0.7
#: A one-sided box replaces the centred one in the flat field where its relative variance is
#: below this fraction of the centred box's (measured: 0.1 keeps the centred box's accuracy
#: on smooth albedo and removes part of the leakage at albedo edges and shadow borders).
FLAT_GAIN = 0.1
#: The least varying box of the flat field that holds a pixel replaces the one chosen among the
#: three placements where its variance relative to its squared mean is under this fraction of
#: the centred box's (`flat_field`): a stretch flat to within a tenth of the deviation, such as a
#: shadow, between edges the centred box straddles.  Measured against an absolute threshold
#: (relative variance 0.005 or 0.002, with `FLAT_GAIN`; docs/design.md, "A shadow between two
#: edges"): all three mend the shadow that asked for it, 0.005 also flattened lit stretches whose
#: carriers the blur or a steep slope had washed out (a plane turned 60 degrees: the thesis
#: pattern's gross outliers 6.0 -> 9.2 %), and this ratio moves the fewest other captures.
FLAT_STRETCH_GAIN = 0.01
#: Offset of a window's start from the pixel, per placement: centred (tried first, the
#: default), ending at the pixel, starting at it.
_PLACEMENTS = (0, -1, 1)


@numba.njit(cache=True, inline="always")
def _window_start(x: int, width: int, window: int, placement: int) -> int:
    """Start of the window of `x`: placement -1 ends at the pixel, 0 is centred on it, +1
    starts at it; windows are shifted inside the line at its ends."""
    offset = window - 1 if placement == -1 else (window // 2 if placement == 0 else 0)
    return min(max(x - offset, 0), width - window)


@numba.njit(cache=True)
def _cumsum0(values: NDArray) -> NDArray:
    """Running sums with a leading 0: ``out[k] = sum(values[:k])``, ``(n + 1,)``."""
    out = np.zeros(values.size + 1, dtype=values.dtype)
    for k in range(values.size):
        out[k + 1] = out[k] + values[k]
    return out


@numba.njit(cache=True)
def flat_field(line: NDArray[np.float64], window: int) -> NDArray[np.float64]:
    """Local mean of each pixel over a box of one window that holds it.  The centred box
    (unbiased on a smooth albedo gradient) is kept unless a one-sided box (ending or starting
    at the pixel) varies much less relative to its mean (`FLAT_GAIN`): then the centred one
    straddles an albedo edge or a shadow border and the one-sided one does not.  And where the
    least varying of all the boxes that hold the pixel is flat beside the centred one
    (`FLAT_STRETCH_GAIN`), it gives the mean: a shadow between two edges less than two windows
    apart has no clean box among the three placements, and a flat field that ramps across it
    puts carriers into the line divided by it."""
    width = line.size
    cum, cum2 = _cumsum0(line), _cumsum0(line * line)
    n_starts = width - window + 1
    means, variations = np.empty(n_starts), np.empty(n_starts)  # per window start, in a loop that vectorises
    for s in range(n_starts):
        mean = (cum[s + window] - cum[s]) / window
        means[s] = mean
        variations[s] = ((cum2[s + window] - cum2[s]) / window - mean * mean) / max(mean * mean, 1e-12)
    least = _running_argmin(variations, window)  # least[e]: the least varying start in (e - window, e]
    last = n_starts - 1
    beyond = np.empty(width - n_starts, dtype=np.intp)  # x past the last start: of x - window + 1 .. last,
    flattest = last  # a minimum grown backward from the line's end
    for x in range(width - 1, last, -1):
        if variations[x - window + 1] <= variations[flattest]:
            flattest = x - window + 1
        beyond[x - n_starts] = flattest
    out = np.empty(width)
    for x in range(width):
        centre = _window_start(x, width, window, _PLACEMENTS[0])
        best = centre
        for k in range(1, len(_PLACEMENTS)):
            s = _window_start(x, width, window, _PLACEMENTS[k])
            if variations[s] < variations[best] and variations[s] < FLAT_GAIN * variations[centre]:
                best = s
        # the boxes that hold x start at max(x - window + 1, 0) .. min(x, last)
        flattest = least[x] if x <= last else beyond[x - n_starts]
        if variations[flattest] < FLAT_STRETCH_GAIN * variations[centre]:
            best = flattest
        out[x] = means[best]
    return out


@numba.njit(cache=True)
def _running_argmin(values: NDArray[np.float64], length: int) -> NDArray[np.intp]:
    """Index of the least of ``values[max(e - length + 1, 0) .. e]`` for every ``e`` (the
    first of equal ones), in one pass with a queue of candidates."""
    n = values.size
    out = np.empty(n, dtype=np.intp)
    queue = np.empty(n, dtype=np.intp)
    head, tail = 0, 0
    for e in range(n):
        while tail > head and values[queue[tail - 1]] > values[e]:
            tail -= 1
        queue[tail] = e
        tail += 1
        if queue[head] <= e - length:
            head += 1
        out[e] = queue[head]
    return out


@numba.njit(cache=True, nogil=True)
def _window_means(omega: NDArray[np.float64], length: int) -> NDArray[np.complex128]:
    """Mean over ``j = 0 .. length - 1`` of ``exp(i omega_n j)``, one per frequency: ``(C,)``
    (the geometric series' closed form)."""
    out = np.zeros(omega.size, dtype=np.complex128)
    for n in range(omega.size):
        if abs(np.sin(omega[n] / 2)) < 1e-9:
            out[n] = np.exp(1j * omega[n] * (length - 1) / 2)
        else:
            out[n] = (1 - np.exp(1j * omega[n] * length)) / (length * (1 - np.exp(1j * omega[n])))
    return out


@numba.njit(cache=True, nogil=True)
def _phasors(omega: NDArray[np.float64], width: int, block: int = 64) -> NDArray[np.complex128]:
    """``exp(-i omega_n x)`` for ``x = 0 .. width - 1``, ``(C, W)``: a product of a coarse
    and a fine table (``x = block a + b``), one complex product per value instead of an exp."""
    out = np.empty((omega.size, width), dtype=np.complex128)
    for n in range(omega.size):
        fine = np.exp(-1j * omega[n] * np.arange(block))
        for a in range(0, width, block):
            coarse = np.exp(-1j * omega[n] * a)
            for b in range(min(block, width - a)):
                out[n, a + b] = coarse * fine[b]
    return out


@numba.njit(cache=True, nogil=True)
def _fit_line(line: NDArray[np.float32], omega: NDArray[np.float64], window: int, short: int, adaptive: bool,
              unexplained: NDArray[np.float32], var: NDArray[np.float32], dc: NDArray[np.float32],
              amp: NDArray[np.float32], misfit: NDArray[np.float32], offset: NDArray[np.float32],
              ramped_first: int, ramped: NDArray[np.float32], sided: NDArray[np.float32], scale: NDArray[np.float32],
              centred: NDArray[np.float32], centred_offset: NDArray[np.float32]) -> None:
    """Best least-squares window fit of ``d + s t + sum_n (c_n e^{i w_n x} + c.c.)`` at every
    pixel of one line; writes the outputs of `demodulate_window` for it (``(W,)`` each, `amp`
    ``(C, W)``), in image units, and if `ramped_first` >= 0 those of `_fit_ramped` (`ramped`
    and `sided`, ``(R, W)`` each).  If `scale` is ``(W,)``: the carriers' local scale error
    (`_scale_errors`) between the one-period windows that end and start at every
    `FOLLOW_SCALE_STEP`-th pixel, where both leave at most `FOLLOW_SCALE_EXPLAINED` of their AC
    energy unexplained, NaN elsewhere.  If `centred` is ``(C, W)``: every carrier's envelope
    from the centred window, and that window's offset into `centred_offset` ``(W,)``.

    The line is divided by its flat field, then every window sum comes from running sums.
    In each window's own phase (the carriers' coefficients times ``exp(+i w_n s)``, ``s`` its
    start) the Gram matrix of the basis (DC, ramp, each carrier's cosine and sine) is the same
    for every start, so one inverse turns every start's projections (window means of the line
    times each basis function) into its exact least-squares fit, and the unexplained energy is
    the window's mean square less the projections times the fit.  (Until the fortieth session
    the carriers' couplings to each other, of the order of the window's rounding to whole
    pixels, were neglected and a 2x2 system solved for the DC and the ramp: docs/accuracy.md,
    "The window fit solved exactly".)

    Each window start is fitted once.  A pixel keeps its centred window unless a one-sided
    one leaves less than `PLACEMENT_GAIN` of its unexplained energy and the least of all.
    The misfit compares the best model's mean over the short window (one period of the
    highest carrier) next to the pixel with the line's own mean there, relative to the DC; the
    short window lies on the chosen window's side (around the pixel for a centred window), so a
    pixel decoded from the clean side of an edge is not judged by light from across it.
    """
    width, n_carriers = line.size, omega.size
    x = np.arange(width)
    raw = line.astype(np.float64)
    flat = np.maximum(flat_field(raw, window), 1e-4)
    block = raw / flat
    phasors = _phasors(omega, width)
    cum_i, cum_i2, cum_xi = _cumsum0(block), _cumsum0(block * block), _cumsum0(block * x)
    cum_q = np.empty((n_carriers, width + 1), dtype=np.complex128)
    for n in range(n_carriers):
        cum_q[n] = _cumsum0(block * phasors[n])
    near0 = _window_means(omega, short)
    inverse = np.linalg.inv(_ramped_gram(omega, window, 0, 0))
    n_starts = width - window + 1
    size = 2 + 2 * n_carriers
    projections = np.empty((size, n_starts))  # in the window's phase
    inv_window = 1.0 / window
    for s in range(n_starts):
        e = s + window
        mean = (cum_i[e] - cum_i[s]) * inv_window
        projections[0, s] = mean
        projections[1, s] = ((cum_xi[e] - cum_xi[s]) * inv_window - (s + (window - 1) / 2) * mean) * inv_window
    for n in range(n_carriers):
        for s in range(n_starts):
            q = (cum_q[n, s + window] - cum_q[n, s]) * inv_window * np.conj(phasors[n, s])
            projections[2 + 2 * n, s], projections[3 + 2 * n, s] = q.real, -q.imag
    coefficients = inverse @ projections
    explained = np.zeros(n_starts)
    for k in range(size):
        for s in range(n_starts):
            explained[s] += projections[k, s] * coefficients[k, s]
    fit_u, fit_var, fit_d, fit_slope = np.empty(n_starts), np.empty(n_starts), np.empty(n_starts), np.empty(n_starts)
    for s in range(n_starts):
        mean_sq = (cum_i2[s + window] - cum_i2[s]) * inv_window
        fit_d[s], fit_slope[s] = coefficients[0, s], coefficients[1, s] * inv_window
        fit_u[s] = max(mean_sq - explained[s], 0.0)
        fit_var[s] = max(mean_sq - projections[0, s] * projections[0, s], 0.0)
    fit_c = np.empty((n_carriers, n_starts), dtype=np.complex128)  # in the window's phase
    for n in range(n_carriers):
        for s in range(n_starts):
            fit_c[n, s] = 0.5 * (coefficients[2 + 2 * n, s] - 1j * coefficients[3 + 2 * n, s])
    chosen, near, prediction = np.empty(width, np.intp), np.empty(width, np.intp), np.empty(width)
    for xi in range(width):
        best, placement = _window_start(xi, width, window, 0), 0
        for k in range(1, len(_PLACEMENTS) if adaptive else 1):
            s = _window_start(xi, width, window, _PLACEMENTS[k])
            if fit_u[s] < fit_u[best] and fit_u[s] < PLACEMENT_GAIN * fit_u[_window_start(xi, width, window, 0)]:
                best, placement = s, _PLACEMENTS[k]
        chosen[xi] = best
        # the short window on the chosen window's side of the pixel (centred for a centred one),
        # so that next to an edge the misfit does not look across it either
        ns = _window_start(xi, width, short, placement) if width >= short else 0
        near[xi] = ns
        prediction[xi] = fit_d[best] + fit_slope[best] * (ns + (short - 1) / 2 - (best + (window - 1) / 2))
    rotated = np.empty((n_carriers, n_starts), dtype=np.complex128)  # the carriers in image phase
    for n in range(n_carriers):
        for s in range(n_starts):  # the prediction's first product, once per start
            rotated[n, s] = fit_c[n, s] * phasors[n, s]
        for xi in range(width):
            best = chosen[xi]
            prediction[xi] += 2 * (rotated[n, best] * np.conj(phasors[n, near[xi]]) * near0[n]).real
            c = fit_c[n, best]
            amp[n, xi] = 2 * np.sqrt(c.real ** 2 + c.imag ** 2) * flat[xi]  # not abs (hypot): 3x faster
    if centred.shape[1] == width:
        for xi in range(width):
            s0 = _window_start(xi, width, window, 0)
            centred_offset[xi] = s0 + (window - 1) / 2 - xi
            for n in range(n_carriers):
                c = fit_c[n, s0]
                centred[n, xi] = 2 * np.sqrt(c.real ** 2 + c.imag ** 2) * flat[xi]
    for xi in range(width):
        best, ns = chosen[xi], near[xi]
        observed = (cum_i[ns + short] - cum_i[ns]) / short
        f = flat[xi]
        unexplained[xi], var[xi], dc[xi] = fit_u[best] * f * f, fit_var[best] * f * f, fit_d[best] * f
        misfit[xi] = abs(observed - prediction[xi]) / max(fit_d[best], 1e-6)
        offset[xi] = best + (window - 1) / 2 - xi
    if ramped_first >= 0:
        _fit_ramped(cum_i, cum_xi, cum_q, block, phasors, omega, window, ramped_first, dc, fit_u, fit_c, offset, ramped,
                    sided)
    if scale.size == width:
        scale[:] = np.nan
        grid = np.arange(0, n_starts - window, FOLLOW_SCALE_STEP)
        errors = _scale_errors(fit_c, phasors, omega, grid, window)
        for k in range(grid.size):
            s0 = grid[k]
            if (fit_u[s0] <= FOLLOW_SCALE_EXPLAINED * fit_var[s0]
                    and fit_u[s0 + window] <= FOLLOW_SCALE_EXPLAINED * fit_var[s0 + window]):
                scale[s0 + window] = errors[k]


#: `demodulate_window` measures the carriers' local scale along every `FOLLOW_SCALE_STEP`-th
#: line at every `FOLLOW_SCALE_STEP`-th pixel, between one-period windows that leave at most
#: `FOLLOW_SCALE_EXPLAINED` of their AC energy unexplained, averages it over
#: `FOLLOW_SCALE_LINES` lines and `FOLLOW_SCALE_WINDOWS` windows (`scale_map`), and where the
#: median of that is above `FOLLOW_SCALE_MIN` fits the lines resampled along it instead.
FOLLOW_SCALE_STEP = 8
FOLLOW_SCALE_EXPLAINED = 0.3
FOLLOW_SCALE_MIN = 0.015
FOLLOW_SCALE_LINES = 15
FOLLOW_SCALE_WINDOWS = 2

#: The window of `_fit_ramped`, in spacing periods.  Over one period a ramp per carrier makes
#: the fit ill-conditioned (condition number 6.6e3 against 14 without, in the 1D model of the
#: docs/accuracy.md, "Sub-stripe depth from one frame"); over two, 5.7; over 1.5 it lost on the captures.
RAMPED_PERIODS = 2
#: `_fit_ramped` leaves out the pixels where the one-period fits at its window's two ends and
#: at the pixel leave unexplained energies (relative to the flat-fielded line's DC of 1) more
#: than `RAMPED_MISFIT` times apart plus `RAMPED_FLOOR` (0.5 % of the DC, squared: noise-free
#: captures, whose fits leave next to nothing, would otherwise differ by any factor).
RAMPED_MISFIT = 2.0
RAMPED_FLOOR = 2.5e-5
#: `_fit_ramped` measures the local carrier scale every this many window starts (it changes
#: slowly along a line; each measurement is an arctangent per carrier).
RAMPED_SCALE_STEP = 8


@numba.njit(cache=True, nogil=True)
def _scale_errors(fitted: NDArray[np.complex128], phasors: NDArray[np.complex128], omega: NDArray[np.float64],
                  starts: NDArray[np.intp], apart: int) -> NDArray[np.float64]:
    """The carriers' local scale error (relative: their local frequency over the line's, less
    1) between the one-period fits at each of `starts` and `apart` pixels after it, from the
    phase the fits' coefficients (`fitted`, window phase; `phasors` turn them to image phase)
    gain from one to the other, the same per radian of carrier frequency for all carriers
    (one local scale), each weighted by its amplitudes: ``(len(starts),)``, 0 where no carrier
    is there."""
    num, den = np.zeros(starts.size), np.zeros(starts.size)
    for c in range(omega.size):
        z = fitted[c, starts + apart] * phasors[c, starts + apart] * np.conj(fitted[c, starts] * phasors[c, starts])
        num += np.abs(z) * omega[c] * np.angle(z)
        den += np.abs(z) * omega[c] * omega[c]
    return np.where(den > 0, num / np.maximum(den, 1e-300), 0.0) / apart


@numba.njit(cache=True, nogil=True)
def _ramped_gram(omega: NDArray[np.float64], length: int, first: int, ramped: int) -> NDArray[np.float64]:
    """Gram matrix of the window fits' basis over a window of `length` pixels, in the window's
    own phase: ``1, t, cos(w_n u), sin(w_n u)`` for every carrier, then (`_fit_ramped`'s) ``t
    cos(w_n u), t sin(w_n u)`` for the `ramped` carriers from `first` on (``u`` the pixel in
    the window, ``t`` its offset from the window's centre over `length`)."""
    n_carriers = omega.size
    size = 2 + 2 * n_carriers + 2 * ramped
    basis = np.empty((size, length))
    t = (np.arange(length) - (length - 1) / 2) / length
    basis[0], basis[1] = 1.0, t
    for n in range(n_carriers):
        basis[2 + 2 * n], basis[3 + 2 * n] = np.cos(omega[n] * np.arange(length)), np.sin(omega[n] * np.arange(length))
    for k in range(ramped):
        base = 2 + 2 * n_carriers + 2 * k
        basis[base], basis[base + 1] = t * basis[2 + 2 * (first + k)], t * basis[3 + 2 * (first + k)]
    return basis @ basis.T / length


@numba.njit(cache=True, nogil=True)
def _fit_ramped(cum_i: NDArray[np.float64], cum_xi: NDArray[np.float64], cum_q: NDArray[np.complex128],
                block: NDArray[np.float64], phasors: NDArray[np.complex128], omega: NDArray[np.float64], window: int,
                first: int, at_pixel: NDArray[np.float32], unexplained: NDArray[np.float64],
                fitted: NDArray[np.complex128], offset: NDArray[np.float32], out: NDArray[np.float32],
                sided: NDArray[np.float32]) -> None:
    """The envelopes of the R carriers ``first .. first + R - 1`` at each pixel of one line, from
    a centred window of `RAMPED_PERIODS` spacing periods fitted with a DC, a ramp, every carrier
    and a ramp of each of those R carriers' envelopes (`_ramped_gram`), relative to the DC fitted
    there: `out` ``(R, W)`` is each envelope over that DC times `at_pixel` ``(W,)`` (the DC the
    envelopes will be divided by); NaN where the window leaves the line, or where the one-period
    fits (`unexplained`, `fitted`: `_fit_line`'s per window start) at its two ends and at the
    pixel leave unexplained energies more than `RAMPED_MISFIT` apart (plus `RAMPED_FLOOR`): an
    edge within the longer window that the one-period windows avoid.  `sided` ``(R, W)``: the
    same from the window that starts at the pixel where its chosen one-period window lies after
    it (`offset` ``(W,)`` > 0, `_fit_line`'s), or ends at it where that one lies before it,
    with the fitted envelopes and DC evaluated at the pixel (the window's first or last pixel:
    the ramps carry them there); NaN elsewhere and on the same terms.

    `cum_i`, `cum_xi`, `cum_q`: `_fit_line`'s running sums of the flat-fielded line `block`
    (alone, times the pixel, times each carrier's ``exp(-i w_n x)`` = `phasors`).  A fringe
    that the stripes cross obliquely changes each envelope along the window, and a changing
    envelope leaks into the neighbouring carriers' fits; the ramps take that change in.  A
    carrier whose local frequency is off drifts in phase across the window, which the ramps
    follow only to first order: the rest of the envelope's loss (the window mean of ``exp(i
    drift t)``) is undone with the local scale measured from the one-period fits at the
    window's two ends (the same phase drift per radian of carrier frequency for all carriers),
    every `RAMPED_SCALE_STEP` starts.  The starts are fitted all at once (their projections, then
    one matrix product)."""
    n_carriers, width, ramped = omega.size, block.size, out.shape[0]
    length = int(round(RAMPED_PERIODS * window))
    second = length - window  # the start of the one-period window at the far end
    out[:] = np.nan
    sided[:] = np.nan
    if length > width or second < 1:
        return
    inverse = np.linalg.inv(_ramped_gram(omega, length, first, ramped))
    half = (length - 1) // 2
    here = (half - (length - 1) / 2) / length  # the pixel's t in its window
    # the rows of the solution that give the DC and each envelope's two parts at the pixel
    # (centred), and at the window's first and last pixels (one-sided)
    rows = np.empty((3 * (1 + 2 * ramped), inverse.shape[0]))
    for j, at in enumerate((here, -(length - 1) / 2 / length, (length - 1) / 2 / length)):
        o = j * (1 + 2 * ramped)
        rows[o] = inverse[0] + at * inverse[1]
        for k in range(ramped):
            cn, rk = 2 + 2 * (first + k), 2 + 2 * n_carriers + 2 * k
            rows[o + 1 + 2 * k] = inverse[cn] + at * inverse[rk]
            rows[o + 2 + 2 * k] = inverse[cn + 1] + at * inverse[rk + 1]
    n = width - length + 1
    projections = np.empty((inverse.shape[0], n))  # each basis function's window mean with the line
    inv_length = 1.0 / length
    for s in range(n):  # in loops: the array expressions' temporaries cost twice as much
        e, centre = s + length, s + (length - 1) / 2
        mean = (cum_i[e] - cum_i[s]) * inv_length
        projections[0, s] = mean
        projections[1, s] = ((cum_xi[e] - cum_xi[s]) * inv_length - centre * mean) * inv_length
    for c in range(n_carriers):
        for s in range(n):
            q = (cum_q[c, s + length] - cum_q[c, s]) * inv_length * np.conj(phasors[c, s])
            projections[2 + 2 * c, s], projections[3 + 2 * c, s] = q.real, -q.imag
    x = np.arange(width)
    for k in range(ramped):
        c, row = first + k, 2 + 2 * n_carriers + 2 * k
        cum_xq = _cumsum0(block * x * phasors[c])
        for s in range(n):
            e, centre = s + length, s + (length - 1) / 2
            r = ((cum_xq[e] - cum_xq[s]) - centre * (cum_q[c, e] - cum_q[c, s])) * inv_length * inv_length
            r *= np.conj(phasors[c, s])
            projections[row, s], projections[row + 1, s] = r.real, -r.imag
    size = 1 + 2 * ramped
    coefficients = rows[:size] @ projections  # the centred windows' (the one-sided ones' below, where wanted)
    # the local scale error, every RAMPED_SCALE_STEP starts
    grid = np.arange(0, n, RAMPED_SCALE_STEP)
    scale_error = _scale_errors(fitted, phasors, omega, grid, second)
    kept = np.ones((ramped, grid.size))  # what the drift over the window left of each envelope
    for k in range(ramped):
        half_turn = 0.5 * omega[first + k] * scale_error * length
        turned = np.abs(half_turn) > 1e-6
        kept[k][turned] = np.maximum(np.sin(half_turn[turned]) / half_turn[turned], 0.5)
    usable = np.zeros(n, np.bool_)
    for s in range(n):
        centred = unexplained[min(max(s + half - window // 2, 0), width - window)]
        left, right = unexplained[s], unexplained[s + second]
        # one part of the window explained worse than another: an edge in it
        usable[s] = max(left, right, centred) <= RAMPED_MISFIT * min(left, right, centred) + RAMPED_FLOOR
    one_sided = np.empty(size)
    for xi in range(width):
        for j in range(3):
            if j == 0:
                s = xi - half
            elif j == 1:  # starting at the pixel, where its chosen one-period window lies after it
                s = xi if offset[xi] > 0.5 else -1
            else:  # ending at it, where that window lies before it
                s = xi - length + 1 if offset[xi] < -0.5 else -1
            if s < 0 or s >= n or not usable[s]:
                continue
            if j == 0:
                column, target = coefficients[:, s], out
            else:  # only where wanted, in loops (all three row sets in the line's matrix product
                # tripled its work, and BLAS's own threads made the demodulation 2.5x slower)
                for q in range(size):
                    total = 0.0
                    for g in range(projections.shape[0]):
                        total += rows[j * size + q, g] * projections[g, s]
                    one_sided[q] = total
                column, target = one_sided, sided
            gain = at_pixel[xi] / max(column[0], 1e-6)
            for k in range(ramped):
                re, im = column[1 + 2 * k], column[2 + 2 * k]
                target[k, xi] = np.sqrt(re * re + im * im) * gain / kept[k, s // RAMPED_SCALE_STEP]


@numba.njit(cache=True, nogil=True)
def _fit_lines(img: NDArray[np.float32], omegas: NDArray[np.float64], windows: NDArray[np.intp], short: int,
               adaptive: bool, lines: NDArray[np.intp], unexplained: NDArray[np.float32], var: NDArray[np.float32],
               dc: NDArray[np.float32], amp: NDArray[np.float32], misfit: NDArray[np.float32],
               offset: NDArray[np.float32], ramped_first: int, ramped: NDArray[np.float32], sided: NDArray[np.float32],
               scale: NDArray[np.float32], centred: NDArray[np.float32], centred_offset: NDArray[np.float32]) -> None:
    """`_fit_line` on the given `lines` of `img` ``(H, W)``, without the GIL (threads run
    disjoint sets of lines); `omegas` ``(H, C)`` radians per pixel, `windows` ``(H,)``;
    outputs ``(H, W)``, `amp` ``(C, H, W)``, if `ramped_first` >= 0 `ramped` and `sided`
    ``(R, H, W)`` (`_fit_ramped`), if `scale` is ``(H, W)`` the scale errors of every
    `FOLLOW_SCALE_STEP`-th line (NaN on the others), and if `centred` is ``(C, H, W)`` the
    centred windows' envelopes and offsets (`centred_offset` ``(H, W)``)."""
    keep_centred = centred_offset.shape[0] == img.shape[0] and centred_offset.shape[1] == img.shape[1]
    for r in lines:
        measure = scale.shape[0] > 1 and r % FOLLOW_SCALE_STEP == 0
        if scale.shape[0] > 1 and not measure:
            scale[r] = np.nan
        _fit_line(img[r], omegas[r], windows[r], short, adaptive, unexplained[r], var[r], dc[r], amp[:, r], misfit[r],
                  offset[r], ramped_first, ramped[:, r] if ramped_first >= 0 else ramped[:, 0],
                  sided[:, r] if ramped_first >= 0 else sided[:, 0],
                  scale[r] if measure else scale[0, :1], centred[:, r] if keep_centred else centred[:, 0],
                  centred_offset[r] if keep_centred else centred_offset[0])


def demodulate_window(image: NDArray[np.floating], carriers: Carriers, *, adaptive: bool = True,
                      albedo: str | None = "steps", ramped: range | None = None, follow_scale: bool = True,
                      centred: bool = False, camera_blur: float | None = None,
                      workers: int | None = None) -> Demodulated:
    """Carrier amplitudes by a sliding-window least-squares fit with edge-aware placement.

    The capture is first divided by the sharp steps of its albedo (`normalise_albedo`), which
    no window can fit.  In every window of one spacing period the line, divided by its flat
    field, is fitted with a DC, a ramp (albedo gradients) and the carriers (`_fit_line`); all sums come from
    running sums, so the cost does not depend on the window length.  Each line gets the
    window of its own carrier scale (`Carriers.line_windows`), so its carriers complete
    whole periods in it.  The lines are fitted by a compiled kernel, in parallel.

    Parameters
    ----------
    image : (H, W) array
        Capture with the carriers along axis 1 (see `along_carriers`).
    carriers : Carriers
        From `detect_carriers`.
    adaptive : bool
        Also fit the windows that end and start at the pixel, and keep the one that leaves
        the least AC energy unexplained (absolute, so a dark window in shadow beats one that
        straddles the shadow border).  The centred window is kept unless a one-sided one
        leaves less than `PLACEMENT_GAIN` of its unexplained energy: where the code changes
        gradually across the window (an oblique stripe border) the centred fit is the
        unbiased one.
        If false, always the centred window.
    albedo : str or None
        Albedo estimate the capture is divided by before the fit (`normalise_albedo`; the
        outputs are multiplied back, so they stay in image units and the ratios the decoder
        takes are those of the normalised capture).  None: no normalisation.
    ramped : range, optional
        Also fit these carriers (indices into `Carriers.frequencies`: a phase channel's) in
        centred windows of `RAMPED_PERIODS` spacing periods with a ramp per carrier
        (`_fit_ramped`): `Demodulated.ramped`.
    follow_scale : bool
        Measure how the carriers' scale changes along the lines, and where it does by more than
        `FOLLOW_SCALE_MIN` (median), fit the lines resampled so that it does not
        (`along_scale`): a surface turned steeply about the phase direction, seen by a projector
        pitched toward the camera, chirps the carriers along each line (+-4.5 % on a plane
        turned 60 degrees about the vertical), and a fixed-frequency window loses the finest
        carriers there.
    centred : bool
        Also keep every pixel's centred window's envelopes (`Demodulated.centred`).
    camera_blur : float, optional
        With the ``"steps"`` estimates: the camera's blur (px) the steps are found for and
        blurred with (`_albedo_steps`' `blur`); None measures it on the capture.
    workers : int, optional
        Threads fitting lines in parallel (default: `default_workers`).

    Returns
    -------
    Demodulated
        In the same (axis-1-along-carriers) frame as `image`.
    """
    workers = default_workers() if workers is None else workers
    img = np.ascontiguousarray(check_image("capture", image), dtype=np.float32)
    h, w = img.shape
    gain = None
    if albedo is not None:
        by_steps = albedo in ("steps", "sharp-steps")
        img, gain = normalise_albedo(img, carriers, estimate=albedo, **({"blur": camera_blur} if by_steps else {}))
    short = _short_window(carriers)
    windows = np.ascontiguousarray(np.broadcast_to(carriers.line_windows(), (h,)), dtype=np.intp)
    if windows.max() > w:
        raise InputError(f"capture is {w} px along the carriers, shorter than one carrier spacing ({windows.max()} px)")
    omegas = np.ascontiguousarray(2 * np.pi * carriers.line_frequencies(slice(0, h)), dtype=np.float64)
    unexplained, var, dc, misfit, offset = (np.empty((h, w), dtype=np.float32) for _ in range(5))
    amp = np.empty((carriers.frequencies.size, h, w), dtype=np.float32)
    first = -1 if ramped is None or len(ramped) == 0 else ramped[0]
    ramp_amp = np.empty((len(ramped), h, w) if first >= 0 else (1, 1, w), dtype=np.float32)
    sided_amp = np.empty_like(ramp_amp)
    scale = np.empty((h, w) if follow_scale else (1, 1), dtype=np.float32)
    centred_amp = np.empty((carriers.frequencies.size, h, w) if centred else (1, 1, 1), dtype=np.float32)
    centred_offset = np.empty((h, w) if centred else (1, 1), dtype=np.float32)
    over_rows(lambda lines: _fit_lines(img, omegas, windows, short, adaptive, lines, unexplained, var, dc, amp, misfit,
                                       offset, first, ramp_amp, sided_amp, scale, centred_amp, centred_offset), h,
                                       workers)
    if follow_scale:
        error, measured = scale_map(scale, carriers)
        if measured.any() and float(np.median(np.abs(error[measured]))) > FOLLOW_SCALE_MIN:
            return along_scale(image, carriers, error, adaptive=adaptive, albedo=albedo, ramped=ramped,
                               centred=centred, workers=workers)
    if gain is not None:  # back to image units; every ratio (what the decoder uses) is unchanged
        amp *= gain[None]
        if centred:
            centred_amp *= gain[None]
        if first >= 0:
            ramp_amp *= gain[None]
            sided_amp *= gain[None]
        dc *= gain
        unexplained *= gain * gain
        var *= gain * gain
    # amplitude noise: residual variance over the window's degrees of freedom, times 2 / L
    dof = np.maximum(windows - 2 * carriers.frequencies.size - 2, 1).astype(np.float32)
    noise = np.sqrt(2 * unexplained / dof[:, None])
    demod = Demodulated(amplitude=amp, dc=dc, residual=unexplained / np.maximum(var, 1e-12), misfit=misfit, noise=noise,
                        offset=offset, ramped=ramp_amp if first >= 0 else None, sided=sided_amp if first >= 0 else None)
    if centred:
        demod = replace(demod, centred=replace(demod, amplitude=centred_amp, offset=centred_offset, ramped=None,
                                               sided=None))
    return demod


def scale_map(scale: NDArray[np.float32], carriers: Carriers) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The carriers' local scale error at every pixel ``(H, W)``: the measured ones (`scale`,
    `_fit_line`'s, NaN where none) averaged over `FOLLOW_SCALE_LINES` lines and
    `FOLLOW_SCALE_WINDOWS` windows around it (0 where none is near), and where that average
    has measurements, ``(H, W)`` bool.  The average also takes out most of the measurements'
    noise, which on a 640x480 capture alone puts their median above `FOLLOW_SCALE_MIN`.

    The sums run in compiled kernels with the frame's ends repeated beyond it (scipy.ndimage's
    ``mode="nearest"``), and the count of measurements is exact: until the thirty-fourth
    session two `scipy.ndimage.uniform_filter` means took 0.2 s at 5 MP on one core, and their
    running sums left a positive residue of ~1e-17 where no measurement was near, so those
    pixels counted as measured with errors near 0 (the median over "measured" pixels came out
    5-10 % lower; no capture of the accuracy benchmark crosses `FOLLOW_SCALE_MIN` either way)."""
    scale = np.ascontiguousarray(scale, dtype=np.float32)
    h, w = scale.shape
    along, across = FOLLOW_SCALE_WINDOWS * int(np.max(carriers.line_windows())), FOLLOW_SCALE_LINES
    line_total, line_count, total, count = (np.empty((h, w)) for _ in range(4))
    # a box of ``size`` pixels spans ``size // 2`` before the pixel (scipy.ndimage's alignment)
    over_rows(lambda rows: _line_box_sums(scale, along // 2, along - along // 2 - 1, rows, line_total, line_count), h)
    over_rows(lambda rows: _across_box_sums(line_total, line_count, across // 2, across - across // 2 - 1, rows,
                                            total, count), h)
    measured = count > 0
    return np.divide(total, count, out=np.zeros((h, w)), where=measured), measured


@numba.njit(cache=True, nogil=True)
def _line_box_sums(scale: NDArray[np.float32], before: int, after: int, rows: NDArray[np.intp],
                   total: NDArray[np.float64], count: NDArray[np.float64]) -> None:
    """For the given `rows` of `scale` ``(H, W)``: the sum of its finite values and their count
    over ``x - before .. x + after`` along axis 1, the line's ends repeated beyond it
    (scipy.ndimage's ``mode="nearest"``), into `total` and `count`."""
    width = scale.shape[1]
    values, counts = np.zeros(width + 1), np.zeros(width + 1)  # prefix sums
    for r in rows:
        for x in range(width):
            finite = np.isfinite(scale[r, x])
            values[x + 1] = values[x] + (scale[r, x] if finite else 0.0)
            counts[x + 1] = counts[x] + (1.0 if finite else 0.0)
        if counts[width] == 0:  # most lines: measured on every FOLLOW_SCALE_STEP-th only
            total[r] = 0.0
            count[r] = 0.0
            continue
        first, last = values[1], values[width] - values[width - 1]
        first_count, last_count = counts[1], counts[width] - counts[width - 1]
        for x in range(width):
            low, high = x - before, x + after
            a, b = max(low, 0), min(high, width - 1) + 1
            value, n = values[b] - values[a], counts[b] - counts[a]
            if low < 0:
                value += -low * first
                n += -low * first_count
            if high > width - 1:
                value += (high - width + 1) * last
                n += (high - width + 1) * last_count
            total[r, x], count[r, x] = value, n


@numba.njit(cache=True, nogil=True)
def _across_box_sums(line_total: NDArray[np.float64], line_count: NDArray[np.float64], before: int, after: int,
                     rows: NDArray[np.intp], total: NDArray[np.float64], count: NDArray[np.float64]) -> None:
    """`line_total` and `line_count` ``(H, W)`` summed over lines ``y - before .. y + after``
    (the frame's first and last lines repeated beyond it), for the given consecutive `rows`,
    into `total` and `count`: a running sum down the block, row by row."""
    height, width = line_total.shape
    for k in range(rows.size):
        y = rows[k]
        if k == 0:
            for x in range(width):
                total[y, x], count[y, x] = 0.0, 0.0
            for j in range(y - before, y + after + 1):
                i = min(max(j, 0), height - 1)
                for x in range(width):
                    total[y, x] += line_total[i, x]
                    count[y, x] += line_count[i, x]
        else:
            enter, leave = min(y + after, height - 1), max(y - 1 - before, 0)
            for x in range(width):
                total[y, x] = total[y - 1, x] + line_total[enter, x] - line_total[leave, x]
                count[y, x] = count[y - 1, x] + line_count[enter, x] - line_count[leave, x]


def along_scale(image: NDArray[np.floating], carriers: Carriers, error: NDArray[np.float64],
                **options: object) -> Demodulated:
    """`demodulate_window` of `image` ``(H, W)`` (carriers along axis 1) with each line
    resampled so that its carriers keep their frequency, then sampled back at the pixels.

    `error` ``(H, W)``: the carriers' local scale error ``e(x)`` (`scale_map`); pixel ``x`` of
    a line sits at ``u(x) = x + sum e`` of the warped coordinate, in which the carriers have
    the line's frequencies.  Each line is resampled (cubic) at ``u = u(0) + k du`` (``du`` the
    line's mean ``1 + e``, so that it keeps its length), fitted at its carriers' frequencies
    per sample (the line's times ``du``), and every output taken back at the sample nearest to
    each pixel (an interpolation would mix the two sides of a depth edge).  Measured
    (docs/accuracy.md, "Sub-stripe depth from one frame"): on a plane turned 60 degrees about
    the vertical (960x720, noise-free) the stripe pattern 91 -> 97 % of the stripes right.  Until the
    thirty-ninth session the lines were fitted at their own frequencies, so a line's mean error
    stayed in the fit: 2-3 % where a projector beside the camera lets depth move the carriers
    (docs/accuracy.md, "Projector offset").  (Resampling at unit steps of ``u`` instead pads the
    shorter lines' ends, and lost 1.1 points of completeness there on a rolled projector.)"""
    h, w = error.shape
    warp = np.arange(w)[None, :] + np.cumsum(error, axis=1)  # u(x), (H, W)
    step = (warp[:, -1:] - warp[:, :1]) / (w - 1)
    samples = warp[:, :1] + np.arange(w)[None, :] * step  # where each resampled pixel lies in u
    pixels = np.arange(w, dtype=np.float64)
    columns = np.stack([np.interp(samples[r], warp[r], pixels) for r in range(h)]).astype(np.float32)
    rows = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    resampled = cv2.remap(np.ascontiguousarray(image, dtype=np.float32), columns, np.ascontiguousarray(rows),
                          cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    line_scale = np.broadcast_to(carriers.scale if carriers.line_scale is None else carriers.line_scale, (h,))
    stepped = replace(carriers, line_scale=line_scale * step[:, 0])  # the carriers per sample of each line
    fitted = demodulate_window(resampled, stepped, follow_scale=False, **options)
    nearest = np.clip(np.rint((warp - warp[:, :1]) / step), 0, w - 1).astype(np.intp)  # each pixel's sample
    return fitted.mapped(lambda a: np.ascontiguousarray(np.take_along_axis(a, np.broadcast_to(nearest, a.shape),
                                                                            axis=-1)))


#: Albedo estimates of `normalise_albedo` (``"steps"`` is the default of `demodulate_window`,
#: ``"sharp-steps"`` the same steps with none blurred, the default with a phase channel; the
#: others were measured worse, see ``benchmarks/albedo_normalisation.py``).
ALBEDO_ESTIMATES = ("steps", "sharp-steps", "closing", "envelopes", "guided", "notch-log", "notch")
#: `_albedo_steps` defaults.  A step is a reflectance ratio of at least e ** `STEP_THRESHOLD`
#: (log units: 1.5; a 0.25/0.9 checker is 1.28, a 0.3/0.8 one 0.98, a 0.4/0.9 one 0.81, a
#: 0.6/0.9 one 0.41).
#: Candidates are where the lag-one-window log ratio of the line changes by at least
#: `STEP_FIND` of that across a short box on either side (`STEP_BOX` of a window, at least
#: `STEP_MIN_BOX` pixels; blur spreads the change, so less than the threshold), sharply
#: (`STEP_SHARPNESS`), the largest within a box, and the two views of the change (at the
#: step, and one window later where the ratio changes back) agreeing within `STEP_AGREEMENT`.
#: The height is the ratio's weighted mean from the step to the next one (at most a window),
#: leaving `STEP_MARGIN` pixels out at each end (blur), over at least ``1 / STEP_SPAN`` of a
#: window; it must reach `STEP_HEIGHT` of the threshold.  Within a window of a line's end only
#: one view exists: there the change must not be the echo of a step a window away
#: (`STEP_ECHO`), and the ratio's two halves must agree within `STEP_CONSTANCY` of the height.
#: The threshold was 1.0 (the earlier detector's, chosen on the 0.25/0.9 checker of issue 8)
#: until the forty-seventh session: a checker just under it lost every step and decoded worst
#: of all (its edges leak into the carriers nearly as much, and none was divided out), e.g. a
#: 0.3/0.8 checker of 25 mm on a 1600x1200 camera 75-83 % complete with medians of 1-8 mm;
#: with 0.8 and the sharpness and flatness tests below 88-91 % and 0.4-1.0 mm
#: (docs/accuracy.md, "Checkers of lower contrast").  Then a checker just under 0.8 lost its
#: steps in turn (0.4/0.9 on the 960x720 sphere: 4 % of sliscan's points a stripe or more off,
#: against 2 % on 0.25/0.9); since the forty-eighth session it is 0.4, with the concentration
#: test below (docs/accuracy.md, "Steps as low as a ratio of 1.5").  The rest were set on the
#: 5 MP seed-0 captures and the 640x480 test rig, and checked on other seeds and rigs.
STEP_THRESHOLD = 0.4
#: A candidate's change across boxes of a third of the step box (at least 2 px) must be at
#: least `STEP_SHARPNESS` of its change across the whole boxes, the same way (`_is_sharp`): a
#: reflectance edge is as sharp as the optics blur it, the steep part of a smooth albedo is
#: not.  So an edge blurred by much more than 2 px (a Gaussian) is not found at a window of
#: 50 px (blurred by 2 / 2.5 px: 37 / 5 of 40 edges; at 110 px all up to 3 px; synthetic
#: lines).  Measured with the threshold of 0.8: without the test it cost the smooth albedo
#: 0.1-0.2 points at 1296x972 and 0.3-0.4 at 5 MP with 12 % more RMS; with it (and the
#: flatness test) 0.06 points at 1296x972 and -0.17 / +0.04 at 5 MP, with 5-10 % less RMS.
STEP_SHARPNESS = 0.5
#: A step under e ** `STEP_FLAT_BELOW` (the threshold until the forty-seventh session) must also
#: be flat (`STEP_FLAT`: the lag ratio the same over its span, an albedo edge), not the border
#: of a limb or a shadow, where the ratio swings with the pattern: without this the 5 MP
#: cylinder's limbs gave such steps, and the phase pattern, which divides them out sharp,
#: decoded 1,500 px beside them more than a stripe off (RMS 2.83 -> 4.78 mm; with it 2.47).
STEP_FLAT_BELOW = 1.0
#: A step's change across the boxes (its evidence) must be at least `STEP_CONCENTRATION` of what
#: an edge of its height blurred by `STEP_SPREAD` changes across them (`_edge_share`: 0.75 of
#: the height at the 3 px boxes of a 640x480 camera, 0.87 at 1296x972's 6, 0.93 at 5 MP's 11):
#: an edge rises within a box, the steep part of a smooth albedo over several (a rise over
#: 15 px changes 0.4 of its height across 6 px boxes, and its height is the whole rise, often
#: above `STEP_FLAT_BELOW`).  A change of `STEP_ENOUGH` is enough at any height: what every
#: candidate needed at the forty-seventh session's threshold (0.7 of 0.8), so the tall steps
#: found then are still found.  Without the test a threshold under 0.8 took such rises for
#: steps: at 0.6 the smooth albedo lost 0.4 points at 1296x972; with it, at 0.4, 0.02-0.09.
STEP_CONCENTRATION = 0.65
STEP_ENOUGH = 0.56
STEP_BOX = 0.125
STEP_MIN_BOX = 2
STEP_FIND = 0.7
STEP_AGREEMENT = 0.5
STEP_HEIGHT = 1.0
STEP_ECHO = 0.5
STEP_CONSTANCY = 0.4
STEP_MARGIN = 3
STEP_SPAN = 6
#: The camera blurs a reflectance edge (its optics and its pixels' aperture), so the capture
#: changes over a pixel or two where the albedo steps; divided by a sharp step, it keeps a
#: spike of the wrong level on either side, which no window fit explains and whose windows are
#: then lost.  So each step whose lag ratio is flat over its span (weighted spread at most
#: `STEP_FLAT` of its height: the same reflectance ratio under every part of the pattern, an
#: albedo edge) is rendered as an edge blurred by a Gaussian of `STEP_SPREAD` camera pixels, in
#: linear albedo, centred where the linear edge is half-way (`_soften_steps`); the others
#: (where the ratio swings with the pattern: a shadow or depth edge, a change of code) stay
#: sharp.
#: Measured on the virtual rig (docs/accuracy.md, "Soft albedo edges"): on the checker 1.7
#: (sliscan's pattern) and 2.3 (the thesis's) points more completeness at 1296x972 (up to 3.2
#: and 4.7 on the cylinder), 0.1-1.9 at 5 MP, nothing on a smooth albedo; a blur of 0.7 px
#: gives 85 % of it.  The phase channel keeps the sharp steps (`demodulate`): its fringe's
#: precision lost there.  `STEP_SPREAD` is also the blur the sharpness and concentration tests
#: assume (`_edge_share`, `_sharp_share`) unless the capture shows a blurrier camera.
STEP_SPREAD = 1.0
#: The camera's blur is measured on each capture's flat steps (`sliscan.edge_blur`); a blur over
#: `STEP_BLUR_BAND` times `STEP_SPREAD` replaces it (in the tests and the soft edges), and the
#: steps are found again.  A 1 px camera measures 1.03-1.06 px (the pixels' aperture adds
#: ``1 / 12`` to the variance), so nothing changes there.  A camera blurred by 2 px lost most of
#: its steps to the sharpness test (an edge blurred by 2 px changes across a third of the box
#: only 0.50 of its change across the box, where 1 px gives 0.72 and the test asks 0.5): 1296x972,
#: 40 mm checker of 0.25 / 0.9, seed 3, sphere / steps / cylinder / objects, sliscan's pattern
#: 85.8 / 93.0 / 84.5 / 82.7 % complete with it, 91.4 / 97.1 / 90.7 / 90.4 % with the measured
#: blur (docs/accuracy.md, "A camera blurrier than assumed"; at 5 MP +0.4 to +2.1 points).
#: Within a window of a line's end, where a step has one view, the sharpness test stays as for
#: 1 px: looser there, it let in a step that flipped the thesis pattern's top bit over 7,000 px
#: at a 5 MP frame's end (gross outliers 0.02 -> 0.17 %).  A sharper camera keeps
#: `STEP_SPREAD`: soft edges of 0.5 px lost 0.5-0.8 points on the cylinder of a 0.5 px camera.
STEP_BLUR_BAND = 1.15
STEP_FLAT = 0.15


@numba.njit(cache=True, nogil=True, inline="always")
def _ratio_mean(cum_g: NDArray[np.float64], cum_w: NDArray[np.float64], lo: int, hi: int) -> float:
    """Weighted mean of the lag-one-window log ratio over pixels ``lo .. hi - 1``."""
    return (cum_g[hi] - cum_g[lo]) / max(cum_w[hi] - cum_w[lo], 1e-12)


@numba.njit(cache=True, nogil=True, inline="always")
def _ratio_less_steps(cum_g: NDArray[np.float64], cum_w: NDArray[np.float64], kept: NDArray[np.intp],
                      heights: NDArray[np.float64], n_kept: int, t: int, lo: int, hi: int) -> float:
    """`_ratio_mean` over ``lo .. hi - 1`` less what the first `n_kept` steps (at `kept`, of
    `heights`, in order) add to it there: a step at ``k`` adds its height up to ``k + t``."""
    span = max(cum_w[hi] - cum_w[lo], 1e-12)
    total = 0.0
    for i in range(n_kept - 1, -1, -1):
        until = kept[i] + t
        if until <= lo:
            break
        total += heights[i] * (cum_w[min(until, hi)] - cum_w[lo]) / span
    return _ratio_mean(cum_g, cum_w, lo, hi) - total


@numba.njit(cache=True, nogil=True, inline="always")
def _is_sharp(cum_g: NDArray[np.float64], cum_w: NDArray[np.float64], change: NDArray[np.float64], at: int, box: int,
              sharpness: float) -> bool:
    """Whether the lag ratio's change at pixel `at` across boxes of a third of `box` (at least
    2 px) is at least `sharpness` of its change across boxes of `box` (`change`), the same way:
    an edge as sharp as the optics blur it, not the steep part of a smooth albedo."""
    inner = max(2, box // 3)
    short = _ratio_mean(cum_g, cum_w, at, at + inner) - _ratio_mean(cum_g, cum_w, at - inner, at)
    return short * change[at] > 0 and abs(short) >= sharpness * abs(change[at])


@numba.njit(cache=True, nogil=True)
def _edge_share(box: int, spread: float) -> float:
    """The share of its height by which an edge blurred by a Gaussian of `spread` px changes the
    mean across boxes of `box` px either side of it (`_line_steps`' change, at the pixel after
    the edge's middle): ``1 - (2 / box) sum_{u < box} (1 - Phi((u + 1/2) / spread))``."""
    tail = 0.0
    for u in range(box):
        tail += 0.5 * math.erfc((u + 0.5) / (spread * math.sqrt(2.0)))
    return 1.0 - 2.0 * tail / box


@numba.njit(cache=True, nogil=True)
def _step_evidence(change: NDArray[np.float64], usable: NDArray[np.bool_], t: int, least: float,
                   evidence: NDArray[np.float64], one_sided: NDArray[np.bool_]) -> None:
    """Per pixel, the log step its two views agree on (0 where they do not, or where it would
    be under `least`: neither view reaches it), into `evidence`; `one_sided` where only one
    view exists (within a window of the line's ends).

    A step of ``L`` at ``x`` changes the lag-``t`` ratio by ``+L`` at ``x`` and by ``-L`` at
    ``x + t`` (`change`, valid where `usable`, 0 elsewhere)."""
    w = change.size
    for x in range(w):
        here = change[x]
        later_usable = x + t < w and usable[x + t]
        later = -change[x + t] if later_usable else 0.0
        one_sided[x] = usable[x] != later_usable
        evidence[x] = 0.0
        if abs(here) < least and abs(later) < least:  # most pixels: no step to agree on
            continue
        if usable[x] and later_usable:
            if here * later > 0 and min(abs(here), abs(later)) >= STEP_AGREEMENT * max(abs(here), abs(later)):
                evidence[x] = 0.5 * (here + later)
        elif usable[x]:  # near the right end: not the echo of a step one window earlier
            echo = x >= t and usable[x - t] and change[x - t] * here < 0 and abs(change[x - t]) >= STEP_ECHO * abs(here)
            evidence[x] = 0.0 if echo else here
        elif later_usable:  # near the left end: not the echo of a step one window later
            echo = x + 2 * t < w and usable[x + 2 * t] and change[x + 2 * t] * later > 0 \
                and abs(change[x + 2 * t]) >= STEP_ECHO * abs(later)
            evidence[x] = 0.0 if echo else later


@numba.njit(cache=True, nogil=True)
def _line_steps(line: NDArray[np.float32], t: int, box: int, floor: float, threshold: float, sharpness: float,
                end_sharpness: float, flat_below: float, least_share: float, judge_flat: bool,
                kept: NDArray[np.intp], heights: NDArray[np.float64], flat: NDArray[np.bool_]) -> int:
    """The albedo steps found along one `line` ``(W,)`` read left to right (window `t`, box
    `box` px): their pixels into `kept` (ascending), log heights into `heights`, and with
    `judge_flat` whether the lag ratio is flat over the span the height was measured on into
    `flat` (`STEP_FLAT`; False for all without); `threshold`, `sharpness` and `flat_below` as in
    `_albedo_steps` (`end_sharpness` the sharpness asked of a step with one view, within a
    window of the line's ends), `least_share` its `concentration` times `_edge_share` (the least change
    across the boxes per unit of height, up to `STEP_ENOUGH`); returns how many."""
    w = line.size
    cum_g, cum_w = np.zeros(w + 1), np.zeros(w + 1)
    logs, change, evidence = np.empty(w), np.empty(w), np.empty(w)
    usable, one_sided = np.empty(w, np.bool_), np.empty(w, np.bool_)
    found = np.empty(w, np.intp)
    for x in range(w):
        logs[x] = np.log(max(line[x], floor))
    sum_g = sum_w = 0.0  # the running sums (0 over the first window)
    for x in range(t, w):
        wt = max(min(line[x], line[x - t]), floor)
        sum_g += wt * (logs[x] - logs[x - t])
        sum_w += wt
        cum_g[x + 1], cum_w[x + 1] = sum_g, sum_w
    for x in range(w):
        usable[x] = x - box >= t and x + box <= w
        change[x] = 0.0
        if usable[x]:
            change[x] = _ratio_mean(cum_g, cum_w, x, x + box) - _ratio_mean(cum_g, cum_w, x - box, x)
    _step_evidence(change, usable, t, STEP_FIND * threshold, evidence, one_sided)
    n_found = 0  # the largest evidence within a box on either side, one per box
    for x in range(w):
        s = abs(evidence[x])
        if s >= STEP_FIND * threshold and (n_found == 0 or x - found[n_found - 1] > box):
            largest = 0.0
            for k in range(max(x - box, 0), min(x + box + 1, w)):
                largest = max(largest, abs(evidence[k]))
            need = end_sharpness if one_sided[x] else sharpness
            if s >= largest and _is_sharp(cum_g, cum_w, change, x if usable[x] else x + t, box, need):
                found[n_found] = x
                n_found += 1
    n_kept = 0
    for j in range(n_found):
        # the height: the ratio from this step to the next (at most a window on), less what
        # the steps kept within a window before still add to it there
        x = found[j]
        end = min(x + t, found[j + 1] if j + 1 < n_found else w)
        lo, hi = max(x + STEP_MARGIN, t), end - STEP_MARGIN
        if hi - lo >= t // STEP_SPAN:
            mid = (lo + hi) // 2
            first = _ratio_less_steps(cum_g, cum_w, kept, heights, n_kept, t, lo, mid)
            second = _ratio_less_steps(cum_g, cum_w, kept, heights, n_kept, t, mid, hi)
            height = 0.5 * (first + second)
            steady = first * second > 0 and abs(first - second) <= STEP_CONSTANCY * abs(height)
            concentrated = abs(evidence[x]) >= min(least_share * abs(height), STEP_ENOUGH)
            if (steady or not one_sided[x]) and abs(height) >= STEP_HEIGHT * threshold and concentrated:
                tall = abs(height) >= STEP_HEIGHT * flat_below
                is_flat = (judge_flat or not tall) and (
                    _ratio_spread(line, logs, t, floor, lo, hi) <= STEP_FLAT * abs(height))
                if tall or is_flat:
                    kept[n_kept], heights[n_kept] = x, height
                    flat[n_kept] = judge_flat and is_flat
                    n_kept += 1
    return n_kept


@numba.njit(cache=True, nogil=True)
def _ratio_spread(line: NDArray[np.float32], logs: NDArray[np.float64], t: int, floor: float, lo: int,
                  hi: int) -> float:
    """Weighted standard deviation of the lag-one-window log ratio over pixels ``lo .. hi - 1``
    (`line` and its floored logs `logs`; weights as in `_line_steps`)."""
    total = first = second = 0.0
    for u in range(lo, hi):
        wt = max(min(line[u], line[u - t]), floor)
        g = logs[u] - logs[u - t]
        total += wt
        first += wt * g
        second += wt * g * g
    mean = first / max(total, 1e-12)
    return math.sqrt(max(second / max(total, 1e-12) - mean * mean, 0.0))


@numba.njit(cache=True, nogil=True)
def _two_way_steps(ahead: NDArray[np.intp], ahead_h: NDArray[np.float64], ahead_flat: NDArray[np.bool_],
                   n_ahead: int, back: NDArray[np.intp], back_h: NDArray[np.float64], back_flat: NDArray[np.bool_],
                   n_back: int, box: int, delta: NDArray[np.float32], flat: NDArray[np.bool_]) -> None:
    """The steps of one line ``(W,)``: their log heights into `delta` (0 elsewhere) and whether
    each is flat into `flat`, from the steps found reading it left to right (`ahead`, ascending
    pixels, log heights `ahead_h`, flat ratios `ahead_flat`) and right to left (`back`: pixels
    of the reversed line, ascending there, with their heights and flatness there): every step
    found either way, the two heights averaged where both found one within `box` px, flat if
    either way's ratio is."""
    w = delta.size
    delta[:] = 0.0
    flat[:] = False
    used = np.zeros(n_back, np.bool_)
    k = n_back - 1  # the reversed line's steps from the right end: ascending pixels here
    for i in range(n_ahead):
        x = ahead[i]
        while k >= 0 and w - back[k] < x - box:
            k -= 1
        nearest, height, is_flat = -1, ahead_h[i], ahead_flat[i]
        for m in range(k, -1, -1):
            at = w - back[m]
            if at > x + box:
                break
            if not used[m] and (nearest < 0 or abs(at - x) < abs(w - back[nearest] - x)):
                nearest = m
        if nearest >= 0:
            used[nearest] = True
            height = 0.5 * (height - back_h[nearest])
            is_flat = is_flat or back_flat[nearest]
        delta[x] += height
        flat[x] |= is_flat
    for m in range(n_back):
        if not used[m]:  # a step up read right to left is a step down read left to right
            delta[w - back[m]] -= back_h[m]
            flat[w - back[m]] |= back_flat[m]


@numba.njit(cache=True, nogil=True)
def _levels_rows(delta: NDArray[np.float32], flat: NDArray[np.bool_], spread: float, rows: NDArray[np.intp],
                 out: NDArray[np.float32]) -> None:
    """The relative albedo of the given `rows` into `out` ``(H, W)``: the running sum of the
    steps' log heights `delta` ``(H, W)`` (1 left of the first), those that are `flat` blurred
    by a Gaussian of `spread` px (`_soften_steps`; 0: none)."""
    for r in rows:
        total, level = 0.0, 1.0
        for x in range(out.shape[1]):
            if delta[r, x] != 0.0:
                total += delta[r, x]
                level = np.exp(total)
            out[r, x] = level
        if spread > 0:
            _soften_steps(delta[r], flat[r], spread, out[r])


@numba.njit(cache=True, nogil=True)
def _soften_steps(delta: NDArray[np.float32], flat: NDArray[np.bool_], spread: float,
                  out: NDArray[np.float32]) -> None:
    """Blur the steps of one line's relative albedo `out` ``(W,)`` (log heights `delta` at their
    pixels) that are `flat` by a Gaussian of `spread` px: each such step becomes ``a0 + (a1 -
    a0) Phi((u - e) / spread)`` in linear albedo (its levels ``a0`` before and ``a1`` after);
    steps closer than the blur's reach add up, as a blur of their sum would.

    The detector finds a step where the LOG of the blurred capture is half-way between the two
    levels, between its pixel ``x`` and ``x - 1``; the blurred linear edge is half-way farther
    toward the bright side (`_bright_side_shift`), so ``e = x - 1/2`` plus that shift."""
    w = out.size
    reach = int(math.ceil(4 * spread)) + 1
    scale = 1.0 / (spread * math.sqrt(2.0))
    total = 0.0
    for x in range(w):
        if delta[x] == 0.0:
            continue
        before, total = math.exp(total), total + delta[x]
        if flat[x]:
            rise = math.exp(total) - before
            centre = x - 0.5 + math.copysign(_bright_side_shift(abs(delta[x]), spread), delta[x])
            for u in range(max(x - reach, 0), min(x + reach, w)):
                sharp = 1.0 if u >= x else 0.0
                out[u] += rise * (0.5 * (1.0 + math.erf((u - centre) * scale)) - sharp)


@numba.njit(cache=True, nogil=True)
def _bright_side_shift(height: float, spread: float) -> float:
    """How far (px) the middle of a linear edge of log height `height` blurred by a Gaussian of
    `spread` px lies from the middle of its log, toward the bright side: the log is half-way
    where the linear share of the rise is ``1 / (sqrt(r) + 1)`` (``r = exp(height)``), which is
    ``Phi(-z)`` at ``z`` blurs from the linear middle (0.40 px for a 0.25 / 0.9 edge at 1 px).
    ``z`` by Newton's method on ``Phi(z) = 1 - 1 / (sqrt(r) + 1)``, from 0 (monotone there)."""
    share = 1.0 - 1.0 / (math.exp(0.5 * height) + 1.0)
    z = 0.0
    for _ in range(12):
        z -= (0.5 * (1.0 + math.erf(z / math.sqrt(2.0))) - share) / (math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi))
    return spread * z


@numba.njit(cache=True, nogil=True)
def _sharp_share(box: int, blur: float) -> float:
    """The share of its change across boxes of `box` px by which an edge blurred by a Gaussian
    of `blur` px changes across boxes of a third of that (at least 2 px): `_is_sharp`'s ratio
    for an albedo edge (0.72 at 6 px boxes and 1 px, 0.50 at 2 px)."""
    return _edge_share(max(2, box // 3), blur) / _edge_share(box, blur)


@numba.njit(cache=True, nogil=True)
def _albedo_steps_rows(img: NDArray[np.float32], windows: NDArray[np.intp], floor: float, threshold: float,
                       sharpness: float, flat_below: float, concentration: float, both_ways: bool, blur: float,
                       judge_flat: bool, rows: NDArray[np.intp], delta: NDArray[np.float32],
                       flat: NDArray[np.bool_]) -> None:
    """The steps `_albedo_steps` finds on the given `rows` of `img` ``(H, W)`` (`windows` per
    row), for a camera blur of `blur` px: their log heights into `delta` ``(H, W)`` (0
    elsewhere) and, with `judge_flat`, whether each is flat into `flat` ``(H, W)``."""
    w = img.shape[1]
    reversed_line = np.empty(w, np.float32)
    ahead, back = np.empty(w, np.intp), np.empty(w, np.intp)
    ahead_h, back_h = np.empty(w), np.empty(w)
    ahead_flat, back_flat = np.empty(w, np.bool_), np.empty(w, np.bool_)
    for r in rows:
        t = windows[r]
        if 3 * t >= w:
            delta[r] = 0.0
            flat[r] = False
            continue
        box = max(STEP_MIN_BOX, int(round(STEP_BOX * t)))
        least_share = concentration * _edge_share(box, blur)
        sharp = sharpness * _sharp_share(box, blur) / _sharp_share(box, STEP_SPREAD)
        end_sharp = max(sharp, sharpness)  # one view only: no looser than for a 1 px camera
        n_ahead = _line_steps(img[r], t, box, floor, threshold, sharp, end_sharp, flat_below, least_share,
                              judge_flat, ahead, ahead_h, ahead_flat)
        n_back = 0
        if both_ways:
            for x in range(w):
                reversed_line[x] = img[r, w - 1 - x]
            n_back = _line_steps(reversed_line, t, box, floor, threshold, sharp, end_sharp, flat_below,
                                 least_share, judge_flat, back, back_h, back_flat)
        _two_way_steps(ahead, ahead_h, ahead_flat, n_ahead, back, back_h, back_flat, n_back, box, delta[r], flat[r])


def _albedo_steps(img: NDArray[np.float32], windows: NDArray[np.intp], *,
                  threshold: float = STEP_THRESHOLD, sharpness: float = STEP_SHARPNESS,
                  flat_below: float = STEP_FLAT_BELOW, concentration: float = STEP_CONCENTRATION,
                  both_ways: bool = True, blur: float | None = None, soft: bool = True) -> NDArray[np.float32]:
    """Relative albedo made of the sharp steps found along each line (1 left of the first).

    Within one code the pattern repeats every window ``T`` along the line, so where the albedo
    steps by a factor ``r`` at ``x0`` the log capture minus itself one window earlier,
    ``g(u) = log I(u) - log I(u - T)``, is ``log r`` on exactly ``[x0, x0 + T)`` and 0 around it,
    whatever the pattern: it steps up by ``log r`` at ``x0`` and back down at ``x0 + T``.  The
    change of its mean (weighted by the smaller of the two intensities, so the noise of the dark
    troughs counts little) across a short box on either side of each pixel finds both; a step
    needs both views to agree, which a change of code or a depth edge (where ``g`` oscillates
    with the pattern instead) rarely does with the same height, and the echo one window after
    a step is not one (its other view is 0); and it must be about as sharp across a third of
    the box as across the box (`sharpness`, `STEP_SHARPNESS`: not the steep part of a smooth
    albedo), and under a height of `flat_below` (`STEP_FLAT_BELOW`) flat over its span (an
    albedo edge, not a limb's or a shadow's border), and its change across the boxes at least
    `concentration` of a blurred edge's (`STEP_CONCENTRATION`: an edge rises within a box, a
    smooth albedo's steep part over several).  Boxes of an eighth of a window, not whole
    windows, so that a strip of one reflectance narrower than a window (a checker square seen
    obliquely) keeps both its edges.  A step's height is ``g``'s mean over the span to the next
    step, less what the steps kept within a window before it still add there (``g`` sums every
    step of the last window).  So a step the detector misses spoils the heights of the steps after it
    within a window, which may then be rejected in turn; read right to left, each height is
    measured on the span before its step instead, where the misses are others.  Each line is
    read both ways (`_line_steps`): a step found either way is kept, and where both ways found
    one within a box its height is the mean of the two (`_two_way_steps`; `both_ways` False:
    left to right only, as until the fourteenth session).  The running sum of
    the heights along the line is the log albedo; a smooth albedo changes ``g`` too slowly to
    count and is left to the flat field.  With `soft` the steps over which ``g`` is flat (an
    albedo edge) are blurred by a Gaussian of the camera's blur, as the camera blurs them
    (False: every step sharp, as until the forty-fifth session).  Lines in threads (compiled
    kernels, `_albedo_steps_rows`, `_levels_rows`).  The constants (`STEP_THRESHOLD` and the
    others) say what is tested.

    The sharpness and concentration tests and the soft edges assume a camera blur of `blur` px
    (a Gaussian sigma, the pixels' aperture included).  None: measured on the capture's own
    flat steps (`sliscan.edge_blur.edge_blur`, found with `STEP_SPREAD`); a blur up to
    `STEP_BLUR_BAND` times `STEP_SPREAD`, a sharper one, or one the capture does not tell
    (too few tall flat steps) counts as `STEP_SPREAD`; a blurrier one finds the steps again
    (the sharpness asked of a step with one view, near a line's end, no looser than for
    `STEP_SPREAD`).
    """
    img = np.ascontiguousarray(img, dtype=np.float32)
    windows = np.ascontiguousarray(np.broadcast_to(windows, (img.shape[0],)), dtype=np.intp)
    floor = _step_floor(img)
    find = functools.partial(_find_steps, img, windows, floor, threshold=threshold, sharpness=sharpness,
                             flat_below=flat_below, concentration=concentration, both_ways=both_ways)
    if blur is None:
        delta, flat, measured = _steps_and_blur(find, img, windows, floor)
        blur = steps_blur(measured)
        if blur != STEP_SPREAD:
            delta, flat = find(blur, soft)
    else:
        delta, flat = find(float(blur), soft)
    out = np.empty(img.shape, dtype=np.float32)
    over_rows(lambda rows: _levels_rows(delta, flat, float(blur) if soft else 0.0, rows, out), img.shape[0])
    return out


def steps_blur(measured: float | None) -> float:
    """The camera blur (px) the albedo steps are found and blurred for, given the one a capture
    measures (`camera_blur`): `STEP_SPREAD` unless it is over `STEP_BLUR_BAND` times that."""
    return STEP_SPREAD if measured is None or measured <= STEP_BLUR_BAND * STEP_SPREAD else measured


def _step_floor(img: NDArray[np.float32]) -> float:
    """The albedo-step detector's floor: intensities under 1 % of the capture's bright level
    (its 99th percentile) count as it."""
    return 0.01 * max(float(np.percentile(img[::4, ::4], 99)), 1e-6)


def _find_steps(img: NDArray[np.float32], windows: NDArray[np.intp], floor: float, blur: float, judge_flat: bool, *,
                threshold: float = STEP_THRESHOLD, sharpness: float = STEP_SHARPNESS,
                flat_below: float = STEP_FLAT_BELOW, concentration: float = STEP_CONCENTRATION,
                both_ways: bool = True) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """The albedo steps of every line of `img` ``(H, W)`` (float32, lines along axis 1;
    `windows` ``(H,)`` intp) for a camera blur of `blur` px (`_albedo_steps_rows`): their log
    heights ``(H, W)`` float32 (0 elsewhere) and, with `judge_flat`, which are flat ``(H, W)``."""
    delta, flat = np.empty(img.shape, dtype=np.float32), np.empty(img.shape, dtype=np.bool_)
    over_rows(lambda rows: _albedo_steps_rows(img, windows, floor, threshold, float(sharpness), float(flat_below),
                                              float(concentration), both_ways, blur, judge_flat, rows, delta, flat),
              img.shape[0])
    return delta, flat


def _steps_and_blur(find: Callable[[float, bool], tuple[NDArray[np.float32], NDArray[np.bool_]]],
                    img: NDArray[np.float32], windows: NDArray[np.intp],
                    floor: float) -> tuple[NDArray[np.float32], NDArray[np.bool_], float | None]:
    """The steps `find` (`_find_steps` with its options bound) finds for `STEP_SPREAD`, which
    are flat, and the camera blur their tall flat ones measure (`edge_blur`; None: too few)."""
    delta, flat = find(STEP_SPREAD, True)
    return delta, flat, edge_blur(img, windows, flat & (np.abs(delta) >= BLUR_HEIGHT), floor)


def camera_blur(image: NDArray[np.floating], spec: PatternSpec, carriers: Carriers | None = None) -> float | None:
    """The camera's blur measured on a composite-pattern capture's albedo edges, as the window
    demodulator measures it before dividing them out (`_albedo_steps`, `sliscan.edge_blur`).

    Parameters
    ----------
    image : (H, W) array
        The camera frame (uint8, uint16 or float in [0, 1]).
    spec : PatternSpec
        What was projected.
    carriers : Carriers, optional
        Found in it earlier (else detected).

    Returns
    -------
    float or None
        A Gaussian's sigma in camera pixels (the pixels' aperture included: a camera blurred by
        1 px reads about 1.04), or None where the capture has too few tall albedo edges to tell
        (a smooth or uniform surface).  The albedo steps assume 1 px unless it is over
        `STEP_BLUR_BAND` px; a camera much blurrier than 2 px also loses the finest carriers.
    """
    img = check_image("capture", image)
    found = carriers if carriers is not None else detect_carriers(img, spec)
    view = np.ascontiguousarray(along_carriers(img, spec), dtype=np.float32)
    windows = np.ascontiguousarray(np.broadcast_to(found.line_windows(), (view.shape[0],)), dtype=np.intp)
    floor = _step_floor(view)
    return _steps_and_blur(functools.partial(_find_steps, view, windows, floor), view, windows, floor)[2]


def normalise_albedo(image: NDArray[np.floating], carriers: Carriers, *, estimate: str = "steps",
                     **options: float | bool) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Divide a capture by an edge-preserving estimate of its albedo (`albedo_estimate`), line
    by line along axis 1.

    Returns
    -------
    (normalised, albedo) : two (H, W) float32 arrays
        ``image / albedo`` and the estimate.
    """
    img = np.asarray(image, dtype=np.float32)
    albedo = albedo_estimate(img, carriers, estimate=estimate, **options)
    return (img / albedo).astype(np.float32), albedo


def albedo_estimate(image: NDArray[np.floating], carriers: Carriers, *, estimate: str = "steps",
                    **options: float | bool) -> NDArray[np.float32]:
    """An edge-preserving estimate of a capture's albedo, line by line along axis 1.

    A reflectance edge multiplies the whole pattern, so inside a window that straddles it the
    carriers are no longer sinusoids of constant amplitude: the step's broadband spectrum lands
    in every carrier band, and dividing by the local mean (the window demodulator's flat field)
    cannot undo it.  Dividing by an estimate that follows the edge sharply but not the pattern
    leaves the pattern, times a constant, on both sides.

    Estimates (`estimate`; keyword `options` in brackets):

    * ``"steps"`` (threshold, sharpness, flat_below, concentration, both_ways, blur, soft;
      see `_albedo_steps`): only the sharp steps, found where the capture stops repeating
      itself one carrier period later; between them 1, so a smooth albedo is left to the flat
      field; a step over which that repetition holds (an albedo edge) blurred as the camera
      blurs it (its blur measured on the capture).  The only one that helped (issue 8).
    * ``"sharp-steps"``: the same steps, none blurred (``soft=False``).
    * ``"closing"`` (size = 1.25 windows): the upper envelope, a morphological closing
      (maximum then minimum filter).  It keeps a step exactly but also every flank of the
      pattern's peaks where the albedo varies within a period: it loses 7 points of stripe
      accuracy on the checker and 23 on the smooth albedo.
    * ``"envelopes"`` (size): the geometric mean of the closing and the opening.
    * ``"guided"`` (size = 1 window, eps = 4 times the median variance): a self-guided
      filter of the log capture (He et al.), nearly a log-domain local mean.
    * ``"notch-log"`` / ``"notch"`` (width = 0.25 spacings): the (log) capture with every
      multiple of each line's carrier spacing notched out (Gaussian notches); in the log
      domain the albedo adds to the pattern, but the pattern's harmonics spread past the
      notches where the surface changes the carriers' local frequency.

    Returns
    -------
    (H, W) float32 array
        Relative for the steps; floored at 1e-4 of the image's maximum for the others.
    """
    img = np.asarray(image, dtype=np.float32)
    if estimate not in ALBEDO_ESTIMATES:
        raise InputError(f"estimate must be one of {', '.join(ALBEDO_ESTIMATES)}, got {estimate!r}")
    h, w = img.shape
    windows = np.broadcast_to(carriers.line_windows(), (h,))
    if estimate in ("steps", "sharp-steps"):
        return _albedo_steps(img, windows, **(options | ({"soft": False} if estimate == "sharp-steps" else {})))
    floor = np.float32(max(float(img.max()), 1e-6) * 1e-4)
    length = max(3, int(np.ceil(options.get("size", 1.0 if estimate == "guided" else 1.25) * float(windows.max()))))
    if estimate in ("closing", "envelopes"):
        albedo = scipy.ndimage.grey_closing(img, size=(1, length), mode="nearest")
        if estimate == "envelopes":
            lower = scipy.ndimage.grey_opening(img, size=(1, length), mode="nearest")
            albedo = np.sqrt(np.maximum(albedo, floor) * np.maximum(lower, floor))
    elif estimate == "guided":
        # a = var / (var + eps): where the window's variance is mostly a step, larger than the
        # pattern's, the output follows the capture; elsewhere it is the local mean
        logi = np.log(np.maximum(img, floor)).astype(np.float64)
        box = functools.partial(scipy.ndimage.uniform_filter1d, size=length, axis=1, mode="nearest")
        mean = box(logi)
        variance = np.maximum(box(logi * logi) - mean * mean, 0)
        a = variance / (variance + options.get("eps", 4.0) * float(np.median(variance)) + 1e-12)
        albedo = np.exp(box(a) * logi + box(mean - a * mean))
    else:
        pad = int(windows.max()) * 2
        work = np.pad(img.astype(np.float64), ((0, 0), (pad, pad)), mode="reflect")
        if estimate == "notch-log":
            work = np.log(np.maximum(work, float(floor)))
        n = work.shape[1]
        first = carriers.line_frequencies(slice(0, h))[:, 0]
        spacing = _common_spacing(carriers.frequencies) * first / carriers.frequencies[0]
        harmonic = np.fft.rfftfreq(n)[None, :] / spacing[:, None]
        k = np.round(harmonic)
        gain = np.where(k >= 1, 1 - np.exp(-0.5 * ((harmonic - k) / (0.5 * options.get("width", 0.25))) ** 2), 1.0)
        smooth = np.fft.irfft(np.fft.rfft(work, axis=1) * gain, n=n, axis=1)[:, pad : pad + w]
        albedo = np.exp(smooth) if estimate == "notch-log" else smooth
    return np.maximum(albedo, floor).astype(np.float32)


def butterworth_bandpass(freqs: NDArray[np.float64], centre: float, half_width: float, order: int) -> NDArray[np.float64]:
    """Butterworth band-pass magnitude ``1 / sqrt(1 + ((f - fc) / hw) ** (2 order))`` (fig. 3.21)."""
    return 1.0 / np.sqrt(1.0 + ((freqs - centre) / half_width) ** (2 * order))


def bandpass_filters(width: int, carriers: Carriers, *, order: int = 4, bandwidth: float = 0.5) -> NDArray[np.float64]:
    """One-sided band-pass transfer functions, one per carrier, ``(C, width)`` over `fftfreq`.

    Each passes its carrier (half-width `bandwidth` times the spacing to the nearest other
    carrier), notches every other carrier with the complement of a band-pass of the same
    shape, blocks DC, and is zero at negative frequencies (the Hilbert step of eq. 3.4; the
    factor 2 restores the amplitude of the analytic signal).
    """
    f = np.fft.fftfreq(width)
    cf = carriers.frequencies
    gaps = np.abs(cf[:, None] - cf[None, :]) + np.diag(np.full(cf.size, np.inf))
    half = bandwidth * np.minimum(gaps.min(axis=1), cf)
    filters = np.empty((cf.size, width))
    for n, fc in enumerate(cf):
        h = butterworth_bandpass(f, fc, half[n], order)
        for m, fm in enumerate(cf):
            if m != n:
                h *= 1.0 - butterworth_bandpass(f, fm, 0.5 * half[m], order)
        h *= 1.0 - butterworth_bandpass(f, 0.0, 0.5 * half[n], order)
        filters[n] = 2.0 * h * (f > 0)
    return filters


def demodulate_bandpass(image: NDArray[np.floating], carriers: Carriers, *, order: int = 4,
                        bandwidth: float = 0.5, chunk_lines: int = 256) -> Demodulated:
    """The thesis's demodulator (section 3.4, eqs. 3.3-3.4): Butterworth band-pass + Hilbert.

    Each line is Fourier transformed; per carrier the spectrum is multiplied by its one-sided
    band-pass (`bandpass_filters`) and inverse transformed; the envelope is the magnitude of
    that analytic signal.  The DC map is a Butterworth low-pass of the same width.

    Parameters
    ----------
    image : (H, W) array
        Capture with the carriers along axis 1.
    carriers : Carriers
    order : int
        Butterworth order.
    bandwidth : float
        Pass-band half-width as a fraction of the spacing to the nearest carrier.
    """
    img = check_image("capture", image)
    h, w = img.shape
    filters = bandpass_filters(w, carriers, order=order, bandwidth=bandwidth)
    f = np.fft.fftfreq(w)
    lowpass = butterworth_bandpass(f, 0.0, 0.5 * bandwidth * carriers.frequencies.min(), order)
    amp = np.empty((filters.shape[0], h, w), dtype=np.float32)
    dc = np.empty((h, w), dtype=np.float32)
    residual = np.empty((h, w), dtype=np.float32)
    for r0 in range(0, h, chunk_lines):
        spec = np.fft.fft(img[r0 : r0 + chunk_lines].astype(np.float64), axis=1)
        mean = np.fft.ifft(spec * lowpass, axis=1).real
        a = np.abs(np.fft.ifft(spec[None] * filters[:, None, :], axis=2))
        power = np.abs(np.fft.ifft(spec * (1 - lowpass), axis=1)) ** 2
        amp[:, r0 : r0 + chunk_lines] = a
        dc[r0 : r0 + chunk_lines] = mean
        residual[r0 : r0 + chunk_lines] = np.clip(1 - 0.5 * np.sum(a * a, axis=0) / np.maximum(power, 1e-12), 0, 1)
    return Demodulated(amplitude=amp, dc=dc, residual=residual)


#: Exposure limits of `check_exposure`: a capture is dark when 99 % of its pixels lie below
#: `DARK_LEVEL` of full scale, saturated when more than `SATURATED_FRACTION` of them reach
#: `SATURATED_LEVEL` (254 of 255).
DARK_LEVEL = 0.03
SATURATED_LEVEL = 254 / 255
SATURATED_FRACTION = 0.5


@numba.njit(cache=True, nogil=True)
def _exposure_rows(image: NDArray[np.float32], rows: NDArray[np.intp], dark: np.float32, saturated: np.float32,
                   counts: NDArray[np.int64]) -> None:
    """Count the pixels of the given rows at or above `dark` and at or above `saturated` into
    ``counts[rows[0]]`` (one slot per block of rows, so that threads do not share one)."""
    bright, full = 0, 0
    for y in rows:
        for x in range(image.shape[1]):
            v = image[y, x]
            bright += v >= dark
            full += v >= saturated
    counts[rows[0], 0], counts[rows[0], 1] = bright, full


def check_exposure(image: NDArray[np.float32]) -> None:
    """Refuse a capture too dark or too saturated to carry the pattern (one-line `InputError`).

    One counting pass over the rows in threads (a percentile would sort: 40 ms more at 5 MP;
    numpy's two comparisons and counts cost ~5 ms there, this ~1 ms)."""
    counts = np.zeros((image.shape[0], 2), np.int64)
    over_rows(lambda rows: _exposure_rows(image, rows, np.float32(DARK_LEVEL), np.float32(SATURATED_LEVEL), counts)
              if rows.size else None, image.shape[0])
    bright, full = counts.sum(axis=0)
    if bright < 0.01 * image.size:
        raise InputError(f"the capture is dark (99 % of pixels below {DARK_LEVEL:.0%} of full scale): is the projector "
                         f"on and the exposure long enough?")
    saturated = full / image.size
    if saturated > SATURATED_FRACTION:
        raise InputError(f"the capture is saturated ({saturated:.0%} of pixels at full scale): shorten the exposure "
                         f"or dim the projector")


def demodulate(image: NDArray[np.floating], spec: PatternSpec, *, method: str = "window",
               carriers: Carriers | None = None, albedo: str | None = "steps",
               centred: bool = False, camera_blur: float | None = None) -> tuple[Demodulated, Carriers]:
    """Detect the carriers (unless given) and demodulate a capture in camera orientation.

    Parameters
    ----------
    image : (H, W) array
        The camera frame.
    spec : PatternSpec
        What was projected.
    method : {"window", "bandpass"}
        `demodulate_window` (default) or the thesis's `demodulate_bandpass`.
    carriers : Carriers, optional
        Reuse carriers found earlier (e.g. for a video of the same rig).
    albedo : str or None
        ``"window"`` only: the albedo estimate the capture is divided by first
        (`normalise_albedo`), None for none; ``"steps"`` is ``"sharp-steps"`` for a pattern
        with a phase channel (its fringe's phase lost where the steps were blurred).
    centred : bool
        ``"window"`` only: also every pixel's centred window's envelopes (`Demodulated.centred`).
    camera_blur : float, optional
        ``"window"`` only: the camera's blur for the albedo steps (`demodulate_window`); None
        measures it on the capture.

    Returns
    -------
    (Demodulated, Carriers)
        Maps are ``(H, W)`` / ``(C, H, W)`` in the camera's own orientation.
    """
    img = check_image("capture", image)
    if method not in ("window", "bandpass"):
        raise InputError(f"method must be 'window' or 'bandpass', got {method!r}")
    check_exposure(img)
    view = along_carriers(img, spec)
    found = carriers if carriers is not None else detect_carriers(img, spec)
    ramped = range(spec.bits, spec.bits + len(spec.phase_carriers))  # the phase channel's carriers
    if albedo == "steps" and spec.phase_carriers:
        albedo = "sharp-steps"  # blurred steps cost the fringe phase (docs/accuracy.md, "Soft albedo edges")
    out = (demodulate_window(view, found, albedo=albedo, ramped=ramped, centred=centred, camera_blur=camera_blur)
           if method == "window" else demodulate_bandpass(view, found))
    if spec.orientation == "columns":
        out = out.mapped(lambda a: np.ascontiguousarray(np.swapaxes(a, -1, -2)))
    return out, found
