"""The numpy form of `sliscan.demodulate._albedo_steps`, the compiled kernel's exactness reference."""

from __future__ import annotations

import numpy as np
import scipy.ndimage
import scipy.special
from numpy.typing import NDArray

from sliscan.demodulate import (STEP_AGREEMENT, STEP_BOX, STEP_CONCENTRATION, STEP_CONSTANCY, STEP_ECHO, STEP_ENOUGH,
                                STEP_FIND, STEP_FLAT, STEP_FLAT_BELOW, STEP_HEIGHT, STEP_MARGIN, STEP_MIN_BOX,
                                STEP_SHARPNESS, STEP_SPAN, STEP_SPREAD, STEP_THRESHOLD)


def _ratio_means(cum_g: NDArray[np.float64], cum_w: NDArray[np.float64], lo: NDArray[np.intp],
                 hi: NDArray[np.intp]) -> NDArray[np.float64]:
    """Weighted means of the lag ratio of each line over ``lo .. hi - 1`` (index arrays, broadcast
    against the lines)."""
    rows = np.arange(cum_g.shape[0])[:, None]
    return (cum_g[rows, hi] - cum_g[rows, lo]) / np.maximum(cum_w[rows, hi] - cum_w[rows, lo], 1e-12)


def _evidence(change: NDArray[np.float64], usable: NDArray[np.bool_], t: int) -> tuple[NDArray, NDArray]:
    """`sliscan.demodulate._step_evidence` for all lines at once: (evidence, one_sided)."""
    w = change.shape[1]
    x = np.arange(w)

    def at(values: NDArray, index: NDArray, fill: float | bool) -> NDArray:  # values[:, index], fill beyond the line
        inside = (index >= 0) & (index < w)
        return np.where(inside, values[:, np.clip(index, 0, w - 1)], fill)

    here = change
    later_usable = at(usable, x + t, False)
    later = np.where(later_usable, -at(change, x + t, 0.0), 0.0)
    small, large = np.minimum(np.abs(here), np.abs(later)), np.maximum(np.abs(here), np.abs(later))
    agree = usable & later_usable & (here * later > 0) & (small >= STEP_AGREEMENT * large)
    before, after = at(change, x - t, 0.0), at(change, x + 2 * t, 0.0)
    right_echo = at(usable, x - t, False) & (before * here < 0) & (np.abs(before) >= STEP_ECHO * np.abs(here))
    left_echo = at(usable, x + 2 * t, False) & (after * later > 0) & (np.abs(after) >= STEP_ECHO * np.abs(later))
    evidence = np.where(agree, 0.5 * (here + later), 0.0)
    evidence = np.where(usable & ~later_usable & ~right_echo, here, evidence)
    evidence = np.where(~usable & later_usable & ~left_echo, later, evidence)
    return evidence, usable != later_usable


def _edge_share(box: int, blur: float) -> float:
    """What an edge blurred by a Gaussian of `blur` px changes across boxes of `box` px, as a
    share of its height."""
    return 1 - 2 * scipy.special.ndtr(-(np.arange(box) + 0.5) / blur).sum() / box


def _one_way_steps(img: NDArray[np.float32], windows: NDArray[np.intp], threshold: float,
                   floor: float, blur: float) -> NDArray[np.float64]:
    """The log height of every step found reading the lines left to right, at its pixel."""
    h, w = img.shape
    step_heights = np.zeros((h, w), dtype=np.float64)
    x = np.arange(w)
    for period in np.unique(windows):  # lines of one window length together (a handful)
        rows = np.nonzero(windows == period)[0]
        t = int(period)
        box = max(STEP_MIN_BOX, int(round(STEP_BOX * t)))
        if 3 * t >= w:
            continue
        im = img[rows].astype(np.float64)
        lg = np.log(np.maximum(im, floor))
        weighted, weight = np.zeros_like(lg), np.zeros_like(lg)
        weight[:, t:] = np.maximum(np.minimum(im[:, t:], im[:, :-t]), floor)
        weighted[:, t:] = weight[:, t:] * (lg[:, t:] - lg[:, :-t])
        zero = np.zeros((rows.size, 1))
        cum_g, cum_w = np.cumsum(np.hstack([zero, weighted]), axis=1), np.cumsum(np.hstack([zero, weight]), axis=1)
        usable = np.broadcast_to((x - box >= t) & (x + box <= w), (rows.size, w))
        lo, mid, hi = np.clip(x - box, 0, w), x, np.clip(x + box, 0, w)
        change = np.where(usable, _ratio_means(cum_g, cum_w, mid, hi) - _ratio_means(cum_g, cum_w, lo, mid), 0.0)
        evidence, one_sided = _evidence(change, usable, t)
        edge_share = _edge_share(box, blur)
        inner = max(2, box // 3)
        # the sharpness asked of an edge blurred by `blur`, relative to one blurred by STEP_SPREAD
        sharpness = STEP_SHARPNESS * (_edge_share(inner, blur) / edge_share) / (
            _edge_share(inner, STEP_SPREAD) / _edge_share(box, STEP_SPREAD))
        strength = np.abs(evidence)
        largest = scipy.ndimage.maximum_filter1d(strength, size=2 * box + 1, axis=1, mode="constant")
        # sharp: the change across boxes of a third of `box` (at its view: here, else a window on)
        at = np.where(usable, x, np.minimum(x + t, w - 1))
        short = (_ratio_means(cum_g, cum_w, at, np.minimum(at + inner, w))
                 - _ratio_means(cum_g, cum_w, np.maximum(at - inner, 0), at))
        full = np.take_along_axis(change, at, axis=1)
        need = np.where(one_sided, max(sharpness, STEP_SHARPNESS), sharpness)  # one view: as for 1 px
        sharp = (short * full > 0) & (np.abs(short) >= need * np.abs(full))
        candidate = (strength >= STEP_FIND * threshold) & (strength >= largest) & sharp
        # one per box: a candidate within `box` after another one is a tie, and the first wins
        count = np.hstack([np.zeros((rows.size, box + 1), np.intp), np.cumsum(candidate, axis=1)])
        earlier = count[:, box:box + w] - count[:, :w]  # candidates in x - box .. x - 1
        line, at = np.nonzero(candidate & (earlier == 0))
        steps = np.zeros((rows.size, w))
        for r in np.unique(line):  # each line's candidates in turn: a height depends on those kept before
            found = at[line == r]
            kept: list[tuple[int, float]] = []
            for j, x0 in enumerate(found):
                end = min(x0 + t, found[j + 1] if j + 1 < found.size else w)
                lo, hi = max(x0 + STEP_MARGIN, t), end - STEP_MARGIN
                if hi - lo < t // STEP_SPAN:
                    continue
                mid = (lo + hi) // 2

                def mean(a: int, b: int) -> float:  # the ratio's mean less what kept steps add there
                    span = max(cum_w[r, b] - cum_w[r, a], 1e-12)
                    earlier_steps = sum(h * (cum_w[r, min(k + t, b)] - cum_w[r, a]) / span
                                        for k, h in kept if k + t > a)
                    return (cum_g[r, b] - cum_g[r, a]) / span - earlier_steps

                first, second = mean(lo, mid), mean(mid, hi)
                height = 0.5 * (first + second)
                steady = first * second > 0 and abs(first - second) <= STEP_CONSTANCY * abs(height)
                concentrated = abs(evidence[r, x0]) >= min(STEP_CONCENTRATION * edge_share * abs(height),
                                                           STEP_ENOUGH)  # not a slow rise
                if (steady or not one_sided[r, x0]) and abs(height) >= STEP_HEIGHT * threshold and concentrated:
                    if abs(height) < STEP_HEIGHT * STEP_FLAT_BELOW:  # a lower step must be flat
                        u = np.arange(lo, hi)
                        wt, g = weight[r, u], lg[r, u] - lg[r, u - t]
                        mean = (wt * g).sum() / wt.sum()
                        if np.sqrt(max((wt * g * g).sum() / wt.sum() - mean**2, 0.0)) > STEP_FLAT * abs(height):
                            continue
                    kept.append((int(x0), height))
                    steps[r, x0] = height
        step_heights[rows] = steps
    return step_heights


def albedo_steps(img: NDArray[np.float32], windows: NDArray[np.intp], *,
                 threshold: float = STEP_THRESHOLD, blur: float = STEP_SPREAD) -> NDArray[np.float32]:
    """`sliscan.demodulate._albedo_steps` in numpy (see its docstring) for a camera blur of
    `blur` px, every step sharp: the steps found either way, heights averaged where both ways
    found one within a box."""
    floor = 0.01 * max(float(np.percentile(img[::4, ::4], 99)), 1e-6)
    ahead = _one_way_steps(img, windows, threshold, floor, blur)
    # read right to left: a step up there at x' is a step down here, starting at w - x'
    back = np.zeros_like(ahead)
    back[:, 1:] = -_one_way_steps(np.ascontiguousarray(img[:, ::-1]), windows, threshold, floor, blur)[:, :0:-1]
    delta = ahead.copy()
    for r in np.nonzero((back != 0).any(axis=1))[0]:
        box = max(STEP_MIN_BOX, int(round(STEP_BOX * int(windows[r]))))
        free = np.flatnonzero(back[r])
        for x in np.flatnonzero(ahead[r]):
            near = free[np.abs(free - x) <= box]
            if near.size:  # the nearest, the leftmost of two as near
                m = near[np.argmin(np.abs(near - x))]
                delta[r, x] = 0.5 * (ahead[r, x] + back[r, m])
                free = free[free != m]
        delta[r, free] += back[r, free]
    return np.exp(np.cumsum(delta, axis=1)).astype(np.float32)
