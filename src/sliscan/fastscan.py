"""The real-time single-shot scan: baseband envelopes to points in one compiled pass (issue 6).

`Scanner(method="baseband")` (``sliscan scan --method baseband``).  The capture is divided by
its albedo, the sharp steps and the flat field (`sliscan.baseband.normalise_lines`, unless
`Scanner.albedo` is None), and demodulated at baseband (`sliscan.baseband`: one transform per
line, each envelope sampled every ~27 pixels), the frame's levels are read from those samples
as `sliscan.decode.decode` reads them from full-size envelopes (`decode.FrameLevels`), and then
one compiled loop over the pixels interpolates each pixel's DC and envelopes, decides its bits
and stripe with `decode`'s per-pixel rules, and triangulates it.  The triangulation is a table:
a stripe pattern's projector coordinate takes one value per stripe, so every camera row and
stripe has its point as a ratio of two affine functions of the column
(`Triangulator.line_table`), and the pixels where that point is a measurement
(`sliscan.pipeline.measurable`) are one run of columns, found once per rig
(`StripeGeometry`).  A rig with lens distortion has no such table (its camera rows are not
lines): the pass decides its stripes and `Triangulator.measure` triangulates them.

What it leaves out, for speed: the window demodulator's misfit and noise estimates (its
one-sided windows are chosen per sample, see `sliscan.baseband`), the decisions by order, the
border refinement and the neighbours' agreement (the 3D filters, speckles and narrow runs, run
after the pass when on, `Scanner`'s default); patterns with a phase channel are not supported (their stripes only unwrap the fringe).  The
thesis's lit all-zero stripe, which needs a walk along the phase direction
(`decode._zero_stripe`), is found after the pass, only for a pattern that projects that code
(`zero_stripe`: 0.2-0.4 s at 5 MP).  Measured against the default (docs/speed.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.ndimage
from numpy.typing import NDArray

from sliscan._threads import over_rows
from sliscan._validate import InputError
from sliscan.baseband import Baseband
from sliscan.decode import ZERO_STRIPE_MIN_DC, FrameLevels, _stripe_of_code, _zero_stripe, is_settled
from sliscan.demodulate import Demodulated
from sliscan.patterns import stripe_center
from sliscan.reconstruct import MeasurableTest, Triangulator
from sliscan.types import PatternSpec, ScanResult


@dataclass(frozen=True, eq=False)
class StripeGeometry:
    """The triangulation of every camera row and stripe of one rig and pattern, prepared once.

    Attributes
    ----------
    centres : (K,) float32 array
        Each stripe's projector line (`sliscan.patterns.stripe_center`).
    table : (H, K, 8) float64 array
        `Triangulator.line_table` of the centres.
    span : (H, K, 2) int64 array
        First and last column whose point is a measurement (`Triangulator.measure` with the
        rig's `MeasurableTest`); first > last where none is.
    gaps : (H, K) int64 array
        -1 where the measured columns are that one run, else the row of `gap_masks` that lists them.
    gap_masks : (G, W) bool array
    measure_with : (Triangulator, MeasurableTest) or None
        For a rig with lens distortion (`Triangulator.row_affine` false), whose camera rows
        are not lines: `table` is zeros and `span` every column, the pass decides the stripes
        only, and `scan_baseband` measures their points with these.
    """

    centres: NDArray[np.float32]
    table: NDArray[np.float64]
    span: NDArray[np.int64]
    gaps: NDArray[np.int64]
    gap_masks: NDArray[np.bool_]
    measure_with: tuple[Triangulator, MeasurableTest] | None = None

    @property
    def tabled(self) -> bool:
        """Whether the pass triangulates from `table` (no lens distortion)."""
        return self.measure_with is None

    @classmethod
    def of(cls, triangulator: Triangulator, test: MeasurableTest, spec: PatternSpec) -> StripeGeometry:
        """Measure every stripe's constant map once (``K`` calls of `Triangulator.measure`);
        for a rig with lens distortion, nothing (`measure_with`)."""
        centres = stripe_center(np.arange(spec.stripes), spec).astype(np.float32)
        h, w = triangulator.shape
        if not triangulator.row_affine:
            span = np.empty((h, centres.size, 2), np.int64)
            span[..., 0], span[..., 1] = 0, w - 1
            return cls(centres=centres, table=np.zeros((h, centres.size, 8)), span=span,
                       gaps=np.full((h, centres.size), -1, np.int64), gap_masks=np.zeros((0, w), bool),
                       measure_with=(triangulator, test))
        span = np.empty((h, centres.size, 2), np.int64)
        gaps = np.full((h, centres.size), -1, np.int64)
        masks = []
        for k, centre in enumerate(centres):
            _, measured = triangulator.measure(np.full((h, w), centre, np.float32), None, test)
            first = np.argmax(measured, axis=1)
            last = w - 1 - np.argmax(measured[:, ::-1], axis=1)
            count = measured.sum(axis=1)
            span[:, k, 0], span[:, k, 1] = np.where(count > 0, first, w), np.where(count > 0, last, -1)
            for y in np.flatnonzero((count > 0) & (count != last - first + 1)):
                gaps[y, k] = len(masks)
                masks.append(measured[y])
        return cls(centres=centres, table=triangulator.line_table(centres), span=span, gaps=gaps,
                   gap_masks=np.array(masks, dtype=bool).reshape(-1, w))


@numba.njit(cache=True, inline="always")
def _sample(samples: NDArray[np.float32], channel: int, line: int, low: int, high: int, t: np.float32) -> np.float32:
    """Channel `channel` of `line` between samples `low` and `high`, `t` of the way to `high`
    (as `Baseband.demodulated` interpolates)."""
    return samples[channel, line, low] * (np.float32(1) - t) + samples[channel, line, high] * t


@numba.njit(cache=True, inline="always")
def _decide(samples: NDArray[np.float32], line: int, low: int, high: int, t: np.float32, floor: np.float32,
            lit_off: NDArray[np.float32], lit_gain: NDArray[np.float32], pilot: int,
            bit_off: NDArray[np.float32], bit_gain: NDArray[np.float32], min_modulation: np.float32,
            half_confidence: np.float32) -> tuple[int, int, int, int, bool, np.float32]:
    """`decode`'s per-pixel decision at a point of `line` between samples `low` and `high`:
    ``(code, unclear, first_unclear, lit_mask, floored, least)``: the Gray code, the bits too
    close to their threshold (a mask, bit 0 the most significant at the mask's top, and the
    first of them), which lit carriers reach `min_modulation` (a mask; the pixel is lit when
    any does; `decode.FrameLevels`: the pilot if there is one, else every bit), whether the DC
    is at its floor, and the smallest bit margin.

    The arithmetic is `decode`'s in float32 with reciprocals (`lit_gain`, `bit_gain`: one over
    the scales' spans), so a level can differ from `decode`'s on the interpolated envelopes in
    its last bits."""
    raw = _sample(samples, 0, line, low, high, t)
    inv_dc = np.float32(1) / max(raw, floor)
    inv_ref, lit_mask = inv_dc, 0
    if pilot >= 0:  # the pilot is the only lit carrier and the bits' reference
        a = _sample(samples, 1 + pilot, line, low, high, t)
        inv_ref = np.float32(1) / max(a, np.float32(1e-6))
        lit_mask = 1 if (a * inv_dc - lit_off[0]) * lit_gain[0] >= min_modulation else 0
    code, unclear, first_unclear = 0, 0, -1
    least = np.float32(np.inf)
    for n in range(bit_off.size):
        a = _sample(samples, 1 + n, line, low, high, t)
        if pilot < 0 and (a * inv_dc - lit_off[n]) * lit_gain[n] >= min_modulation:  # every bit is a lit carrier
            lit_mask |= 1 << n
        level = (a * inv_ref - bit_off[n]) * bit_gain[n]
        code = (code << 1) | (1 if level >= 0.5 else 0)
        margin = abs(level - np.float32(0.5))
        least = min(least, margin)
        unclear <<= 1
        if not margin >= half_confidence:
            unclear |= 1
            if first_unclear < 0:
                first_unclear = n
    return code, unclear, first_unclear, lit_mask, raw < floor, least


@numba.njit(cache=True, inline="always")
def _confidence(least: float) -> np.float32:
    """`decode`'s confidence of a smallest bit margin: twice it, clipped to [0, 1]."""
    return np.float32(min(max(2 * least, 0.0), 1.0))


@numba.njit(cache=True, inline="always")
def _stripe(code: int, unclear: int, first_unclear: int, lit_mask: int, stripe_of_code: NDArray[np.int64],
            stripe_borders: bool) -> int:
    """The stripe `_decide`'s outputs decide (`decode`'s per-pixel rules), -1 for none."""
    s = stripe_of_code[code]
    count = 0 if unclear == 0 else (1 if unclear & (unclear - 1) == 0 else 2)
    settled = is_settled(code, count, first_unclear, stripe_of_code, stripe_borders)
    return s if lit_mask != 0 and s >= 0 and settled else -1


@numba.njit(cache=True, inline="always")
def _decide_pixel(samples: NDArray[np.float32], line: int, low: int, high: int, t: np.float32, floor: np.float32,
                  lit_off: NDArray[np.float32], lit_gain: NDArray[np.float32],
                  pilot: int, bit_off: NDArray[np.float32], bit_gain: NDArray[np.float32], min_modulation: np.float32,
                  half_confidence: np.float32, stripe_of_code: NDArray[np.int64],
                  stripe_borders: bool) -> tuple[int, np.float32]:
    """One pixel's stripe (-1 for none) and confidence between samples `low` and `high`."""
    code, unclear, first, lit_mask, _, least = _decide(samples, line, low, high, t, floor, lit_off,
                                                       lit_gain, pilot, bit_off, bit_gain, min_modulation,
                                                       half_confidence)
    return (_stripe(code, unclear, first, lit_mask, stripe_of_code, stripe_borders),
            _confidence(least) if lit_mask != 0 else np.float32(0))


@numba.njit(cache=True, nogil=True)
def _scan_lines(samples: NDArray[np.float32], step: float, transposed: bool, floor: np.float32, inv_top: np.float32,
                lit_off: NDArray[np.float32], lit_gain: NDArray[np.float32],
                pilot: int, bit_off: NDArray[np.float32], bit_gain: NDArray[np.float32], min_modulation: np.float32,
                half_confidence: np.float32, stripe_borders: bool, stripe_of_code: NDArray[np.int64],
                centres: NDArray[np.float32], table: NDArray[np.float64], span: NDArray[np.int64],
                gaps: NDArray[np.int64], gap_masks: NDArray[np.bool_], tabled: bool, lines: NDArray[np.intp],
                points: NDArray[np.float32], valid: NDArray[np.bool_], texture: NDArray[np.float32],
                proj_map: NDArray[np.float32], stripe: NDArray[np.int16], confidence: NDArray[np.float32]) -> None:
    """`scan_baseband`'s pixels of the given lines (camera rows, or columns if `transposed`),
    every output written in place; without a table (`StripeGeometry.tabled`) every output but
    the points, and `valid` where a stripe is decided.

    Each line's samples are decided first (`_decide`).  Between two samples every level is a
    ratio of two functions linear in the position, so it moves monotonically from one
    sample's value to the next: where both samples have the same DC floor state and either no
    lit carrier or the same code, the same unclear bits and a lit carrier in common, every
    pixel between them decides the same, and only its point is computed (its confidence is interpolated
    between the samples'); the other pixels are decided on their own (`_decide_pixel`)."""
    length, inv_step = samples.shape[2], 1.0 / step
    width = valid.shape[0] if transposed else valid.shape[1]
    codes, unclears, firsts, lits = np.empty((4, length), np.int64)
    floored, leasts = np.empty(length, np.bool_), np.empty(length, np.float32)
    segments = np.empty(length, np.int64)  # stripe of a uniform segment, -1 none, -2 mixed
    starts = np.empty(length + 1, np.int64)  # the pixels between samples i and i + 1: starts[i] .. starts[i + 1] - 1
    i = 0
    for at in range(width):
        while i <= int(at * inv_step):
            starts[i], i = at, i + 1
    starts[i:] = width
    for line in lines:
        for i in range(length):
            codes[i], unclears[i], firsts[i], lits[i], floored[i], leasts[i] = _decide(
                samples, line, i, i, np.float32(0), floor, lit_off, lit_gain, pilot, bit_off, bit_gain,
                min_modulation, half_confidence)
        for i in range(length):
            j = min(i + 1, length - 1)  # the last sample (the line's end) describes no pixel after it
            if lits[i] == lits[j] == 0 and floored[i] == floored[j]:
                segments[i] = -1  # unlit throughout, whatever the code
            elif (codes[i] == codes[j] and unclears[i] == unclears[j] and floored[i] == floored[j]
                  and (lits[i] & lits[j]) != 0):
                segments[i] = _stripe(codes[i], unclears[i], firsts[i], lits[i], stripe_of_code, stripe_borders)
            else:
                segments[i] = -2
        for i in range(length):
            high, s = min(i + 1, length - 1), segments[i]
            start, stop = starts[i], starts[i + 1]
            if s != -2 and not transposed and (s < 0 or gaps[line, s] < 0):
                # one decision and one run of measured columns: straight loops, coefficients read once
                y, lit = line, lits[i]
                d0, d1, c0, c1 = samples[0, y, i], samples[0, y, high], leasts[i], leasts[high]
                for x in range(start, stop):
                    t = np.float32(x * inv_step - i)
                    texture[y, x] = min(max((d0 * (np.float32(1) - t) + d1 * t) * inv_top, np.float32(0)),
                                        np.float32(1))
                    confidence[y, x] = _confidence(c0 * (np.float32(1) - t) + c1 * t) if lit else np.float32(0)
                first, end = stop, stop
                if s >= 0:
                    first, end = max(start, span[y, s, 0]), min(stop, span[y, s, 1] + 1)
                    a0, a1, a2, b0, b1, b2 = (table[y, s, 0], table[y, s, 1], table[y, s, 2], table[y, s, 3],
                                              table[y, s, 4], table[y, s, 5])
                    e0, e1, centre = table[y, s, 6], table[y, s, 7], centres[s]
                    for x in range(first, end):
                        if tabled:
                            inv = 1.0 / (e0 + e1 * x)
                            points[y, x, 0] = np.float32((a0 + b0 * x) * inv)
                            points[y, x, 1] = np.float32((a1 + b1 * x) * inv)
                            points[y, x, 2] = np.float32((a2 + b2 * x) * inv)
                        proj_map[y, x], stripe[y, x], valid[y, x] = centre, s, True
                for x in range(start, stop):
                    if not first <= x < end:
                        points[y, x, 0] = points[y, x, 1] = points[y, x, 2] = np.nan
                        proj_map[y, x], stripe[y, x], valid[y, x] = np.nan, -1, False
                continue
            for at in range(start, stop):
                y, x = (at, line) if transposed else (line, at)
                t = np.float32(at * inv_step - i)
                texture[y, x] = min(max(_sample(samples, 0, line, i, high, t) * inv_top, np.float32(0)), np.float32(1))
                p = s
                if s == -2:
                    p, confidence[y, x] = _decide_pixel(samples, line, i, high, t, floor, lit_off, lit_gain, pilot,
                                                        bit_off, bit_gain, min_modulation, half_confidence,
                                                        stripe_of_code, stripe_borders)
                else:
                    confidence[y, x] = _confidence(leasts[i] * (1 - t) + leasts[high] * t) if lits[i] else 0
                ok = p >= 0
                if ok:
                    g = gaps[y, p]
                    ok = gap_masks[g, x] if g >= 0 else span[y, p, 0] <= x <= span[y, p, 1]
                if ok:
                    if tabled:
                        inv = 1.0 / (table[y, p, 6] + table[y, p, 7] * x)
                        for k in range(3):
                            points[y, x, k] = np.float32((table[y, p, k] + table[y, p, 3 + k] * x) * inv)
                    proj_map[y, x], stripe[y, x] = centres[p], p
                else:
                    points[y, x, 0] = points[y, x, 1] = points[y, x, 2] = np.nan
                    proj_map[y, x], stripe[y, x] = np.nan, -1
                valid[y, x] = ok


#: About how many samples each of `frame_levels`' two-means clusterings reads (between this
#: and 4 times it: `decode._Scale.of`'s regular grid of the H x 96 samples, every 4th in both
#: directions at 1280x1024, every 5th or 6th at 5 MP: 5-6.5k samples).  A cluster's median from ~2500 samples is off by well under
#: 1 % of the off-on span, against a decision margin (`min_confidence`) of 5 %; 20k samples
#: cost 3x the time (8.7 against 3.5 ms per frame at 1280x1024).
LEVEL_SAMPLES = 5_000


def frame_levels(baseband: Baseband, spec: PatternSpec, *, min_modulation: float = 0.3) -> FrameLevels:
    """`decode.FrameLevels` of the baseband samples (a frame ``(H, L)`` of them; there is no
    noise estimate, so no noise test)."""
    samples = baseband.samples
    return FrameLevels.of(Demodulated(amplitude=samples[1:], dc=samples[0], residual=np.zeros_like(samples[0])), spec,
                          min_modulation=min_modulation, min_snr=0.0, limit=LEVEL_SAMPLES)


def scan_baseband(baseband: Baseband, levels: FrameLevels, spec: PatternSpec, geometry: StripeGeometry,
                  shape: tuple[int, int], *, min_modulation: float = 0.3, min_confidence: float = 0.1,
                  stripe_borders: bool = True, zero_code_dc: float = ZERO_STRIPE_MIN_DC,
                  workers: int | None = None, out: ScanResult | None = None) -> ScanResult:
    """Points of one frame from its baseband envelopes (see the module docstring).

    Parameters
    ----------
    baseband : Baseband
        `sliscan.baseband.demodulate_baseband` of the capture in its carrier orientation.
    levels : FrameLevels
        `frame_levels` of it, with the same `min_modulation`.
    spec : PatternSpec
        A stripe pattern (no phase channel).
    geometry : StripeGeometry
        Of the rig and `spec` (for a rig with lens distortion the points are measured after the
        pass, `Triangulator.measure`: 0.3-0.5 s more at 5 MP with both lenses).
    shape : (H, W)
        The camera's.
    min_modulation, min_confidence, stripe_borders, zero_code_dc
        As in `sliscan.decode.decode` (its per-pixel tests; there is no noise or residual
        estimate to test against; a pattern that projects the all-zero code gets that stripe
        after the pass, `zero_stripe`).
    workers : int, optional
        Threads over the camera rows.
    out : ScanResult, optional
        Whose arrays to overwrite (`outputs`).

    Returns
    -------
    ScanResult
        Without timings: `out`'s arrays if given, else new ones.
    """
    samples = baseband.samples
    # the texture is the capture's DC: with an albedo, the normalised DC times it, written by the
    # pass over the albedo's smallest sampled value (so nothing is clipped before the product)
    albedo = baseband.sampled_albedo()
    least = 1.0 if albedo is None else max(float(albedo.min()), 1e-6)
    top = max(float(np.percentile(samples[0] if albedo is None else samples[0] * albedo, 99.5)), 1e-6)
    h, w = shape
    points, valid, texture, proj_map, stripe, confidence = outputs(shape, out)
    pilot = spec.pilot_index if spec.pilot is not None else -1
    transposed = spec.orientation == "columns"
    over_rows(lambda lines: _scan_lines(
        samples, baseband.step, transposed, np.float32(levels.floor), np.float32(least / top),
        levels.lit_scale.off, (1 / levels.lit_scale.span).astype(np.float32), pilot,
        levels.bits.off, (1 / levels.bits.span).astype(np.float32),
        np.float32(min_modulation), np.float32(0.5 * min_confidence), stripe_borders, _stripe_of_code(spec),
        geometry.centres, geometry.table, geometry.span, geometry.gaps, geometry.gap_masks, geometry.tabled, lines,
        points, valid, texture, proj_map, stripe, confidence), w if transposed else h, workers)
    if baseband.albedo is not None:
        texture *= baseband.albedo.T if transposed else baseband.albedo
        texture *= np.float32(1 / least)
        np.minimum(texture, 1, out=texture)
    if spec.pilot is None and not spec.skip_zero_code:  # the lit all-zero stripe (the thesis's pattern)
        _add_zero_stripe(zero_stripe(stripe, texture, spec, min_dc=zero_code_dc) & ~valid, geometry, points, valid,
                         proj_map, stripe)
    if geometry.measure_with is not None:  # lens distortion: the decided stripes' points, measured
        triangulator, test = geometry.measure_with
        measured_points, measured = triangulator.measure(proj_map, valid, test)
        points[...] = measured_points
        valid &= measured
        dropped = ~valid
        proj_map[dropped], stripe[dropped] = np.nan, -1
    return ScanResult(points=points, valid=valid, texture=texture, proj_map=proj_map, stripe=stripe,
                      confidence=confidence)


#: How far from stripe 2 a pixel of stripe 1 may lie along the phase direction to start
#: `zero_stripe`'s walk, in lengths of stripe 1 (the median over the lines that have it).
ZERO_SEED_REACH = 2.0


def zero_stripe(stripe: NDArray[np.int16], dc: NDArray[np.float32], spec: PatternSpec, *,
                min_dc: float) -> NDArray[np.bool_]:
    """The pixels of the lit all-zero stripe (``(H, W)`` bool): `decode._zero_stripe`'s walk from
    stripe 1 away from stripe 2 along the phase direction, on the pass's `stripe` (-1 none) and
    `dc`, but only from the stripe-1 pixels within `ZERO_SEED_REACH` lengths of stripe 1 of a
    stripe-2 pixel.  The per-pixel decisions leave stray stripe-1 pixels (in the ambient light
    beyond the projector's, say), and the walk starts from the first one of each line: on the
    thesis pattern's 480x360 sphere (`tests/test_fastscan.py`) 3815 pixels made stripe 0, 49 %
    of them right, against 9129 and 92 % from the kept ones; on the 5 MP sphere 251 829 and
    97.6 % against 240 951 and 97.8 % (scratch `/tmp/s19/zero3.py`)."""
    axis = 0 if spec.orientation == "rows" else 1  # the phase direction in the camera
    one, two = stripe == 1, stripe == 2
    lengths = one.sum(axis=axis)
    if not lengths.any():
        return np.zeros(stripe.shape, bool)
    reach = max(3, int(ZERO_SEED_REACH * np.median(lengths[lengths > 0])))
    near_two = scipy.ndimage.maximum_filter1d(two, 2 * reach + 1, axis=axis)
    return _zero_stripe(np.where(one & ~near_two, np.int16(-1), stripe), dc, spec, min_dc=min_dc)


def _add_zero_stripe(zero: NDArray[np.bool_], geometry: StripeGeometry, points: NDArray[np.float32],
                     valid: NDArray[np.bool_], proj_map: NDArray[np.float32], stripe: NDArray[np.int16]) -> None:
    """Make the pixels of `zero` ``(H, W)`` stripe 0, in place: valid, with their points from the
    table where those are measurements (all of them without a table: `scan_baseband` measures
    them after)."""
    ys, xs = np.nonzero(zero)
    if geometry.tabled:
        g = geometry.gaps[ys, 0]
        inside = (geometry.span[ys, 0, 0] <= xs) & (xs <= geometry.span[ys, 0, 1])
        if (g >= 0).any():
            inside[g >= 0] = geometry.gap_masks[g[g >= 0], xs[g >= 0]]
        ys, xs = ys[inside], xs[inside]
        t = geometry.table[ys, 0]
        x = xs[:, None].astype(np.float64)
        points[ys, xs] = ((t[:, 0:3] + t[:, 3:6] * x) / (t[:, 6:7] + t[:, 7:8] * x)).astype(np.float32)
    valid[ys, xs], proj_map[ys, xs], stripe[ys, xs] = True, geometry.centres[0], 0


def outputs(shape: tuple[int, int], out: ScanResult | None = None) -> tuple[NDArray, ...]:
    """A scan's arrays for a camera of `shape` ``(H, W)``, in `ScanResult` field order: new
    (uninitialised) ones, or `out`'s after checking that each has the shape, dtype and C order
    `scan_baseband` writes.

    Raises
    ------
    InputError
        If `out` does not fit, naming the first array that does not.
    """
    h, w = shape
    layout = {"points": ((h, w, 3), np.float32), "valid": ((h, w), np.bool_), "texture": ((h, w), np.float32),
              "proj_map": ((h, w), np.float32), "stripe": ((h, w), np.int16), "confidence": ((h, w), np.float32)}
    if out is None:
        return tuple(np.empty(size, dtype) for size, dtype in layout.values())
    for name, (size, dtype) in layout.items():
        array = getattr(out, name)
        if array.shape != size or array.dtype != dtype or not array.flags.c_contiguous or not array.flags.writeable:
            raise InputError(f"out.{name} is {array.dtype} {array.shape}, not a writeable C-ordered {np.dtype(dtype)} "
                             f"{size} array: out= takes an earlier scan's result of this camera")
    return tuple(getattr(out, name) for name in layout)
