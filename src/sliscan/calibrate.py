"""Direct linear transform (DLT) calibration of the camera and the projector (thesis 4.3-4.4).

Each device is a pinhole ``x ~ M @ [Xw, Yw, Zw, 1]`` (eqs. 4.1-4.6) with a 3x4 matrix `M`
mapping world millimetres to pixels (pixel centres at integers, x = column, y = row).  `M` is
estimated from known world points and the pixels that see them, either by SVD (eq. 4.9-4.10,
`dlt_svd`) or by linear least squares with ``m34 = 1`` (eqs. 4.17-4.19, `dlt_least_squares`).
`calibrate_points` calibrates both devices from the rows of a G file.

From captured images (issue 5), on the decoded maps of a multi-shot sequence coding both
projector directions (`sliscan.sequences.decode_frames`):

- `calibrate_target`, the thesis's workflow (4.0-4.2): the circle centres of a 3-D target
  (`sliscan.targets`) matched to its known world coordinates (`match_circles`), the projector
  coordinates read there, the G rows and the DLT, with the perspective bias of the circle
  centres removed (`ellipse_centres`);
- `calibrate_board`, the planar workflow: chessboard corners in several poses (`board_view`),
  the camera and the projector (an inverse camera) calibrated with OpenCV, intrinsics and lens
  distortion included, and their relative pose; world = camera frame.

Both can give every point's reprojection residual vector beside the calibration (`Residuals`:
``calibrate_board(..., with_residuals=True)``, `target_residuals`), for the plots of
`sliscan.figures.plot_residuals`; the calibration JSON keeps only their RMS and maximum.

Both estimators return the same normalised form: the first three entries of the third row have
unit norm, so that row is the device's viewing direction and ``M[2] @ [Xw, Yw, Zw, 1]`` is the
depth in mm in front of the device (positive for the calibration points).

References
----------
.. [1] R. Hartley, "In defense of the eight-point algorithm", IEEE TPAMI 19(6), 580-593 (1997).
   :doi:`10.1109/34.601246`
.. [2] R. Hartley and A. Zisserman, *Multiple View Geometry in Computer Vision*, 2nd ed.,
   section 7.1 (the DLT for camera matrices) and 4.4.4 (normalisation).
.. [3] J. Heikkila, "Geometric camera calibration using circular control points", IEEE TPAMI
   22(10), 1066-1077 (2000) (the image of a circle's centre is not its ellipse's centre).
   :doi:`10.1109/34.879788`
.. [4] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11),
   1330-1334 (2000) (OpenCV's `calibrateCamera`). :doi:`10.1109/34.888718`
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, overload

import cv2
import numpy as np
import scipy.optimize
import scipy.spatial
from numpy.typing import ArrayLike, NDArray

from sliscan import lens
from sliscan._validate import InputError, atomic_write_text, check_finite_matrix
from sliscan.formats.premat5 import check_g, phase_to_pixel, pixel_to_phase
from sliscan.lens import has_distortion
from sliscan.pmp import ProjectorMap
from sliscan.targets import Board, CircleTarget, detect_circles, projector_points
from sliscan.types import Calibration, Device, _load_json

#: Fewest points for a DLT: 11 unknowns, 2 equations per point.
MIN_POINTS = 6

# Centred world points whose smallest singular value is below this fraction of the largest are
# treated as coplanar: a flat target leaves the DLT underdetermined, and a nearly flat one
# amplifies pixel noise by about the inverse of this ratio.
_COPLANAR_RATIO = 1e-3
# A second-smallest singular value of the normalised design matrix below this fraction of the
# largest means the null space is not one-dimensional: the solution is not unique.
_NULLSPACE_RATIO = 1e-10
# Condition number of M[:, :3] above which the estimate is not a projective camera.
_MAX_CONDITION = 1e12

FloatArray = NDArray[np.float64]


def _check_pairs(world: ArrayLike, pixels: ArrayLike) -> tuple[FloatArray, FloatArray]:
    world = np.asarray(world, dtype=np.float64)
    pixels = np.asarray(pixels, dtype=np.float64)
    if world.ndim != 2 or world.shape[1] != 3:
        raise InputError(f"world must have shape (N, 3) (Xw, Yw, Zw), got {world.shape}")
    if pixels.shape != (world.shape[0], 2):
        raise InputError(f"pixels must have shape ({world.shape[0]}, 2) (x, y), got {pixels.shape}")
    for name, arr in (("world", world), ("pixels", pixels)):
        bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
        if bad.size:
            raise InputError(f"{name} has non-finite values (NaN or inf) at point {bad[0]}")
    return world, pixels


def _check_dlt_input(world: ArrayLike, pixels: ArrayLike) -> tuple[FloatArray, FloatArray]:
    world, pixels = _check_pairs(world, pixels)
    n = world.shape[0]
    if n < MIN_POINTS:
        raise InputError(f"need at least {MIN_POINTS} calibration points, got {n}")
    s = np.linalg.svd(world - world.mean(axis=0), compute_uv=False)
    if s[2] <= _COPLANAR_RATIO * s[0]:
        ratio = s[2] / s[0] if s[0] > 0 else 0.0
        raise InputError(f"world points are coplanar (thickness/extent {ratio:.1e} <= {_COPLANAR_RATIO:g}); "
                         "a DLT needs non-coplanar (3-D) calibration points")
    if np.ptp(pixels, axis=0).max() == 0:
        raise InputError("degenerate calibration: every point has the same pixel coordinates")
    return world, pixels


def _similarity(points: FloatArray) -> FloatArray:
    """Hartley's normalising similarity: centroid to 0, mean distance to sqrt(dim)."""
    dim = points.shape[1]
    centroid = points.mean(axis=0)
    scale = np.sqrt(dim) / np.mean(np.linalg.norm(points - centroid, axis=1))
    t = np.eye(dim + 1) * scale
    t[:dim, dim] = -scale * centroid
    t[dim, dim] = 1.0
    return t


def _normalised_design(world: FloatArray, pixels: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Eq. 4.9's matrix A (2N x 12) in Hartley-normalised coordinates, with both transforms."""
    u = _similarity(world)
    t = _similarity(pixels)
    xw = np.c_[world, np.ones(len(world))] @ u.T
    xy = (np.c_[pixels, np.ones(len(pixels))] @ t.T)[:, :2]
    zeros = np.zeros_like(xw)
    a = np.empty((2 * len(world), 12))
    a[0::2] = np.hstack([xw, zeros, -xy[:, :1] * xw])
    a[1::2] = np.hstack([zeros, xw, -xy[:, 1:] * xw])
    return a, t, u


def _finish(m_normalised: FloatArray, t: FloatArray, u: FloatArray, world: FloatArray) -> FloatArray:
    """Undo the normalisation, scale to a unit viewing direction, point depth forward; check."""
    m = np.linalg.solve(t, m_normalised.reshape(3, 4)) @ u
    norm = np.linalg.norm(m[2, :3])
    if not norm > 1e-12 * np.linalg.norm(m):
        raise InputError("degenerate calibration: the solution has no viewing direction (camera at infinity)")
    m /= norm
    depth = world @ m[2, :3] + m[2, 3]
    if np.median(depth) < 0:
        m = -m
        depth = -depth
    behind = int(np.count_nonzero(depth <= 0))
    if behind:
        raise InputError(f"degenerate calibration: {behind} of {len(world)} points lie behind the solved device")
    if np.linalg.cond(m[:, :3]) > _MAX_CONDITION:
        raise InputError("degenerate calibration: the solved 3x3 part is singular (points or pixels degenerate)")
    return m


def dlt_svd(world: ArrayLike, pixels: ArrayLike) -> FloatArray:
    """Projection matrix by the SVD solution of ``A m = 0`` (thesis eqs. 4.9-4.10).

    The coordinates are first normalised as Hartley recommends [1]_ (world points and pixels
    each translated to their centroid and scaled to a mean distance of sqrt(3) and sqrt(2)),
    which keeps the 2N x 12 design matrix well conditioned; the right singular vector of the
    smallest singular value is then mapped back to the original coordinates.

    Parameters
    ----------
    world : (N, 3) float array
        Xw, Yw, Zw of the calibration points in mm; N >= 6, not all in one plane.
    pixels : (N, 2) float array
        x (column), y (row) where the device sees each point, in pixels.

    Returns
    -------
    matrix : (3, 4) float64 array
        World -> pixel, ``x ~ matrix @ [Xw, Yw, Zw, 1]``, scaled so ``norm(matrix[2, :3]) == 1``
        and the points have positive depth ``matrix[2] @ [Xw, Yw, Zw, 1]`` (mm).

    Raises
    ------
    InputError
        Fewer than 6 points, non-finite values, coplanar world points, or a degenerate
        solution (the null space is not one-dimensional, or the result is not a camera).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> true = np.array([[800., 0, 320, 0], [0, 800, 240, 0], [0, 0, 1, 0]])
    >>> world = rng.uniform([-100, -100, 700], [100, 100, 900], size=(20, 3))
    >>> pixels = Device(true, (640, 480)).project(world)
    >>> bool(np.allclose(dlt_svd(world, pixels), true, atol=1e-6))
    True
    """
    world, pixels = _check_dlt_input(world, pixels)
    a, t, u = _normalised_design(world, pixels)
    _, s, vt = np.linalg.svd(a, full_matrices=False)
    if s[-2] <= _NULLSPACE_RATIO * s[0]:
        raise InputError("degenerate calibration: the DLT has more than one solution (points in a special configuration)")
    return _finish(vt[-1], t, u, world)


def dlt_least_squares(world: ArrayLike, pixels: ArrayLike) -> FloatArray:
    """Projection matrix by linear least squares with ``m34 = 1`` (thesis eqs. 4.17-4.19).

    Solves ``A m = B`` (eq. 4.17-4.18) for the other 11 entries with `numpy.linalg.lstsq`
    (an orthogonal factorisation, not the normal-equation inverse ``(A^T A)^-1 A^T B``).  The
    coordinates are Hartley-normalised first, as in `dlt_svd`; there ``m34`` is the depth of
    the points' centroid, which is never zero for points in front of the device, so fixing it
    to 1 loses no solution (in raw coordinates it fails when the world origin lies in the
    device's focal plane).

    Parameters
    ----------
    world : (N, 3) float array
        Xw, Yw, Zw of the calibration points in mm; N >= 6, not all in one plane.
    pixels : (N, 2) float array
        x (column), y (row) where the device sees each point, in pixels.

    Returns
    -------
    matrix : (3, 4) float64 array
        Normalised as in `dlt_svd`.

    Raises
    ------
    InputError
        As `dlt_svd`; degenerate when the 11-column system is rank deficient.
    """
    world, pixels = _check_dlt_input(world, pixels)
    a, t, u = _normalised_design(world, pixels)
    m, _, rank, _ = np.linalg.lstsq(a[:, :11], -a[:, 11], rcond=None)
    if rank < 11:
        raise InputError(f"degenerate calibration: the least-squares system has rank {rank} < 11")
    return _finish(np.append(m, 1.0), t, u, world)


def reprojection_residuals(matrix: ArrayLike, world: ArrayLike, pixels: ArrayLike) -> FloatArray:
    """Distance between where `matrix` projects each world point and where it was seen.

    Parameters
    ----------
    matrix : (3, 4) float array
        World (mm) -> pixel projection matrix.
    world : (N, 3) float array
        Xw, Yw, Zw in mm.
    pixels : (N, 2) float array
        Observed x, y in pixels.

    Returns
    -------
    residuals : (N,) float64 array
        Euclidean reprojection error of each point, in pixels.
    """
    world, pixels = _check_pairs(world, pixels)
    # The size does not enter the projection; Device only lends its validated `project`.
    projected = Device(matrix, (1, 1)).project(world)
    return np.hypot(*(projected - pixels).T)


def summarize_residuals(residuals: ArrayLike) -> dict[str, float]:
    """RMS and maximum of reprojection residuals.

    Parameters
    ----------
    residuals : (N,) float array
        Per-point distances in pixels (`reprojection_residuals`).

    Returns
    -------
    summary : dict
        ``{"rms_px": sqrt(mean(r**2)), "max_px": max(r)}``.  For Gaussian pixel noise of
        standard deviation sigma per coordinate, a DLT fit of N points leaves
        ``rms_px ~ sigma * sqrt((2N - 11) / N)`` (11 fitted parameters).

    Examples
    --------
    >>> summarize_residuals([3.0, 4.0])
    {'rms_px': 3.5355339059327378, 'max_px': 4.0}
    """
    r = np.asarray(residuals, dtype=np.float64)
    return {"rms_px": float(np.sqrt(np.mean(r**2))), "max_px": float(np.max(r))}


_METHODS: dict[str, Callable[[ArrayLike, ArrayLike], FloatArray]] = {
    "svd": dlt_svd,
    "lstsq": dlt_least_squares,
}


def calibrate_points(g_rows: ArrayLike, camera_size: tuple[int, int], projector_size: tuple[int, int], *,
                     method: str = "svd", phases: bool = True) -> Calibration:
    """Calibrate the camera and the projector from calibration-grid rows (a G file).

    Parameters
    ----------
    g_rows : (N, 7) float array
        ``Xw Yw Zw xc yc xp yp`` per point: world in mm, camera pixels, and the projector
        coordinates, as phases in radians (``x = phase * size / 2pi``, the thesis's
        convention, see `sliscan.formats.premat5.phase_to_pixel`) or, with ``phases=False``,
        projector pixels.
    camera_size, projector_size : (W, H) tuple of int
        Image sizes in pixels.
    method : {"svd", "lstsq"}
        `dlt_svd` (section 4.3) or `dlt_least_squares` (section 4.4).
    phases : bool
        Whether the last two columns are phases (True) or projector pixels (False).

    Returns
    -------
    calibration : Calibration
        Both matrices and sizes; ``extra`` holds ``method``, ``points`` (N) and ``residuals``:
        ``{"camera": {"rms_px", "max_px"}, "projector": {"rms_px", "max_px"}}``.

    Raises
    ------
    InputError
        Bad rows or method, or a failed DLT for either device (message starts with
        ``camera:`` or ``projector:``).
    """
    if method not in _METHODS:
        raise InputError(f"method must be one of {sorted(_METHODS)}, got {method!r}")
    rows = check_g(g_rows)
    world = rows[:, :3]
    projector_px = rows[:, 5:7]
    if phases:
        projector_px = np.c_[phase_to_pixel(rows[:, 5], projector_size[0]),
                             phase_to_pixel(rows[:, 6], projector_size[1])]
    devices = {}
    residuals = {}
    for name, size, pixels in (("camera", camera_size, rows[:, 3:5]), ("projector", projector_size, projector_px)):
        try:
            matrix = _METHODS[method](world, pixels)
        except InputError as exc:
            raise InputError(f"{name}: {exc}") from None
        devices[name] = Device(matrix, size)
        residuals[name] = summarize_residuals(reprojection_residuals(matrix, world, pixels))
    return Calibration(devices["camera"], devices["projector"],
                       {"method": method, "residuals": residuals, "points": int(len(rows))})


# --------------------------------------------------------------------------------------------
# The thesis's workflow: a 3-D circle target (sections 4.0-4.2)
# --------------------------------------------------------------------------------------------

#: Default largest reprojection RMS (px) of a DLT that accepts a match of circles to the target.
MAX_MATCH_RMS_PX = 2.0
# Orderings of the circles that `match_circles` verifies with a DLT (the cheapest candidates).
_MATCH_CANDIDATES = 12
# Rotations tried when aligning the target's layout with the image, in degrees.
_MATCH_ANGLES = np.radians(np.arange(0.0, 360.0, 2.0))
# Rounds of the perspective-bias correction of circle centres (the second changes < 0.001 px).
_BIAS_ITERATIONS = 2
# Outline points of a circle for the centroid of its image (`outline_centroids`).
_OUTLINE_POINTS = 128


def _whiten(points: FloatArray) -> FloatArray:
    """2-D points centred and scaled to unit covariance: what is left of an affine map is a
    rotation or a reflection."""
    centred = points - points.mean(axis=0)
    eigval, eigvec = np.linalg.eigh(np.cov(centred.T))
    return centred @ eigvec / np.sqrt(np.maximum(eigval, 1e-12 * eigval.max()))


def _match_rms(world: FloatArray, pixels: FloatArray) -> tuple[float, FloatArray] | None:
    """RMS reprojection error (px) and matrix of a DLT, or None if it fails or is left-handed."""
    try:
        matrix = dlt_svd(world, pixels)
    except InputError:
        return None
    if np.linalg.det(matrix[:, :3]) <= 0:  # a mirrored camera: the ordering is a reflection
        return None
    return float(np.sqrt(np.mean(reprojection_residuals(matrix, world, pixels) ** 2))), matrix


def match_circles(image_points: ArrayLike, world: ArrayLike, *, max_rms_px: float = MAX_MATCH_RMS_PX
                  ) -> NDArray[np.intp]:
    """Which detected circle is which circle of the target.

    The target's centres, projected on their two principal axes, give its layout as seen
    face-on; the layout and the image points are each whitened (centred, unit covariance), so
    that an affine view of the layout differs from the image by a rotation or a reflection only.
    Every rotation in 2-degree steps, mirrored or not, gives an assignment (Hungarian, squared
    distances); the cheapest distinct ones are verified with a DLT (`dlt_svd`), reassigned by
    reprojecting the target with it, and fitted again.  The ordering with the smallest RMS
    reprojection error wins; mirrored cameras (``det M[:, :3] < 0``: a right-handed target
    frame seen in a mirror) are refused.

    Parameters
    ----------
    image_points : (M, 2) array
        Detected circle centres ``(x, y)`` in pixels, ``M >= N`` (extra blobs are left out).
    world : (N, 3) array
        The target's circle centres in mm, in a right-handed frame, not coplanar.
    max_rms_px : float
        Largest RMS reprojection error (px) of an accepted ordering.

    Returns
    -------
    order : (N,) int array
        ``image_points[order[k]]`` is the image of ``world[k]``.

    Raises
    ------
    InputError
        Too few image points, no ordering within `max_rms_px`, or two orderings within it (a
        target whose layout has a symmetry cannot be told apart).
    """
    pts = np.asarray(image_points, dtype=np.float64).reshape(-1, 2)
    world = np.asarray(world, dtype=np.float64)
    if len(pts) < len(world):
        raise InputError(f"found {len(pts)} circles, the target has {len(world)}")
    centred = world - world.mean(axis=0)
    layout = _whiten(centred @ np.linalg.svd(centred, full_matrices=False)[2][:2].T)
    image = _whiten(pts)
    candidates: dict[tuple[int, ...], float] = {}
    for mirror in (1.0, -1.0):
        for angle in _MATCH_ANGLES:
            c, s = np.cos(angle), np.sin(angle)
            turned = layout @ np.array([[c, -s], [s, c]]).T * [1.0, mirror]
            cost = scipy.spatial.distance.cdist(turned, image, "sqeuclidean")
            rows, cols = scipy.optimize.linear_sum_assignment(cost)
            candidates.setdefault(tuple(cols[np.argsort(rows)]), float(cost[rows, cols].sum()))
    fits: dict[tuple[int, ...], float] = {}
    for order in sorted(candidates, key=candidates.__getitem__)[:_MATCH_CANDIDATES]:
        first = _match_rms(world, pts[list(order)])
        if first is None:
            continue
        reprojected = Device(first[1], (1, 1)).project(world)
        rows, cols = scipy.optimize.linear_sum_assignment(scipy.spatial.distance.cdist(reprojected, pts))
        refined = tuple(int(k) for k in cols[np.argsort(rows)])
        second = _match_rms(world, pts[list(refined)])
        if second is not None:
            fits[refined] = second[0]
    ranked = sorted(fits, key=fits.__getitem__)
    if not ranked or fits[ranked[0]] > max_rms_px:
        best = f" (best reprojection RMS {fits[ranked[0]]:.3g} px)" if ranked else ""
        raise InputError(f"cannot match the {len(pts)} circles found to the target's {len(world)}{best}; is the "
                         "target file's frame right-handed, and does the camera see every circle?")
    if len(ranked) > 1 and fits[ranked[1]] <= max_rms_px:
        raise InputError(f"the target is ambiguous: two orderings of its circles fit (RMS {fits[ranked[0]]:.3g} "
                         f"and {fits[ranked[1]]:.3g} px); give it a layout without symmetry")
    return np.array(ranked[0], dtype=np.intp)


def ellipse_centres(matrix: ArrayLike, target: CircleTarget) -> FloatArray:
    """Centre of the image ellipse of every circle of a target, seen through `matrix`.

    A circle of radius ``r`` in its plane is the conic ``diag(1, 1, -r**2)`` in in-plane
    coordinates; the plane's homography ``H = M [u, v, C_h]`` maps it to the image conic
    ``Q = H^-T diag(1, 1, -r**2) H^-1``, whose centre is ``-Q[:2, :2]^-1 Q[:2, 2]``.  Its
    distance from ``M C_h`` (the image of the centre) is the perspective bias of a detected
    circle centre [3]_.

    Parameters
    ----------
    matrix : (3, 4) array
        World (mm) -> pixel projection.
    target : CircleTarget
        With `normals` and `radius_mm`.

    Returns
    -------
    centres : (N, 2) float64 array
        ``(x, y)`` in pixels.
    """
    if target.normals is None:
        raise InputError("the target has no normals and radius_mm: the ellipse centres are unknown")
    m = check_finite_matrix("matrix", matrix, (3, 4))
    n = target.normals
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(n, u)
    h = np.stack([u @ m[:, :3].T, v @ m[:, :3].T, target.centres @ m[:, :3].T + m[:, 3]], axis=-1)
    h_inv = np.linalg.inv(h)
    q = np.swapaxes(h_inv, 1, 2) @ np.diag([1.0, 1.0, -target.radius_mm**2]) @ h_inv
    return -np.linalg.solve(q[:, :2, :2], q[:, :2, 2:])[..., 0]


def _brightness(maps: Mapping[str, ProjectorMap]) -> NDArray[np.float32]:
    """The camera image under uniform light, from any decoded direction."""
    if not maps:
        raise InputError("no decoded projector maps")
    return next(iter(maps.values())).brightness


def calibrate_target(maps: Mapping[str, ProjectorMap], target: CircleTarget, projector_size: tuple[int, int], *,
                     method: str = "svd", interpolate: bool = True,
                     max_rms_px: float = MAX_MATCH_RMS_PX) -> tuple[Calibration, FloatArray]:
    """Calibrate camera and projector from one capture of a 3-D circle target (thesis 4.0-4.4).

    The circles are found in the decoded `brightness` (`sliscan.targets.detect_circles`),
    matched to the target's circles (`match_circles`), the projector ``(xp, yp)`` is read at
    each centre (`sliscan.targets.projector_points`: bilinear from valid pixels, a robust local
    fit where the circle did not decode), and both devices are calibrated by the DLT
    (`calibrate_points`).  With the target's normals and radius the camera centres are then
    moved from the ellipse centres to the images of the circle centres (`ellipse_centres`,
    with the calibration just found), the projector coordinates read again there, and the DLT
    repeated: twice.

    Parameters
    ----------
    maps : {"columns": ProjectorMap, "rows": ProjectorMap}
        `sliscan.sequences.decode_frames` of a sequence coding both directions.
    target : CircleTarget
        The circles' world coordinates (mm).
    projector_size : (W, H) tuple of int
    method : {"svd", "lstsq"}
        The DLT (thesis 4.3 or 4.4).
    interpolate : bool
        Sub-pixel maps (PMP, Gray code + phase): bilinear at the centres where possible.  False
        for plain Gray code: a local fit everywhere.
    max_rms_px : float
        See `match_circles`.

    Returns
    -------
    calibration : Calibration
        As `calibrate_points`; ``extra`` also holds ``circles`` (N) and
        ``perspective_bias_px`` (the largest correction applied, 0 without normals).
    g_rows : (N, 7) float64 array
        The G file's rows (``Xw Yw Zw xc yc xp_phase yp_phase``) of the final DLT.

    Raises
    ------
    InputError
        Too few circles, no match, a circle without projector coordinates, or a failed DLT.
    """
    brightness = _brightness(maps)
    camera_size = (brightness.shape[1], brightness.shape[0])
    found = detect_circles(brightness)
    observed = found[match_circles(found, target.centres, max_rms_px=max_rms_px)]
    neighbour = scipy.spatial.cKDTree(observed).query(observed, k=2)[0][:, 1]
    half_window = max(3, int(np.median(neighbour) / 2))
    camera, bias = observed, np.zeros_like(observed)
    for step in range(_BIAS_ITERATIONS + 1):
        projector = projector_points(maps, camera, half_window=half_window, interpolate=interpolate)
        bad = np.flatnonzero(np.isnan(projector).any(axis=1))
        if bad.size:
            x, y = camera[bad[0]]
            raise InputError(f"no projector coordinates decoded around circle {bad[0]} at ({x:.1f}, {y:.1f}) px "
                             f"({bad.size} of {len(camera)} circles)")
        rows = np.c_[target.centres, camera, pixel_to_phase(projector[:, 0], projector_size[0]),
                     pixel_to_phase(projector[:, 1], projector_size[1])]
        calibration = calibrate_points(rows, camera_size, projector_size, method=method)
        if target.normals is None or step == _BIAS_ITERATIONS:
            break
        bias = ellipse_centres(calibration.camera.matrix, target) - calibration.camera.project(target.centres)
        camera = observed - bias
    extra = {**calibration.extra, "circles": len(rows),
             "perspective_bias_px": float(np.max(np.linalg.norm(bias, axis=1)))}
    return Calibration(calibration.camera, calibration.projector, extra), rows


# --------------------------------------------------------------------------------------------
# The planar workflow: board poses (chessboard or circle grid), OpenCV calibration with lens distortion
# --------------------------------------------------------------------------------------------

#: Fewest good board views `calibrate_board` takes.
MIN_BOARD_VIEWS = 3
#: A view counts when at least this fraction of its points have projector coordinates.
MIN_PROJECTOR_CORNERS = 0.5
# A view is flagged as an outlier when its RMS exceeds this multiple of the median view's RMS
# and this many pixels.
_OUTLIER_FACTOR = 2.0
_OUTLIER_FLOOR_PX = 0.5
# Half-window of the projector's local fit around a board point, in neighbour spacings: a chessboard
# corner's window stays inside its four squares; a circle's reaches past the (undecoded) dark disc.
_FIT_WINDOW = {"corner": 0.4, "circle": 0.6}


@dataclass(frozen=True, eq=False)
class BoardView:
    """The board points (chessboard corners, circle centres) of one pose, in the camera and in
    the projector.

    Attributes
    ----------
    camera : (N, 2) float64 array
        Points ``(x, y)`` in camera pixels, OpenCV's order (`sliscan.targets.Board.points`).
    projector : (N, 2) float64 array
        The same points' ``(xp, yp)`` in projector pixels; NaN where not decoded.
    """

    camera: FloatArray
    projector: FloatArray


def board_view(maps: Mapping[str, ProjectorMap], board: Board, *, interpolate: bool = False) -> BoardView:
    """Find a board's points in one decoded pose and read the projector there.

    The points come from the decoded `brightness` (the white frame; `Board.detect`: chessboard
    corners or circle centres); each point's projector ``(xp, yp)`` from the decoded maps
    (`sliscan.targets.projector_points`): a robust local quadratic fit to the decoded pixels in a
    window around it (0.8 neighbour spacings wide for a corner, 1.2 for a circle), which skips the
    black squares and dark discs that do not decode.

    Parameters
    ----------
    maps : {"columns": ProjectorMap, "rows": ProjectorMap}
    board : Board
        The board (kind and OpenCV's pattern size matter here).
    interpolate : bool
        See `sliscan.targets.projector_points` (False: the local fit everywhere).

    Raises
    ------
    InputError
        The board is not found, or fewer than half its points have projector coordinates.
    """
    points = board.detect(_brightness(maps))
    if points is None:
        raise InputError(f"no {board.describe()} found")
    half_window = max(3, int(_FIT_WINDOW[board.feature] * board.image_spacing(points)))
    # A circle's centre lies in its dark disc, where decoding is noisiest: always the local fit.
    projector = projector_points(maps, points, half_window=half_window, interpolate=interpolate and not board.circles)
    decoded = int(np.all(np.isfinite(projector), axis=1).sum())
    if decoded < MIN_PROJECTOR_CORNERS * len(points):
        raise InputError(f"only {decoded} of {len(points)} board {board.feature}s have decoded projector coordinates")
    return BoardView(points, projector)


def _vector_rms(vectors: FloatArray) -> float:
    """RMS length (px) of residual vectors ``(N, 2)``."""
    return float(np.sqrt(np.mean(np.sum(np.asarray(vectors, dtype=np.float64) ** 2, axis=1))))


@dataclass(frozen=True, eq=False)
class Residuals:
    """Every point's reprojection residual vector, per view: kept beside a calibration (for
    `sliscan.figures.plot_residuals`), not in its JSON.

    Attributes
    ----------
    labels : tuple of str
        One name per view.
    camera, projector : tuple of (N_k, 2) float64 arrays
        Per view, ``projected - observed`` ``(dx, dy)`` in pixels, one row per point the device
        was calibrated with.
    points : str
        What a point is (``"corner"``, ``"circle"``), for the plot.
    """

    labels: tuple[str, ...]
    camera: tuple[FloatArray, ...]
    projector: tuple[FloatArray, ...]
    points: str = "point"

    def rms(self, device: str) -> list[float]:
        """Per-view RMS residual length (px) of ``"camera"`` or ``"projector"``."""
        return [_vector_rms(v) for v in getattr(self, device)]

    def save(self, path: str | os.PathLike) -> Path:
        """Write as JSON (atomically): ``{"labels": [...], "points": "corner", "camera": [view
        [[dx, dy], ...], ...], "projector": [...]}``, for ``sliscan report --residuals``."""
        data = {"labels": list(self.labels), "points": self.points,
                **{d: [np.asarray(v, dtype=np.float64).reshape(-1, 2).tolist() for v in getattr(self, d)]
                   for d in ("camera", "projector")}}
        return atomic_write_text(path, json.dumps(data) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike) -> Residuals:
        """Read what `save` wrote.

        Raises
        ------
        InputError
            If the file is not such JSON: the labels, a list of per-view ``(N, 2)`` finite
            residuals per device, one per label.
        """
        d = _load_json(path)
        labels, points = d.get("labels"), d.get("points", "point")
        if not isinstance(labels, list) or not labels or not all(isinstance(x, str) for x in labels):
            raise InputError(f"{path}: 'labels' must be a non-empty list of view names")
        if not isinstance(points, str):
            raise InputError(f"{path}: 'points' must be a string (corner, circle, ...)")
        devices = []
        for device in ("camera", "projector"):
            views = d.get(device)
            if not isinstance(views, list) or len(views) != len(labels):
                raise InputError(f"{path}: '{device}' must list one view of residuals per label ({len(labels)})")
            try:
                arrays = tuple(np.asarray(v, dtype=np.float64).reshape(-1, 2) for v in views)
            except (TypeError, ValueError):
                raise InputError(f"{path}: '{device}' residuals must be lists of [dx, dy] numbers") from None
            if not all(np.all(np.isfinite(a)) and a.size for a in arrays):
                raise InputError(f"{path}: '{device}' residuals must be non-empty and finite")
            devices.append(arrays)
        return cls(tuple(labels), devices[0], devices[1], points)


def _view_residuals(objects: list[NDArray[np.float32]], images: list[NDArray[np.float32]],
                    rvecs: Sequence[FloatArray], tvecs: Sequence[FloatArray], k: FloatArray,
                    dist: FloatArray) -> list[FloatArray]:
    """Per-view residual vectors ``projected - observed`` (px) of one calibrated device."""
    return [(cv2.projectPoints(o, r, t, k, dist)[0][:, 0] - i).astype(np.float64)
            for o, i, r, t in zip(objects, images, rvecs, tvecs)]


def target_residuals(calibration: Calibration, g_rows: ArrayLike, *, label: str = "target") -> Residuals:
    """Residual vectors of every circle of a `calibrate_target` result, from its G rows.

    Parameters
    ----------
    calibration : Calibration
        The DLT result (``projector.size`` converts the phases to pixels).
    g_rows : (N, 7) array
        The rows it was calibrated from (``Xw Yw Zw xc yc xp_phase yp_phase``).
    label : str
        The view's name.

    Returns
    -------
    residuals : Residuals
        One view; its RMS values are the ``residuals`` of the calibration's ``extra``.
    """
    rows = check_g(g_rows)
    width, height = calibration.projector.size
    projector_px = np.c_[phase_to_pixel(rows[:, 5], width), phase_to_pixel(rows[:, 6], height)]
    world = rows[:, :3]
    return Residuals((label,), (calibration.camera.project(world) - rows[:, 3:5],),
                     (calibration.projector.project(world) - projector_px,), "circle")


def triangulate_correspondences(calibration: Calibration, camera_points: ArrayLike,
                                projector_points_: ArrayLike) -> FloatArray:
    """World points of camera <-> projector point pairs, both lens models applied.

    Each device's pixels are undistorted to normalised coordinates (`sliscan.lens.undistort`
    with its ``intrinsics`` and ``distortion``; a device without intrinsics is a plain
    pinhole), then the two rays are intersected linearly (`cv2.triangulatePoints`).

    Parameters
    ----------
    calibration : Calibration
    camera_points, projector_points_ : (N, 2) arrays
        ``(xc, yc)`` and ``(xp, yp)`` in pixels.

    Returns
    -------
    points : (N, 3) float64 array
        World coordinates in mm.
    """
    rays, extrinsics = [], []
    for device, pts in ((calibration.camera, camera_points), (calibration.projector, projector_points_)):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 1, 2)
        if device.intrinsics is None:
            rays.append(pts[:, 0].T)
            extrinsics.append(device.matrix)
            continue
        ideal = pts[:, 0] if not has_distortion(device.distortion) else lens.undistort(
            pts[:, 0], device.intrinsics, device.distortion)
        rays.append(np.linalg.solve(device.intrinsics, np.c_[ideal, np.ones(len(ideal))].T)[:2])
        extrinsics.append(np.linalg.solve(device.intrinsics, device.matrix))
    homogeneous = cv2.triangulatePoints(extrinsics[0], extrinsics[1], rays[0], rays[1])
    return (homogeneous[:3] / homogeneous[3]).T


def board_geometry(points: ArrayLike, board: Board) -> dict[str, float]:
    """How flat and how regular triangulated board points are.

    Parameters
    ----------
    points : (N, 3) array
        The board's points (corners, circle centres) in OpenCV's order, NaN where missing, in
        the unit of ``board.spacing``.
    board : Board

    Returns
    -------
    geometry : dict
        ``planarity_rms``: RMS distance of the points from their least-squares plane;
        ``spacing_mean`` and ``spacing_std``: distance between neighbouring points
        (`Board.neighbours`: along rows and columns, the asymmetric grid's diagonals), scaled
        to the board's nominal `spacing` (all in its unit); ``spacing_error``: relative error
        of the mean distance, ``spacing_mean / spacing - 1``.
    """
    pts = np.asarray(points, dtype=np.float64)
    finite = np.all(np.isfinite(pts), axis=1)
    centred = pts[finite] - pts[finite].mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    pairs = board.neighbours()
    ratio = np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1) / board.nearest
    steps = board.spacing * ratio[np.isfinite(ratio)]
    return {"planarity_rms": float(np.sqrt(np.mean((centred @ normal) ** 2))),
            "spacing_mean": float(steps.mean()), "spacing_std": float(steps.std()),
            "spacing_error": float(steps.mean() / board.spacing - 1)}


@dataclass(frozen=True, eq=False)
class _BoardFit:
    """OpenCV's calibration of both devices from board views: intrinsics ``k``, distortion ``d``
    and per-view board poses ``r`` (Rodrigues), ``t`` of the camera (``c``) and the projector
    (``p``), the projector's pose relative to the camera, and OpenCV's standard deviations of
    each device's ``fx, fy, cx, cy`` (px; `cv2.calibrateCameraExtended`, from the residuals)."""

    kc: FloatArray
    dc: FloatArray
    rc: tuple[FloatArray, ...]
    tc: tuple[FloatArray, ...]
    kp: FloatArray
    dp: FloatArray
    rp: tuple[FloatArray, ...]
    tp: tuple[FloatArray, ...]
    rotation: FloatArray
    translation: FloatArray
    stereo_rms_px: float
    camera_std: FloatArray
    projector_std: FloatArray


def _fit_board(objects: list[NDArray[np.float32]], camera: list[NDArray[np.float32]],
               projector: list[NDArray[np.float32]], decoded: list[NDArray[np.bool_]], camera_size: tuple[int, int],
               projector_size: tuple[int, int], projector_distortion: bool) -> _BoardFit:
    """`calibrate_board`'s OpenCV calls on the points of every view (`objects`: the board's
    points of each view; `camera`, `projector`: their images, `decoded`: which have projector
    coordinates)."""
    flags = cv2.CALIB_FIX_K3
    projector_flags = flags if projector_distortion else (
        flags | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_ZERO_TANGENT_DIST)
    shared = [o[m] for o, m in zip(objects, decoded)]
    _, kc, dc, rc, tc, std_c = cv2.calibrateCameraExtended(objects, camera, tuple(camera_size), None, None,
                                                           flags=flags)[:6]
    _, kp, dp, rp, tp, std_p = cv2.calibrateCameraExtended(shared, projector, tuple(projector_size), None, None,
                                                           flags=projector_flags)[:6]
    stereo = cv2.stereoCalibrate(shared, [c[m] for c, m in zip(camera, decoded)], projector, kc, dc, kp, dp,
                                 tuple(camera_size), flags=cv2.CALIB_FIX_INTRINSIC)
    return _BoardFit(kc, dc.ravel()[:5], tuple(rc), tuple(tc), kp, dp.ravel()[:5], tuple(rp), tuple(tp),
                     stereo[5], stereo[6].ravel(), float(stereo[0]), std_c.ravel()[:4], std_p.ravel()[:4])


def outline_centroids(device: Device, centres: ArrayLike, axes: ArrayLike, radius: float) -> FloatArray:
    """Area centroid ``(N, 2)`` px of each circle's image, through the device's lens.

    The circle ``centre + radius (cos a u + sin a v)`` (`axes` ``(2, 3)``: the unit vectors
    ``u, v`` of its plane, mm) is projected at `_OUTLINE_POINTS` angles with `Device.project`
    (pinhole, then lens distortion) and the centroid of that polygon is taken (shoelace).  That
    is where a darkness-weighted detector (`sliscan.targets.detect_circle_grid`) finds a dark
    disc: under a pinhole the image ellipse's centre (`ellipse_centres`, the perspective bias),
    and through a lens also the lens's second-order pull on the disc's area (a barrel lens pulls
    an off-axis disc's centroid toward the image centre: 0.002 px at 200 px from it on the
    rig of benchmarks/distortion.py, enough to take the focal length 0.05 px off).
    """
    angles = 2 * np.pi * np.arange(_OUTLINE_POINTS) / _OUTLINE_POINTS
    ring = np.c_[np.cos(angles), np.sin(angles)] @ np.asarray(axes, dtype=np.float64)  # (K, 3)
    outline = device.project(np.asarray(centres, dtype=np.float64)[:, None, :] + radius * ring)  # (N, K, 2)
    x, y = outline[..., 0], outline[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * yn - xn * y
    area = 3 * cross.sum(axis=1)
    return np.c_[((x + xn) * cross).sum(axis=1) / area, ((y + yn) * cross).sum(axis=1) / area]


def _circle_bias(board: Board, fit: _BoardFit, view: int) -> tuple[FloatArray, FloatArray]:
    """Bias ``(N, 2)`` px of one view's circle centres in the camera and in the projector.

    Camera: where the detector finds each disc (`outline_centroids`, with the view's pose and
    the camera's lens) minus the image of its centre.  Projector: its coordinates are read at
    that camera point, i.e. at the board point that the camera sees there (undistorted, then
    back through the board plane's homography), so its bias is that point's projector image
    minus the circle centre's (both through the projector's lens).
    """
    layout = board.points().astype(np.float64)
    rotation = cv2.Rodrigues(fit.rc[view])[0]
    pose = np.c_[rotation, fit.tc[view].ravel()]
    camera = Device(fit.kc @ pose, (1, 1), intrinsics=fit.kc, distortion=fit.dc)
    found = outline_centroids(camera, layout, np.eye(3)[:2], float(board.radius))
    ideal = lens.undistort(found, fit.kc, fit.dc) if has_distortion(fit.dc) else found
    on_board = np.c_[ideal, np.ones(len(layout))] @ np.linalg.inv(camera.matrix[:, [0, 1, 3]]).T
    seen = np.c_[on_board[:, :2] / on_board[:, 2:], np.zeros(len(layout))]
    projector_pose = fit.rotation @ pose + np.c_[np.zeros((3, 3)), fit.translation]
    projector = Device(fit.kp @ projector_pose, (1, 1), intrinsics=fit.kp, distortion=fit.dp)
    return found - camera.project(layout), projector.project(seen) - projector.project(layout)


@overload
def calibrate_board(views: Sequence[BoardView], board: Board, camera_size: tuple[int, int],
                    projector_size: tuple[int, int], *, projector_distortion: bool = ...,
                    with_residuals: Literal[False] = ...) -> Calibration: ...


@overload
def calibrate_board(views: Sequence[BoardView], board: Board, camera_size: tuple[int, int],
                    projector_size: tuple[int, int], *, projector_distortion: bool = ...,
                    with_residuals: Literal[True]) -> tuple[Calibration, Residuals]: ...


def calibrate_board(views: Sequence[BoardView], board: Board, camera_size: tuple[int, int],
                    projector_size: tuple[int, int], *, projector_distortion: bool = True,
                    with_residuals: bool = False) -> Calibration | tuple[Calibration, Residuals]:
    """Calibrate camera and projector (intrinsics, lens distortion, relative pose) from board views.

    The camera is calibrated from the points of every view (`cv2.calibrateCamera`, Zhang's
    method [4]_), the projector as an inverse camera from the points that have projector
    coordinates, then the projector's pose relative to the camera from the points both have
    (`cv2.stereoCalibrate` with both intrinsics fixed).  Distortion: ``k1, k2, p1, p2`` (``k3``
    fixed at 0: a few poses do not pin it down).  World = camera frame: the camera's matrix is
    ``Kc [I | 0]``, the projector's ``Kp [R | t]`` (DESIGN.md), in the unit of ``board.spacing``.

    A circle grid with its `radius` has the perspective bias of its centres removed
    (`_circle_bias`, as `calibrate_target` does for the 3-D target [3]_): the calibration is
    repeated twice with the camera and projector points corrected by the bias that the previous
    one predicts.

    Parameters
    ----------
    views : sequence of BoardView
        At least `MIN_BOARD_VIEWS` poses (`board_view`).
    board : Board
        The board (chessboard or circle grid, its spacing in mm or any unit: the world unit of
        the result).
    camera_size, projector_size : (W, H) tuple of int
    projector_distortion : bool
        Estimate the projector's lens distortion (True) or fix it at 0 (False).
    with_residuals : bool
        Also return every point's residual vectors.

    Returns
    -------
    calibration : Calibration
        Both devices with ``intrinsics`` and ``distortion``.  ``extra``: ``method``
        (``"opencv-board"``), ``board`` (`Board.to_dict`), ``residuals`` (camera and
        projector RMS and max over every point, px), ``stereo_rms_px``, ``intrinsics_std_px``
        (per device, OpenCV's standard deviations of ``fx``, ``fy``, ``cx``, ``cy`` in px: a
        principal point that the poses pin down poorly turns the whole calibration's world, the
        camera frame, by about its error over the focal length), ``perspective_bias_px``
        (the largest camera correction of a circle centre; 0 for a chessboard or a grid without
        radius), ``views`` (per view: ``camera_rms_px``, ``projector_rms_px``, ``corners`` (the
        board's points), ``projector_corners`` (those with projector coordinates) and the
        `board_geometry` of its points triangulated with the result) and ``outlier_views``
        (indices of views whose camera or projector RMS exceeds twice the median view's and
        0.5 px).
    residuals : Residuals
        Only with ``with_residuals``: per view (``"view 0"``, ...), the camera's residual vectors
        of every point and the projector's of the decoded ones; their per-view RMS values are
        the ``views``' ``camera_rms_px`` and ``projector_rms_px``.

    Raises
    ------
    InputError
        Too few views, or a view with another number of points than the board's.
    """
    if len(views) < MIN_BOARD_VIEWS:
        raise InputError(f"need at least {MIN_BOARD_VIEWS} board views, got {len(views)}")
    layout = board.points()
    bad = [k for k, v in enumerate(views) if len(v.camera) != len(layout) or len(v.projector) != len(layout)]
    if bad:
        raise InputError(f"view {bad[0]} has {len(views[bad[0]].camera)} points, the {board.describe()} has "
                         f"{len(layout)}")
    decoded = [np.all(np.isfinite(v.projector), axis=1) for v in views]
    objects = [layout] * len(views)
    camera_points = [v.camera.astype(np.float64) for v in views]
    projector_points_ = [v.projector.astype(np.float64) for v in views]
    bias = [np.zeros_like(c) for c in camera_points]
    corrected = board.radius is not None
    for step in range(_BIAS_ITERATIONS + 1 if corrected else 1):
        if step:
            biases = [_circle_bias(board, fit, k) for k in range(len(views))]
            bias = [b[0] for b in biases]
            camera_points = [v.camera - b[0] for v, b in zip(views, biases)]
            projector_points_ = [v.projector - b[1] for v, b in zip(views, biases)]
        camera_images = [c.astype(np.float32) for c in camera_points]
        projector_images = [p[m].astype(np.float32) for p, m in zip(projector_points_, decoded)]
        fit = _fit_board(objects, camera_images, projector_images, decoded, camera_size, projector_size,
                         projector_distortion)
    camera = Device(fit.kc @ np.eye(3, 4), camera_size, intrinsics=fit.kc, distortion=fit.dc)
    projector = Device(fit.kp @ np.c_[fit.rotation, fit.translation], projector_size, intrinsics=fit.kp,
                       distortion=fit.dp)
    camera_vectors = _view_residuals(objects, camera_images, fit.rc, fit.tc, fit.kc, fit.dc)
    projector_vectors = _view_residuals([layout[m] for m in decoded], projector_images, fit.rp, fit.tp, fit.kp,
                                        fit.dp)
    camera_rms = [_vector_rms(v) for v in camera_vectors]
    projector_rms = [_vector_rms(v) for v in projector_vectors]
    camera_errors = np.linalg.norm(np.concatenate(camera_vectors), axis=1)
    projector_errors = np.linalg.norm(np.concatenate(projector_vectors), axis=1)
    calibration = Calibration(camera, projector)
    per_view = []
    for k in range(len(views)):
        points = np.full((len(layout), 3), np.nan)
        points[decoded[k]] = triangulate_correspondences(calibration, camera_points[k][decoded[k]],
                                                         projector_points_[k][decoded[k]])
        per_view.append({"camera_rms_px": camera_rms[k], "projector_rms_px": projector_rms[k],
                         "corners": len(layout), "projector_corners": int(decoded[k].sum()),
                         **board_geometry(points, board)})
    limits = [max(_OUTLIER_FACTOR * float(np.median(rms)), _OUTLIER_FLOOR_PX) for rms in (camera_rms, projector_rms)]
    outliers = [k for k in range(len(views)) if camera_rms[k] > limits[0] or projector_rms[k] > limits[1]]
    extra = {"method": "opencv-board", "board": board.to_dict(),
             "residuals": {"camera": summarize_residuals(camera_errors),
                           "projector": summarize_residuals(projector_errors)},
             "stereo_rms_px": fit.stereo_rms_px,
             "intrinsics_std_px": {device: dict(zip(("fx", "fy", "cx", "cy"), map(float, std)))
                                   for device, std in (("camera", fit.camera_std), ("projector", fit.projector_std))},
             "perspective_bias_px": float(max(np.linalg.norm(b, axis=1).max() for b in bias)),
             "views": per_view, "outlier_views": outliers}
    result = Calibration(camera, projector, extra)
    if not with_residuals:
        return result
    labels = tuple(f"view {k}" for k in range(len(views)))
    return result, Residuals(labels, tuple(camera_vectors), tuple(projector_vectors), board.feature)
