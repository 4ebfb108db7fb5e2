"""Classic Gray code sequences, in OpenCV's ``structured_light::GrayCodePattern`` frame order.

Each projector line (column for ``"columns"``, row for ``"rows"``) belongs to the code
``floor(line / code_width)``; its binary-reflected Gray code has ``spec.gray_bits(direction)``
bits, and every bit is projected as a pattern (white where the bit is 1) and then its inverse.
Frame order (OpenCV's, with ``code_width = 1``): the column bits, most significant first, each
pattern then its inverse; then the row bits likewise; then all white and all black.  Codes past
the projector's last line are never projected (1024x768: 10 bits per direction, 42 frames).

A camera pixel is decoded like OpenCV's ``GrayCodePattern::decode``: it is lit where
``white - black > black_threshold`` (the shadow mask), and each bit is 1 where the pattern is
brighter than its inverse; a bit is reliable where ``|pattern - inverse| >= white_threshold``.
OpenCV decodes a pixel only if every bit is reliable (``max_dropped_bits=0, border_bit=False``
here), which on a real, blurred rig rejects most pixels: the finest stripes (1-2 projector
lines) are washed out.  By default sliscan degrades gracefully instead:

- a trailing run of unreliable (finest) bits, up to `max_dropped_bits`, is dropped: Gray to
  binary is prefix-preserving, so the reliable prefix names a block of ``2**dropped``
  consecutive codes, and the pixel gets the block's centre line and its width
  (`GrayCodeMap.block`, in projector lines);
- one unreliable bit followed by reliable finer bits is the pixel straddling that bit's own
  transition, between two adjacent codes that differ in that bit only (the Gray property): it
  is decided by the sign of ``pattern - inverse``, which costs at most one code (one block).
  Two or more such bits reject the pixel.

The decoded projector coordinate is the centre line of the code, or of the block (the line
itself for a full code with ``code_width = 1``).

With ``steps > 0`` (a Gray code + phase shift hybrid) ``steps`` phase-shifted fringes of period
``2 code_width`` follow, per direction (columns first), after the black frame (`sliscan.pmp`'s
eq. 2.1 with ``f = lines / (2 code_width)``).  The Gray code then only numbers half periods: the
coordinate is unwrapped from the centre of the decoded half period (`pmp.unwrap_step`), whose
error stays within a quarter period, so a Gray code switching a line early or late at a
period border cannot cost a whole period (the usual period-border correction).  The unwrapping
needs the whole code, so no bit is dropped; a border bit decided by its sign is one code off at
most, which the unwrapping absorbs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.stats
from numpy.typing import NDArray

from sliscan._validate import InputError
from sliscan.patterns import bits_to_code, code_bits, gray_decode, gray_encode
from sliscan.pmp import QUANTISATION_NOISE, Fringes, ProjectorMap, fit_fringes, fringe_frames, line_image, \
    modulation_threshold, unwrap_step
from sliscan.types import PatternSpec

#: OpenCV's default thresholds (5 and 40 of 255), in [0, 1] image units.
WHITE_THRESHOLD = 5 / 255
BLACK_THRESHOLD = 40 / 255
#: Default `decode_graycode` limit on the dropped finest bits (see its docstring for why).
MAX_DROPPED_BITS = 3


@dataclass(frozen=True, eq=False)
class GrayCodeMap(ProjectorMap):
    """The `ProjectorMap` of a Gray code capture, with the resolution each pixel's code reached.

    Attributes
    ----------
    block : (H, W) int32 array
        Width, in projector lines, of the block of lines that the pixel's decoded code (or
        reliable code prefix) identifies: ``code_width`` for a full code, ``code_width *
        2**dropped`` with the `dropped` finest bits left out (less where the projector edge cuts
        the block); 0 where not valid.  `coord` is the block's centre, so the pixel's line lies
        within ``coord +- block / 2`` (one code more for a bit decided at its border).  With
        phase (``steps > 0``) the code's block, which the phase refines to a sub-pixel `coord`.
    """

    block: NDArray[np.int32]


def white_black_frames(spec: PatternSpec) -> tuple[int, int]:
    """Frame indices of the all-white and the all-black frames."""
    white = 2 * sum(spec.gray_bits(d) for d in spec.directions)
    return white, white + 1


def _pair_start(spec: PatternSpec, direction: str) -> int:
    """Index of the first pattern frame of `direction`."""
    return 2 * sum(spec.gray_bits(d) for d in spec.directions[:spec.directions.index(direction)])


def _phase_start(spec: PatternSpec, direction: str) -> int:
    """Index of the first phase-shifted frame of `direction` (hybrid sequences)."""
    return white_black_frames(spec)[1] + 1 + spec.steps * spec.directions.index(direction)


def code_planes(spec: PatternSpec, direction: str) -> NDArray[np.uint8]:
    """Gray code bits of every projector line along `direction`: ``(bits, lines)`` uint8,
    most significant bit first.

    >>> code_planes(PatternSpec(kind="graycode", projector_size=(8, 8), orientation="columns"), "columns").tolist()
    [[0, 0, 0, 0, 1, 1, 1, 1], [0, 0, 1, 1, 1, 1, 0, 0], [0, 1, 1, 0, 0, 1, 1, 0]]
    """
    codes = gray_encode(np.arange(spec.lines(direction)) // spec.code_width)
    return code_bits(codes, spec.gray_bits(direction)).T.copy()


def pattern_frames(spec: PatternSpec) -> NDArray[np.float32]:
    """Every image of a ``graycode`` spec in projection order: ``(frame_count, H_p, W_p)``
    float32 in {0, 1} (the fringes of a hybrid on the 1/255 grid, pre-corrected)."""
    frames = []
    for direction in spec.directions:
        for plane in code_planes(spec, direction):
            image = line_image(plane, direction, spec.projector_size)
            frames += [image, 1 - image]
    w, h = spec.projector_size
    frames += [np.ones((h, w), np.float32), np.zeros((h, w), np.float32)]
    if spec.steps:
        for direction in spec.directions:
            frames += fringe_frames(spec, direction, spec.lines(direction) / (2 * spec.code_width))
    return np.stack(frames)


def bit_pairs(frames: NDArray[np.float32], spec: PatternSpec, direction: str) -> NDArray[np.float32]:
    """The pattern/inverse frames of every Gray code bit of `direction`: ``(bits, 2, H, W)``,
    most significant bit first; a bit is 1 where the pattern is brighter than its inverse.

    Parameters
    ----------
    frames : (frame_count, H, W) float32 array
        The whole capture in the spec's order.
    """
    bits = spec.gray_bits(direction)
    start = _pair_start(spec, direction)
    return frames[start:start + 2 * bits].reshape(bits, 2, *frames.shape[1:])


def phase_fit(frames: NDArray[np.float32], spec: PatternSpec, direction: str) -> Fringes:
    """The N-step fit of a hybrid sequence's phase-shifted fringes along `direction` (``steps > 0``).

    Parameters
    ----------
    frames : (frame_count, H, W) float32 array
        The whole capture in the spec's order.
    """
    start = _phase_start(spec, direction)
    return fit_fringes(frames[start:start + spec.steps])


def check_order(frames: NDArray[np.float32], spec: PatternSpec) -> None:
    """Refuse a capture whose white frame is clearly darker than its black frame (frames out of
    order, or a different sequence): mean levels differing by more than `WHITE_THRESHOLD`."""
    white, black = white_black_frames(spec)
    if frames[white].mean() + WHITE_THRESHOLD < frames[black].mean():
        raise InputError(f"frames out of order: the white frame ({white}) is darker than the black frame ({black})")


def pair_noise(pairs: NDArray[np.float32]) -> float:
    """Camera noise (standard deviation per frame, image units) from the pattern/inverse pairs.

    A pattern and its inverse add up to the same light for every bit (the projector drive is
    0 or 1 in both, so neither gamma nor blur changes the sum): the spread of the pair sums
    over the bits is noise alone, ``2 sigma**2`` per sum, with ``bits - 1`` degrees of freedom
    per pixel.  Median over the image, scaled by the chi-square median; never below
    `pmp.QUANTISATION_NOISE`.

    Parameters
    ----------
    pairs : (bits, 2, H, W) float32 array
    """
    sums = pairs.sum(axis=1)
    spread = np.sum((sums - sums.mean(axis=0)) ** 2, axis=0)
    variance = float(np.median(spread)) / (2 * scipy.stats.chi2.ppf(0.5, len(pairs) - 1)) if len(pairs) > 1 else 0.0
    return max(math.sqrt(variance), QUANTISATION_NOISE)


def code_block(start: NDArray[np.integer], codes: NDArray[np.integer] | int, spec: PatternSpec,
               direction: str) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
    """Centre line and width (in projector lines) of blocks of `codes` consecutive codes from
    code `start` (a block may be cut short by the projector edge).

    Parameters
    ----------
    start : integer array
        First code of each block.
    codes : integer array broadcasting with `start`, or int
        Codes per block (1: a single code).

    >>> centre, width = code_block(np.array([0, 47, 32]), np.array([1, 1, 32]),
    ...                            PatternSpec(kind="graycode", code_width=16), "rows")
    >>> centre.tolist(), width.tolist()
    ([7.5, 759.5, 639.5], [16, 16, 256])
    """
    first = start * spec.code_width
    last = np.minimum(first + codes * spec.code_width, spec.lines(direction)) - 1
    return (0.5 * (first + last)).astype(np.float32), (last - first + 1).astype(np.int32)


def decode_graycode(frames: NDArray[np.float32], spec: PatternSpec, direction: str, *,
                    white_threshold: float = WHITE_THRESHOLD, black_threshold: float = BLACK_THRESHOLD,
                    max_dropped_bits: int = MAX_DROPPED_BITS, border_bit: bool = True,
                    min_snr: float = 5.0, max_ambiguity: float = 0.35) -> GrayCodeMap:
    """Projector coordinate along `direction` of every camera pixel of a ``graycode`` capture.

    ``max_dropped_bits=0, border_bit=False`` is OpenCV's rule exactly (every bit reliable).

    Parameters
    ----------
    frames : (frame_count, H, W) float32 array
        The whole capture in the spec's order (`sliscan.sequences.check_frames`).
    spec : PatternSpec
        A ``graycode`` spec.
    direction : {"rows", "columns"}
        One of ``spec.directions``.
    white_threshold : float
        Smallest ``|pattern - inverse|`` (image units) for a bit to be reliable (OpenCV's
        whiteThreshold, 5/255 by default).
    black_threshold : float
        ``white - black`` must exceed it for the pixel to count as lit (OpenCV's
        blackThreshold, 40/255 by default).
    max_dropped_bits : int
        Most finest bits dropped when unreliable (a trailing run of unreliable bits), at most
        ``bits - 1``; the pixel then gets the centre of the block of ``2**dropped`` codes its
        reliable prefix identifies.  0: every bit must be decided.  Ignored with phase
        (``steps > 0``), whose unwrapping needs the whole code.  The default 3 (blocks of at
        most 8 lines) was measured on the virtual rig (1024x768 projector, realistic
        conditions): with 1 px projector and camera blur 2 bits already reach the plateau
        (sphere at 1296x972: 42 % decoded by OpenCV's rule, 80 % by the default, median 3D
        error 0.37 -> 0.42 mm; tilted plane at 640x480: 11 % -> 94 %), with 2 px blur the third
        bit adds 7 % (87 -> 94 % of the plane) and a fourth nothing.
    border_bit : bool
        Decide by its sign one unreliable bit that reliable finer bits follow (a pixel on that
        bit's transition, between two adjacent codes: at most one code or block off); two or
        more such bits reject the pixel.  False: such a pixel is rejected (OpenCV).
    min_snr, max_ambiguity : float
        Hybrid sequences: the fringes' modulation test (`pmp.modulation_threshold`, with the
        noise of `pair_noise`, which an uncorrected projector gamma does not inflate) and the
        largest accepted distance of the unwrapping from an integer order.  The half-period
        code alone puts that distance within +-0.25 (also for a code decided one off at its
        border, which still gives the right order); one off elsewhere puts it between 0.25 and
        0.5, hence the default 0.35 (noise permitting).

    Returns
    -------
    GrayCodeMap
        `coord` is the centre line of the code or block (integer for a full code with
        ``code_width = 1``) or, with phase, a sub-pixel line; `index` the first code of the
        block, or the fringe order with phase; `block` the block's width in lines;
        `confidence` the weakest decided bit's ``|pattern - inverse|`` over ``white - black``
        (dropped bits left out; a bit decided at its border makes it small).
    """
    if max_dropped_bits < 0:
        raise InputError(f"max_dropped_bits must be >= 0, got {max_dropped_bits}")
    check_order(frames, spec)
    white_index, black_index = white_black_frames(spec)
    white, black = frames[white_index], frames[black_index]
    bits = spec.gray_bits(direction)
    pairs = bit_pairs(frames, spec, direction)
    difference = pairs[:, 0] - pairs[:, 1]
    strength = np.abs(difference)
    weak = strength < white_threshold
    trailing = np.logical_and.accumulate(weak[::-1], axis=0).sum(axis=0)  # (H, W) weak finest bits
    dropped = np.minimum(trailing, 0 if spec.steps else min(max_dropped_bits, bits - 1))
    kept = np.arange(bits)[:, None, None] < bits - dropped  # (bits, H, W)
    by_sign = (weak & kept).sum(axis=0)  # weak bits before a reliable one: decided by their sign
    weakest = np.where(kept, strength, np.inf).min(axis=0)
    code = gray_decode(bits_to_code(difference > 0)) >> dropped << dropped  # the block's first code
    span = white - black
    valid = ((span > black_threshold) & (trailing == dropped) & (by_sign <= int(border_bit))
             & (code * spec.code_width < spec.lines(direction)))
    coord, block = code_block(code, 1 << dropped, spec, direction)
    index = code
    if spec.steps:
        fit = phase_fit(frames, spec, direction)
        coord, index, distance = unwrap_step(coord, fit.cycles, 2 * spec.code_width)
        threshold = modulation_threshold(pair_noise(pairs), spec.steps, min_snr)
        valid &= ((fit.modulation > threshold) & (np.abs(distance) <= max_ambiguity) & (coord >= -0.5)
                  & (coord < spec.lines(direction) - 0.5))
    with np.errstate(divide="ignore", invalid="ignore"):
        contrast = np.where(span > 0, weakest / span, 0)
    return GrayCodeMap(coord=np.where(valid, coord, np.nan).astype(np.float32), valid=valid,
                       index=np.where(valid, index, -1).astype(np.int32),
                       confidence=np.clip(contrast, 0, 1).astype(np.float32), brightness=white,
                       block=np.where(valid, block, 0).astype(np.int32))
