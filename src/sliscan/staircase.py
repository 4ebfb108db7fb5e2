"""Removing the stripe staircase: projector lines interpolated between located stripe borders.

A stripe pattern's decoder knows each pixel's stripe, so its projector line is the stripe's
centre, and the depth is a staircase (the "blinds" of the thesis's figs. 6.3-6.4): a stripe of
the 4-bit pattern is 48 projector lines, 60-120 mm deep at 0.8 m.  But the projector line of
every *border* between two stripes is known exactly (half way between the last line of one and
the first of the next), and the camera sees each border sharply along the phase direction: the
demodulator's windows run along the carriers, so the bit that flips there changes level within
a pixel or two down the phase direction, as sharply as the optics blur it.

`interpolate_lines` therefore walks each camera line along the phase direction, and where two
runs of neighbouring stripes meet (across at most `MAX_GAP` of a stripe of undecided pixels),
it places the border where the level of the one bit that flips between them crosses the
midpoint of its two sides' levels (linearly between pixels; the levels' gain varies with the
light, so the midpoint comes from the pixels near the border, past the blurred ones, not 0.5).
A lit pixel the decoder left undecided in a one-pixel gap between the two runs (its flipping
bit near half way, no margin to decide) takes the stripe of the border's side its centre lies
on.
Each run's pixels then get the line of a monotone cubic through the borders along the line
(Fritsch-Carlson, as scipy's PCHIP: it follows a surface's curvature, which a straight line
between two borders would cut); a run with one border (at a depth or shadow edge, or the
frame's end) is extended from it with the mean slope of the two-border runs around it (or, with
none near, that of the run beyond its border, else the median slope of all the frame's
two-border runs: the rig's geometry sets it more than the surface does), and one with none
(cut at both ends by edges or gaps within its stripe) takes the mean line of its stripe's
pixels beside it along the carriers that have one (`lines_beside`), or, with none near, keeps
its stripe's centre.  Where a border crosses the carriers' lines obliquely, a
demodulation window off the pixel's centre (`Demodulated.offset`) sees the border where it lies
at that window's centre: each line is moved back by its slope along the carriers times that
offset.  Every line is first clipped to its stripe's range (a decoded stripe is never
changed; only that move may take a line a little past its stripe's border).

Where a border crosses the carriers' lines obliquely (a surface turned about the phase
direction), the adaptive demodulator picks windows that end or start at the pixel on either
side of it, and the level of the flipping bit jumps between them instead of changing smoothly:
the crossing lies up to a few pixels off.  The centred windows' levels change across such a
border symmetrically, so `prefer_centred` takes the lines (and, a pixel between the two
placements, the stripe) that the decoding of the centred windows' levels gives
(`Demodulated.centred`) wherever the border drifts across a window and they agree with the
chosen windows'.

With a phase channel the interpolated line replaces the phase's where the two agree
(`prefer_borders`): the borders are the more precise, the phase the more robust.  Measured on
the virtual rig: docs/accuracy.md, "Removing the staircase".
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

from sliscan._threads import over_rows
from sliscan.decode import Decoded
from sliscan.demodulate import along_carriers
from sliscan.patterns import code_bits, stripe_center, stripe_codes, stripe_of_line
from sliscan.types import PatternSpec

#: A border is located between two runs of neighbouring stripes at most this fraction of a
#: stripe's height (camera pixels along the phase direction) apart; runs of one stripe that
#: far apart are joined.
MAX_GAP = 0.25
#: A run with one border takes the mean slope of the runs with two within this fraction of a
#: stripe's height (along both axes).
SLOPE_REACH = 0.5
#: Central differences of the interpolated lines along the carriers steeper than this (projector
#: lines per camera pixel) cross a depth edge: `interpolate_lines` leaves them out of the slope.
MAX_SLOPE = 2.0
#: `prefer_borders` takes the border-interpolated line where it lies within this many projector
#: lines of the phase channel's.
BORDER_AGREEMENT = 2.0
#: `prefer_centred` takes the line from the centred windows' levels where it lies within this
#: many projector lines of the chosen windows' (1 kept 70-90 % of the gain on the turned planes) ...
CENTRED_AGREEMENT = 2.0
#: ... and where the border moves at least this many camera pixels along the phase direction
#: over half a window along the carriers (0 took the centred windows' bias at albedo steps on
#: the checkered captures; 0.5 and more gave up part of the gain on the spheres).
CENTRED_MIN_DRIFT = 0.25
#: The levels either side of a border are averaged over at most `SIDE` pixels of each run,
#: leaving out the `SKIP` next to the border (blur mixes the two sides' levels there, unevenly
#: where the border falls off a pixel's centre, and a demodulation window smears a border that
#: crosses the carriers obliquely over several pixels); a shorter run gives what it has.  The
#: flipping bit's level stays the same across the run (its other border flips another bit).
SIDE = 5
SKIP = 5
#: The crossing is looked for this many pixels into each run as well as in the gap between them:
#: where the decoder's transition lies a pixel off the level's midpoint.
CROSSING_REACH = 1
#: A lit pixel left undecided between two runs of neighbouring stripes, in a gap of at most this
#: many pixels, gets the stripe of the side of the located border its centre lies on (the
#: flipping bit sits near half way there, so the decoder had no margin to decide it).
FILL_GAP = 1
#: A run with no border takes the mean line of the pixels of its stripe that have one within
#: this many demodulation windows along the carriers and `BESIDE_ROWS` pixels either side along
#: the phase direction (`lines_beside`).  Its stripe's centre, the thesis's staircase, is half a
#: stripe off at its ends, and such runs lie where the stripes cross the carriers' lines
#: obliquely (a sphere's sides) or between gaps, where the same stripe's lines beside them are
#: known.  Measured on the virtual rig (docs/accuracy.md, "Removing the staircase"): RMS error
#: 0-7 % lower on each of the 36 captures of the sphere, steps and tilted plane (both stripe
#: patterns, 5 MP seed 0 and 1296x972 seeds 0-1; 2.5 % on average), 1-2 % on the cylinder and
#: the objects, not tuned on (4 of 24 captures up to 1.9 % higher); medians, completeness and
#: stripes unchanged within 0.1 %.  The mean of a box stays in the stripe's range of lines, where
#: the nearest line alone, tried before, lost on the steps; 3 windows gained less, 12 as much.
BESIDE_REACH = 6
BESIDE_ROWS = 2


def border_lines(spec: PatternSpec) -> NDArray[np.float64]:
    """Projector line of the border between stripe ``k`` and ``k + 1``, ``(S - 1,)``: half way
    between the last line of the one and the first of the other.

    >>> border_lines(PatternSpec())[:2].tolist()
    [47.5, 95.5]
    """
    per = spec.phase_lines / spec.stripes
    return np.ceil(np.arange(1, spec.stripes) * per - 0.5) - 0.5


def flipping_planes(spec: PatternSpec) -> NDArray[np.intp]:
    """Bit plane (0 the most significant, as `Decoded.levels`) that flips between stripe ``k``
    and ``k + 1``, ``(S - 1,)``: Gray codes of neighbours differ in exactly one bit.

    >>> flipping_planes(PatternSpec(bits=3, carriers=(32.0, 64.0, 96.0), weights=(1.0, 1.0, 1.0))).tolist()
    [2, 1, 2, 0, 2, 1, 2]
    """
    planes = code_bits(stripe_codes(spec), spec.bits).astype(np.intp)  # (S, K)
    return np.argmax(planes[1:] != planes[:-1], axis=1).astype(np.intp)


@numba.njit(cache=True, inline="always")
def _side_mean(levels: NDArray[np.float32], plane: int, r: int, a: int, b: int) -> float:
    """Mean of ``levels[plane, r, a:b + 1]``."""
    total = 0.0
    for x in range(a, b + 1):
        total += levels[plane, r, x]
    return total / (b - a + 1)


@numba.njit(cache=True, inline="always")
def _crossing(levels: NDArray[np.float32], plane: int, r: int, a: int, b: int, high: float, low: float) -> float:
    """Where ``levels[plane, r]`` first crosses from the `high` side of the midpoint of `high`
    and `low` to the other between pixels `a` and `b` (linearly between pixels); the middle of
    ``a .. b`` if it does not."""
    middle, sign = 0.5 * (high + low), 1.0 if high > low else -1.0
    for x in range(a, b):
        v0, v1 = (levels[plane, r, x] - middle) * sign, (levels[plane, r, x + 1] - middle) * sign
        if v0 > 0 >= v1:
            return x + v0 / (v0 - v1)
    return 0.5 * (a + b)


@numba.njit(cache=True, inline="always")
def _secant(position: NDArray[np.float64], line: NDArray[np.float64], j: int, count: int) -> float:
    """Slope from border `j` to border ``j + 1`` (of `count`; NaN position: none), NaN if either
    is missing or both have one line."""
    if j < 0 or j + 1 >= count or not (np.isfinite(position[j]) and np.isfinite(position[j + 1])):
        return np.nan
    if line[j + 1] == line[j]:
        return np.nan
    return (line[j + 1] - line[j]) / max(position[j + 1] - position[j], 1e-6)


@numba.njit(cache=True, inline="always")
def _tangent(position: NDArray[np.float64], line: NDArray[np.float64], j: int, count: int) -> float:
    """Slope of the line at border `j` for a monotone cubic through the borders (Fritsch-Carlson,
    as scipy's PCHIP): the weighted harmonic mean of the secants on either side where both
    exist, else the three-point estimate from the two secants on the one side (limited as
    PCHIP's end slopes are), else the one secant."""
    d0, d1 = _secant(position, line, j - 1, count), _secant(position, line, j, count)
    if np.isfinite(d0) and np.isfinite(d1):
        if d0 * d1 <= 0:
            return 0.0
        h0, h1 = position[j] - position[j - 1], position[j + 1] - position[j]
        w0, w1 = 2 * h1 + h0, h1 + 2 * h0
        return (w0 + w1) / (w0 / d0 + w1 / d1)
    if np.isfinite(d1):  # the first border of a stretch: the secants after it
        near, far, h0 = d1, _secant(position, line, j + 1, count), position[j + 1] - position[j]
        h1 = position[j + 2] - position[j + 1] if np.isfinite(far) else 0.0
    elif np.isfinite(d0):  # the last: the secants before it
        near, far, h0 = d0, _secant(position, line, j - 2, count), position[j] - position[j - 1]
        h1 = position[j - 1] - position[j - 2] if np.isfinite(far) else 0.0
    else:
        return np.nan
    if not np.isfinite(far):
        return near
    m = ((2 * h0 + h1) * near - h0 * far) / (h0 + h1)
    if m * near <= 0:
        return 0.0
    if near * far <= 0 and abs(m) > 3 * abs(near):
        return 3 * near
    return m


@numba.njit(cache=True, nogil=True)
def _interpolate_rows(stripe: NDArray[np.int16], valid: NDArray[np.bool_], lit: NDArray[np.bool_],
                      levels: NDArray[np.float32], planes: NDArray[np.intp], borders: NDArray[np.float64],
                      max_gap: int, rows: NDArray[np.intp],
                      slope: NDArray[np.float32], anchor: NDArray[np.float32], line_at: NDArray[np.float32],
                      near_slope: NDArray[np.float32], between: NDArray[np.float32], offset: NDArray[np.float32],
                      described: NDArray[np.float32], side: NDArray[np.int16]) -> None:
    """The borders along the given `rows` (phase direction along axis 1), into the ``(H, W)``
    outputs (NaN elsewhere): for the valid pixels of a run between two borders of different
    lines the line's `slope` (lines per pixel), one border (`anchor`, its position; `line_at`,
    its line) and the cubic between the two (`between`); for a run with one border that
    border, and the slope of the run beyond it (`near_slope`) if that one has two.  With
    `offset` ``(H, W)`` (`Demodulated.offset`, framed likewise; ``(1, 1)``: none), `described`:
    where along the carriers the levels that placed the run's borders were measured, relative
    to the pixel (interpolated between its two borders).  `side` (int16, -1 elsewhere): the
    stripe of every pixel given a line, which includes the `lit` pixels left undecided in a
    gap of at most `FILL_GAP` between two runs, on the side of the border their centre lies
    on."""
    width = stripe.shape[1]
    first, last = np.empty(width, np.intp), np.empty(width, np.intp)
    label, own_first, own_last = np.empty(width, np.intp), np.empty(width, np.intp), np.empty(width, np.intp)
    position, line, moved = np.empty(width), np.empty(width), np.zeros(width)
    offsets = offset.shape[0] > 1
    for r in rows:
        n, x = 0, 0  # the runs of one stripe, joined across gaps of at most max_gap pixels
        while x < width:
            if not valid[r, x]:
                x += 1
                continue
            if n > 0 and label[n - 1] == stripe[r, x] and x - last[n - 1] - 1 <= max_gap:
                last[n - 1] = x
            else:
                first[n], last[n], label[n] = x, x, stripe[r, x]
                n += 1
            x += 1
        for i in range(n - 1):  # the border after run i, if any: its position and line
            position[i] = np.nan
            k, k2 = label[i], label[i + 1]
            if abs(k - k2) != 1 or first[i + 1] - last[i] - 1 > max_gap:
                continue
            plane = planes[min(k, k2)]
            a = max(first[i], last[i] - SKIP - SIDE + 1)  # each side's pixels, past the blurred ones
            high = _side_mean(levels, plane, r, a, max(a, last[i] - SKIP))
            b = min(last[i + 1], first[i + 1] + SKIP + SIDE - 1)
            low = _side_mean(levels, plane, r, min(b, first[i + 1] + SKIP), b)
            position[i] = _crossing(levels, plane, r, max(first[i], last[i] - CROSSING_REACH),
                                    min(last[i + 1], first[i + 1] + CROSSING_REACH), high, low)
            line[i] = borders[min(k, k2)]
            if offsets:  # the offset of the windows at the crossing, between its two pixels
                j = min(int(position[i]), width - 2)
                f = position[i] - j
                moved[i] = (1 - f) * offset[r, j] + f * offset[r, j + 1]
        own_first[:n], own_last[:n] = first[:n], last[:n]  # the runs' own pixels, as decoded
        for i in range(n - 1):  # the pixels between two runs: to the side of the border they lie on
            if np.isfinite(position[i]):
                last[i] = min(max(int(np.floor(position[i])), last[i]), first[i + 1] - 1)
                first[i + 1] = last[i] + 1
        for i in range(n):
            before = i > 0 and np.isfinite(position[i - 1])
            after = i < n - 1 and np.isfinite(position[i])
            if not (before or after):
                continue
            own, near = _secant(position, line, i - 1, n - 1), np.nan  # own: two borders of different lines
            if np.isfinite(own) or before:
                y0, l0 = position[i - 1], line[i - 1]
                if not np.isfinite(own):
                    near = _secant(position, line, i - 2, n - 1)  # the run before the border
            else:
                y0, l0 = position[i], line[i]
                near = _secant(position, line, i, n - 1)  # the run after it
            m0 = m1 = own
            if np.isfinite(own):
                m0, m1 = _tangent(position, line, i - 1, n - 1), _tangent(position, line, i, n - 1)
            for x in range(first[i], last[i] + 1):
                in_gap = (x < own_first[i] and own_first[i] - own_last[i - 1] - 1 <= FILL_GAP
                          or x > own_last[i] and own_first[i + 1] - own_last[i] - 1 <= FILL_GAP)
                if valid[r, x] or (lit[r, x] and in_gap):
                    side[r, x] = label[i]
                    slope[r, x], anchor[r, x], line_at[r, x], near_slope[r, x] = own, y0, l0, near
                    if np.isfinite(own):  # cubic Hermite between the two borders
                        h = max(position[i] - y0, 1e-6)
                        t = (x - y0) / h
                        between[r, x] = ((2 * t ** 3 - 3 * t ** 2 + 1) * l0 + (t ** 3 - 2 * t ** 2 + t) * h * m0
                                         + (3 * t ** 2 - 2 * t ** 3) * line[i] + (t ** 3 - t ** 2) * h * m1)
                    if offsets:
                        if before and after:
                            t = min(max((x - position[i - 1]) / max(position[i] - position[i - 1], 1e-6), 0.0), 1.0)
                            described[r, x] = (1 - t) * moved[i - 1] + t * moved[i]
                        else:
                            described[r, x] = moved[i - 1] if before else moved[i]


def interpolate_lines(decoded: Decoded, spec: PatternSpec, *, stripe_px: float,
                      offset: NDArray[np.float32] | None = None, window: int = 1,
                      typical_slope: bool = True, beside_reach: float = BESIDE_REACH) -> Decoded:
    """`decoded` with each valid pixel's projector line interpolated between the stripe borders
    around it instead of its stripe's centre (see the module's docstring); the decoded stripes
    unchanged, and the lit pixels the decoder left undecided between two runs of neighbouring
    stripes (gaps of at most `FILL_GAP` pixels) valid, with the stripe of the border's side
    they lie on.

    Parameters
    ----------
    decoded : Decoded
        A stripe pattern's decoding (camera orientation), with its bit levels.
    spec : PatternSpec
        The pattern.
    stripe_px : float
        About how many camera pixels one stripe spans along the phase direction (sets the
        largest gap a border may lie in, `MAX_GAP`, and the reach of `SLOPE_REACH`).
    offset : (H, W) array, optional
        `Demodulated.offset`: where along the carriers each pixel's levels were measured.  Where
        a border crosses the carriers' lines obliquely, a window off the pixel's centre sees it
        where it lies at that window's centre; each line is moved back by the line's slope along
        the carriers (measured on the interpolated lines over `window` pixels) times that offset.
    window : int
        The demodulation window, pixels along the carriers (with `offset`).
    typical_slope : bool
        Extend a run with one border and no slope near it (no two-border run within
        `SLOPE_REACH`, none beyond its border) with the median slope of the frame's two-border
        runs; false leaves its stripe's centre (with a phase channel the phase places those
        pixels better than a guessed slope).
    beside_reach : float
        A run with no border takes the mean line of its stripe's pixels within this many
        `window` along the carriers that have one (`lines_beside`); 0 leaves its stripe's
        centre (for the benchmark's record).
    """
    # the kernels walk each line along the phase direction (axis 1 of these views); the arrays
    # themselves stay in the camera's orientation (no transposed copies)
    view = lambda a: a.swapaxes(-1, -2) if spec.orientation == "rows" else a  # noqa: E731
    shape = decoded.stripe.shape
    slope, anchor, line_at, near_slope, between, described, line = (np.full(shape, np.nan, np.float32)
                                                                     for _ in range(7))
    side = np.full(shape, -1, np.int16)
    moved = np.zeros((1, 1), np.float32) if offset is None else view(np.asarray(offset, np.float32))
    stripe, valid = view(decoded.stripe), view(decoded.valid)
    planes, borders = flipping_planes(spec), border_lines(spec)
    max_gap = max(1, int(round(MAX_GAP * stripe_px)))
    lit = view(decoded.lit)
    over_rows(lambda rows: _interpolate_rows(stripe, valid, lit, view(decoded.levels), planes, borders, max_gap,
                                             rows, view(slope), view(anchor), view(line_at), view(near_slope),
                                             view(between), moved, view(described), view(side)), stripe.shape[0])
    new_stripe = np.where(side >= 0, side, decoded.stripe).astype(np.int16)
    new_valid = decoded.valid | (side >= 0)
    stripe, valid = view(new_stripe), view(new_valid)
    # a run with one border takes the mean slope of the two-border runs around it
    known = np.isfinite(slope)
    typical = np.nan  # the frame's typical slope, the last resort
    if typical_slope:
        sampled = slope[::4, ::4][known[::4, ::4]]
        typical = float(np.median(sampled)) if sampled.size else np.nan
    reach = max(1, int(round(SLOPE_REACH * stripe_px)))
    size = (2 * reach + 1, 2 * reach + 1)
    weight = cv2.boxFilter(known.astype(np.float32), -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    total = cv2.boxFilter(np.where(known, slope, np.float32(0)), -1, size, normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    centres = stripe_center(np.arange(spec.stripes), spec)
    low = np.concatenate([[2 * centres[0] - borders[0]], borders])  # each stripe's range of lines
    high = np.concatenate([borders, [2 * centres[-1] - borders[-1]]])
    over_rows(lambda rows: _assemble_rows(view(slope), view(anchor), view(line_at), view(near_slope), view(between),
                                          view(weight), view(total), typical, stripe, valid, low, high, rows,
                                          view(line)),
              stripe.shape[0])
    if offset is not None:  # after the clip: the stripe was decided from the same offset windows
        along = along_carriers(line, spec)
        with np.errstate(invalid="ignore"):
            move = slope_along_carriers(along, window) * along_carriers(described, spec)
        np.subtract(along, move, out=along, where=~np.isnan(move))  # NaN: no slope or no border
    missing = new_valid & np.isnan(line)  # no border in the run
    if beside_reach > 0 and missing.any():
        beside = lines_beside(line, new_stripe, new_valid & ~missing, missing, spec,
                              reach=max(1, int(round(beside_reach * window))))
        line[missing] = beside[missing]
        missing &= np.isnan(line)
    line[missing] = centres[np.clip(new_stripe[missing], 0, spec.stripes - 1)]  # nothing beside: the centre
    return replace(decoded, proj_map=line, stripe=new_stripe, valid=new_valid)


@numba.njit(cache=True, nogil=True)
def _beside_rows(line: NDArray[np.float32], stripe: NDArray[np.int16], known: NDArray[np.bool_],
                 wanted: NDArray[np.bool_], reach: int, rows_reach: int, stripes: int, rows: NDArray[np.intp],
                 out: NDArray[np.float32]) -> None:
    """`lines_beside` for the given `rows` (carriers along axis 1), into `out`: per stripe, running
    sums of the `known` lines over a box ``2 reach + 1`` pixels along the carriers and
    ``2 rows_reach + 1`` across, read at the `wanted` pixels (left as they are where the box
    holds none of their stripe)."""
    height, width = line.shape
    total, count = np.zeros(stripes), np.zeros(stripes, np.int64)
    for r in rows:
        if not wanted[r].any():
            continue
        total[:] = 0.0
        count[:] = 0
        r0, r1 = max(0, r - rows_reach), min(height, r + rows_reach + 1)
        for x in range(-reach, width):
            enter, leave = x + reach, x - reach - 1
            if enter < width:
                for q in range(r0, r1):
                    if known[q, enter]:
                        total[stripe[q, enter]] += line[q, enter]
                        count[stripe[q, enter]] += 1
            if leave >= 0:
                for q in range(r0, r1):
                    if known[q, leave]:
                        total[stripe[q, leave]] -= line[q, leave]
                        count[stripe[q, leave]] -= 1
            if x >= 0 and wanted[r, x] and count[stripe[r, x]] > 0:
                out[r, x] = total[stripe[r, x]] / count[stripe[r, x]]


def lines_beside(line: NDArray[np.float32], stripe: NDArray[np.int16], known: NDArray[np.bool_],
                 wanted: NDArray[np.bool_], spec: PatternSpec, *, reach: int,
                 rows_reach: int = BESIDE_ROWS) -> NDArray[np.float32]:
    """At each `wanted` pixel, the mean of the `known` pixels' lines of its own stripe within
    `reach` pixels along the carriers and `rows_reach` across; NaN elsewhere, and where there
    are none.

    Parameters
    ----------
    line : (H, W) float array
        Projector lines (camera orientation); read where `known`.
    stripe : (H, W) int array
        Stripe indices; pixels whose index lies outside ``[0, spec.stripes)`` are left out.
    known, wanted : (H, W) bool arrays
    spec : PatternSpec
        The pattern (its orientation says which way the carriers run).
    reach, rows_reach : int
        The box's half sizes in pixels, along the carriers and across them.

    >>> spec = PatternSpec()  # rows: carriers along the camera's rows
    >>> line = np.array([[10.0, np.nan, 14.0, 99.0]], np.float32).repeat(3, axis=0)
    >>> stripe = np.array([[1, 1, 1, 2]], np.int16).repeat(3, axis=0)
    >>> wanted = np.isnan(line)
    >>> lines_beside(line, stripe, ~wanted, wanted, spec, reach=2)[1].tolist()
    [nan, 12.0, nan, nan]
    """
    frame = lambda a: np.ascontiguousarray(along_carriers(a, spec))  # noqa: E731  (a transpose for columns)
    inside = (stripe >= 0) & (stripe < spec.stripes)  # the kernel indexes its per-stripe sums by them
    values, stripes = frame(line.astype(np.float32, copy=False)), frame(stripe.astype(np.int16, copy=False))
    have, need = frame(known & inside), frame(wanted & inside)
    out = np.full(values.shape, np.nan, np.float32)
    over_rows(lambda rows: _beside_rows(values, stripes, have, need, reach, rows_reach, spec.stripes, rows, out),
              values.shape[0])
    return along_carriers(out, spec)


@numba.njit(cache=True, nogil=True)
def _assemble_rows(slope: NDArray[np.float32], anchor: NDArray[np.float32], line_at: NDArray[np.float32],
                   near_slope: NDArray[np.float32], between: NDArray[np.float32], weight: NDArray[np.float32],
                   total: NDArray[np.float32], typical: float, stripe: NDArray[np.int16], valid: NDArray[np.bool_],
                   low: NDArray[np.float64], high: NDArray[np.float64], rows: NDArray[np.intp],
                   out: NDArray[np.float32]) -> None:
    """`interpolate_lines`' line of every valid pixel of the given `rows` (phase direction along
    axis 1), into `out`: the cubic between two borders, else the line from the run's one border
    with the slope of the two-border runs around it (`total` over `weight`), else the run's
    beyond it, else the `typical` one (the frame's median), clipped to the stripe's range
    (`low`, `high` per stripe); NaN where the run has no border (or no slope is known)."""
    for r in rows:
        for x in range(stripe.shape[1]):
            if not valid[r, x]:
                continue
            k = min(max(stripe[r, x], 0), low.size - 1)
            value = between[r, x]
            if not np.isfinite(value):
                s = slope[r, x]
                if not np.isfinite(s):
                    s = total[r, x] / weight[r, x] if weight[r, x] >= 1 else near_slope[r, x]
                if not np.isfinite(s):
                    s = typical
                value = line_at[r, x] + s * (x - anchor[r, x])
            if np.isfinite(value):
                out[r, x] = min(max(value, low[k]), high[k])


@numba.njit(cache=True, nogil=True)
def _slope_rows(line: NDArray[np.float32], window: int, least: float, rows: NDArray[np.intp],
                out: NDArray[np.float32]) -> None:
    """`slope_along_carriers` for the given `rows` of `line`, into `out`: per row the central
    differences that stay on one surface and their count, summed over an odd `window` as a
    running sum (in float64, as OpenCV's box filter sums float32 rows); NaN where fewer than
    `least` of them are summed."""
    width = line.shape[1]
    radius = window // 2
    value, usable = np.zeros(width + 2 * radius), np.zeros(width + 2 * radius)  # zero beyond the ends
    for r in rows:
        for x in range(1, width - 1):
            step = np.float32(0.5) * (line[r, x + 1] - line[r, x - 1])
            ok = abs(step) < MAX_SLOPE  # NaN compares false
            value[radius + x] = step if ok else 0.0
            usable[radius + x] = 1.0 if ok else 0.0
        total, count = 0.0, 0.0
        for i in range(window):
            total += value[i]
            count += usable[i]
        for x in range(width):
            if x > 0:
                total += value[x - 1 + window] - value[x - 1]
                count += usable[x - 1 + window] - usable[x - 1]
            if count >= least:
                out[r, x] = np.float32(total) / np.float32(count)
            else:
                out[r, x] = np.nan


def slope_along_carriers(line: NDArray[np.float32], window: int) -> NDArray[np.float32]:
    """Mean change of `line` ``(H, W)`` (carriers along axis 1) per pixel along the carriers
    over `window` pixels, from the central differences that stay on one surface (under
    `MAX_SLOPE` lines per pixel), where at least a quarter of them do; NaN elsewhere."""
    line = np.ascontiguousarray(line, dtype=np.float32)  # a transposed view for a columns pattern
    out = np.empty(line.shape, np.float32)
    over_rows(lambda rows: _slope_rows(line, max(1, window) | 1, 0.25 * max(window, 1), rows, out), line.shape[0])
    return out


def prefer_centred(lines: Decoded, centred: Decoded, offset: NDArray[np.float32], spec: PatternSpec, *,
                   stripe_px: float, window: int, agreement: float = CENTRED_AGREEMENT,
                   min_drift: float = CENTRED_MIN_DRIFT) -> Decoded:
    """`lines` (`interpolate_lines` of a decoding) with the lines and stripes of `centred`
    (`interpolate_lines` of the same capture decoded from its centred windows' levels,
    `Demodulated.centred`) where the border crosses the carriers obliquely; validity unchanged.

    Where a border crosses the carriers obliquely the centred windows place it better (on the
    virtual rig's plane turned 30 degrees about the vertical, border positions 0.36 camera
    pixels median off against 0.81), so a pixel between the two placements takes the centred
    decoding's stripe, one away.  Taken where both are valid with stripes at most one apart and
    lines within `agreement` projector lines of each other (next to a depth or shadow edge a
    centred window mixes the two sides), where the border drifts at least `min_drift` camera pixels
    along the phase direction over half a `window` along the carriers (the slope of `lines`
    along the carriers against `stripe_px`, a stripe's height; at a border along the carriers
    the chosen windows are as good, and next to an albedo step better), and where the centred
    window is centred on the pixel (`offset` ``(H, W)``, the centred windows'
    `Demodulated.offset`, at most half a pixel as for an even window: within half a window of
    the frame's ends the window is shifted inside, and the chosen windows' lines were measured
    better there).
    """
    slope = along_carriers(slope_along_carriers(along_carriers(lines.proj_map, spec), window), spec)
    lines_per_px = spec.phase_lines / spec.stripes / stripe_px  # along the phase direction
    with np.errstate(invalid="ignore"):
        oblique = np.abs(slope) * (window / 2) >= min_drift * lines_per_px  # NaN compares false
        agree = (lines.valid & centred.valid & (np.abs(centred.stripe.astype(np.int32) - lines.stripe) <= 1)
                 & (np.abs(offset) <= 0.5) & oblique & (np.abs(centred.proj_map - lines.proj_map) <= agreement))
    return replace(lines, proj_map=np.where(agree, centred.proj_map, lines.proj_map).astype(np.float32),
                   stripe=np.where(agree, centred.stripe, lines.stripe).astype(np.int16))


def prefer_borders(refined: Decoded, border_line: NDArray[np.float32], spec: PatternSpec, *,
                   agreement: float = BORDER_AGREEMENT) -> Decoded:
    """A phase channel's decoding (`sliscan.fringe.refine`) with the border-interpolated line
    (`interpolate_lines` of the same capture's Gray code) wherever that lies within
    `agreement` projector lines of the phase's, and the stripe of that line there (as
    `sliscan.fringe.refine` numbers a line's stripe); validity unchanged.

    The borders place a pixel more precisely than the phase (on the virtual rig's planes 0.2
    projector lines RMS against 0.7: each border is seen sharply along the phase direction,
    while the fringe's phase is a window's estimate), but a wrong stripe or a border missed
    moves a run's line by up to a stripe, which the phase, unwrapped robustly, does not.
    `border_line` ``(H, W)``: NaN where not interpolated.
    """
    with np.errstate(invalid="ignore"):
        agree = np.abs(border_line - refined.proj_map) <= agreement
    line = np.where(agree, border_line, refined.proj_map).astype(np.float32)
    stripe = np.where(agree, stripe_of_line(line, spec), refined.stripe).astype(np.int16)
    return replace(refined, proj_map=line, stripe=stripe)
