"""Isolated wrong codes: small patches of the projector map that jump away from their neighbours.

A wrong bit turns a patch of pixels into another stripe (or another fringe period), which
triangulates to a blob of points floating far in front of or behind the surface.  Along a
camera ray the projector coordinate is a monotone proxy of depth, so a jump in the projector
map between neighbouring pixels is a depth discontinuity.  A real discontinuity (the edge of an
object, a step) separates two LARGE regions; a wrong code makes a SMALL one.  `remove_speckles`
cuts the map at every jump larger than `max_jump`, then drops the connected regions smaller
than `min_region_px`: OpenCV's speckle filter for stereo disparity, run on the projector map.

A single-shot pattern adds a second kind: a patch narrower than one demodulation window along
the carriers, next to a depth edge.  Every window that decoded it reached across the edge and
mixed the light of both surfaces into a code that is neither's; such a patch can be large in
area (a sliver along a limb) and so survive the speckle filter.  `remove_narrow_runs` drops
the runs of a camera line that are shorter than the window and jump away from the nearest
valid pixels on both sides.

A multi-frame capture has a third: the pixels along a depth edge (a silhouette against the
wall behind it) that the camera's blur mixes from both surfaces.  Each decodes consistently to
a code between the two, usually near the brighter one's, so no per-pixel test flags it, and it
triangulates to a point flying between the surfaces or onto the one behind.
`remove_jump_edges` drops the pixels beside a jump in the projector map, on both sides of it,
and the pixels beside a gap across which another surface lies.

And one more along the edge of a shadow: the first pixels inside it receive, through the
blur, enough of the lit side's light to decode the lit side's code, and triangulate off both
surfaces.  `shadow_side` finds them by their light: a pixel at the end of a run that is
darker than halfway between the lit side and the shadow has its centre in the shadow
(`remove_shadow_sides` for a multi-frame capture; `sliscan.fringe.refine` for the phase
channel).

Beyond wrong codes, `remove_run_ends` trims a margin off the ends of every run along the
carriers, where a single-shot pattern's windows reach across an edge: not on by default, a
trade of completeness for accuracy.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._threads import over_rows
from sliscan._validate import InputError
from sliscan.types import PatternSpec

#: int16 code of "no value" in the quantised map (the speckle filter's newVal).
_EMPTY = -1
#: Largest quantised value; the map is scaled so that `lines` projector lines fit below it.
_INT16_TOP = 32000
#: `remove_narrow_runs` continues a run across invalid gaps up to this share of the window.
#: Measured (docs/design.md, the narrow-run filter): on the thesis pattern's
#: captures the gross outliers fell 2-7x (5 MP smooth sphere 0.113 -> 0.017 %) for at most 0.1
#: point of completeness; bridging whole windows took 0.05 point more of sliscan's own
#: pattern's right stripes, a sixteenth of one kept half the gain.
NARROW_RUN_BRIDGE = 0.25
#: `remove_jump_edges` looks across gaps up to this many camera pixels wide.  Measured while
#: choosing it (twenty-ninth session, scratch, 1296x972, realistic sphere, seed 0): with a
#: reach of 1 / 4 / 8 / 12 / 16, PMP's RMS 4.2 / 3.4 / 2.4 / 1.4 / 1.1 mm at 98.8 / 98.5 / 98.5
#: / 98.4 / 98.4 % completeness, the Gray code's 4.2 / 3.9 / 3.2 / 3.0 / 2.9 mm; a tilted
#: plane lost nothing at any reach (the threshold grows with the distance).
JUMP_REACH = 16


#: `shadow_side` defaults: a pixel at the end of a run of kept pixels along an axis (the next
#: one undecoded, or a jump) is dropped while its DC is below the midpoint of the DC
#: `SHADOW_SIDE_REACH` pixels inward and `SHADOW_SIDE_REACH` pixels outward and the outward one
#: is under `SHADOW_SIDE_DARKER` of the inward one; then the next pixel inward is tested, up to
#: `SHADOW_SIDE_STEPS` pixels.  Blur is symmetric, so a pixel darker than halfway between the
#: lit surface and its shadow has its centre in the shadow, which the lit side's blurred light
#: (and with it the lit side's fringe and code) reaches.
SHADOW_SIDE_REACH = 2
SHADOW_SIDE_DARKER = 0.6
SHADOW_SIDE_STEPS = 3

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


def _map_and_mask(proj_map: ArrayLike, valid: ArrayLike) -> tuple[NDArray, NDArray[np.bool_]]:
    """The projector map and its valid mask as arrays, checked: ``(H, W)`` each, the mask bool."""
    proj, mask = np.asarray(proj_map), np.asarray(valid)
    if proj.ndim != 2 or mask.shape != proj.shape or mask.dtype != np.bool_:
        raise InputError(f"need an (H, W) projector map and a bool mask of the same shape, "
                         f"got {proj.shape} and {mask.dtype} {mask.shape}")
    return proj, mask


@numba.njit(cache=True, nogil=True)
def _quantise_rows(proj: NDArray, valid: NDArray[np.bool_], unit_scale: NDArray[np.floating], rows: NDArray[np.intp],
                   out: NDArray[np.int16]) -> None:
    """`remove_speckles`' int16 map for the given rows: ``(proj + 1) scale`` rounded (half to
    even) and clipped to ``[0, _INT16_TOP]`` where `valid` and `proj` is finite, else `_EMPTY`;
    `unit_scale` holds 1 and the scale in the dtype the arithmetic runs in (numpy's for `proj`)."""
    for y in rows:
        for x in range(proj.shape[1]):
            p = proj[y, x]
            if valid[y, x] and np.isfinite(p):
                out[y, x] = np.int16(min(max(np.rint((p + unit_scale[0]) * unit_scale[1]), 0), _INT16_TOP))
            else:
                out[y, x] = _EMPTY


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
    proj, mask = _map_and_mask(proj_map, valid)
    if not (lines >= 1 and max_jump > 0):
        raise InputError(f"lines and max_jump must be positive, got {lines} and {max_jump}")
    size = default_min_region(proj.shape) if min_region_px is None else int(min_region_px)
    scale = _INT16_TOP / (lines + 1)
    quantised = np.empty(proj.shape, dtype=np.int16)
    values, inside = np.ascontiguousarray(proj), np.ascontiguousarray(mask)
    unit_scale = np.array([1, scale], dtype=np.float32 if proj.dtype == np.float32 else np.float64)
    over_rows(lambda rows: _quantise_rows(values, inside, unit_scale, rows, quantised), proj.shape[0])
    cv2.filterSpeckles(quantised, _EMPTY, size, max(1, int(max_jump * scale)))
    return quantised != _EMPTY


@numba.njit(cache=True, nogil=True)
def _narrow_runs(proj: NDArray[np.float32], valid: NDArray[np.bool_], max_jump: float, max_length: int,
                 bridge: int, rows: NDArray[np.intp], keep: NDArray[np.bool_]) -> None:
    """`remove_narrow_runs` along axis 1 for the given rows (`keep` starts as `valid`)."""
    w = proj.shape[1]
    for y in rows:
        x = 0
        while x < w:
            if not valid[y, x]:
                x += 1
                continue
            start = x  # a run: valid pixels, each within max_jump of the one before, across
            while True:  # gaps of at most `bridge` pixels (a gap does not make two surfaces of one)
                nxt = x + 1
                while nxt < w and nxt - x <= bridge and not valid[y, nxt]:
                    nxt += 1
                if nxt < w and nxt - x <= bridge and valid[y, nxt] and abs(proj[y, nxt] - proj[y, x]) <= max_jump:
                    x = nxt
                else:
                    break
            end = x
            x += 1
            if end - start + 1 >= max_length:
                continue
            left = start - 1
            while left >= 0 and start - left <= max_length and not valid[y, left]:
                left -= 1
            right = end + 1
            while right < w and right - end <= max_length and not valid[y, right]:
                right += 1
            has_left = left >= 0 and start - left <= max_length
            has_right = right < w and right - end <= max_length
            if not (has_left or has_right):
                continue  # nothing to disagree with: an isolated fragment, left to the speckle filter
            if has_left and abs(proj[y, left] - proj[y, start]) <= max_jump:
                continue
            if has_right and abs(proj[y, right] - proj[y, end]) <= max_jump:
                continue
            keep[y, start:end + 1] = False


@numba.njit(cache=True, inline="always")
def run_end(coarse: NDArray[np.float32], start: int, max_jump: float) -> int:
    """End (exclusive) of the run of a line that starts at `start` (a finite `coarse`): the
    consecutive pixels with a finite `coarse` that changes by at most `max_jump` from each to
    the next."""
    end = start + 1
    while end < coarse.size and np.isfinite(coarse[end]) and abs(coarse[end] - coarse[end - 1]) <= max_jump:
        end += 1
    return end


@numba.njit(cache=True, nogil=True)
def _run_bounds_rows(line: NDArray[np.float32], jump: float, rows: NDArray[np.intp], first: NDArray[np.int32],
                     end: NDArray[np.int32]) -> None:
    """`run_bounds` on the given `rows`, into `first` and `end`."""
    width = line.shape[1]
    for r in rows:
        start = 0
        while start < width:
            if not np.isfinite(line[r, start]):
                first[r, start] = end[r, start] = start
                start += 1
                continue
            stop = run_end(line[r], start, jump)
            first[r, start:stop], end[r, start:stop] = start, stop
            start = stop


def run_bounds(line: NDArray[np.float32], *, jump: float) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """The first pixel and one past the last of the run along axis 1 that each finite pixel of
    `line` ``(H, W)`` lies in, two ``(H, W)`` int32 arrays; a run ends at a NaN or where
    neighbours differ by more than `jump`; a NaN pixel's run is empty (both its own column).

    >>> first, end = run_bounds(np.array([[1, 2, np.nan, 5, 60, 61, 62]], np.float32), jump=10.0)
    >>> first.tolist(), end.tolist()
    ([[0, 0, 2, 3, 4, 4, 4]], [[2, 2, 2, 4, 7, 7, 7]])
    """
    line = np.ascontiguousarray(line, dtype=np.float32)
    first, end = np.empty(line.shape, np.int32), np.empty(line.shape, np.int32)
    over_rows(lambda rows: _run_bounds_rows(line, jump, rows, first, end), line.shape[0])
    return first, end


def run_lengths(line: NDArray[np.float32], *, jump: float) -> NDArray[np.int32]:
    """Length (pixels) of the run along axis 1 that each finite pixel of `line` ``(H, W)`` lies
    in (`run_bounds`), ``(H, W)`` int32; 0 on NaN.

    >>> line = np.array([[1, 2, np.nan, 5, 60, 61, 62]], np.float32)
    >>> run_lengths(line, jump=10.0).tolist()
    [[2, 2, 0, 1, 3, 3, 3]]
    """
    first, end = run_bounds(line, jump=jump)
    return end - first


def inner_pixels(first: NDArray[np.int32], end: NDArray[np.int32], reach: int) -> NDArray[np.bool_]:
    """The pixels at least `reach` pixels along axis 1 from either end of their run, ``(H, W)``
    bool, from `run_bounds`' `first` and `end`.

    >>> line = np.array([[1, 2, 3, 4, 5, np.nan, 7, 8, 9, np.nan, 11, np.nan, np.nan]], np.float32)
    >>> inner_pixels(*run_bounds(line, jump=10.0), 1).astype(int).tolist()
    [[0, 1, 1, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0]]
    """
    x = np.arange(first.shape[1], dtype=np.int32)
    return (x - first >= reach) & (end - 1 - x >= reach)


def remove_jump_edges(proj_map: ArrayLike, valid: ArrayLike, *, max_jump: float,
                      reach: int | None = None) -> NDArray[np.bool_]:
    """Valid mask without the pixels along a depth edge: those beside a jump, and those beside a
    gap across which another surface lies.

    The camera's blur mixes the light of a depth edge's two surfaces into the pixels along it.
    Where both sides decode, the mixed pixels sit in a jump of the projector map (a valid
    8-neighbour more than `max_jump` away): both sides of it go, since which side a mixed pixel
    lands on depends on which surface is brighter there.  Where the decoder left a gap along
    the edge (a sphere's grazing limb), the first pixel beyond it decodes, consistently, to the
    surface behind (the wall's row, on the sphere's limb): a pixel beside a gap goes when a
    valid pixel within `reach` pixels (Chebyshev distance d) differs from it by more than
    ``max_jump * d``, more than one surface's steepest slope allows.  Measured (docs/design.md,
    mixed pixels): on the realistic sphere at 1296x972 (seeds 1, 2) PMP's RMS 4.9 ->
    0.37 mm and the Gray code's 4.4 -> 2.2 mm, for 0.2-0.4 points of completeness; a tilted
    plane loses nothing.

    Parameters
    ----------
    proj_map, valid, max_jump
        As for `remove_narrow_runs`.
    reach : int, optional
        Widest gap (camera pixels) looked across.  Default `JUMP_REACH`.

    Returns
    -------
    (H, W) bool array

    Examples
    --------
    >>> proj = np.tile(np.where(np.arange(12) < 6, 100.0, 200.0), (3, 1))   # a step between columns 5 and 6
    >>> keep = remove_jump_edges(proj, np.ones(proj.shape, bool), max_jump=6)
    >>> keep[0].astype(int).tolist()
    [1, 1, 1, 1, 1, 0, 0, 1, 1, 1, 1, 1]
    >>> valid = np.ones(proj.shape, bool); valid[:, 5:8] = False              # the same across a gap
    >>> (remove_jump_edges(proj, valid, max_jump=6)[0] != valid[0]).nonzero()[0].tolist()
    [4, 8]
    """
    proj, mask = _map_and_mask(proj_map, valid)
    reach = JUMP_REACH if reach is None else int(reach)
    if not (max_jump > 0 and reach >= 1):
        raise InputError(f"max_jump and reach must be positive, got {max_jump} and {reach}")
    inside = np.ascontiguousarray(mask & np.isfinite(proj))
    values = np.ascontiguousarray(np.where(inside, proj, 0), dtype=np.float32)
    neighbours = np.ones((3, 3), np.uint8)
    top = np.finfo(np.float32).max
    raised, lowered = np.where(inside, values, -top), np.where(inside, values, top)  # the outside never wins
    beside_jump = inside & ((cv2.dilate(raised, neighbours) - values > max_jump)
                            | (values - cv2.erode(lowered, neighbours) > max_jump))
    beside_gap = inside & (cv2.erode(inside.astype(np.uint8), neighbours, borderType=cv2.BORDER_REPLICATE) == 0)
    candidate = np.flatnonzero(beside_gap & ~beside_jump)
    # Which rings each candidate searches: the distances come in bands (1, 2], (2, 4], (4, 8], ...;
    # a pixel at a distance d of band (inner, outer] can differ by more than max_jump d only if
    # the extremes within `outer` lie more than max_jump (inner + 1) away (a dilation per band,
    # each growing the last; then a compiled search of the flagged candidates' rings).
    here = values.ravel()[candidate]
    bands = np.zeros(candidate.size, np.uint8)
    edges = _band_edges(reach)
    highest, lowest, grown = raised, lowered, 0
    for bit, (inner, outer) in enumerate(zip([1] + edges, edges)):
        grow = np.ones((2 * (outer - grown) + 1,) * 2, np.uint8)
        highest, lowest, grown = cv2.dilate(highest, grow), cv2.erode(lowest, grow), outer  # extremes within outer
        limit = max_jump * (inner + 1)
        reached = (highest.ravel()[candidate] - here > limit) | (here - lowest.ravel()[candidate] > limit)
        bands |= reached.astype(np.uint8) << bit
    flagged = bands > 0
    candidate, bands = candidate[flagged], bands[flagged]
    across = np.zeros(candidate.size, bool)
    over_rows(lambda chunk: _across_gaps(values, inside, candidate, bands, np.array(edges, np.int64),
                                         float(max_jump), chunk, across), candidate.size)
    out = mask & ~beside_jump
    out.ravel()[candidate[across]] = False
    return out


def _band_edges(reach: int) -> list[int]:
    """The outer distances of `remove_jump_edges`' bands of rings: 2, 4, 8, ... up to `reach`.

    >>> _band_edges(16), _band_edges(5), _band_edges(1)
    ([2, 4, 8, 16], [2, 4, 5], [])
    """
    edges: list[int] = []
    while reach >= 2 and (not edges or edges[-1] < reach):
        edges.append(min(2 * edges[-1] if edges else 2, reach))
    return edges


@numba.njit(cache=True, nogil=True)
def _across_gaps(values: NDArray[np.float32], inside: NDArray[np.bool_], candidate: NDArray[np.intp],
                 bands: NDArray[np.uint8], edges: NDArray[np.int64], max_jump: float, chunk: NDArray[np.intp],
                 out: NDArray[np.bool_]) -> None:
    """`remove_jump_edges`' gap test for the candidates (flat pixel indices) numbered in `chunk`:
    marks `out` where a pixel `inside` at Chebyshev distance d differs by more than
    ``max_jump d``, searching ring by ring (nearest first) the bands of rings that `bands` flags
    (bit k: the rings out to ``edges[k]``)."""
    width = values.shape[1]
    for i in chunk:
        y, x = candidate[i] // width, candidate[i] % width
        here = values[y, x]
        inner = 1
        for k in range(edges.size):
            if (bands[i] >> k) & 1:
                for d in range(inner + 1, edges[k] + 1):
                    if _ring_differs(values, inside, y, x, d, here, max_jump * d):
                        out[i] = True
                        break
                if out[i]:
                    break
            inner = edges[k]


@numba.njit(cache=True, nogil=True)
def _ring_differs(values: NDArray[np.float32], inside: NDArray[np.bool_], y: int, x: int, d: int, here: float,
                  limit: float) -> bool:
    """Whether a pixel `inside` at Chebyshev distance exactly `d` from ``(y, x)`` differs from
    `here` by more than `limit`."""
    height, width = values.shape
    for dy in range(-d, d + 1):
        yy = y + dy
        if yy < 0 or yy >= height:
            continue
        step = 1 if dy == -d or dy == d else 2 * d  # the top and bottom rows whole, else both ends
        for xx in range(x - d, x + d + 1, step):
            if 0 <= xx < width and inside[yy, xx] and abs(values[yy, xx] - here) > limit:
                return True
    return False


def remove_narrow_runs(proj_map: ArrayLike, valid: ArrayLike, *, max_jump: float, window: int,
                       axis: int = 1, bridge: float = NARROW_RUN_BRIDGE) -> NDArray[np.bool_]:
    """Valid mask without the wrong codes that straddle a depth edge along the carriers.

    Along `axis` (the carrier direction), the valid pixels form runs in which neighbours
    differ by at most `max_jump`; a run goes on across a gap of invalid pixels no longer than
    `bridge` windows (a wrong code torn into pieces by undecided pixels is still one patch:
    judged piece by piece, each piece had its neighbour piece to agree with).  A run shorter
    than `window` pixels whose nearest valid pixels within `window` on both sides (or on the
    one side that has any) jump by more than `max_jump` is dropped: every demodulation window
    that decoded it reached across its borders.  A real surface narrower than a window cannot
    be decoded by one anyway.

    Parameters
    ----------
    proj_map : (H, W) float array
        Projector coordinate per camera pixel (projector pixels along the phase direction).
    valid : (H, W) bool array
    max_jump : float
        Largest difference (projector pixels) between neighbours of one surface
        (`default_max_jump`).
    window : int
        Demodulation window along the carriers, camera pixels (`Carriers.window`).
    axis : {1, 0}
        The carrier direction: 1 (camera x) for patterns coding rows, 0 for columns.
    bridge : float
        Longest gap a run goes on across, as a share of `window` (`NARROW_RUN_BRIDGE`).

    Returns
    -------
    (H, W) bool array

    Examples
    --------
    >>> proj = np.tile(np.full(200, 100.0, np.float32), (3, 1))
    >>> proj[1, 90:110] = 400                                # a 20 px sliver of a wrong code
    >>> keep = remove_narrow_runs(proj, np.ones(proj.shape, bool), max_jump=72, window=60)
    >>> int((~keep).sum()), bool(keep[1, :90].all())
    (20, True)
    >>> proj[1] = 100; proj[1, :40] = 400                     # at the frame's edge, torn in two
    >>> valid = np.ones(proj.shape, bool); valid[1, 20:24] = False
    >>> keep = remove_narrow_runs(proj, valid, max_jump=72, window=60)
    >>> int((valid & ~keep).sum()), bool(keep[1, 40:].all())
    (36, True)
    """
    proj, mask = _map_and_mask(proj_map, valid)
    if axis not in (0, 1) or not (window >= 1 and max_jump > 0):
        raise InputError(f"need axis 0 or 1, a positive window and max_jump, got {axis}, {window}, {max_jump}")
    if axis == 0:
        return remove_narrow_runs(proj.T, mask.T, max_jump=max_jump, window=window, bridge=bridge).T
    inside = np.ascontiguousarray(mask & np.isfinite(proj))
    values = np.ascontiguousarray(proj, dtype=np.float32)
    keep = inside.copy()
    gap = max(int(bridge * window), 1)
    over_rows(lambda rows: _narrow_runs(values, inside, float(max_jump), int(window), gap, rows, keep), proj.shape[0])
    return keep


def remove_run_ends(proj_map: ArrayLike, valid: ArrayLike, *, margin: int, max_jump: float,
                    axis: int = 1) -> NDArray[np.bool_]:
    """Valid mask without the pixels within `margin` pixels of either end of their run along
    `axis`: a run of valid pixels ends at an invalid one, a jump of more than `max_jump`
    (projector lines) or the frame's edge (`run_bounds`).

    A single-shot pattern is demodulated in windows along the carriers, and near a depth or
    shadow edge every window reaches across it or is clipped by it: the points there carry
    most of the error left (docs/accuracy.md, "Points near run ends").  Trimming them trades
    completeness for accuracy, an edge filter as scanners offer one; `margin` 0 keeps all.

    Parameters
    ----------
    proj_map, valid, max_jump, axis
        As for `remove_narrow_runs`.
    margin : int
        Camera pixels trimmed from each end of every run, >= 0.

    Returns
    -------
    (H, W) bool array

    Examples
    --------
    >>> proj = np.array([[10, 11, 12, 13, 14, 15, 90, 91, 92, 93]], np.float32)
    >>> remove_run_ends(proj, np.ones(proj.shape, bool), margin=1, max_jump=5).astype(int).tolist()
    [[0, 1, 1, 1, 1, 0, 0, 1, 1, 0]]
    """
    proj, mask = _map_and_mask(proj_map, valid)
    if axis not in (0, 1) or margin < 0 or not max_jump > 0:
        raise InputError(f"need axis 0 or 1, a margin >= 0 and a positive max_jump, got {axis}, {margin}, {max_jump}")
    if axis == 0:
        return remove_run_ends(proj.T, mask.T, margin=margin, max_jump=max_jump).T
    line = np.where(mask, proj, np.nan).astype(np.float32)
    return mask & inner_pixels(*run_bounds(line, jump=max_jump), margin)


@numba.njit(cache=True, nogil=True)
def _shadow_side_rows(line: NDArray[np.float32], dc: NDArray[np.float32], axis: int, jump: float, reach: int,
                      darker: float, steps: int, rows: NDArray[np.intp], out: NDArray[np.bool_]) -> None:
    """`shadow_side` for the run ends on the given `rows`; marks `out` (pixels up to `steps`
    inward of them, so on other rows too when `axis` is 0: a mark is only ever set)."""
    height, width = line.shape
    dr, dx = (1, 0) if axis == 0 else (0, 1)
    for r in rows:
        for x in range(width):
            here = line[r, x]
            if not np.isfinite(here):
                continue
            for step in (1, -1):  # the end facing the pixel `step` along the axis
                br, bx = r + dr * step, x + dx * step
                if (0 <= br < height and 0 <= bx < width and np.isfinite(line[br, bx])
                        and abs(line[br, bx] - here) <= jump):
                    continue  # not a run end on this side
                pr, px = r, x
                for _ in range(steps):
                    ir, ix = pr - dr * step * reach, px - dx * step * reach
                    orow, ox = pr + dr * step * reach, px + dx * step * reach
                    if not (0 <= ir < height and 0 <= ix < width and 0 <= orow < height and 0 <= ox < width):
                        break
                    if not np.isfinite(line[pr, px]):
                        break
                    if (pr != r or px != x) and abs(line[pr, px] - line[pr + dr * step, px + dx * step]) > jump:
                        break  # walked off the run
                    lit, shadow = dc[ir, ix], dc[orow, ox]
                    if not (shadow < darker * lit and dc[pr, px] < 0.5 * (lit + shadow)):
                        break
                    out[pr, px] = True
                    pr, px = pr - dr * step, px - dx * step


def shadow_side(line: NDArray[np.float32], dc: NDArray[np.float32], *, jump: float, axis: int = 0,
                reach: int = SHADOW_SIDE_REACH, darker: float = SHADOW_SIDE_DARKER,
                steps: int = SHADOW_SIDE_STEPS) -> NDArray[np.bool_]:
    """The kept pixels at the ends of runs along `axis` that lie on the shadow's side of a light
    edge, ``(H, W)`` bool.

    A run ends where the next pixel along the axis is undecoded or more than `jump` lines
    off.  Its last pixel is taken when the DC `reach` pixels outward is under `darker` times
    the DC `reach` pixels inward, and its own DC is below their midpoint; then the pixel
    before it, up to `steps` pixels.  Such a pixel's centre sees the shadow (blur is
    symmetric: the edge is where the light is halfway), but blur, or a demodulation window
    that ends at it, brings it enough of the lit side's light to decode that side's code and
    fringe: triangulated on its own ray, that is a point off both surfaces.  On the virtual
    rig's steps the boxes' shadows on the wall below them made such rows one to three pixels
    deep along every horizontal edge (phase channel, 5 MP smooth steps: RMS error 5.9 -> 4.2
    mm, completeness unchanged to 0.1 points; multi-shot: `remove_shadow_sides`; docs/design.md).

    Parameters
    ----------
    line : (H, W) float32 array
        Projector lines, NaN where not kept.
    dc : (H, W) float32 array
        Each pixel's light.  For the phase channel (`sliscan.fringe.refine`): down the phase
        direction (`axis` 0) `Demodulated.dc`, whose window lies along the carriers; along the
        carriers (`axis` 1) the capture itself, since there `Demodulated.dc` is the mean of a
        window that may lie on the other side of the edge.  For a multi-frame capture, its own
        light along both axes (`remove_shadow_sides`).
    jump : float
        Lines between neighbours that end a run.
    axis : {0, 1}
        Along which axis the runs are followed.

    >>> line = np.full((12, 1), 50.0, np.float32); line[8:] = np.nan      # kept rows 0-7
    >>> dc = np.array([1, 1, 1, 1, 1, 0.9, 0.6, 0.4, 0.15, 0.1, 0.1, 0.1], np.float32)[:, None]
    >>> np.nonzero(shadow_side(line, dc, jump=25.0)[:, 0])[0].tolist()    # 0.4 < (0.9 + 0.1) / 2
    [7]
    >>> shadow_side(line.T.copy(), dc.T.copy(), jump=25.0, axis=1).nonzero()[1].tolist()
    [7]
    """
    out = np.zeros(line.shape, bool)
    dc = np.asarray(dc, dtype=np.float32)
    over_rows(lambda rows: _shadow_side_rows(line, dc, axis, jump, reach, darker, steps, rows, out), line.shape[0])
    return out


def remove_shadow_sides(proj_map: ArrayLike, valid: ArrayLike, light: ArrayLike, *,
                        max_jump: float) -> NDArray[np.bool_]:
    """Valid mask without the pixels on the shadow's side of a light edge (`shadow_side`), at
    the ends of runs along both image axes.

    For a multi-frame capture, whose every pixel's light is its own (no demodulation window):
    blur lends the first pixels of a shadow (the steps' shadows on the wall below them, the
    wall beside a sphere's limb) the lit side's light, code and phase.  Measured (docs/design.md,
    mixed pixels): after `remove_jump_edges`, on the realistic steps at
    1296x972 (seeds 1, 2) PMP's RMS 5.3 -> 1.6 mm, the Gray code's 1.9 -> 0.5 mm, for at most
    0.1 points of completeness on smooth albedo; a checker's dark squares cost the Gray codes
    1.2-1.8 points (their edges pass for shadows) for RMS 3.8-4.9 -> 0.4-1.0 mm.

    Parameters
    ----------
    proj_map, valid, max_jump
        As for `remove_narrow_runs`; a jump of more than `max_jump` ends a run.
    light : (H, W) float array
        Each pixel's light: the mean of a PMP capture's frames, a Gray code capture's white frame.

    Returns
    -------
    (H, W) bool array

    Examples
    --------
    >>> light = np.tile(np.array([1, 1, 1, 1, 1, 0.9, 0.6, 0.4, 0.15, 0.1, 0.1, 0.1], np.float32), (3, 1))
    >>> valid = np.ones(light.shape, bool); valid[:, 8:] = False            # the decoder stopped at column 7
    >>> remove_shadow_sides(np.full(light.shape, 50.0), valid, light, max_jump=6)[1].astype(int).tolist()
    [1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0]
    """
    proj, mask = _map_and_mask(proj_map, valid)
    brightness = np.asarray(light, dtype=np.float32)
    if brightness.shape != proj.shape:
        raise InputError(f"need the light of every pixel, {proj.shape}, got {brightness.shape}")
    line = np.where(mask, proj, np.nan).astype(np.float32)
    dark = shadow_side(line, brightness, jump=max_jump) | shadow_side(line, brightness, jump=max_jump, axis=1)
    return mask & ~dark
