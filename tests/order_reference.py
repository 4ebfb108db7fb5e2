"""The order decoding of `sliscan.stripe_order` written out plainly, for the tests: the evidence
per pixel in numpy, and the max-product recursion over an explicit transition matrix.

Independent of the kernels' layout (padded rows, blocks of lines, shifted costs, float32): if
both agree, the kernels compute what the module's docstring says.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sliscan.stripe_order import OrderCosts


def evidence(levels: NDArray, noise: NDArray, span: NDArray, lit: NDArray, on: NDArray,
             costs: OrderCosts) -> NDArray[np.float64]:
    """``(H, W, S + 1)`` costs of every state (stripes in the order of `on` ``(S, K)``, then dark)."""
    lv = np.asarray(levels, np.float64)  # (K, H, W)
    sd2 = (np.asarray(noise, np.float64)[None] / np.asarray(span, np.float64)[:, None, None]) ** 2
    out = []
    for code in np.asarray(on, bool):
        gain = np.maximum(lv[code].sum(axis=0) / max(code.sum(), 1), 1e-3)
        expected = np.where(code[:, None, None], gain[None], 0.0)
        var = sd2 + (costs.model_error * gain[None]) ** 2
        bits = np.minimum((lv - expected) ** 2 / (2 * var), costs.bit_cap).sum(axis=0)
        d = gain - 1
        prior = np.where(gain < 1, d * d / (2 * costs.gain_sd ** 2 * gain), d * d / (2 * (costs.gain_sd / 2) ** 2))
        out.append(bits + prior + np.where(lit, 0.0, costs.unlit))
    out.append(np.where(lit, costs.dark_lit, 0.0))
    cost = np.stack(out, axis=-1)
    usable = np.all(np.isfinite(lv), axis=0) & np.isfinite(np.asarray(noise))
    return np.where(usable[..., None], cost, 0.0)


def transitions(states: int, costs: OrderCosts, step: float, back: float) -> NDArray[np.float64]:
    """``(S + 1, S + 1)`` cost of going from state i (row) to state j (column), dark last."""
    t = np.full((states + 1, states + 1), costs.jump)
    idx = np.arange(states)
    t[idx, idx] = 0.0
    t[idx[:-1], idx[:-1] + 1] = min(step, costs.jump)
    t[idx[1:], idx[1:] - 1] = min(back, costs.jump)
    t[:states, states] = t[states, :states] = costs.dark
    t[states, states] = 0.0
    return t


def decode_column(cost: NDArray, t: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Max-marginal decoding of one line: labels (S = dark), margins and own costs, ``(H,)`` each."""
    h, n = cost.shape
    fwd, bwd = np.empty((h, n)), np.zeros((h, n))
    fwd[0] = cost[0]
    for y in range(1, h):
        fwd[y] = (fwd[y - 1][:, None] + t).min(axis=0) + cost[y]
    for y in range(h - 2, -1, -1):
        bwd[y] = (t + (cost[y + 1] + bwd[y + 1])[None, :]).min(axis=1)
    total = fwd + bwd
    order = np.sort(total, axis=1)
    label = total.argmin(axis=1)
    return label, order[:, 1] - order[:, 0], cost[np.arange(h), label]
