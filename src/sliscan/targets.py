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


def _dark_centroid(image: NDArray[np.float32], blob: NDArray[np.bool_], grow: int) -> tuple[float, float] | None:
    """Darkness-weighted centroid of a dark blob, against the background fitted around it.

    The background is a plane fitted to a ring of pixels around the blob; the weight of a pixel
    is ``1 - I / background`` (clipped at 0) over the blob grown by `grow` pixels, which holds
    the blurred edge.  For a dark ellipse of uniform albedo the weight is uniform inside and the
    centroid is the ellipse's centre, unchanged by a symmetric blur.  None: no bright ring.
    """
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))
    inner = cv2.dilate(blob.astype(np.uint8), kernel).astype(bool)
    outer = cv2.dilate(inner.astype(np.uint8), kernel).astype(bool)
    ring = outer & ~inner
    ry, rx = np.nonzero(ring)
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
    u8 = np.round(img * 255).astype(np.uint8)
    _, dark = cv2.threshold(cv2.GaussianBlur(u8, (3, 3), 0), 0, 1, cv2.THRESH_BINARY_INV | cv2.THRESH_OTSU)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=8)
    h, w = img.shape
    x0, y0, bw, bh, area = (stats[:, k] for k in range(5))
    inside = (x0 > 0) & (y0 > 0) & (x0 + bw < w) & (y0 + bh < h)
    candidates = np.flatnonzero(inside & (area >= np.pi * min_radius_px**2) & (area < 0.25 * h * w))
    centres = []
    for label in candidates[candidates > 0]:
        grow = 2 + int(np.ceil(0.25 * np.sqrt(area[label] / np.pi)))
        pad = 2 * grow + 1
        sy = slice(max(y0[label] - pad, 0), min(y0[label] + bh[label] + pad, h))
        sx = slice(max(x0[label] - pad, 0), min(x0[label] + bw[label] + pad, w))
        blob = labels[sy, sx] == label
        ys, xs = np.nonzero(blob)
        a, b = _moment_ellipse(xs.astype(np.float64), ys.astype(np.float64))
        fill = area[label] / (np.pi * a * b)
        if not (_ELLIPSE_FILL[0] <= fill <= _ELLIPSE_FILL[1] and a <= max_aspect * b):
            continue
        centre = _dark_centroid(img[sy, sx], blob, grow)
        if centre is not None:
            centres.append((centre[0] + sx.start, centre[1] + sy.start))
    return np.array(centres, dtype=np.float64).reshape(-1, 2)


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


def local_fit(coord: ArrayLike, valid: ArrayLike, points: ArrayLike, half_window: int) -> FloatArray:
    """Robust local quadratic fit of a decoded map around sub-pixel points, evaluated there.

    For each point, the valid pixels of the ``(2 h + 1)**2`` window around it (``h`` =
    `half_window`) are fitted by least squares with ``c0 + c1 dx + c2 dy + c3 dx**2 + c4 dx dy
    + c5 dy**2`` (``dx, dy`` from the point); pixels whose residual exceeds 3 robust standard
    deviations (median absolute deviation, never under 1 projector pixel) are dropped and the
    fit repeated, three times.  The value is ``c0``.  A quadratic follows the camera -> projector
    map of a plane (a homography) and lens distortion closely over a window smaller than a
    chessboard square; it averages the quantisation of plain Gray code coordinates and bridges
    the pixels that did not decode (dark circles, black squares).

    Parameters
    ----------
    coord, valid, points
        As for `bilinear`.
    half_window : int
        Window half-size in camera pixels (>= 2).

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
    dx = (px - pts[:, :1]) / half_window
    dy = (py - pts[:, 1:]) / half_window
    design = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=-1)  # (N, K, 6)
    beta = np.zeros((len(pts), 6))
    for _ in range(_FIT_ITERATIONS):
        weights = use.astype(np.float64)
        normal = np.einsum("nk,nki,nkj->nij", weights, design, design) + 1e-9 * np.eye(6)
        rhs = np.einsum("nk,nki,nk->ni", weights, design, z)
        beta = np.linalg.solve(normal, rhs[..., None])[..., 0]
        residual = np.abs(z - np.einsum("nki,ni->nk", design, beta))
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
        code, whose integer coordinates need the averaging).

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
        fitted = local_fit(m.coord, m.valid, points, half_window)
        if interpolate:
            direct = bilinear(m.coord, m.valid, points)
            fitted = np.where(np.isnan(direct), fitted, direct)
        out.append(fitted)
    return np.stack(out, axis=-1)
