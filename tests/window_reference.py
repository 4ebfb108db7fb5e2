"""The straightforward numpy sliding-window fit, as sliscan computed it before the compiled
kernel (`sliscan.demodulate._fit_line`): the tests check the kernel against it.

Every sum is a whole-chunk numpy expression over ``(carriers, lines, width)`` arrays in
float64 / complex128, exactly as in the original module; only `fit_lines` (was
``_fit_lines``) is public here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sliscan.demodulate import FLAT_GAIN, PLACEMENT_GAIN, Carriers

def _window_bounds(width: int, window: int, placement: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Start and end (exclusive) of each pixel's window: placement -1 ends at the pixel,
    0 is centred on it, +1 starts at it; windows are shifted inside the line at its ends."""
    x = np.arange(width)
    offset = {-1: window - 1, 0: window // 2, 1: 0}[placement]
    start = np.clip(x - offset, 0, width - window)
    return start, start + window


def _running_mean(cum: NDArray, start: NDArray[np.intp], end: NDArray[np.intp], window: int) -> NDArray:
    return (cum[:, end] - cum[:, start]) / window


def _cumsum0(values: NDArray) -> NDArray:
    out = np.zeros((values.shape[0], values.shape[1] + 1), dtype=values.dtype)
    np.cumsum(values, axis=1, out=out[:, 1:])
    return out


@dataclass(frozen=True, eq=False)
class _WindowTables:
    """Per-line, per-window-start constants of the local least-squares fit (`_fit_windows`).

    For carrier n of line r and a window of length L starting at s, with ``t`` the offset
    from the window's centre: ``g[n, r, s]`` = mean of ``exp(-i w_rn x)`` and ``h[n, r, s]``
    = mean of ``t exp(-i w_rn x)`` over the window (closed forms: a geometric series times
    ``exp(-i w s)``); ``near[n, r, s]`` = mean of ``exp(+i w_rn x)`` over the short window
    starting at s; ``t2`` = mean of ``t**2``.
    """

    phasors: NDArray[np.complex128]  # (C, lines, W)
    g: NDArray[np.complex128]  # (C, lines, W)
    h: NDArray[np.complex128]  # (C, lines, W)
    near: NDArray[np.complex128]  # (C, lines, W)
    pairs: tuple[tuple[int, int], ...]  # (n, m), n <= m
    sums: NDArray[np.complex128]  # (pairs, lines, W): mean of exp(i (w_n + w_m) x)
    diffs: NDArray[np.complex128]  # (pairs, lines, W): mean of exp(i (w_n - w_m) x); 1 for n == m
    t2: float
    window: int
    short: int

    @classmethod
    def build(cls, width: int, freqs: NDArray[np.float64], window: int, short: int) -> _WindowTables:
        """`freqs` is ``(lines, C)`` in cycles per pixel."""
        omega = 2 * np.pi * freqs.T[:, :, None]  # (C, lines, 1)
        x = np.arange(width, dtype=np.float64)
        phasors = np.exp(-1j * omega * x)
        j = np.arange(window, dtype=np.float64)
        t = j - (window - 1) / 2
        series = np.exp(-1j * omega * j)  # (C, lines, L)
        g = phasors * series.mean(axis=-1, keepdims=True)
        h = phasors * (series * t).mean(axis=-1, keepdims=True)
        near = np.exp(1j * omega * x) * np.exp(1j * omega * np.arange(short)).mean(axis=-1, keepdims=True)
        pairs = tuple((n, m) for n in range(omega.shape[0]) for m in range(n, omega.shape[0]))
        sums = np.stack([_window_mean_phasor(omega[n] + omega[m], x, j) for n, m in pairs])
        diffs = np.stack([_window_mean_phasor(omega[n] - omega[m], x, j) for n, m in pairs])
        return cls(phasors, g, h, near, pairs, sums, diffs, float(np.mean(t * t)), window, short)


def _window_mean_phasor(omega: NDArray[np.float64], x: NDArray[np.float64], j: NDArray[np.float64]) -> NDArray[np.complex128]:
    """Mean of ``exp(i omega x)`` over the window starting at each x: ``(lines, W)``."""
    return np.exp(1j * omega * x) * np.exp(1j * omega * j).mean(axis=-1, keepdims=True)


def _flat_field(lines: NDArray[np.float64], window: int) -> NDArray[np.float64]:
    """Local mean of each pixel over the box of one window, ending at, centred on or starting
    at the pixel.  The centred box (unbiased on a smooth albedo gradient) is kept unless a
    one-sided box varies much less relative to its mean (`FLAT_GAIN`): then the centred
    one straddles an albedo edge or a shadow border and the one-sided one does not."""
    w = lines.shape[1]
    cum, cum2 = _cumsum0(lines), _cumsum0(lines * lines)
    best_mean = best_var = centre_var = None
    for placement in (0, -1, 1):
        start, end = _window_bounds(w, window, placement)
        mean = _running_mean(cum, start, end, window)
        var = (_running_mean(cum2, start, end, window) - mean * mean) / np.maximum(mean * mean, 1e-12)
        if best_mean is None:
            best_mean, best_var, centre_var = mean, var, var
        else:
            better = (var < best_var) & (var < FLAT_GAIN * centre_var)
            best_mean, best_var = np.where(better, mean, best_mean), np.where(better, var, best_var)
    return best_mean


def _fit_windows(cums: tuple, start: NDArray[np.intp], near_start: NDArray[np.intp],
                 tables: _WindowTables) -> tuple[NDArray, ...]:
    """Least-squares fit of ``d + s t + sum_n (c_n e^{i w_n x} + c.c.)`` in each window.

    Over one spacing period the carriers are nearly orthogonal to each other and to the DC,
    but not to a ramp: an albedo gradient across the window would leak into every carrier.
    With the couplings of the DC and the ramp to each carrier known per window start
    (`_WindowTables`), the carriers are eliminated (``c_n = q_n - d g_n - s h_n``) and the
    remaining 2x2 system for the DC and the ramp is solved exactly, element-wise.  Only the
    carriers' couplings to each other (of the order of the window's rounding to whole
    pixels) are neglected.

    Returns ``(unexplained AC energy, AC energy, dc, amplitudes (C, ...), prediction,
    observed)``, where `prediction` is the fitted model's mean over the short window starting
    at `near_start` and `observed` the line's own mean there.
    """
    cum_i, cum_i2, cum_xi, cum_q = cums
    win = tables.window
    end = start + win
    centre = start + (win - 1) / 2
    m0 = _running_mean(cum_i, start, end, win)
    m1 = _running_mean(cum_xi, start, end, win) - centre * m0
    q = np.stack([_running_mean(cq, start, end, win) for cq in cum_q])  # (C, lines, W)
    g, h = tables.g[:, :, start], tables.h[:, :, start]
    gg = 2 * np.sum(np.abs(g) ** 2, axis=0)
    hh = 2 * np.sum(np.abs(h) ** 2, axis=0)
    gh = 2 * np.sum((g * np.conj(h)).real, axis=0)
    a11, a12, b1 = 1 - gg, -gh, m0 - 2 * np.sum((q * np.conj(g)).real, axis=0)
    a21, a22, b2 = -gh, tables.t2 - hh, m1 - 2 * np.sum((q * np.conj(h)).real, axis=0)
    det = a11 * a22 - a12 * a21
    det = np.where(np.abs(det) > 1e-12, det, 1e-12)
    d = (b1 * a22 - a12 * b2) / det
    slope = (a11 * b2 - a21 * b1) / det
    c = q - d * g - slope * h
    mean_sq = _running_mean(cum_i2, start, end, win)
    var = np.maximum(mean_sq - m0 * m0, 0)
    # mean of (I - model)^2 = <I,I> - 2 <I,model> + <model,model>, every Gram term exact, so
    # the small neglected couplings only enter to second order.
    cross = d * m0 + slope * m1 + 2 * np.sum((np.conj(c) * q).real, axis=0)
    model_sq = (d * d + slope * slope * tables.t2 + 4 * d * np.sum((c * np.conj(g)).real, axis=0)
                + 4 * slope * np.sum((c * np.conj(h)).real, axis=0))
    for k, (n, m) in enumerate(tables.pairs):
        weight = 2.0 if n == m else 4.0
        model_sq = model_sq + weight * (c[n] * c[m] * tables.sums[k][:, start]).real
        model_sq = model_sq + (2 * np.abs(c[n]) ** 2 if n == m else 4 * (c[n] * np.conj(c[m]) * tables.diffs[k][:, start]).real)
    unexplained = np.maximum(mean_sq - 2 * cross + model_sq, 0)
    short = tables.short
    prediction = (d + slope * (near_start + (short - 1) / 2 - centre)
                  + 2 * np.sum((c * tables.near[:, :, near_start]).real, axis=0))
    observed = _running_mean(cum_i, near_start, near_start + short, short)
    return unexplained, var, d, 2 * np.abs(c), prediction, observed


def fit_lines(img: NDArray[np.float32], carriers: Carriers, lines: NDArray[np.intp], window: int, short: int,
               *, adaptive: bool) -> tuple[NDArray, ...]:
    """Best window fit of some lines that share one window length.

    Returns ``(unexplained, var, dc, amp (C, n, W), misfit, offset)`` for ``img[lines]``.  The
    centred window is kept unless a one-sided one leaves less than `PLACEMENT_GAIN` of its
    unexplained energy and the least of all.
    """
    w = img.shape[1]
    x = np.arange(w, dtype=np.float64)
    raw = img[lines].astype(np.float64)
    # Divide out the local mean (a box of one spacing period, which cancels every carrier):
    # albedo multiplies the whole pattern, and a smooth albedo divided by its own local
    # mean is flat to second order, so the carriers keep a constant amplitude in the window.
    flat = np.maximum(_flat_field(raw, window), 1e-4)
    block = raw / flat
    tables = _WindowTables.build(w, carriers.line_frequencies(lines), window, short)
    cums = (_cumsum0(block), _cumsum0(block * block), _cumsum0(block * x),
            [_cumsum0(block * ph) for ph in tables.phasors])
    placements = (0, -1, 1) if adaptive else (0,)

    def placed(placement: int) -> tuple[NDArray, ...]:  # the misfit's short window on the same side
        start = _window_bounds(w, window, placement)[0]
        offset = np.broadcast_to(start + (window - 1) / 2 - x, raw.shape)  # the window's centre from the pixel
        return (*_fit_windows(cums, start, _window_bounds(w, short, placement)[0], tables), offset)

    best = list(placed(placements[0]))
    centre_unexplained = best[0]
    for placement in placements[1:]:
        fit = placed(placement)
        better = (fit[0] < best[0]) & (fit[0] < PLACEMENT_GAIN * centre_unexplained)
        for i, value in enumerate(fit):
            best[i] = np.where(better[None] if value.ndim == 3 else better, value, best[i])
    unexplained, var, mean, amp, prediction, observed, offset = best
    misfit = np.abs(observed - prediction) / np.maximum(mean, 1e-6)
    # back to image units at the pixel
    return unexplained * flat**2, var * flat**2, mean * flat, amp * flat, misfit, offset
