"""The straightforward numpy sliding-window fit that `sliscan.demodulate._fit_line` (the
compiled kernel) computes: the tests check the kernel against it.

One line at a time, every window start at once: the window's samples as a sliding view, the
least-squares fit by the pseudo-inverse of the window's design matrix, the model evaluated
sample by sample where the kernel uses closed forms and running sums.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sliscan.demodulate import FLAT_GAIN, FLAT_STRETCH_GAIN, PLACEMENT_GAIN, Carriers


def window_starts(width: int, window: int, placement: int, half: int) -> NDArray[np.intp]:
    """Start of each pixel's window of `window` samples: placement -1 ends at the pixel, 0
    starts `half` before it, +1 starts at it; shifted inside the line at its ends."""
    offset = {-1: window - 1, 0: half, 1: 0}[placement]
    return np.clip(np.arange(width) - offset, 0, width - window)


def window_means(values: NDArray[np.float64], window: int) -> NDArray[np.float64]:
    """Mean of `values` over the window starting at every start, ``(W - window + 1,)``."""
    return np.lib.stride_tricks.sliding_window_view(values, window).mean(axis=1)


def flat_field(line: NDArray[np.float64], window: int) -> NDArray[np.float64]:
    """Local mean of each pixel over a box of `window` pixels, centred on the pixel unless a
    box ending or starting at it varies much less relative to its mean, or the least varying
    box that holds it is flat beside the centred one."""
    means = window_means(line, window)
    variation = (window_means(line * line, window) - means**2) / np.maximum(means**2, 1e-12)
    centred = window_starts(line.size, window, 0, window // 2)
    best = centred.copy()
    for placement in (-1, 1):
        start = window_starts(line.size, window, placement, window // 2)
        better = (variation[start] < variation[best]) & (variation[start] < FLAT_GAIN * variation[centred])
        best = np.where(better, start, best)
    starts = np.arange(line.size)[:, None] - np.arange(window)[None, :]  # every box holding each pixel
    holding = (starts >= 0) & (starts < means.size)
    least = np.where(holding, variation[np.clip(starts, 0, means.size - 1)], np.inf)
    flattest = np.take_along_axis(starts, np.argmin(least, axis=1)[:, None], axis=1)[:, 0]
    stretch = variation[flattest] < FLAT_STRETCH_GAIN * variation[centred]
    return means[np.where(stretch, flattest, best)]


def fit_line(line: NDArray[np.float32], omega: NDArray[np.float64], window: int, short: int,
             adaptive: bool) -> tuple[NDArray, ...]:
    """Best least-squares fit of a DC, a ramp and the carriers (`omega`, radians per pixel)
    over a window of `window` pixels at every pixel of `line`.

    Returns ``(unexplained, var, dc, amp (C, W), misfit, offset)`` in image units, as
    `demodulate_window` reports them for the line.
    """
    width = line.size
    raw = line.astype(np.float64)
    flat = np.maximum(flat_field(raw, window), 1e-4)
    block = raw / flat
    centre, half = (window - 1) / 2, window // 2
    j = np.arange(window)
    waves = np.column_stack([f(w * j) for w in omega for f in (np.cos, np.sin)])
    design = np.column_stack([np.ones(window), (j - centre) / window, waves])  # (window, 2 + 2C)
    samples = np.lib.stride_tricks.sliding_window_view(block, window)  # (starts, window)
    fits = samples @ np.linalg.pinv(design).T  # (starts, 2 + 2C)
    models = fits @ design.T  # each start's model over its window
    unexplained = ((samples - models) ** 2).mean(axis=1)
    var = window_means(block * block, window) - window_means(block, window) ** 2
    amplitude = np.hypot(fits[:, 2::2], fits[:, 3::2]).T  # (C, starts)

    centred = window_starts(width, window, 0, half)
    chosen, placement = centred.copy(), np.zeros(width, np.intp)
    if adaptive:
        for side in (-1, 1):
            start = window_starts(width, window, side, half)
            better = (unexplained[start] < unexplained[chosen]) & (unexplained[start] < PLACEMENT_GAIN * unexplained[centred])
            chosen, placement = np.where(better, start, chosen), np.where(better, side, placement)
    # the misfit: the chosen model's mean over the short window on its side of the pixel
    # against the line's own mean there, relative to the fitted DC
    near = np.stack([window_starts(width, short, side, short // 2) for side in (-1, 0, 1)])[placement + 1,
                                                                                            np.arange(width)]
    u = near[:, None] + np.arange(short)[None, :] - chosen[:, None]  # the short window's samples in the window
    model_waves = np.concatenate([np.stack([f(w * u) for f in (np.cos, np.sin)], axis=-1) for w in omega], axis=-1)
    basis = np.concatenate([np.ones(u.shape + (1,)), ((u - centre) / window)[..., None], model_waves], axis=-1)
    prediction = np.einsum("xkb,xb->x", basis, fits[chosen]) / short
    observed = np.lib.stride_tricks.sliding_window_view(block, short).mean(axis=1)[near]
    dc = fits[chosen, 0]
    misfit = np.abs(observed - prediction) / np.maximum(dc, 1e-6)
    offset = chosen + centre - np.arange(width)
    return (unexplained[chosen] * flat**2, np.maximum(var[chosen], 0) * flat**2, dc * flat,
            amplitude[:, chosen] * flat, misfit, offset)


def fit_lines(img: NDArray[np.float32], carriers: Carriers, lines: NDArray[np.intp], short: int,
              *, adaptive: bool) -> tuple[NDArray, ...]:
    """`fit_line` on ``img[lines]``, each line with its own window and frequencies; outputs
    stacked: ``(n, W)`` each, the amplitudes ``(C, n, W)``."""
    windows = np.broadcast_to(carriers.line_windows(), (img.shape[0],))
    omegas = 2 * np.pi * carriers.line_frequencies(lines)
    fits = [fit_line(img[r], omega, int(windows[r]), short, adaptive) for r, omega in zip(lines, omegas)]
    stacked = [np.stack(values) for values in zip(*fits)]
    stacked[3] = np.moveaxis(stacked[3], 0, 1)
    return tuple(stacked)
