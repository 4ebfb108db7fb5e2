"""`sliscan.pmp.decode_pmp` as plain numpy (before its compiled kernel): composed of the module's
own per-frequency fit and unwrapping step.  `test_pmp.py` compares the kernel with it."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sliscan.pmp import ProjectorMap, fringe_fits, modulation_threshold, noise_level, unwrap_step
from sliscan.types import PatternSpec


def unit_coordinate(cycles: NDArray[np.float32], lines: int) -> NDArray[np.float32]:
    """Projector line of a unit-frequency phase (any real `cycles`, wrapped here) in
    ``[-0.5, lines - 0.5)``: the projector's extent, so the wrap falls between its two ends."""
    shifted = cycles + np.float32(0.5 / lines)
    return ((shifted - np.floor(shifted)) * np.float32(lines) - np.float32(0.5)).astype(np.float32)


def decode_pmp(frames: NDArray[np.float32], spec: PatternSpec, direction: str, *, min_snr: float = 5.0,
               max_ambiguity: float = 0.3) -> ProjectorMap:
    """The projector coordinate as `sliscan.pmp.decode_pmp` computes it, in numpy."""
    fits = fringe_fits(frames, spec, direction)
    sigma = noise_level(fits, spec.steps)
    lines = spec.lines(direction)
    freqs = spec.frequencies
    unit = fits[0].cycles if freqs[0] == 1 else fits[1].cycles - fits[0].cycles
    coord = unit_coordinate(unit, lines)
    order = np.zeros(coord.shape, dtype=np.int32)
    ambiguity = np.zeros(coord.shape, dtype=np.float32)
    for fit, f in zip(fits[1:], freqs[1:]):
        coord, order, distance = unwrap_step(coord, fit.cycles, lines / f)
        ambiguity = np.maximum(ambiguity, np.abs(distance))
    modulation = np.min([fit.modulation for fit in fits], axis=0)
    valid = ((modulation > modulation_threshold(sigma, spec.steps, min_snr)) & (ambiguity <= max_ambiguity)
             & (coord >= -0.5) & (coord < lines - 0.5))
    finest = fits[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        visibility = np.where(finest.dc > 0, finest.modulation / finest.dc, 0)
    return ProjectorMap(coord=np.where(valid, coord, np.nan).astype(np.float32), valid=valid,
                        index=np.where(valid, order, -1).astype(np.int32),
                        confidence=np.clip(visibility, 0, 1).astype(np.float32),
                        brightness=np.mean([fit.dc for fit in fits], axis=0).astype(np.float32))
