"""The numpy form of `sliscan.demodulate._albedo_steps`, the compiled kernel's exactness reference."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
import scipy.ndimage

from sliscan.demodulate import STEP_APEX, STEP_SHARPNESS, STEP_THRESHOLD


def _shifted(values: NDArray[np.float64], shift: int) -> NDArray[np.float64]:
    """``values[:, x - shift]`` along axis 1 (edge values repeated beyond the ends)."""
    if shift > 0:
        return np.concatenate([np.repeat(values[:, :1], shift, axis=1), values[:, :-shift]], axis=1)
    return np.concatenate([values[:, -shift:], np.repeat(values[:, -1:], -shift, axis=1)], axis=1)


def albedo_steps(img: NDArray[np.float32], windows: NDArray[np.intp], *, threshold: float = STEP_THRESHOLD,
                  apex: float = STEP_APEX, sharpness: float = STEP_SHARPNESS) -> NDArray[np.float32]:
    """`sliscan.demodulate._albedo_steps` in numpy (see its docstring), as it was before the kernel."""
    h, w = img.shape
    floor = np.float32(0.01 * max(float(np.percentile(img[::4, ::4], 99)), 1e-6))
    logi = np.log(np.maximum(img, floor))
    out = np.zeros((h, w), dtype=np.float64)
    for period in np.unique(windows):  # lines of one window length together (a handful)
        rows = np.nonzero(windows == period)[0]
        t = int(period)
        if 3 * t >= w:
            continue
        lg, im = logi[rows].astype(np.float64), img[rows].astype(np.float64)
        weighted, weight = np.zeros_like(lg), np.zeros_like(lg)
        weight[:, t:] = np.maximum(np.minimum(im[:, t:], im[:, :-t]), floor)
        weighted[:, t:] = weight[:, t:] * (lg[:, t:] - lg[:, :-t])
        zero = np.zeros((rows.size, 1))
        cum_g, cum_w = np.cumsum(np.hstack([zero, weighted]), axis=1), np.cumsum(np.hstack([zero, weight]), axis=1)
        starts = np.arange(w)
        ends = np.minimum(starts + t, w)
        mean = (cum_g[:, ends] - cum_g[:, starts]) / np.maximum(cum_w[:, ends] - cum_w[:, starts], 1e-12)
        peak = mean - 0.5 * (_shifted(mean, t) + _shifted(mean, -t))
        strength = np.abs(peak)
        q = max(int(round(apex * t)), 1)
        fall = (mean - 0.5 * (_shifted(mean, q) + _shifted(mean, -q))) * np.sign(peak)
        largest = scipy.ndimage.maximum_filter1d(strength, size=t | 1, axis=1, mode="nearest")
        steps = (strength >= threshold) & (strength >= largest) & (fall >= sharpness * strength)
        out[rows] = np.cumsum(np.where(steps, peak, 0.0), axis=1)
    return np.exp(out).astype(np.float32)


