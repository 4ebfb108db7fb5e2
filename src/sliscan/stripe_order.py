"""Gray code decoding along the phase direction, by the order the stripes come in.

`sliscan.decode` decides each pixel's bits on their own.  A pixel's evidence can be weak and
still leave no doubt in context: on a surface the stripes follow each other in order along
every camera line in the phase direction (camera `y` for the ``rows`` orientation), stripe
``s`` after ``s - 1``, the code changing at a few borders per stripe height, jumping only at
depth edges and shadows.  So each such line is decoded as a whole, by dynamic programming
(a hidden Markov chain over the stripes and a "dark" state, max-product):

* **Evidence** (`emission`): for every pixel and stripe, how badly the pixel's bit levels
  (`Decoded.levels`: 0 off, 1 on) fit the stripe's code, seen with an unknown gain ``g``: the
  light that reaches a surface turning away from the projector falls with the angle of
  incidence while the ambient part of the DC (which the levels are relative to) does not, so
  the "on" levels of a pixel near a limb read 0.3 instead of 1 with a perfectly clear code.
  The gain is fitted per stripe (the mean of its on bits' levels) with a prior around 1
  (near log-normal); the deviations count in units of the pixel's noise
  (`Demodulated.noise`) plus a model error proportional to the gain, each bit's cost capped
  (one corrupted bit costs a bounded amount).  The dark state has no carrier: cheap where `decode._lit` found none,
  costly where it did.
* **Order** (the transition costs): staying costs nothing, the next stripe along the order
  `step`, the previous one `back`, any other (a depth edge) `jump`, entering or leaving the
  dark state `dark`; in nats.
* **Decision**: each pixel takes the label of the best path through it; its margin is how
  much worse (in nats) the best path through any other label at that pixel is (max-marginals
  from a forward and a backward pass).  A small margin means the context does not settle it.
  `decode` keeps a pixel when its margin is large enough, its own evidence does not
  contradict its label badly, and enough of its stripe's run down the column got that stripe
  from the per-pixel decisions (`anchored_runs`).

The direction the stripe numbers grow along the lines is the rig's (a camera upside down
reverses it); `stripe_direction` reads it from the per-pixel decisions.

Lines in threads (compiled kernels over blocks of 64 lines decoded side by side: the
innermost loops run across the block, so they vectorise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from sliscan._threads import over_rows
from sliscan.patterns import code_bits, code_to_stripe, stripe_codes
from sliscan.reconstruct import device_centre
from sliscan.types import Calibration, PatternSpec


@dataclass(frozen=True)
class OrderCosts:
    """The costs of `decode_by_order`, in nats (negative log probabilities).

    Attributes
    ----------
    step, back, jump, dark : float
        Transition costs from one pixel to the next along the phase direction: to the next
        stripe in the order, to the previous one, to any other stripe, into or out of the dark
        state.  Staying costs 0.
    model_error : float
        Standard deviation of a bit level's departure from its code, as a fraction of the
        pixel's gain (blur at stripe borders, crosstalk, leakage), added to the noise.
    bit_cap : float
        The most one bit's misfit can cost.
    gain_sd : float
        Width of the gain's prior: about the standard deviation of its natural log below 1
        (above 1: half of it); see `emission`.
    dark_lit, unlit : float
        Cost of the dark state on a pixel where a carrier was detected (`Decoded.lit`), and of
        any stripe where none was.
    """

    step: float = 4.0
    back: float = 12.0
    jump: float = 15.0
    dark: float = 8.0
    model_error: float = 0.15
    bit_cap: float = 6.0
    gain_sd: float = 1.0
    dark_lit: float = 10.0
    unlit: float = 10.0


def stripe_direction(stripe: NDArray[np.integer], valid: NDArray[np.bool_], spec: PatternSpec, *,
                     reach: int = 4) -> int:
    """+1 if stripe numbers grow with the camera coordinate along the phase direction (camera
    `y` for ``rows``, `x` for ``columns``), -1 if they fall, 0 if the decisions do not tell.

    Counts the pairs of valid pixels `reach` apart along that direction whose stripes differ
    by one; a direction needs three times the pairs of the other (and 100 of them).
    """
    s = np.where(valid, stripe, -1).astype(np.int32)
    s = s if spec.orientation == "rows" else s.T
    a, b = s[:-reach], s[reach:]
    both = (a >= 0) & (b >= 0)
    up = int(np.count_nonzero(both & (b - a == 1)))
    down = int(np.count_nonzero(both & (a - b == 1)))
    if up >= 100 and up >= 3 * down:
        return 1
    if down >= 100 and down >= 3 * up:
        return -1
    return 0


def rig_direction(calibration: Calibration, spec: PatternSpec) -> int:
    """`stripe_direction` as the rig's geometry gives it: +1 if the projector line (and so the
    stripe number) grows with the camera coordinate along the phase direction, -1 if it falls
    (0 for a degenerate rig).

    Two camera pixels 8 px apart along the phase direction at the frame's centre are taken to
    world points on their rays four baselines in front of the camera (the pinhole matrices; the
    ordering constraint makes the sign the same at any depth both devices see) and projected into
    the projector.  Unlike the per-pixel decisions it holds where a lost bit reads a large part of
    the frame in reverse (a defocused projector's wall: a third of the decided pairs stepping
    back).
    """
    camera, projector = calibration.camera.matrix, calibration.projector.matrix
    origin = device_centre(camera)
    reach = 4 * np.linalg.norm(device_centre(projector) - origin)
    step = np.array([0.0, 8.0]) if spec.orientation == "rows" else np.array([8.0, 0.0])
    middle = np.array(calibration.camera.size, dtype=np.float64) / 2
    pixels = np.array([[*middle, 1.0], [*(middle + step), 1.0]])
    # a pixel's ray is M^-1 [x, y, 1] from the centre (M the matrix's left 3x3), in front of the
    # camera when det(M) is positive: the point's depth is det(M) times its homogeneous w, here 1
    rays = np.linalg.solve(camera[:, :3], pixels.T).T * np.sign(np.linalg.det(camera[:, :3]))
    points = origin + reach * rays / np.linalg.norm(rays, axis=1, keepdims=True)
    seen = points @ projector[:, :3].T + projector[:, 3]
    lines = seen[:, 1 if spec.orientation == "rows" else 0] / seen[:, 2]
    change = lines[1] - lines[0]
    return 0 if abs(change) < 1e-6 else int(np.sign(change))


#: Fast-math flags of the kernels: everything but "no NaNs" and "no infinities" (the recursion
#: pads with +inf), so that their loops vectorise.
FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


#: Lines of `_order_columns`' blocks: their evidence is computed row by row (contiguous reads),
#: then each line is decoded from it.
BLOCK = 64


@numba.njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy")
def emission(levels: NDArray[np.float32], noise: NDArray[np.float32], bit_gains: NDArray[np.float32],
             span: NDArray[np.float32], lit: NDArray[np.bool_], on: NDArray[np.float32], costs: NDArray[np.float32],
             y: int, x0: int, n: int, out: NDArray[np.float32], work: NDArray[np.float32]) -> None:
    """The evidence of the pixels ``(y, x0 .. x0 + n - 1)`` against every state, into the first
    `n` columns of `out` ``(S + 1, BLOCK)``, n <= `BLOCK` (nats): each stripe's misfit, then the
    dark state's; the other columns get 0 (no evidence).

    A stripe's code (`on` ``(K, S)``: 1 where bit `k` of stripe `s` is on) is fitted with the
    gain ``g`` = the mean of its on bits' levels (at least 1e-3); each bit costs ``(level - g on)
    ** 2 / (2 (sd ** 2 + (model_error g) ** 2))``, at most `bit_cap` (``sd = noise[y, x] /
    (span[k] bit_gains[k, y, x])``: what the bits' envelopes were divided by divides their noise
    too; the gains are 1 where `bit_gains` has shape (0, 0, 0)), and the gain has the prior
    ``(g - 1) ** 2 / (2 s ** 2 g)`` below 1 (``s`` = `gain_sd`: near ``(ln g / s) ** 2 / 2``
    without a logarithm) and ``(g - 1) ** 2 / (2 (s / 2) ** 2)`` above.  A bit whose gain in
    `bit_gains` is 0 at a pixel (a bit lost there: `sliscan.decode.lost_bit_alternates`) counts
    neither in the gain nor in the cost there.  A pixel with a non-finite level or noise gives no
    evidence (0 for every state).  `costs` as in `_order_columns`; `work` ``(3 K + 4, BLOCK)`` is
    working memory.

    The pixels' levels and noise are first copied into `work` (padded to `BLOCK`), so every
    loop after that runs over `BLOCK` contiguous values of local rows: a fixed trip count
    without aliasing doubts, which the compiler vectorises (2x faster than reading the levels'
    rows in place, measured on the 5 MP sphere)."""
    bits, states = on.shape
    model2, cap, prior = costs[4] * costs[4], costs[5], np.float32(0.5) / (costs[6] * costs[6])
    level, var = work[:bits], work[bits:2 * bits]  # the levels and 2 sd ** 2 of each bit
    used = work[2 * bits:3 * bits]  # 1 where the bit counts, 0 where it is lost
    gain, spread, base, count = work[3 * bits], work[3 * bits + 1], work[3 * bits + 2], work[3 * bits + 3]
    divided = bit_gains.shape[0] > 0
    for k in range(bits):
        inv = np.float32(1) / span[k]
        for i in range(n):
            level[k, i] = levels[k, y, x0 + i]
            v = noise[y, x0 + i] * inv
            used[k, i] = 1
            if divided:
                g = bit_gains[k, y, x0 + i]
                if g > 0:
                    v /= g
                else:
                    level[k, i], v, used[k, i] = 0, 1, 0
            var[k, i] = np.float32(2) * v * v
        for i in range(n, BLOCK):
            level[k, i], var[k, i], used[k, i] = 0, 1, 1
    for i in range(n):
        base[i] = np.float32(0) if lit[y, x0 + i] else costs[8]
    for i in range(n, BLOCK):
        base[i] = 0
    for s in range(states):
        for i in range(BLOCK):
            gain[i], count[i] = 0, 0
        for k in range(bits):
            o = on[k, s]
            for i in range(BLOCK):
                gain[i] += o * level[k, i]
                count[i] += o * used[k, i]
        row = out[s]
        for i in range(BLOCK):
            g = max(gain[i] * (np.float32(1) / max(count[i], np.float32(1))), np.float32(1e-3))
            gain[i] = g
            spread[i] = np.float32(2) * model2 * g * g
            d = g - np.float32(1)
            row[i] = (prior * d * d / g if g < 1 else np.float32(4) * prior * d * d) + base[i]
        for k in range(bits):
            o = on[k, s]
            for i in range(BLOCK):
                e = level[k, i] - o * gain[i]
                t = e * e / (var[k, i] + spread[i])
                row[i] += used[k, i] * (t if t < cap else cap)
    for i in range(n):
        out[states, i] = costs[7] if lit[y, x0 + i] else np.float32(0)
    for i in range(n, BLOCK):
        for s in range(states + 1):
            out[s, i] = 0
    for i in range(n):
        usable = np.isfinite(noise[y, x0 + i])
        for k in range(bits):
            usable = usable and np.isfinite(levels[k, y, x0 + i])
        if not usable:
            for s in range(states + 1):
                out[s, i] = 0


@numba.njit(cache=True, nogil=True, inline="always", fastmath=FAST, error_model="numpy")
def _relax(prev: NDArray[np.float32], here: NDArray[np.float32], step: np.float32, back: np.float32,
           jump: np.float32, to_dark: np.float32, best: NDArray[np.float32], out: NDArray[np.float32]) -> None:
    """One step of the max-product recursion for a block of lines at once, into `out`
    ``(S + 3, n)``: the best cost of arriving at each state from `prev` (laid out as `out`:
    +inf, the S stripes in order, +inf, the dark state) plus `here` ``(S + 1, n)`` (the states'
    evidence, stripes then dark).  Each line's entries are shifted so their smallest is 0
    (costs stay small in float32; every margin is a difference within one line's row, which the
    shift leaves alone).  `best` ``(n,)`` is working memory.  Loops run along the lines."""
    states = here.shape[0] - 1
    dark = states + 2
    n = here.shape[1]
    best[:] = np.inf
    for s in range(1, states + 1):
        for i in range(n):
            best[i] = min(best[i], prev[s, i])
    for i in range(n):  # dark first: `best` then becomes the recursion's base
        out[dark, i] = min(prev[dark, i], best[i] + to_dark) + here[states, i]
        best[i] = min(best[i] + jump, prev[dark, i] + to_dark)
    for s in range(1, states + 1):
        for i in range(n):
            out[s, i] = min(min(prev[s, i], best[i]), min(prev[s - 1, i] + step, prev[s + 1, i] + back)) + here[s - 1, i]
    best[:] = out[dark]
    for s in range(1, states + 1):
        for i in range(n):
            best[i] = min(best[i], out[s, i])
    for s in range(1, states + 1):
        for i in range(n):
            out[s, i] -= best[i]
    for i in range(n):
        out[dark, i] -= best[i]


@numba.njit(cache=True, nogil=True, fastmath=FAST, error_model="numpy")
def _order_columns(levels: NDArray[np.float32], noise: NDArray[np.float32], bit_gains: NDArray[np.float32],
                   span: NDArray[np.float32], lit: NDArray[np.bool_], on: NDArray[np.float32], costs: NDArray[np.float32],
                   blocks: NDArray[np.intp], stripe: NDArray[np.int16], margin: NDArray[np.float32],
                   misfit: NDArray[np.float32]) -> None:
    """`decode_by_order` for the given blocks of `BLOCK` columns of ``(K, H, W)`` `levels` (the
    phase direction along axis 1, stripes numbered in the order they come down it); writes
    `stripe` (-1: dark), `margin` and `misfit` ``(H, W)``.  The columns of a block are decoded
    side by side (the innermost loops run across them).

    `costs`: step, back, jump, dark, model error, bit cap, gain sd, dark on a lit pixel,
    stripe on an unlit one (`OrderCosts`); `on` ``(K, S)``; `bit_gains` as in `emission`."""
    bits, h, w = levels.shape
    states = on.shape[1]
    dark = states + 2
    step, back, jump, to_dark = costs[0], costs[1], costs[2], costs[3]
    cost = np.empty((h, states + 1, BLOCK), dtype=np.float32)
    # forward and backward messages laid out as +inf, stripes, +inf, dark (see `_relax`)
    fwd = np.full((h, states + 3, BLOCK), np.inf, dtype=np.float32)
    below = np.full((states + 3, BLOCK), np.inf, dtype=np.float32)
    ahead = np.full((states + 3, BLOCK), np.inf, dtype=np.float32)
    nothing = np.zeros((states + 1, BLOCK), dtype=np.float32)
    work = np.empty(BLOCK, np.float32)
    scratch = np.empty((3 * bits + 4, BLOCK), np.float32)
    first, second = np.empty(BLOCK, np.float32), np.empty(BLOCK, np.float32)
    label = np.empty(BLOCK, np.int32)
    for block in blocks:
        x0 = block * BLOCK
        n = min(x0 + BLOCK, w) - x0  # the columns of a block beyond the image have no evidence
        for y in range(h):
            emission(levels, noise, bit_gains, span, lit, on, costs, y, x0, n, cost[y], scratch)
        fwd[0, 1:states + 1] = cost[0, :states]
        fwd[0, dark] = cost[0, states]
        for y in range(1, h):
            _relax(fwd[y - 1], cost[y], step, back, jump, to_dark, work, fwd[y])
        # the backward pass, each row decided as soon as its message is known
        below[1:states + 1] = 0
        below[dark] = 0
        for y in range(h - 1, -1, -1):
            if y < h - 1:
                # what lies below row y, its evidence included, relaxed against the order running
                # upwards (the next stripe down is the previous one up); the message excludes
                # row y's own evidence
                evidence = cost[y + 1]
                for s in range(states):
                    for i in range(BLOCK):
                        ahead[s + 1, i] = below[s + 1, i] + evidence[s, i]
                for i in range(BLOCK):
                    ahead[dark, i] = below[dark, i] + evidence[states, i]
                _relax(ahead, nothing, back, step, jump, to_dark, work, below)
            first[:], second[:], label[:] = np.inf, np.inf, states
            forward = fwd[y]
            for s in range(states + 1):
                k = s + 1 if s < states else dark
                for i in range(BLOCK):
                    total = forward[k, i] + below[k, i]
                    better = total < first[i]
                    second[i] = first[i] if better else min(second[i], total)
                    label[i] = s if better else label[i]
                    first[i] = total if better else first[i]
            for i in range(n):
                stripe[y, x0 + i] = -1 if label[i] == states else label[i]
                margin[y, x0 + i] = second[i] - first[i]
                misfit[y, x0 + i] = cost[y, label[i], i]


@numba.njit(cache=True, nogil=True)
def _anchored_columns(stripe: NDArray[np.int16], anchors: NDArray[np.int16], alternates: NDArray[np.int16],
                      min_share: float, lines: NDArray[np.intp], out: NDArray[np.bool_]) -> None:
    """`anchored_runs` for the given columns (the phase direction along axis 0)."""
    h = stripe.shape[0]
    for x in lines:
        start = 0
        while start < h:
            end, anchored = start, 0
            while end < h and stripe[end, x] == stripe[start, x]:
                anchored += anchors[end, x] == stripe[start, x] or alternates[end, x] == stripe[start, x]
                end += 1
            keep = anchored > 0 and anchored >= min_share * (end - start) and stripe[start, x] >= 0
            for y in range(start, end):
                out[y, x] = keep
            start = end


def anchored_runs(stripe: NDArray[np.int16], anchors: NDArray[np.int16], spec: PatternSpec, *,
                  min_share: float = 0.0, alternates: NDArray[np.int16] | None = None) -> NDArray[np.bool_]:
    """Pixels of `stripe` ``(H, W)`` whose run (pixels of one stripe in a row along the phase
    direction) holds at least one pixel, and at least `min_share` of its pixels, where
    `anchors` ``(H, W)`` (stripes decided pixel by pixel, -1 where not) has the same stripe.

    The order fills in a stripe where its own pixels are unclear but its neighbours are sure;
    a run that no pixel vouches for on its own (a blurred capture, light leaking into a shadow)
    is the order's guess alone, and is dropped.
    """
    def frame(a: NDArray) -> NDArray:
        return np.ascontiguousarray(a if spec.orientation == "rows" else a.T, dtype=np.int16)

    s, anchor = frame(stripe), frame(anchors)
    other = frame(np.full(stripe.shape, -1, np.int16) if alternates is None else alternates)
    out = np.empty(s.shape, dtype=bool)
    over_rows(lambda lines: _anchored_columns(s, anchor, other, float(min_share), lines, out), s.shape[1])
    return out if spec.orientation == "rows" else np.ascontiguousarray(out.T)


@numba.njit(cache=True, nogil=True)
def _reversed_columns(stripe: NDArray[np.int16], min_run: int, max_step: int, lost: NDArray[np.int16],
                      lines: NDArray[np.intp], out: NDArray[np.bool_], restored: NDArray[np.int16]) -> None:
    """`reversed_runs` for the given columns (the stripe numbers growing along axis 0; -1: no
    stripe)."""
    h = stripe.shape[0]
    label, first, last, size = (np.empty(h, np.int16), np.empty(h, np.intp), np.empty(h, np.intp),
                                np.empty(h, np.intp))
    back = np.zeros(h, np.bool_)  # whether each long run is entered by a step back
    for x in lines:
        out[:, x] = False
        restored[:, x] = -1
        runs = 0  # runs of one stripe, pixels without a stripe skipped
        for y in range(h):
            s = stripe[y, x]
            if s < 0:
                continue
            if runs == 0 or s != label[runs - 1]:
                label[runs], first[runs], size[runs] = s, y, 0
                runs += 1
            last[runs - 1] = y
            size[runs - 1] += 1
        long = 0  # the runs of at least `min_run` pixels, those of one stripe joined
        for i in range(runs):
            if size[i] < min_run:
                continue
            if long > 0 and label[i] == label[long - 1]:
                last[long - 1] = last[i]
                continue
            label[long], first[long], last[long] = label[i], first[i], last[i]
            long += 1
        for i in range(1, long):
            back[i] = -max_step <= label[i] - label[i - 1] < 0
        start = 1
        while start < long:  # chains of runs entered by a step back (two at least), each after its head
            end = start
            while back[start] and end + 1 < long and back[end + 1]:
                end += 1
            if end == start:
                start += 1
                continue
            bit = -1  # the one lost bit that, set again, makes the chain go forward from its head
            for k in range(lost.shape[0]):
                previous, forward = label[start - 1], True
                for i in range(start, end + 1):
                    again = lost[k, label[i]]
                    forward = forward and again >= 0 and 1 <= again - previous <= max_step
                    previous = again
                if forward:
                    bit = k if bit == -1 else -2
            for i in range(start, end + 1):
                for y in range(first[i], last[i] + 1):
                    if stripe[y, x] == label[i]:
                        out[y, x] = True
                        restored[y, x] = lost[bit, label[i]] if bit >= 0 else -1
            start = end + 1


def lost_bit_stripes(spec: PatternSpec) -> NDArray[np.int16]:
    """The stripe each stripe is with one bit set again, ``(K, S)`` int16: entry ``[k, s]`` is the
    stripe whose code is stripe `s`'s with bit `k` (most significant first) on, -1 where `s` has
    it on already or no stripe has that code.

    A bit lost where every stripe has it on reads the reflected Gray code's mirror: with the most
    significant bit lost, 4-bit stripe 8 reads 7 and 12 reads 3.

    >>> from sliscan.types import PatternSpec
    >>> lost_bit_stripes(PatternSpec(projector_size=(1024, 768), bits=4))[0, [7, 3, 8]].tolist()
    [8, 12, -1]
    """
    codes = stripe_codes(spec)
    mask = (1 << np.arange(spec.bits - 1, -1, -1))[:, None]
    again = code_to_stripe(codes[None, :] | mask, spec)
    return np.where((codes[None, :] & mask) == 0, again, -1).astype(np.int16)


def reversed_runs(stripe: NDArray[np.int16], spec: PatternSpec, direction: int, *, min_share: float = 0.25,
                  max_step: int = 2) -> tuple[NDArray[np.bool_], NDArray[np.int16]]:
    """Pixels of `stripe` ``(H, W)`` (-1: none) on runs that come in reverse order along the
    phase direction, and the stripes they read with the lost bit set again.

    A run is reversed when it is entered by a step back (against `direction`,
    `stripe_direction`) of at most `max_step` stripes next to another such step, counting only
    the runs of at least `min_share` of a stripe's mean height in the frame (the frame's lines
    along the phase direction over ``spec.stripes``; 3 pixels at least): the few pixels of a
    stripe border read a stripe early or late, or a sliver by a limb, are skipped like pixels
    without a stripe.

    On a surface that both the camera and the projector see, the stripes come in order along
    the phase direction, and with the projector beside the camera along that direction a depth
    edge keeps the order too (the epipolar ordering constraint: a thin object before a wall is
    the exception), so one step back is rare and two in a row are a mirror: a bit lost where
    every stripe has it on (the most significant bit on a carrier a defocused projector
    blurs away), which reads each stripe as the one before the last one read, all the way down a
    column (one step back each, two where a stripe goes undecided).  The lines are read the way
    the stripe numbers grow (up the frame for `direction` -1, a camera upside down), and the run
    before such a chain, entered going forward, is its head and is kept.  Steps back of more than `max_step`
    stripes do not chain: a wrong excursion between right runs (a jump, a step back, a jump back)
    would take the right run after it along (counting every step back, the thesis's smooth 5 MP
    sphere went 0.12 -> 0.15 % of its lit pixels more than one stripe off, RMS 10.8 -> 12.1 mm).
    `direction` 0 marks nothing.

    Returns
    -------
    reversed : (H, W) bool array
        The pixels of the chains' runs after their heads.
    restored : (H, W) int16 array
        Where exactly one bit (`lost_bit_stripes`), set again on every run of a chain, makes the
        chain go forward from its head in steps of one to `max_step` stripes: the stripes so
        read; -1 elsewhere.
    """
    none = np.full(stripe.shape, -1, dtype=np.int16)
    if direction == 0:
        return np.zeros(stripe.shape, dtype=bool), none
    def frame(a: NDArray) -> NDArray:  # the phase direction along axis 0, an involution
        return a if spec.orientation == "rows" else a.T

    def upward(a: NDArray) -> NDArray:  # the stripe numbers growing along axis 0, an involution
        return a if direction > 0 else a[::-1]

    s = np.ascontiguousarray(upward(frame(stripe)), dtype=np.int16)
    min_run = max(3, int(min_share * s.shape[0] / spec.stripes))
    lost = lost_bit_stripes(spec)
    out, restored = np.empty(s.shape, dtype=bool), np.empty(s.shape, dtype=np.int16)
    over_rows(lambda lines: _reversed_columns(s, min_run, int(max_step), lost, lines, out, restored), s.shape[1])
    return np.ascontiguousarray(frame(upward(out))), np.ascontiguousarray(frame(upward(restored)))


def decode_by_order(levels: NDArray[np.float32], noise: NDArray[np.float32], span: NDArray[np.float64],
                    lit: NDArray[np.bool_], spec: PatternSpec, direction: int, costs: OrderCosts = OrderCosts(), *,
                    bit_gains: NDArray[np.float32] | None = None,
                    ) -> tuple[NDArray[np.int16], NDArray[np.float32], NDArray[np.float32]]:
    """Stripes decoded line by line along the phase direction (see the module's docstring).

    Parameters
    ----------
    levels : (K, H, W) float32 array
        Bit levels (`Decoded.levels`: 0 = the bit's off level, 1 = its on level).
    noise : (H, W) float32 array
        Standard deviation of the envelopes' noise relative to the levels' reference (the
        DC or the pilot: `Demodulated.noise` divided by it); 0 where unknown.
    span : (K,) float64 array
        Each bit's on minus off level relative to the reference: bit `n`'s level has the
        noise ``noise / span[n]``.
    lit : (H, W) bool array
        Pixels where a carrier was detected.
    spec : PatternSpec
        The pattern: its codes (the all-zero one, if projected, is left to the dark state:
        no carrier tells it from shadow) and orientation.
    direction : {1, -1, 0}
        `stripe_direction`; 0 makes the previous stripe as cheap as the next.
    costs : OrderCosts
    bit_gains : (K, H, W) float32 array, optional
        What the bits' envelopes were divided by (`sliscan.decode.blur_gains`): bit `n`'s
        noise is then ``noise / (span[n] bit_gains[n])``.

    Returns
    -------
    stripe : (H, W) int16 array
        Stripe index, -1 for the dark state.
    margin : (H, W) float32 array
        Nats between the best labelling and the best one with another label at the pixel.
    misfit : (H, W) float32 array
        The pixel's own evidence against its label (`emission`), nats.
    """
    codes = stripe_codes(spec)
    stripes = np.arange(spec.stripes)
    if not spec.skip_zero_code:
        stripes = stripes[codes != 0]
    order = stripes if direction >= 0 else stripes[::-1]
    on = np.ascontiguousarray(code_bits(codes[order], spec.bits).T, dtype=np.float32)  # (K, S)
    step, back = (costs.step, costs.back) if direction != 0 else (costs.step, costs.step)
    table = np.array([step, back, costs.jump, costs.dark, costs.model_error, costs.bit_cap, costs.gain_sd,
                      costs.dark_lit, costs.unlit], dtype=np.float32)

    def frame(a: NDArray) -> NDArray:  # the phase direction along axis -2
        return np.ascontiguousarray(a if spec.orientation == "rows" else np.swapaxes(a, -1, -2))

    lv, sd, mask = frame(levels), frame(np.asarray(noise, dtype=np.float32)), frame(lit)
    gains = np.zeros((0, 0, 0), np.float32) if bit_gains is None else frame(np.asarray(bit_gains, dtype=np.float32))
    span = np.ascontiguousarray(span, dtype=np.float32)
    h, w = mask.shape
    index = np.empty((h, w), dtype=np.int16)
    margin, misfit = np.empty((h, w), dtype=np.float32), np.empty((h, w), dtype=np.float32)
    over_rows(lambda blocks: _order_columns(lv, sd, gains, span, mask, on, table, blocks, index, margin, misfit),
              -(-w // BLOCK))
    stripe = np.where(index >= 0, order.astype(np.int16)[np.maximum(index, 0)], np.int16(-1)).astype(np.int16)
    if spec.orientation != "rows":
        stripe, margin, misfit = (np.ascontiguousarray(a.T) for a in (stripe, margin, misfit))
    return stripe, margin, misfit
