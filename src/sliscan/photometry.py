"""Projector photometry (thesis section 3.2): gamma, optical roll-off, and carrier planning.

A user characterises a rig once, before scanning:

1. **Gamma** (3.2.1, table 3.2).  Project a full-range sine (a ``carrier_only`` pattern with one
   low carrier and ``a_p = b_p = 0.5``) and capture it.  `estimate_gamma` finds the sine's local
   phase at every camera pixel from the capture itself (the fundamental of any monotone
   response has the projected phase, so no geometry is needed), divides out each pixel's local
   mean and fundamental amplitude (the unknown albedo, shading and ambient light: an affine map
   per pixel), and compares the result with the ideal sine passed through candidate gammas:
   the thesis's table of errors, a continuous estimate (the gamma of least error), and, where
   the sine spans the whole drive range, the response itself as a look-up table (camera level
   against drive level, up to an affine map).
2. **Roll-off** (3.2.2, figs. 3.9-3.12).  Project a carrier-only pattern (gamma pre-corrected,
   see below) and capture it.  `measure_rolloff` detects the carriers, measures each one's
   amplitude relative to the local mean at every lit pixel, and divides by the amplitude that
   was projected, giving each carrier's relative attenuation; `compensating_weights` turns it
   into carrier weights that pre-compensate it (fig. 3.13).
3. `Characterization` holds both, reads and writes them as JSON, and `apply` gives the
   compensated, pre-corrected `PatternSpec` that decoding then reads.

**Why the thesis lost its lowest carrier** (3.2.2, fig. 3.15).  A nonlinearity ``g`` of the
projected sum of carriers (a projector gamma, a pre-correction that does not match it, camera
saturation) adds products at every ``sum_i k_i f_i`` with integer ``k_i``: harmonics ``2 f_i``,
sums and differences ``f_i +- f_j``, third-order ``2 f_i - f_j``, ...  The thesis's carriers
32, 64, 96, 128 are multiples of 32, so every product is a multiple of 32 too and lands on a
carrier or on DC: ``64 - 32 = 96 - 64 = 128 - 96 = 32``, ``2 * 32 = 64``, ``32 + 64 = 96``.  Where
a bit is off, its carrier is filled by its neighbours' products and reads as on.
`plan_carriers` picks carriers (on a grid of one spacing, so sliscan's window demodulator still
separates them) none of whose products up to a given order falls in another carrier's pass band
or on DC.  Measuring roll-off with an uncorrected gamma suffers the same products: they land on
the thesis's carriers coherently and bias their heights, so project the carrier-only pattern
pre-corrected with the measured gamma, or pass the measured response to `measure_rolloff`.

References
----------
P. Gupta, "Gray Code Composite Pattern Structured Light Illumination", MS thesis, University of
Kentucky, 2007, section 3.2 (table 3.2, figs. 3.9-3.15).
"""

from __future__ import annotations

import functools
import itertools
import json
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.ndimage
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, atomic_write_text, check_image, to_uint8
from sliscan.demodulate import along_carriers, demodulate_window, detect_carriers
from sliscan.patterns import linear_pattern, precorrect, render_pattern
from sliscan.types import PatternSpec, _load_json

__all__ = [
    "GAMMA_CANDIDATES",
    "Characterization",
    "GammaFit",
    "Rolloff",
    "carrier_products",
    "gamma_response",
    "projected_amplitudes",
    "sine_phase",
    "compensating_weights",
    "estimate_gamma",
    "measure_rolloff",
    "plan_carriers",
    "sine_target",
]

#: The candidate gammas of the thesis's table 3.2.
GAMMA_CANDIDATES = (2.0, 2.4, 2.5, 3.0, 3.5)
#: Drive levels of a measured response look-up table (every 8 of 256 drive steps).
RESPONSE_LEVELS = 33
#: A gamma fit's residual must stay below this fraction of the fitted sine's variance; a wrong
#: pattern (or no pattern) leaves far more.
MIN_EXPLAINED = 0.9
#: A carrier measured weaker than this fraction of the strongest is not a carrier of the
#: pattern (wrong pattern, or optics that cannot resolve it: weights could not compensate).
MIN_ATTENUATION = 0.1
#: The frame is split into TILES x TILES tiles, each estimated alone for the spread.
TILES = 3
#: Largest accepted spread (standard deviation) of the tiles' gammas: more means the albedo
#: varies at the sine's scale and biases the estimate.
MAX_GAMMA_SPREAD = 0.04
#: Fewest usable pixels (lit, modulated, clear of edges) an estimate may rest on.
MIN_PIXELS = 2000


# --------------------------------------------------------------------------------------------
# Targets and responses
# --------------------------------------------------------------------------------------------


def sine_target(projector_size: tuple[int, int], *, cycles: float = 8.0, **changes: Any) -> PatternSpec:
    """The gamma target: a full-range sine, `cycles` periods across the projector width.

    A ``carrier_only`` pattern with one carrier and ``a_p = b_p = 0.5``.  A low frequency
    keeps the optics' roll-off of its harmonics small (8 cycles per 1024 px: a 128 px period,
    whose third harmonic a 1 px Gaussian blur attenuates by 1 %).

    >>> spec = sine_target((1024, 768))
    >>> spec.kind, spec.carriers, spec.a_p, spec.b_p
    ('carrier_only', (8.0,), 0.5, 0.5)
    """
    width = projector_size[0] if changes.get("orientation", "rows") == "rows" else projector_size[1]
    base = dict(kind="carrier_only", projector_size=tuple(projector_size), bits=1,
                carriers=(cycles * width / 1024.0,), weights=(1.0,), a_p=0.5, b_p=0.5)
    base.update(changes)
    return PatternSpec(**base)


def gamma_response(gamma: float, levels: int = RESPONSE_LEVELS) -> NDArray[np.float64]:
    """The response ``d ** gamma`` at `levels` evenly spaced drive levels ``d`` in [0, 1].

    >>> gamma_response(2.0, 3).tolist()
    [0.0, 0.25, 1.0]
    """
    return np.linspace(0.0, 1.0, levels) ** gamma


def _light(drive: NDArray[np.floating], response: ArrayLike) -> NDArray[np.float64]:
    """Projected light (normalised response) of drive levels through a response table."""
    table = np.asarray(response, dtype=np.float64)
    return np.interp(drive, np.linspace(0.0, 1.0, table.size), table)


# --------------------------------------------------------------------------------------------
# Gamma (thesis 3.2.1, table 3.2)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GammaFit:
    """What `estimate_gamma` found.

    Attributes
    ----------
    gamma : float
        Continuous estimate: the gamma of least error.
    table : tuple of (gamma, error) pairs
        The thesis's table 3.2: RMS difference between the captured sine, with each pixel's
        albedo and ambient light divided out, and the ideal sine through each candidate gamma
        (in units of the fundamental's amplitude).
    response : tuple of float or None
        The projector response (linear light, 0 at drive 0, 1 at full drive) at
        `RESPONSE_LEVELS` evenly spaced drive levels, as `PatternSpec.response` takes it;
        None when the sine does not span the whole drive range.
    samples : int
        Camera pixels the estimate rests on.
    spread : float
        Standard deviation of the gammas estimated in each tile of a 3 x 3 split of the frame
        alone: how far the estimate can be trusted.
    """

    gamma: float
    table: tuple[tuple[float, float], ...]
    response: tuple[float, ...] | None
    samples: int
    spread: float

    def to_dict(self) -> dict[str, Any]:
        return {"gamma": self.gamma, "table": [list(row) for row in self.table],
                "response": None if self.response is None else list(self.response), "samples": self.samples,
                "spread": self.spread}


def _check_kind(spec: PatternSpec, *, sine: bool) -> None:
    if spec.kind != "carrier_only" or (sine and len(spec.all_carriers) != 1):
        wanted = "a single-carrier carrier-only pattern (a sine)" if sine else "a carrier-only pattern"
        raise InputError(f"this measurement needs the capture of {wanted}; the pattern spec is a "
                         f"{spec.kind} pattern with {len(spec.all_carriers)} carriers")


def _hann_filter(lines: NDArray, length: int) -> NDArray:
    """Each line convolved with a normalised Hann window of `length` pixels (edges: nearest)."""
    kernel = np.hanning(length + 2)[1:-1]
    kernel /= kernel.sum()
    return scipy.ndimage.convolve1d(lines, kernel, axis=1, mode="nearest")


def sine_phase(view: NDArray[np.float32], frequency: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Local phase, fundamental amplitude and mean of a captured sine, by quadrature.

    Each line is mixed down by its own carrier frequency and averaged over a Hann window of
    two periods (whose nulls fall on DC and every harmonic after mixing).

    Parameters
    ----------
    view : (H, W) float32 array
        The capture with the carrier along axis 1.
    frequency : (H,) float array
        Carrier frequency of each line, cycles per camera pixel.

    Returns
    -------
    phase : (H, W) float64 array
        Phase of the projected sine at each pixel, radians (modulo 2 pi).
    amplitude, mean : (H, W) float64 arrays
        Fundamental amplitude and local mean, image units.
    local_frequency : (H, W) float64 array
        Derivative of the phase along the line, cycles per pixel.
    """
    h, w = view.shape
    x = np.arange(w, dtype=np.float64)
    lengths = np.maximum(np.round(2.0 / frequency).astype(int), 4)
    phase, amplitude, mean, local = (np.empty((h, w)) for _ in range(4))
    for length in np.unique(lengths):
        rows = np.flatnonzero(lengths == length)
        omega = 2 * np.pi * frequency[rows, None]
        lines = view[rows].astype(np.float64)
        mixed = lines * np.exp(-1j * omega * x)
        c = _hann_filter(mixed.real, int(length)) + 1j * _hann_filter(mixed.imag, int(length))
        phase[rows] = np.angle(c) + omega * x
        amplitude[rows] = 2 * np.abs(c)
        mean[rows] = _hann_filter(lines, int(length))
        step = np.angle(c[:, 1:] * np.conj(c[:, :-1])) / (2 * np.pi) + frequency[rows, None]
        local[rows] = np.concatenate([step, step[:, -1:]], axis=1)
    return phase, amplitude, mean, local


def _sine_samples(image: ArrayLike,
                  spec: PatternSpec) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
    """Projected phase, normalised capture ``(I - mean) / amplitude`` and tile index (of a
    `TILES` x `TILES` split of the frame) of the usable pixels, each ``(N,)``.

    Usable: lit (local mean above a fifth of the bright end), modulated like most lit pixels,
    with a local frequency within 20 % of the line's, and at least a window from the ends
    of the line.
    """
    img = check_image("capture", image)
    view = along_carriers(img, spec)
    # In the log image albedo and shading add instead of multiplying, so a texture as coarse as
    # the sine does not spread its peak (the detection locks on the harmonic otherwise).
    carriers = detect_carriers(np.log(np.maximum(img, 2.0 / 255)), spec)
    frequency = carriers.line_frequencies(np.arange(view.shape[0]))[:, 0]
    phase, amplitude, mean, local = sine_phase(view, frequency)
    lit = mean > 0.2 * np.percentile(mean, 99)
    depth = amplitude / np.maximum(mean, 1e-6)
    usual = np.median(depth[lit]) if lit.any() else 0.0
    ok = lit & (depth > 0.5 * usual) & (depth < 2 * usual) & (np.abs(local / frequency[:, None] - 1) < 0.2)
    margin = int(np.ceil(2.0 / frequency.min()))
    ok[:, :margin] = ok[:, -margin:] = False
    # a window that reaches an unusable pixel (an edge, a shadow) is not trusted either
    ok = scipy.ndimage.binary_erosion(ok, np.ones((3, margin // 2 * 2 + 1), bool))
    if ok.sum() < MIN_PIXELS:
        raise InputError(f"no usable sine in the capture ({int(ok.sum())} lit, modulated pixels; "
                         f"at least {MIN_PIXELS} are needed)")
    rows, cols = np.nonzero(ok)
    tile = (rows * TILES // ok.shape[0]) * TILES + cols * TILES // ok.shape[1]
    return phase[ok], (view[ok] - mean[ok]) / amplitude[ok], tile


def _sine_light(phase: NDArray[np.float64], spec: PatternSpec, gamma: float) -> NDArray[np.float64]:
    """Light ``d ** gamma`` of the drive ``d`` the projector got at each projected phase."""
    linear = spec.a_p + spec.b_p * spec.all_weights[0] * np.cos(phase)
    drive = to_uint8(precorrect(linear, spec)) / 255.0  # render_pattern's quantisation
    return drive**gamma


def _normalised_model(phase: NDArray[np.float64], spec: PatternSpec, gamma: float) -> NDArray[np.float64]:
    """The ideal sine through `gamma`, minus its mean, over its fundamental's amplitude."""
    grid = np.linspace(-np.pi, np.pi, 512, endpoint=False)
    light = _sine_light(grid, spec, gamma)
    fundamental = 2 * np.mean(light * np.cos(grid))
    return (_sine_light(phase, spec, gamma) - light.mean()) / fundamental


def _fit_error(phase: NDArray[np.float64], value: NDArray[np.float64], spec: PatternSpec, gamma: float) -> float:
    """RMS residual of ``value ~ o + s * model(gamma)`` (least-squares ``o`` and ``s``)."""
    model = _normalised_model(phase, spec, gamma)
    design = np.stack([np.ones_like(model), model], axis=1)
    coef, *_ = np.linalg.lstsq(design, value, rcond=None)
    return float(np.sqrt(np.mean((value - design @ coef) ** 2)))


def _response_table(phase: NDArray[np.float64], value: NDArray[np.float64], spec: PatternSpec,
                    levels: int) -> tuple[float, ...] | None:
    """Normalised capture against drive level: a local linear fit at each of `levels` evenly
    spaced levels (every sample shares a triangular weight between its two nearest levels),
    scaled to 0 at drive 0 and 1 at full drive.  None unless the drive spans [0, 1] and every
    level has samples nearby."""
    drive = _sine_light(phase, spec, 1.0)
    if drive.min() > 0.5 / (levels - 1) or drive.max() < 1 - 0.5 / (levels - 1):
        return None
    pos = drive * (levels - 1)
    low = np.minimum(np.floor(pos).astype(int), levels - 2)
    sums = np.zeros((5, levels))
    for level, weight in ((low, 1 - (pos - low)), (low + 1, pos - low)):
        offset = drive - level / (levels - 1)
        for k, term in enumerate((weight, weight * offset, weight * offset**2, weight * value,
                                  weight * offset * value)):
            sums[k] += np.bincount(level, term, minlength=levels)
    s0, s1, s2, sy, sxy = sums
    det = s0 * s2 - s1 * s1
    if np.any(s0 < 20) or np.any(det <= 1e-12 * s0 * s0):
        return None
    at_level = (s2 * sy - s1 * sxy) / det
    curve = np.maximum.accumulate(at_level - at_level[0])
    curve = curve / curve[-1] + np.linspace(0.0, 1e-6, levels)  # strictly increasing
    return tuple(float(v) for v in curve / curve[-1])


def estimate_gamma(image: ArrayLike, spec: PatternSpec, *, candidates: tuple[float, ...] = GAMMA_CANDIDATES,
                   levels: int = RESPONSE_LEVELS, bounds: tuple[float, float] = (0.3, 6.0)) -> GammaFit:
    """Projector gamma from the capture of a sine (thesis 3.2.1, table 3.2).

    Works on any scene: the sine's phase at each pixel comes from the capture (`sine_phase`),
    and each pixel's albedo and ambient light (an affine map of the light) are divided out with
    its local mean and fundamental amplitude.  The drive each phase got is known from `spec`
    (its pre-correction and 8-bit quantisation included), so the estimate is the projector's
    own gamma whatever the pattern was pre-corrected with.

    Parameters
    ----------
    image : (H, W) array
        Capture of the pattern `spec` (uint8, uint16 or float in [0, 1]).
    spec : PatternSpec
        A ``carrier_only`` pattern with a single carrier (`sine_target`).
    candidates : tuple of float
        Gammas of the table (default: the thesis's).
    levels : int
        Drive levels of the response table.
    bounds : (float, float)
        Search interval of the continuous estimate.

    Returns
    -------
    GammaFit

    Raises
    ------
    InputError
        If `spec` is not a sine, the capture shows no usable sine (flat, dark, another pattern),
        or the best fit leaves more than ``1 - MIN_EXPLAINED`` of it unexplained.
    """
    _check_kind(spec, sine=True)
    phase, value, tile = _sine_samples(image, spec)
    table = tuple((float(g), _fit_error(phase, value, spec, g)) for g in candidates)
    gamma, error = _best_gamma(phase, value, spec, bounds)
    explained = 1 - error**2 / float(np.var(_normalised_model(phase, spec, gamma)))
    if explained < MIN_EXPLAINED or not bounds[0] * 1.01 < gamma < bounds[1] * 0.99:
        raise InputError(f"the capture is not a sine of this pattern: the best response (gamma {gamma:.2f}, "
                         f"searched in {bounds[0]:g}..{bounds[1]:g}) leaves {1 - explained:.0%} of it unexplained")
    counts = np.bincount(tile, minlength=TILES * TILES)
    tiles = [_best_gamma(phase[tile == t], value[tile == t], spec, bounds)[0]
             for t in np.flatnonzero(counts >= MIN_PIXELS // 4)]
    spread = float(np.std(tiles)) if len(tiles) > 1 else 0.0
    if spread > MAX_GAMMA_SPREAD:
        raise InputError(f"the gamma varies across the capture (tiles from {min(tiles):.2f} to {max(tiles):.2f}): "
                         "the surface's albedo varies at the sine's scale; capture the sine on a plain matte target")
    return GammaFit(gamma=gamma, table=table, response=_response_table(phase, value, spec, levels),
                    samples=int(phase.size), spread=spread)


def _best_gamma(phase: NDArray[np.float64], value: NDArray[np.float64], spec: PatternSpec,
                bounds: tuple[float, float]) -> tuple[float, float]:
    """The gamma of least `_fit_error` within `bounds`, and that error."""
    best = scipy.optimize.minimize_scalar(lambda g: _fit_error(phase, value, spec, g), bounds=bounds,
                                          method="bounded", options={"xatol": 1e-4})
    return float(best.x), float(best.fun)


# --------------------------------------------------------------------------------------------
# Roll-off (thesis 3.2.2, figs. 3.9-3.13)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Rolloff:
    """What `measure_rolloff` found.

    Attributes
    ----------
    carriers : tuple of float
        The measured carriers (``PatternSpec.all_carriers``), cycles per projector width.
    attenuation : tuple of float
        Each carrier's captured amplitude over its projected amplitude, relative to the least
        attenuated one (1).
    samples : int
        Camera pixels the estimate rests on.
    """

    carriers: tuple[float, ...]
    attenuation: tuple[float, ...]
    samples: int

    def to_dict(self) -> dict[str, Any]:
        return {"carriers": list(self.carriers), "attenuation": list(self.attenuation), "samples": self.samples}


def projected_amplitudes(spec: PatternSpec, response: ArrayLike | None = None) -> NDArray[np.float64]:
    """Amplitude of each carrier in the projected light of a carrier-only pattern.

    The light is the spec's linear pattern (its pre-correction taken as right) or, with the
    projector's measured `response`, that response of the 8-bit drive image; amplitudes come
    from a least-squares fit of a DC and every carrier along one line.

    Returns
    -------
    (C,) float64 array
        In units of full projector light, ordered like ``spec.all_carriers``.
    """
    if response is None:
        line = np.clip(along_carriers(linear_pattern(spec), spec)[0], 0.0, 1.0)
    else:
        line = _light(along_carriers(render_pattern(spec), spec)[0].astype(np.float64), response)
    x = 2 * np.pi * np.arange(line.size) / spec.orthogonal_lines
    f = np.asarray(spec.all_carriers)
    design = np.concatenate([np.ones((line.size, 1)), np.cos(np.outer(x, f)), np.sin(np.outer(x, f))], axis=1)
    coef, *_ = np.linalg.lstsq(design, line, rcond=None)
    return np.hypot(coef[1 : f.size + 1], coef[f.size + 1 :])


def measure_rolloff(image: ArrayLike, spec: PatternSpec, *, response: ArrayLike | None = None) -> Rolloff:
    """Relative attenuation of each carrier from the capture of a carrier-only pattern (3.2.2).

    The carriers are detected (`detect_carriers`) and demodulated (`demodulate_window`); at
    every lit pixel whose window the carrier model explains, each carrier's amplitude is taken
    relative to the local mean (which divides out albedo and shading alike for every carrier);
    the median over those pixels, over the projected amplitude (`projected_amplitudes`), is the
    carrier's attenuation.

    Parameters
    ----------
    image : (H, W) array
        Capture of `spec` on any scene.
    spec : PatternSpec
        A ``carrier_only`` pattern (fig. 3.9), ideally pre-corrected with the measured gamma.
    response : array, optional
        The projector's measured response (`GammaFit.response`, or `gamma_response`); default:
        the spec's pre-correction is taken as right.  Without either, the products of an
        uncorrected gamma land on the thesis's carriers and bias them.

    Raises
    ------
    InputError
        If `spec` is not carrier-only, no carriers are found, too few pixels are usable, or a
        carrier comes out weaker than `MIN_ATTENUATION` of the strongest.
    """
    _check_kind(spec, sine=False)
    img = check_image("capture", image)
    carriers = detect_carriers(img, spec)
    demod = demodulate_window(along_carriers(img, spec), carriers)
    dc = demod.dc
    lit = dc > 0.2 * np.percentile(dc, 99)
    ratio = demod.amplitude / np.maximum(dc, 1e-6)
    total = ratio.sum(axis=0)
    usual = np.median(total[lit]) if lit.any() else 0.0
    # windows the carrier model explains (unmodelled products raise every residual alike)
    clean = demod.residual < max(0.2, 2 * float(np.median(demod.residual[lit]))) if lit.any() else lit
    ok = lit & clean & (total > 0.5 * usual)
    if ok.sum() < MIN_PIXELS:
        raise InputError(f"no usable carriers in the capture ({int(ok.sum())} lit, modulated pixels; "
                         f"at least {MIN_PIXELS} are needed)")
    gain = np.median(ratio[:, ok], axis=1) / projected_amplitudes(spec, response)
    attenuation = gain / gain.max()
    weak = np.flatnonzero(attenuation < MIN_ATTENUATION)
    if weak.size:
        f = spec.all_carriers[weak[0]]
        raise InputError(f"carrier {f:g} comes out at {attenuation[weak[0]]:.0%} of the strongest: not a capture "
                         "of this carrier-only pattern, or optics that cannot resolve it")
    return Rolloff(carriers=spec.all_carriers, attenuation=tuple(float(a) for a in attenuation), samples=int(ok.sum()))


def compensating_weights(rolloff: Rolloff, spec: PatternSpec) -> tuple[float, ...]:
    """Carrier weights for `spec` that pre-compensate a measured roll-off (fig. 3.13).

    Each carrier's design weight is divided by its attenuation, interpolated linearly in
    ``log(attenuation)`` against ``frequency**2`` (exact for a Gaussian blur) between the
    measured carriers, then all are scaled so their sum is unchanged: the pattern spans the
    same drive range as before.

    Returns
    -------
    tuple of float
        Parallel to ``spec.all_weights`` (bits, then the pilot).

    Raises
    ------
    InputError
        If a carrier of `spec` lies outside the measured ones (no extrapolation).

    >>> r = Rolloff(carriers=(32.0, 128.0), attenuation=(1.0, 0.5), samples=0)
    >>> [round(w, 3) for w in compensating_weights(r, PatternSpec(bits=2, carriers=(32, 128), weights=(1, 1)))]
    [0.667, 1.333]
    """
    measured = np.asarray(rolloff.carriers)
    wanted = np.asarray(spec.all_carriers)
    outside = wanted[(wanted < measured.min() * (1 - 1e-6)) | (wanted > measured.max() * (1 + 1e-6))]
    if outside.size:
        raise InputError(f"carrier {outside[0]:g} lies outside the measured roll-off "
                         f"({measured.min():g}..{measured.max():g} cycles per width): measure it with these carriers")
    order = np.argsort(measured)
    log_att = np.interp(wanted**2, measured[order] ** 2, np.log(np.asarray(rolloff.attenuation)[order]))
    design = np.asarray(spec.all_weights)
    weights = design / np.exp(log_att)
    weights *= np.abs(design).sum() / np.abs(weights).sum()
    return tuple(float(w) for w in weights)


# --------------------------------------------------------------------------------------------
# The characterisation file
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Characterization:
    """A rig's measured projector response and roll-off: what ``sliscan characterize`` writes.

    JSON: ``{"kind": "sliscan characterization", "projector_size": [W, H],
    "gamma": {"gamma", "table", "response", "samples", "spread"} or null,
    "rolloff": {"carriers", "attenuation", "samples"} or null}``.
    """

    projector_size: tuple[int, int]
    gamma: GammaFit | None = None
    rolloff: Rolloff | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "sliscan characterization", "projector_size": list(self.projector_size),
                "gamma": None if self.gamma is None else self.gamma.to_dict(),
                "rolloff": None if self.rolloff is None else self.rolloff.to_dict()}

    def save(self, path: str | os.PathLike) -> None:
        """Write the JSON atomically."""
        atomic_write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike) -> Characterization:
        """Read a characterisation JSON; raises `InputError` naming the file."""
        d = _load_json(path)
        if d.get("kind") != "sliscan characterization":
            raise InputError(f"{path}: not a sliscan characterization (no \"kind\": \"sliscan characterization\")")
        try:
            gamma = None if d.get("gamma") is None else GammaFit(
                gamma=float(d["gamma"]["gamma"]), table=tuple((float(g), float(e)) for g, e in d["gamma"]["table"]),
                response=None if d["gamma"].get("response") is None else tuple(map(float, d["gamma"]["response"])),
                samples=int(d["gamma"]["samples"]), spread=float(d["gamma"]["spread"]))
            rolloff = None if d.get("rolloff") is None else Rolloff(
                carriers=tuple(map(float, d["rolloff"]["carriers"])),
                attenuation=tuple(map(float, d["rolloff"]["attenuation"])), samples=int(d["rolloff"]["samples"]))
            size = tuple(int(v) for v in d["projector_size"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{path}: malformed characterization ({type(exc).__name__}: {exc})") from None
        if rolloff is not None and (len(rolloff.carriers) != len(rolloff.attenuation)
                                    or not all(a > 0 for a in rolloff.attenuation)):
            raise InputError(f"{path}: rolloff needs one positive attenuation per carrier")
        return cls(projector_size=size, gamma=gamma, rolloff=rolloff)  # type: ignore[arg-type]

    def apply(self, spec: PatternSpec) -> PatternSpec:
        """`spec` pre-corrected with the measured response (the table if there is one, else the
        gamma) and with carrier weights that compensate the measured roll-off."""
        if tuple(spec.projector_size) != tuple(self.projector_size):
            (pw, ph), (cw, ch) = spec.projector_size, self.projector_size
            raise InputError(f"the characterization is of a {cw}x{ch} projector, the pattern is for {pw}x{ph}")
        changes: dict[str, Any] = {}
        if self.gamma is not None:
            changes = ({"gamma": 1.0, "response": self.gamma.response} if self.gamma.response is not None
                       else {"gamma": self.gamma.gamma, "response": None})
        if self.rolloff is not None:
            weights = compensating_weights(self.rolloff, spec)
            changes["weights"] = weights[: spec.bits]
            if spec.pilot is not None:
                changes["pilot_weight"] = weights[-1]
        return spec.with_(**changes)


# --------------------------------------------------------------------------------------------
# Carrier planning
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=64)
def _combinations(channels: int, order: int) -> NDArray[np.int64]:
    """Every integer vector ``k`` (``(M, channels)``, read-only) with ``2 <= sum |k_i| <= order``,
    one of each ``+-k`` pair (its first nonzero entry positive)."""
    rows = []
    for n in range(2, order + 1):  # n units spread over the channels with signs
        for picks in itertools.combinations_with_replacement(range(channels), n):
            counts = np.bincount(picks, minlength=channels)
            used = np.flatnonzero(counts)
            for signs in itertools.product((1, -1), repeat=used.size - 1):
                k = counts.copy()
                k[used[1:]] *= np.asarray(signs, dtype=np.int64)
                rows.append(k)
    out = np.array(rows, dtype=np.int64).reshape(-1, channels)
    out.setflags(write=False)
    return out


def carrier_products(carriers: ArrayLike, order: int) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Frequencies ``|sum_i k_i f_i|`` of the intermodulation products up to `order`.

    Parameters
    ----------
    carriers : (C,) array
        Carrier frequencies (any unit).
    order : int
        Largest ``sum |k_i|`` (2: harmonics, sums and differences; 3: also ``2 f_i - f_j``, ...).

    Returns
    -------
    frequencies : (M,) float64 array
    combinations : (M, C) int64 array
        The ``k`` of each product.

    >>> f, k = carrier_products([32, 64, 96, 128], 2)
    >>> sorted(set(f[f <= 128].tolist()))  # every product lands on a carrier
    [32.0, 64.0, 96.0, 128.0]
    """
    f = np.asarray(carriers, dtype=np.float64)
    k = _combinations(f.size, order)
    return np.abs(k @ f), k


def _clashes(grid: NDArray[np.int64], order: int, reach: float) -> bool:
    """Whether a product of the integer carriers `grid` (up to `order`) lies within `reach`
    (grid units) of a carrier it does not contain, or of DC."""
    freq, k = carrier_products(grid, order)
    near = np.abs(freq[:, None] - grid[None, :].astype(np.float64)) < reach - 1e-9
    return bool(np.any(freq < reach - 1e-9) or np.any(near))


@functools.lru_cache(maxsize=256)
def _search(top: int, channels: int, order: int, reach: float) -> tuple[int, ...] | None:
    """Largest (lexicographically, highest first) set of `channels` integers in ``[1, top]``
    that contains `top` and has no clash (`_clashes`); None if there is none."""

    def extend(chosen: tuple[int, ...], below: int) -> tuple[int, ...] | None:
        if len(chosen) == channels:
            return chosen
        for n in range(below - 1, channels - len(chosen) - 1, -1):
            trial = chosen + (n,)
            if not _clashes(np.array(trial), order, reach):
                found = extend(trial, n)
                if found is not None:
                    return found
        return None

    return extend((top,), top)


def plan_carriers(width: int, channels: int, *, highest: float | None = None, half_width: float | None = None,
                  order: int = 3, max_grid: int = 64) -> tuple[float, ...]:
    """Carriers whose nonlinearity products miss every other carrier's pass band and DC.

    Carriers are placed on a grid ``n * d`` (integer ``n``), the top one at `highest`, so that
    sliscan's window demodulator, whose window is one grid period ``1 / d``, keeps them
    orthogonal; the coarsest grid (shortest window) with a valid set wins, and on it the set
    with the highest carriers.  A set is valid when no product ``|sum_i k_i f_i|`` with
    ``2 <= sum |k_i| <= order`` lies within `half_width` of a carrier or of DC.

    Parameters
    ----------
    width : int
        Projector pixels along the carrier direction.
    channels : int
        Number of carriers (bits, plus a pilot if one is wanted).
    highest : float, optional
        Highest usable carrier, cycles per width; default ``width / 8`` (an 8-pixel period,
        the thesis's highest).
    half_width : float, optional
        Pass-band half-width of each carrier, cycles per width; default one grid spacing (the
        window demodulator's resolution).
    order : int
        Expected nonlinearity order (2 for a mild gamma; 3 covers ``2 f_i - f_j``).

    Returns
    -------
    tuple of float
        Carrier frequencies in cycles per width, lowest first.

    Raises
    ------
    InputError
        If no valid set exists on any grid up to `max_grid` steps below `highest`.

    >>> [round(f, 2) for f in plan_carriers(1024, 4, order=2)]  # = spread_carriers: a 56 px window
    [73.14, 91.43, 109.71, 128.0]
    >>> [round(f, 2) for f in plan_carriers(1024, 4, order=3)]  # a 96 px window
    [53.33, 96.0, 117.33, 128.0]
    """
    top = width / 8 if highest is None else float(highest)
    if channels < 1 or order < 1 or not 0 < top < width / 2:
        raise InputError(f"plan_carriers needs channels >= 1, order >= 1 and 0 < highest < {width / 2:g}, "
                         f"got {channels}, {order}, {top:g}")
    for steps in range(channels, max_grid + 1):
        spacing = top / steps
        reach = 1.0 if half_width is None else half_width / spacing
        found = _search(steps, channels, order, reach)
        if found is not None:
            return tuple(float(n * spacing) for n in sorted(found))
    raise InputError(f"no {channels} carriers up to {top:g} cycles per width avoid the products of order {order} "
                     f"on a grid of up to {max_grid} steps; lower the order or the half-width")
