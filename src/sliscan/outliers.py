"""Isolated wrong codes: small patches of the projector map that jump away from their neighbours.

A wrong bit turns a patch of pixels into another stripe (or another fringe period), which
triangulates to a blob of points floating far in front of or behind the surface.  Along a
camera ray the projector coordinate is a monotone proxy of depth, so a jump in the projector
map between neighbouring pixels is a depth discontinuity.  A real discontinuity (the edge of an
object, a step) separates two LARGE regions; a wrong code makes a SMALL one.  `remove_speckles`
cuts the map at every jump larger than `max_jump`, then drops the connected regions smaller
than `min_region_px`: OpenCV's speckle filter for stereo disparity, run on the projector map.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError
from sliscan.types import PatternSpec

#: int16 code of "no value" in the quantised map (the speckle filter's newVal).
_EMPTY = -1
#: Largest quantised value; the map is scaled so that `lines` projector lines fit below it.
_INT16_TOP = 32000


def default_min_region(shape: tuple[int, int]) -> int:
    """Smallest region (pixels) kept by default: 0.02 % of the image, at least 25 pixels.

    A wrong code on the virtual rig makes patches of tens to a few hundred pixels at
    1296x972 (0.1 % of the frame is 1260 pixels); real objects are far larger.
    """
    return max(25, int(round(2e-4 * shape[0] * shape[1])))


def default_max_jump(spec: PatternSpec, direction: str) -> float:
    """Largest step (projector pixels) between neighbouring pixels of one surface, per pattern.

    * composite kinds: 1.5 stripes (neighbouring stripes are one stripe apart; a wrong bit
      jumps by two stripes or more);
    * ``pmp``: half the finest fringe period (a wrong fringe order jumps by a whole period);
    * ``graycode`` with phase: one code (half the fringe period, as for PMP);
    * plain ``graycode``: 8 codes (a wrong fine bit moves a point by a few lines, harmless; a
      wrong coarse bit by many).

    >>> default_max_jump(PatternSpec(kind="pmp", steps=4, frequencies=(1, 8, 64), b_p=0.5), "rows")
    6.0
    """
    if spec.kind == "pmp":
        return spec.lines(direction) / max(spec.frequencies) / 2
    if spec.kind == "graycode":
        return float(spec.code_width * (1 if spec.steps else 8))
    return 1.5 * spec.phase_lines / spec.stripes


def remove_speckles(proj_map: ArrayLike, valid: ArrayLike, *, lines: int, max_jump: float,
                    min_region_px: int | None = None) -> NDArray[np.bool_]:
    """Valid mask without the small regions that jump away from their neighbours.

    Parameters
    ----------
    proj_map : (H, W) float array
        Projector coordinate per camera pixel (projector pixels along the phase direction).
    valid : (H, W) bool array
        Pixels with a decoded coordinate.
    lines : int
        Projector lines along the phase direction (the largest value `proj_map` can take).
    max_jump : float
        Largest difference (projector pixels) between 4-neighbours of one region: for a
        stripe code, a little more than one stripe (neighbouring stripes are one apart on a
        smooth surface); for phase, a few projector pixels.
    min_region_px : int, optional
        Regions with fewer pixels are dropped.  Default `default_min_region`.

    Returns
    -------
    (H, W) bool array
        `valid` with the small regions removed.

    Examples
    --------
    >>> proj = np.tile(np.arange(100, dtype=np.float32) / 4, (60, 1))   # a smooth ramp
    >>> proj[20:24, 30:34] += 300                                       # a wrong-code patch
    >>> keep = remove_speckles(proj, np.ones(proj.shape, bool), lines=768, max_jump=8)
    >>> int((~keep).sum()), bool(keep[:20].all())
    (16, True)
    """
    proj = np.asarray(proj_map)
    mask = np.asarray(valid)
    if proj.ndim != 2 or mask.shape != proj.shape or mask.dtype != np.bool_:
        raise InputError(f"need an (H, W) projector map and a bool mask of the same shape, "
                         f"got {proj.shape} and {mask.dtype} {mask.shape}")
    if not (lines >= 1 and max_jump > 0):
        raise InputError(f"lines and max_jump must be positive, got {lines} and {max_jump}")
    size = default_min_region(proj.shape) if min_region_px is None else int(min_region_px)
    scale = _INT16_TOP / (lines + 1)
    inside = mask & np.isfinite(proj)
    quantised = np.full(proj.shape, _EMPTY, dtype=np.int16)
    quantised[inside] = np.clip(np.rint((proj[inside] + 1) * scale), 0, _INT16_TOP)
    cv2.filterSpeckles(quantised, _EMPTY, size, max(1, int(max_jump * scale)))
    return inside & (quantised != _EMPTY)
