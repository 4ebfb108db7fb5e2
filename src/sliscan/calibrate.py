"""Direct linear transform (DLT) calibration of the camera and the projector (thesis 4.3-4.4).

Each device is a pinhole ``x ~ M @ [Xw, Yw, Zw, 1]`` (eqs. 4.1-4.6) with a 3x4 matrix `M`
mapping world millimetres to pixels (pixel centres at integers, x = column, y = row).  `M` is
estimated from known world points and the pixels that see them, either by SVD (eq. 4.9-4.10,
`dlt_svd`) or by linear least squares with ``m34 = 1`` (eqs. 4.17-4.19, `dlt_least_squares`).
`calibrate_points` calibrates both devices from the rows of a G file.

Both estimators return the same normalised form: the first three entries of the third row have
unit norm, so that row is the device's viewing direction and ``M[2] @ [Xw, Yw, Zw, 1]`` is the
depth in mm in front of the device (positive for the calibration points).

References
----------
.. [1] R. Hartley, "In defense of the eight-point algorithm", IEEE TPAMI 19(6), 580-593 (1997).
   :doi:`10.1109/34.601246`
.. [2] R. Hartley and A. Zisserman, *Multiple View Geometry in Computer Vision*, 2nd ed.,
   section 7.1 (the DLT for camera matrices) and 4.4.4 (normalisation).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError
from sliscan.formats.premat5 import check_g, phase_to_pixel
from sliscan.types import Calibration, Device

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
