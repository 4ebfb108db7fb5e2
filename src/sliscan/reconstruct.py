"""Triangulation: camera pixel + projector line -> world point (thesis eqs. 4.13-4.22).

A camera pixel ``(xc, yc)`` gives two planes through the camera centre (eqs. 4.1-4.2 rearranged)
and the decoded projector coordinate gives a third plane through the projector centre: the
projector row ``yp`` (eq. 4.5, the ``rows`` orientation, eqs. 4.20-4.22) or the column ``xp``
(eq. 4.4, the ``columns`` orientation).  The world point solves the 3x3 system ``C P = D``::

    (Mc[0, :3] - xc Mc[2, :3]) . P = xc Mc[2, 3] - Mc[0, 3]
    (Mc[1, :3] - yc Mc[2, :3]) . P = yc Mc[2, 3] - Mc[1, 3]
    (Mp[k, :3] - p  Mp[2, :3]) . P = p  Mp[2, 3] - Mp[k, 3]      k = 1 (rows, p = yp) or 0 (columns, p = xp)

solved for every pixel at once with the adjugate (Cramer's rule) in float64.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError
from sliscan.types import ORIENTATIONS, Calibration, Device

# |det C| / (|c1| |c2| |c3|) is the volume spanned by the three unit plane normals (1 when they
# are orthogonal, 0 when the camera ray lies in the projector plane).  Below this the point is
# reported as NaN: it is ~1e6 times more sensitive to the projector coordinate than a right angle.
MIN_PLANE_SINE = 1e-6

# Iterative undistortion: stop after 50 iterations or when the point moves less than 1e-10 px.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)


def _check_setup(calibration: Calibration, orientation: str) -> None:
    if orientation not in ORIENTATIONS:
        raise InputError(f"orientation must be one of {ORIENTATIONS}, got {orientation!r}")
    if calibration.projector.distortion is not None and np.any(calibration.projector.distortion):
        raise InputError("projector lens distortion is not supported yet (the calibration has nonzero projector "
                         "distortion)")
    camera = calibration.camera
    if camera.distortion is not None and np.any(camera.distortion) and camera.intrinsics is None:
        raise InputError("the camera has lens distortion but no intrinsics (K) to undistort with")


def _undistort(camera: Device, xc: NDArray[np.float64], yc: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """Observed camera pixels -> pixels of the ideal pinhole ``K [R | t]`` (OpenCV, ``P = K``)."""
    if camera.distortion is None or not np.any(camera.distortion) or xc.size == 0:
        return xc, yc
    src = np.stack([xc, yc], axis=-1).reshape(-1, 1, 2)
    dst = cv2.undistortPoints(src, camera.intrinsics, camera.distortion, R=None, P=camera.intrinsics,
                              criteria=_UNDISTORT_CRITERIA)
    return dst[:, 0, 0].astype(np.float64), dst[:, 0, 1].astype(np.float64)


Vec = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def _cross(u: Vec, v: Vec) -> Vec:
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _dot(u: Vec, v: Vec) -> NDArray[np.float64]:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _solve(xc: NDArray[np.float64], yc: NDArray[np.float64], p: NDArray[np.float64], calibration: Calibration,
           orientation: str) -> NDArray[np.float64]:
    """World points (N, 3) of N camera pixels and projector coordinates; NaN where ill-posed.

    Vectors are kept as three (N,) component arrays: the rows of C, their cross products (the
    adjugate's columns) and the solution are plain elementwise float64 arithmetic.
    """
    xc, yc = _undistort(calibration.camera, xc, yc)
    mc = calibration.camera.matrix
    mp = calibration.projector.matrix
    k = 1 if orientation == "rows" else 0
    planes = [(mc[0], xc, mc[2]), (mc[1], yc, mc[2]), (mp[k], p, mp[2])]
    c = [(row[0] - coord * last[0], row[1] - coord * last[1], row[2] - coord * last[2])
         for row, coord, last in planes]
    d = [coord * last[3] - row[3] for row, coord, last in planes]
    adj = [_cross(c[1], c[2]), _cross(c[2], c[0]), _cross(c[0], c[1])]
    det = _dot(c[0], adj[0])
    norms = np.sqrt(_dot(c[0], c[0]) * _dot(c[1], c[1]) * _dot(c[2], c[2]))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = np.where(np.abs(det) > MIN_PLANE_SINE * norms, 1.0 / det, np.nan)
    return np.stack([(d[0] * adj[0][j] + d[1] * adj[1][j] + d[2] * adj[2][j]) * inv_det for j in range(3)], axis=-1)


def _check_proj_map(name: str, value: ArrayLike, shape: tuple[int, int]) -> NDArray:
    """A real (H, W) array of `shape` whose entries are finite or NaN (not inf)."""
    arr = np.asarray(value)
    if arr.shape != shape:
        raise InputError(f"{name} must have shape {shape} (H, W), got {arr.shape}")
    if arr.dtype == np.bool_ or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name} must be a real-valued (float or int) array, got {arr.dtype}")
    if np.any(np.isinf(arr)):
        raise InputError(f"{name} has infinite values (use NaN for undecoded pixels)")
    return arr


def triangulate(proj_map: ArrayLike, calibration: Calibration, *, orientation: str = "rows",
                valid: ArrayLike | None = None, chunk_rows: int = 64) -> NDArray[np.float32]:
    """World point seen by every camera pixel (thesis eqs. 4.13-4.22).

    Parameters
    ----------
    proj_map : (H, W) float array
        Projector coordinate seen by each camera pixel, in projector pixels: the row `yp` for
        the ``rows`` orientation, the column `xp` for ``columns``; NaN where undecoded.  (H, W)
        is the calibrated camera's shape.
    calibration : Calibration
        Camera and projector world (mm) -> pixel matrices.  If the camera has distortion
        coefficients, the camera pixel grid is first undistorted with ``cv2.undistortPoints``
        (``P = K``) into the ideal pinhole ``K [R | t]`` that `matrix` describes.
    orientation : {"rows", "columns"}
        Which projector coordinate `proj_map` holds; selects the projector matrix's second
        (eq. 4.20) or first (eq. 4.11) row for the third equation.
    valid : (H, W) bool array, optional
        Pixels to triangulate.  Default: where `proj_map` is finite.
    chunk_rows : int
        Camera rows solved together; bounds the temporary memory (a few hundred bytes per pixel).

    Returns
    -------
    xyz_w : (H, W, 3) float32 array
        Xw, Yw, Zw in mm; NaN where invalid, undecoded, or where the camera ray is (nearly)
        parallel to the projector plane (see `MIN_PLANE_SINE`).  The scan's valid mask is
        ``np.isfinite(xyz_w[..., 0])``.

    Raises
    ------
    InputError
        If `proj_map` or `valid` is not (H, W) of the camera, `orientation` is unknown, or the
        projector has lens distortion (not supported yet).

    Examples
    --------
    A camera at the origin and a projector 200 mm above it (y points down) look at a plane
    500 mm away:

    >>> K = np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]])
    >>> camera = Device(K @ np.eye(3, 4), (64, 48))
    >>> projector = Device(K @ np.c_[np.eye(3), [0, 200, 0]], (64, 48))
    >>> yc, xc = np.mgrid[0:48, 0:64]
    >>> on_plane = 500 * np.stack([(xc - 32) / 100, (yc - 24) / 100, np.ones((48, 64))], axis=-1)
    >>> yp_map = projector.project(on_plane)[..., 1]
    >>> xyz_w = triangulate(yp_map, Calibration(camera, projector))
    >>> float(np.abs(xyz_w[..., 2] - 500).max()) < 1e-3
    True
    """
    _check_setup(calibration, orientation)
    shape = calibration.camera.shape
    proj_map = _check_proj_map("proj_map", proj_map, shape)
    mask = np.isfinite(proj_map)
    if valid is not None:
        valid = np.asarray(valid)
        if valid.dtype != np.bool_ or valid.shape != shape:
            raise InputError(f"valid must be a bool array of shape {shape} (H, W), got {valid.dtype} {valid.shape}")
        mask &= valid
    if isinstance(chunk_rows, bool) or not isinstance(chunk_rows, (int, np.integer)) or chunk_rows < 1:
        raise InputError(f"chunk_rows must be a positive integer, got {chunk_rows!r}")
    xyz_w = np.full((*shape, 3), np.nan, dtype=np.float32)
    for top in range(0, shape[0], chunk_rows):
        rows, cols = np.nonzero(mask[top:top + chunk_rows])
        rows += top
        xyz_w[rows, cols] = _solve(cols.astype(np.float64), rows.astype(np.float64),
                                   proj_map[rows, cols].astype(np.float64), calibration, orientation)
    return xyz_w


def triangulate_points(xc: ArrayLike, yc: ArrayLike, proj: ArrayLike, calibration: Calibration, *,
                       orientation: str = "rows") -> NDArray[np.float64]:
    """World points of scattered camera pixels and their projector coordinates.

    The same solver as `triangulate`, for points that are not a full camera grid.

    Parameters
    ----------
    xc, yc : (N,) float arrays
        Camera pixel coordinates (x = column, y = row, as observed: undistorted here if the
        camera has distortion coefficients); finite.
    proj : (N,) float array
        Projector row `yp` (``rows``) or column `xp` (``columns``) in pixels; NaN allowed.
    calibration : Calibration
    orientation : {"rows", "columns"}

    Returns
    -------
    xyz_w : (N, 3) float64 array
        Xw, Yw, Zw in mm; NaN where `proj` is NaN or the system is ill-conditioned.

    Examples
    --------
    >>> K = np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]])
    >>> camera = Device(K @ np.eye(3, 4), (64, 48))
    >>> projector = Device(K @ np.c_[np.eye(3), [0, 200, 0]], (64, 48))
    >>> point = np.array([[10.0, 20.0, 500.0]])
    >>> (xc, yc), yp = camera.project(point).T, projector.project(point)[:, 1]
    >>> triangulate_points(xc, yc, yp, Calibration(camera, projector)).round(6)
    array([[ 10.,  20., 500.]])
    """
    _check_setup(calibration, orientation)
    arrays = [np.asarray(v, dtype=np.float64) for v in (xc, yc, proj)]
    shapes = [a.shape for a in arrays]
    if any(a.ndim != 1 for a in arrays) or len(set(shapes)) != 1:
        raise InputError(f"xc, yc and proj must be 1-D arrays of one length, got shapes {shapes}")
    if not (np.all(np.isfinite(arrays[0])) and np.all(np.isfinite(arrays[1]))):
        raise InputError("xc and yc must be finite")
    if np.any(np.isinf(arrays[2])):
        raise InputError("proj has infinite values (use NaN for undecoded points)")
    return _solve(*arrays, calibration, orientation)
