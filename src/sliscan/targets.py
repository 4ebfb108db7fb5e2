"""Calibration targets in camera images: circle centres, chessboard corners, and the projector
coordinates decoded there (issue 5; thesis 4.0-4.2).

Two kinds of target feed `sliscan.calibrate`:

- a **3-D circle target** (the thesis's fig. 4.1: dark circles on at least two non-coplanar
  planes, world coordinates known), described by a `CircleTarget` JSON file; its circles are
  found with `detect_circles` in the albedo (white) image;
- a **planar chessboard** seen in several poses; its inner corners are found with OpenCV
  (`detect_chessboard`).

At every such image point the camera -> projector correspondence decoded from a multi-shot
sequence (`sliscan.sequences.decode_frames`) is read with `projector_points`: bilinear
interpolation where the four pixels around the point decoded, otherwise a robust local
quadratic fit (`local_fit`) to the decoded pixels around it, which bridges the pixels that do not
decode (the dark circles, the black squares of a chessboard).  The fit is a plain polynomial
regression with outlier rejection, not the "local homographies" of Moreno and Taubin (2012),
which the issue rules out.

Conventions (DESIGN.md): pixel centres at integers, ``x`` = column, ``y`` = row; image points
are ``(N, 2)`` arrays of ``(x, y)``; world coordinates in mm.

Circle target JSON::

    {"radius_mm": 10.0,                        # optional, with "normals"
     "circles": [[Xw, Yw, Zw], ...],           # centres in mm, N >= 6, not all coplanar
     "normals": [[nx, ny, nz], ...]}           # optional: unit normal of each circle's plane

With the radius and the normals, calibration removes the perspective bias of the detected
centres (the centre of a circle's image ellipse is not the image of its centre).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import scipy.spatial
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, atomic_write_text, check_image
from sliscan.pmp import ProjectorMap

FloatArray = NDArray[np.float64]

#: Fewest decoded pixels a local fit accepts (6 coefficients, with room for outliers).
MIN_FIT_PIXELS = 24
# A blob counts as an ellipse when its area is this close to the area of the ellipse with its
# second moments (exactly 1 for a filled ellipse, less for any other shape).
_ELLIPSE_FILL = (0.85, 1.1)
# Outliers of a local fit: residuals beyond this many robust standard deviations, and never
# below this many projector pixels (plain Gray code coordinates are integers: +-0.5 is normal).
_REJECT_SIGMAS = 3.0
_REJECT_FLOOR_PX = 1.0
_FIT_ITERATIONS = 3


@dataclass(frozen=True, eq=False)
class CircleTarget:
    """A 3-D calibration target of circles with known centres (thesis fig. 4.1).

    Attributes
    ----------
    centres : (N, 3) float64 array
        Circle centres in world mm.
    normals : (N, 3) float64 array or None
        Unit normal of each circle's plane (sign irrelevant); with `radius_mm`, enables the
        correction of the perspective bias of the detected centres.
    radius_mm : float or None
        Circle radius in mm.
    """

    centres: FloatArray
    normals: FloatArray | None = None
    radius_mm: float | None = None

    def __post_init__(self) -> None:
        centres = np.asarray(self.centres, dtype=np.float64)
        if centres.ndim != 2 or centres.shape[1] != 3 or not np.all(np.isfinite(centres)):
            raise InputError(f"circles must be finite [Xw, Yw, Zw] triples, got shape {centres.shape}")
        object.__setattr__(self, "centres", centres)
        if (self.normals is None) != (self.radius_mm is None):
            raise InputError("give both normals and radius_mm (for the perspective correction) or neither")
        if self.normals is not None:
            normals = np.asarray(self.normals, dtype=np.float64)
            if normals.shape != centres.shape or not np.all(np.isfinite(normals)):
                raise InputError(f"normals must be one finite [nx, ny, nz] per circle ({len(centres)}), "
                                 f"got shape {normals.shape}")
            length = np.linalg.norm(normals, axis=1, keepdims=True)
            if np.any(length == 0):
                raise InputError("normals must be non-zero")
            object.__setattr__(self, "normals", normals / length)
            if not (np.isfinite(self.radius_mm) and self.radius_mm > 0):
                raise InputError(f"radius_mm must be positive, got {self.radius_mm}")
            object.__setattr__(self, "radius_mm", float(self.radius_mm))

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"circles": self.centres.tolist()}
        if self.normals is not None:
            d["normals"] = self.normals.tolist()
            d["radius_mm"] = self.radius_mm
        return d

    def save(self, path: str | os.PathLike) -> Path:
        """Write the target JSON (module docstring), atomically."""
        return atomic_write_text(path, json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike) -> CircleTarget:
        """Read a target JSON; raises `InputError` naming the file."""
        p = Path(path)
        try:
            d = json.loads(p.read_text())
        except OSError as exc:
            raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"{p}: not valid JSON ({exc})") from None
        unknown = sorted(set(d) - {"circles", "normals", "radius_mm"}) if isinstance(d, dict) else []
        if not isinstance(d, dict) or "circles" not in d or unknown:
            raise InputError(f"{p}: a circle target is a JSON object with 'circles' (and optionally 'normals', "
                             f"'radius_mm'){f'; unknown keys {unknown}' if unknown else ''}")
        try:
            return cls(d["circles"], d.get("normals"), d.get("radius_mm"))
        except (InputError, TypeError, ValueError) as exc:
            raise InputError(f"{p}: {exc}") from None


# --------------------------------------------------------------------------------------------
# Circle centres
# --------------------------------------------------------------------------------------------


def _moment_ellipse(xs: FloatArray, ys: FloatArray) -> tuple[float, float]:
    """Semi-axes (a >= b, pixels) of the ellipse with the second moments of a pixel set."""
    cov = np.cov(np.stack([xs, ys])) + np.eye(2) / 12.0  # each pixel is a unit square
    eig = np.linalg.eigvalsh(cov)
    return 2.0 * float(np.sqrt(eig[1])), 2.0 * float(np.sqrt(max(eig[0], 0.0)))


def _distance_to(mask: NDArray[np.bool_]) -> NDArray[np.float32]:
    """Euclidean distance (px) of every pixel to the nearest pixel of `mask` (0 on it)."""
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def _dark_centroid(image: NDArray[np.float32], blob: NDArray[np.bool_], grow: int,
                   exclude: NDArray[np.bool_] | None = None) -> tuple[float, float] | None:
    """Darkness-weighted centroid of a dark blob, against the background fitted around it.

    The background is a plane fitted to a ring of pixels around the blob; the weight of a pixel
    is ``1 - I / background`` (clipped at 0) over the blob grown by `grow` pixels, which holds
    the blurred edge.  For a dark ellipse of uniform albedo the weight is uniform inside and the
    centroid is the ellipse's centre, unchanged by a symmetric blur.  Other dark blobs nearby
    (`exclude`, which must hold every blob within `grow` of the ring): the ring keeps `grow`
    pixels away from them, and where two grown blobs would overlap the pixels are weighted only
    on this blob's side of the middle, so that a crowded grid's blurred edges are cut short on
    no side.  None: no bright ring.
    """
    near = _distance_to(blob)
    inner = near <= grow
    ring = (near > grow) & (near <= 2 * grow)
    if exclude is not None and exclude.any():
        other = _distance_to(exclude)
        ring &= other > grow
        inner &= near <= other
    ry, rx = np.nonzero(ring)
    if len(rx) < 3:
        return None
    design = np.c_[np.ones(len(rx)), rx, ry]
    plane, *_ = np.linalg.lstsq(design, image[ry, rx].astype(np.float64), rcond=None)
    iy, ix = np.nonzero(inner)
    background = plane[0] + plane[1] * ix + plane[2] * iy
    if background.min() <= 0:
        return None
    weight = np.clip(1.0 - image[iy, ix] / background, 0.0, None)
    if weight.sum() <= 0:
        return None
    return float(weight @ ix / weight.sum()), float(weight @ iy / weight.sum())


def _blob_centre(image: NDArray[np.float32], labels: NDArray[np.int32], label: int, box: NDArray[np.integer], *,
                 max_aspect: float) -> tuple[float, float] | None:
    """Sub-pixel centre ``(x, y)`` of one dark blob of a labelled image (label 0: background), or
    None when it is not an ellipse of axis ratio up to `max_aspect` (`_ELLIPSE_FILL`) or has no
    bright ring.  `box` is its ``x0, y0, width, height, area`` (`cv2.connectedComponentsWithStats`)."""
    x0, y0, bw, bh, area = (int(v) for v in box[:5])
    h, w = labels.shape
    grow = 2 + int(np.ceil(0.25 * np.sqrt(area / np.pi)))
    pad = 3 * grow + 2  # the ring reaches 2 grow out; any blob within grow of it must be seen
    sy = slice(max(y0 - pad, 0), min(y0 + bh + pad, h))
    sx = slice(max(x0 - pad, 0), min(x0 + bw + pad, w))
    window = labels[sy, sx]
    blob = window == label
    ys, xs = np.nonzero(blob)
    a, b = _moment_ellipse(xs.astype(np.float64), ys.astype(np.float64))
    fill = area / (np.pi * a * b)
    if not (_ELLIPSE_FILL[0] <= fill <= _ELLIPSE_FILL[1] and a <= max_aspect * b):
        return None
    centre = _dark_centroid(image[sy, sx], blob, grow, exclude=(window > 0) & ~blob)
    return None if centre is None else (centre[0] + sx.start, centre[1] + sy.start)


def _dark_blobs(image: NDArray[np.float32]) -> tuple[int, NDArray[np.int32], NDArray[np.int32]]:
    """Connected components below Otsu's threshold (after a 3x3 Gaussian): count, labels, stats."""
    u8 = np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
    _, dark = cv2.threshold(cv2.GaussianBlur(u8, (3, 3), 0), 0, 1, cv2.THRESH_BINARY_INV | cv2.THRESH_OTSU)
    return cv2.connectedComponentsWithStats(dark, connectivity=8)[:3]


def detect_circles(image: ArrayLike, *, min_radius_px: float = 3.0, max_aspect: float = 5.0) -> FloatArray:
    """Sub-pixel centres of the dark circles (ellipses, in perspective) of a bright target.

    Dark blobs are found below Otsu's threshold; a blob is kept when it does not touch the image
    border, its area is at least that of a circle of `min_radius_px`, its area fills the ellipse
    of its second moments (85-110 %: ellipses and nothing else) and that ellipse's axis ratio is
    at most `max_aspect`.  Each centre is the darkness-weighted centroid of the blob against a
    background plane fitted around it (`_dark_centroid`): the centre of the image ellipse, to a
    few hundredths of a pixel under blur and noise.

    The centre of a circle's image ellipse is not the image of the circle's centre: under
    perspective it is displaced by about ``f r**2 sin(2 tilt) / (2 Z**2)`` pixels (focal length
    ``f`` in px, radius ``r`` and distance ``Z`` in mm); for a 10 mm circle tilted 45 degrees at
    800 mm and f = 1200 px that is 0.09 px.  `sliscan.calibrate.calibrate_target` removes it when
    the target gives the circles' normals and radius.

    Parameters
    ----------
    image : (H, W) array
        The target under uniform light (the white frame, or the decoded `brightness`); uint8,
        uint16 or float in [0, 1].
    min_radius_px : float
        Smallest circle radius considered, in pixels.
    max_aspect : float
        Largest accepted ratio of the ellipse's axes (a circle seen this obliquely is too
        foreshortened to locate).

    Returns
    -------
    centres : (M, 2) float64 array
        ``(x, y)`` of each circle, sorted by row then column of the blob's first pixel.
    """
    img = check_image("image", image)
    _, labels, stats = _dark_blobs(img)
    h, w = img.shape
    x0, y0, bw, bh, area = (stats[:, k] for k in range(5))
    inside = (x0 > 0) & (y0 > 0) & (x0 + bw < w) & (y0 + bh < h)
    candidates = np.flatnonzero(inside & (area >= np.pi * min_radius_px**2) & (area < 0.25 * h * w))
    centres = [_blob_centre(img, labels, label, stats[label], max_aspect=max_aspect)
               for label in candidates[candidates > 0]]
    return np.array([c for c in centres if c is not None], dtype=np.float64).reshape(-1, 2)


# --------------------------------------------------------------------------------------------
# Chessboard corners
# --------------------------------------------------------------------------------------------


def detect_chessboard(image: ArrayLike, inner_corners: tuple[int, int]) -> FloatArray | None:
    """Sub-pixel inner corners of a chessboard (`cv2.findChessboardCorners` + `cv2.cornerSubPix`).

    Parameters
    ----------
    image : (H, W) array
        The board under uniform light (white frame); uint8, uint16 or float in [0, 1].
    inner_corners : (columns, rows) tuple of int
        Inner corners per board row and per board column (OpenCV's ``patternSize``, e.g. (9, 7)).

    Returns
    -------
    corners : (columns * rows, 2) float64 array or None
        ``(x, y)`` in OpenCV's order (along a board row first); None if the board is not found.
    """
    img = check_image("image", image)
    u8 = np.round(img * 255).astype(np.uint8)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(u8, tuple(inner_corners), flags=flags)
    if not found:
        return None
    corners = corners.reshape(-1, 1, 2).astype(np.float32)
    half = int(np.clip(corner_spacing(corners, inner_corners) / 4, 2, 11))
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    refined = cv2.cornerSubPix(u8, corners, (half, half), (-1, -1), criteria)
    return refined.reshape(-1, 2).astype(np.float64)


def corner_spacing(corners: ArrayLike, inner_corners: tuple[int, int]) -> float:
    """Median distance (px) between neighbouring corners along the board's rows."""
    grid = np.asarray(corners, dtype=np.float64).reshape(inner_corners[1], inner_corners[0], 2)
    return float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))


# --------------------------------------------------------------------------------------------
# Circle grids and planar boards
# --------------------------------------------------------------------------------------------

#: Planar boards `Board` describes: OpenCV's chessboard and its two circle grids.
BOARD_KINDS = ("chessboard", "symmetric", "asymmetric")
# A refined circle centre farther than this fraction of the grid spacing from OpenCV's blob
# centre belongs to another blob: the blob centre is kept.
_REFINE_MAX_SHIFT = 0.25


def _blob_detector(shape: tuple[int, int], count: int) -> cv2.SimpleBlobDetector:
    """OpenCV's blob detector scaled to the image: circles of 2 px radius up to the largest
    that `count` of them fit in the image, any darkness, foreshortened up to 10:1."""
    params = cv2.SimpleBlobDetector_Params()
    params.minArea = float(np.pi * 2.0**2)
    params.maxArea = float(shape[0] * shape[1] / (4 * count))
    params.minDistBetweenBlobs = 2.0
    params.minThreshold, params.maxThreshold, params.thresholdStep = 10.0, 245.0, 5.0
    params.filterByInertia, params.minInertiaRatio = True, 0.1
    params.filterByConvexity, params.minConvexity = True, 0.9
    return cv2.SimpleBlobDetector_create(params)


def _refine_circle(image: NDArray[np.float32], centre: FloatArray, half: int) -> FloatArray | None:
    """Darkness-weighted centre (`_blob_centre`) of the dark blob under an approximate `centre`,
    found below Otsu's threshold in the ``(2 half + 1)**2`` window around it; None if there is
    none, it touches the window's border, or it is not an ellipse."""
    h, w = image.shape
    cx, cy = int(round(centre[0])), int(round(centre[1]))
    sy, sx = slice(max(cy - half, 0), min(cy + half + 1, h)), slice(max(cx - half, 0), min(cx + half + 1, w))
    window = image[sy, sx]
    _, labels, stats = _dark_blobs(window)
    label = labels[cy - sy.start, cx - sx.start] if 0 <= cy - sy.start < window.shape[0] and \
        0 <= cx - sx.start < window.shape[1] else 0
    if label == 0:
        return None
    x0, y0, bw, bh = stats[label, :4]
    if x0 == 0 or y0 == 0 or x0 + bw == window.shape[1] or y0 + bh == window.shape[0]:
        return None
    found = _blob_centre(window, labels, label, stats[label], max_aspect=10.0)
    return None if found is None else np.array([found[0] + sx.start, found[1] + sy.start])


def detect_circle_grid(image: ArrayLike, pattern_size: tuple[int, int], *, asymmetric: bool) -> FloatArray | None:
    """Sub-pixel centres of a symmetric or asymmetric grid of dark circles, in OpenCV's order.

    `cv2.findCirclesGrid` finds and orders the grid with a blob detector scaled to the image
    (`_blob_detector`; retried with ``CALIB_CB_CLUSTERING``, more tolerant of perspective);
    each centre is then refined to the darkness-weighted centroid of its blob against the
    background around it (as `detect_circles`: the image ellipse's centre to a few hundredths of
    a pixel, where OpenCV's blob centres, averaged over thresholds, are good to about 0.1 px).
    A blob that cannot be refined keeps OpenCV's centre.  The perspective bias of circle
    centres (`detect_circles`) is left to `sliscan.calibrate.calibrate_board`.

    Parameters
    ----------
    image : (H, W) array
        The board under uniform light; uint8, uint16 or float in [0, 1].
    pattern_size : (columns, rows) tuple of int
        OpenCV's ``patternSize``: circles per row and rows (asymmetric: e.g. (4, 11)).
    asymmetric : bool
        OpenCV's asymmetric grid (every second row shifted by half the spacing) or a symmetric one.

    Returns
    -------
    centres : (columns * rows, 2) float64 array or None
        ``(x, y)`` row by row; None if the grid is not found.
    """
    img = check_image("image", image)
    img = img / max(float(np.percentile(img, 99.5)), 1e-6)  # white at the 99.5th percentile
    u8 = np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    size = tuple(int(v) for v in pattern_size)
    count = size[0] * size[1]
    base = cv2.CALIB_CB_ASYMMETRIC_GRID if asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    detector = _blob_detector(img.shape, count)
    for flags in (base, base | cv2.CALIB_CB_CLUSTERING):
        found, coarse = cv2.findCirclesGrid(u8, size, flags=flags, blobDetector=detector)
        if found:
            break
    else:
        return None
    coarse = coarse.reshape(-1, 2).astype(np.float64)
    spacing = float(np.median(scipy.spatial.cKDTree(coarse).query(coarse, k=2)[0][:, 1]))
    # The window holds the circle, its background ring and the neighbours next to that ring
    # (`_blob_centre`): a neighbour cut off by the window would leak its blurred edge into the ring.
    half = int(np.ceil(1.5 * spacing)) + 8
    refined = coarse.copy()
    for k, centre in enumerate(coarse):
        better = _refine_circle(img, centre, half)
        if better is not None and np.hypot(*(better - centre)) < _REFINE_MAX_SHIFT * spacing:
            refined[k] = better
    return refined


@dataclass(frozen=True)
class Board:
    """A planar calibration board: OpenCV's chessboard or one of its circle grids.

    Attributes
    ----------
    kind : {"chessboard", "symmetric", "asymmetric"}
    size : (columns, rows) tuple of int
        OpenCV's ``patternSize``: a chessboard's inner corners per row and per column (e.g.
        (9, 7)); a circle grid's circles per row and rows (e.g. (4, 11) asymmetric).
    spacing : float
        World unit (mm) of the layout: the chessboard's square side; the symmetric grid's
        distance between neighbouring circles; for the asymmetric grid OpenCV's: rows are
        `spacing` apart, the circles of a row ``2 spacing`` apart, every second row shifted
        by `spacing` (so diagonal neighbours are ``sqrt(2) spacing`` apart).
    radius : float or None
        Circle radius (same unit), optional: with it `sliscan.calibrate.calibrate_board`
        removes the perspective bias of the circle centres.

    Examples
    --------
    >>> Board("asymmetric", (4, 11), 20.0).points()[:5, :2].tolist()
    [[0.0, 0.0], [40.0, 0.0], [80.0, 0.0], [120.0, 0.0], [20.0, 20.0]]
    """

    kind: str
    size: tuple[int, int]
    spacing: float
    radius: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in BOARD_KINDS:
            raise InputError(f"board kind must be one of {BOARD_KINDS}, got {self.kind!r}")
        try:
            cols, rows = (int(v) for v in self.size)
        except (TypeError, ValueError):
            raise InputError(f"board size must be (columns, rows), got {self.size!r}") from None
        least = 2 if self.kind == "chessboard" else 3
        if cols < least or rows < least or (cols, rows) != tuple(self.size):
            raise InputError(f"a {self.kind} board needs at least {least}x{least} points, got {self.size}")
        object.__setattr__(self, "size", (cols, rows))
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise InputError(f"board spacing must be positive, got {self.spacing}")
        if self.radius is not None:
            if self.kind == "chessboard":
                raise InputError("a chessboard has no circle radius")
            if not (np.isfinite(self.radius) and 0 < 2 * self.radius < self.nearest):
                raise InputError(f"circle radius must be positive and less than half the distance between "
                                 f"neighbouring circles ({self.nearest / 2:g}), got {self.radius}")

    @property
    def circles(self) -> bool:
        """Whether the board is a circle grid."""
        return self.kind != "chessboard"

    @property
    def feature(self) -> str:
        """What a point is: ``"corner"`` or ``"circle"``."""
        return "circle" if self.circles else "corner"

    def describe(self) -> str:
        """E.g. ``"chessboard of 9x7 inner corners"``, ``"asymmetric circle grid of 4x11 circles"``."""
        size = f"{self.size[0]}x{self.size[1]}"
        return f"chessboard of {size} inner corners" if self.kind == "chessboard" else \
            f"{self.kind} circle grid of {size} circles"

    def points(self) -> NDArray[np.float32]:
        """``(columns * rows, 3)`` board points ``(x, y, 0)`` in OpenCV's order (row by row)."""
        cols, rows = self.size
        j, i = np.mgrid[0:rows, 0:cols]
        x = 2 * i + j % 2 if self.kind == "asymmetric" else i
        return np.c_[x.ravel() * self.spacing, j.ravel() * self.spacing, np.zeros(cols * rows)].astype(np.float32)

    @property
    def nearest(self) -> float:
        """Distance between neighbouring points (world unit): `spacing`, ``sqrt(2) spacing`` for
        the asymmetric grid's diagonal neighbours."""
        return self.spacing * (np.sqrt(2.0) if self.kind == "asymmetric" else 1.0)

    def neighbours(self) -> NDArray[np.intp]:
        """``(M, 2)`` index pairs of neighbouring points, `nearest` apart on the board."""
        layout = self.points()[:, :2].astype(np.float64)
        return np.array(sorted(scipy.spatial.cKDTree(layout).query_pairs(1.001 * self.nearest)), dtype=np.intp)

    def detect(self, image: ArrayLike) -> FloatArray | None:
        """The board's points in a camera image (`detect_chessboard` or `detect_circle_grid`),
        ``(N, 2)`` in OpenCV's order; None if not found."""
        if self.kind == "chessboard":
            return detect_chessboard(image, self.size)
        return detect_circle_grid(image, self.size, asymmetric=self.kind == "asymmetric")

    def image_spacing(self, points: ArrayLike) -> float:
        """Median distance (px) between neighbouring detected points."""
        pts = np.asarray(points, dtype=np.float64)
        pairs = self.neighbours()
        return float(np.median(np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1)))

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"kind": self.kind, "size": list(self.size), "spacing": float(self.spacing)}
        if self.radius is not None:
            d["radius"] = float(self.radius)
        return d


# --------------------------------------------------------------------------------------------
# Projector coordinates at image points
# --------------------------------------------------------------------------------------------


def bilinear(coord: ArrayLike, valid: ArrayLike, points: ArrayLike) -> FloatArray:
    """Bilinear interpolation of a decoded map at sub-pixel points, from valid pixels only.

    Parameters
    ----------
    coord : (H, W) array
        Decoded projector coordinate per camera pixel (projector pixels).
    valid : (H, W) bool array
    points : (N, 2) array
        Camera ``(x, y)``, pixel centres at integers.

    Returns
    -------
    values : (N,) float64 array
        NaN where a point lies outside the image or one of its four pixels is not valid.
    """
    coord = np.asarray(coord, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    h, w = coord.shape
    x0 = np.floor(pts[:, 0]).astype(np.int64)
    y0 = np.floor(pts[:, 1]).astype(np.int64)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1)
    x0, y0 = np.where(inside, x0, 0), np.where(inside, y0, 0)
    fx, fy = pts[:, 0] - x0, pts[:, 1] - y0
    corners = [(y0, x0, (1 - fx) * (1 - fy)), (y0, x0 + 1, fx * (1 - fy)), (y0 + 1, x0, (1 - fx) * fy),
               (y0 + 1, x0 + 1, fx * fy)]
    ok = inside & np.all([valid[yy, xx] for yy, xx, _ in corners], axis=0)
    with np.errstate(invalid="ignore"):
        value = sum(wt * coord[yy, xx] for yy, xx, wt in corners)
    return np.where(ok, value, np.nan)


def local_fit(coord: ArrayLike, valid: ArrayLike, points: ArrayLike, half_window: int, *,
              block: ArrayLike | None = None) -> FloatArray:
    """Robust local quadratic fit of a decoded map around sub-pixel points, evaluated there.

    For each point, the valid pixels of the ``(2 h + 1)**2`` window around it (``h`` =
    `half_window`) are fitted by least squares with ``c0 + c1 dx + c2 dy + c3 dx**2 + c4 dx dy
    + c5 dy**2`` (``dx, dy`` from the point); pixels whose residual exceeds 3 robust standard
    deviations (median absolute deviation, never under 1 projector pixel) are dropped and the
    fit repeated, three times.  The value is ``c0``.  A quadratic follows the camera -> projector
    map of a plane (a homography) and lens distortion closely over a window smaller than a
    chessboard square; it averages the quantisation of plain Gray code coordinates and bridges
    the pixels that did not decode (dark circles, black squares).

    With `block`, each pixel's coordinate is the centre of a block of that many projector lines
    (a plain Gray code decoded gracefully, `sliscan.graycode.GrayCodeMap.block`): its error is
    uniform over the block, of variance ``block**2 / 12``, so the fit weights it by
    ``1 / block**2`` and tests its residual in units of its block, relative to the window's
    finest block (a full code's pixels keep weight 1 and the 1-pixel floor).

    Parameters
    ----------
    coord, valid, points
        As for `bilinear`.
    half_window : int
        Window half-size in camera pixels (>= 2).
    block : (H, W) int or float array, optional
        Width in projector lines that each pixel's coordinate stands for (> 0 where valid).
        None: every pixel alike.

    Returns
    -------
    values : (N,) float64 array
        NaN where fewer than `MIN_FIT_PIXELS` valid inliers remain or the valid pixels do not
        surround the point (every one of them on one side of it).
    """
    if half_window < 2:
        raise InputError(f"half_window must be at least 2 pixels, got {half_window}")
    coord = np.asarray(coord, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    h, w = coord.shape
    offsets = np.arange(-half_window, half_window + 1)
    oy, ox = (a.ravel() for a in np.meshgrid(offsets, offsets, indexing="ij"))
    cx, cy = np.round(pts[:, 0]).astype(np.int64), np.round(pts[:, 1]).astype(np.int64)
    px, py = cx[:, None] + ox, cy[:, None] + oy  # (N, K)
    inside = (px >= 0) & (py >= 0) & (px < w) & (py < h)
    pxc, pyc = np.clip(px, 0, w - 1), np.clip(py, 0, h - 1)
    use = inside & valid[pyc, pxc]
    z = np.where(use, coord[pyc, pxc], 0.0)
    if block is None:
        scale = np.ones(use.shape)
    else:
        width = np.asarray(block, dtype=np.float64)[pyc, pxc]
        use &= width > 0
        finest = np.min(np.where(use, width, np.inf), axis=1, keepdims=True)
        scale = np.where(use, width / np.where(np.isfinite(finest), finest, 1.0), 1.0)  # in finest blocks
    dx = (px - pts[:, :1]) / half_window
    dy = (py - pts[:, 1:]) / half_window
    design = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=-1)  # (N, K, 6)
    beta = np.zeros((len(pts), 6))
    for _ in range(_FIT_ITERATIONS):
        weights = use / scale**2
        normal = np.einsum("nk,nki,nkj->nij", weights, design, design) + 1e-9 * np.eye(6)
        rhs = np.einsum("nk,nki,nk->ni", weights, design, z)
        beta = np.linalg.solve(normal, rhs[..., None])[..., 0]
        residual = np.abs(z - np.einsum("nki,ni->nk", design, beta)) / scale
        masked = np.where(use, residual, np.nan)
        with np.errstate(all="ignore"):
            sigma = 1.4826 * np.nanmedian(masked, axis=1, keepdims=True)
        use &= residual <= np.maximum(_REJECT_SIGMAS * np.nan_to_num(sigma), _REJECT_FLOOR_PX)
    surrounded = np.all([np.any(use & (d > 0), axis=1) & np.any(use & (d < 0), axis=1) for d in (dx, dy)], axis=0)
    ok = (use.sum(axis=1) >= MIN_FIT_PIXELS) & surrounded
    return np.where(ok, beta[:, 0], np.nan)


def projector_points(maps: Mapping[str, ProjectorMap], points: ArrayLike, *, half_window: int,
                     interpolate: bool = True) -> FloatArray:
    """Projector ``(xp, yp)`` at camera points, from both decoded directions.

    Parameters
    ----------
    maps : {"columns": ProjectorMap, "rows": ProjectorMap}
        `sliscan.sequences.decode_frames` of a sequence coding both directions.
    points : (N, 2) array
        Camera ``(x, y)``.
    half_window : int
        Window half-size of `local_fit`, in camera pixels.
    interpolate : bool
        True: `bilinear` where the four pixels around a point decoded, `local_fit` elsewhere
        (sub-pixel maps: PMP, Gray code + phase).  False: `local_fit` everywhere (plain Gray
        code, whose integer coordinates need the averaging), weighting the pixels of a
        gracefully decoded map by their blocks (`sliscan.graycode.GrayCodeMap.block`).

    Returns
    -------
    projector : (N, 2) float64 array
        ``(xp, yp)`` in projector pixels; NaN where neither method gives a value.

    Raises
    ------
    InputError
        If `maps` lacks a direction.
    """
    missing = [d for d in ("columns", "rows") if d not in maps]
    if missing:
        raise InputError(f"calibration needs projector columns and rows decoded (a sequence with orientation "
                         f"'both'); missing {missing[0]}")
    out = []
    for direction in ("columns", "rows"):
        m = maps[direction]
        fitted = local_fit(m.coord, m.valid, points, half_window,
                           block=None if interpolate else getattr(m, "block", None))
        if interpolate:
            direct = bilinear(m.coord, m.valid, points)
            fitted = np.where(np.isnan(direct), fitted, direct)
        out.append(fitted)
    return np.stack(out, axis=-1)
