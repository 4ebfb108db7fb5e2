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
import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError
from sliscan._threads import default_workers, over_rows
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


@numba.njit(cache=True, nogil=True)
def _evaluate_rows(coef: NDArray[np.float64], centre: float, proj_map: NDArray, mask: NDArray[np.bool_],
                   quad: NDArray[np.float64], rows: NDArray[np.intp], out: NDArray[np.float32]) -> None:
    """``out[y, x] = (a + b q) / (c + d q)``, ``q = p - centre``, for the given rows (see
    `Triangulator`), NaN where
    `mask` is false or the system is ill-posed: ``|c + d p| <= MIN_PLANE_SINE |c3(p)|`` with
    ``|c3(p)|**2 = quad[0] + quad[1] p + quad[2] p**2``."""
    for y in rows:
        for x in range(proj_map.shape[1]):
            p = np.float64(proj_map[y, x])
            k = coef[y, x]
            den = k[6] + k[7] * (p - centre)
            if not mask[y, x] or abs(den) <= MIN_PLANE_SINE * np.sqrt(quad[0] + quad[1] * p + quad[2] * p * p):
                out[y, x, :] = np.nan
                continue
            for j in range(3):
                out[y, x, j] = (k[j] + k[3 + j] * (p - centre)) / den


class Triangulator:
    """`triangulate` with the per-pixel work done once for a rig: for a fixed camera pixel the
    system ``C P = D`` depends on the projector coordinate ``p`` only through its third row,
    affinely, so by Cramer's rule every world coordinate is a ratio of two affine functions
    of ``p`` with a common denominator::

        P_j = (a_j + b_j p) / (c + d p),    (a_j, b_j, c, d) per pixel

    With ``n = c1 x c2`` (the camera rows' planes), ``u, u3 = Mp[k, :3], Mp[k, 3]`` and
    ``v, v3 = Mp[2, :3], Mp[2, 3]``: ``a = d1 (c2 x u) + d2 (u x c1) - u3 n``, ``b = -d1 (c2 x v)
    - d2 (v x c1) + v3 n``, ``c = u . n``, ``d = -v . n``, all divided by ``|c1| |c2|`` (so the
    ill-conditioning test of `_solve` (`MIN_PLANE_SINE`) reads ``|c + d p| > MIN_PLANE_SINE
    |u - p v|``) and re-expanded about the projector's middle line.  The camera grid is
    undistorted once, here.  The coefficients are float64 (``(H, W, 8)``, 64 bytes per
    pixel: float32 ones lose up to 0.02 mm where the projector coordinate is ill-conditioned,
    as for columns on a vertical baseline); the points agree with `_solve`'s to float32
    rounding.

    Parameters
    ----------
    calibration : Calibration
    orientation : {"rows", "columns"}
        As in `triangulate`.
    chunk_rows : int
        Camera rows prepared together (bounds the temporary memory).
    workers : int, optional
        Threads evaluating rows in parallel (default: all the CPUs this process may use).
    """

    def __init__(self, calibration: Calibration, orientation: str = "rows", *, chunk_rows: int = 64,
                 workers: int | None = None) -> None:
        _check_setup(calibration, orientation)
        if isinstance(chunk_rows, bool) or not isinstance(chunk_rows, (int, np.integer)) or chunk_rows < 1:
            raise InputError(f"chunk_rows must be a positive integer, got {chunk_rows!r}")
        self.shape = calibration.camera.shape
        self.workers = default_workers() if workers is None else workers
        mc, mp = calibration.camera.matrix, calibration.projector.matrix
        k = 1 if orientation == "rows" else 0
        u, u3, v, v3 = mp[k, :3], mp[k, 3], mp[2, :3], mp[2, 3]
        self._quad = np.array([u @ u, -2 * (u @ v), v @ v])
        self._centre = (calibration.projector.size[1 - k] - 1) / 2
        h, w = self.shape
        self._coef = np.empty((h, w, 8), dtype=np.float64)
        for top in range(0, h, chunk_rows):
            yc, xc = np.mgrid[top:min(top + chunk_rows, h), 0:w].astype(np.float64)
            xc, yc = _undistort(calibration.camera, xc.ravel(), yc.ravel())
            c1 = np.outer(-xc, mc[2, :3]) + mc[0, :3]
            c2 = np.outer(-yc, mc[2, :3]) + mc[1, :3]
            d1 = (xc * mc[2, 3] - mc[0, 3])[:, None]
            d2 = (yc * mc[2, 3] - mc[1, 3])[:, None]
            n = np.cross(c1, c2)
            a = d1 * np.cross(c2, u) + d2 * np.cross(u, c1) - u3 * n
            b = -d1 * np.cross(c2, v) - d2 * np.cross(v, c1) + v3 * n
            scale = 1.0 / (np.linalg.norm(c1, axis=1) * np.linalg.norm(c2, axis=1))[:, None]
            den_a, den_b = n @ u[:, None], -(n @ v[:, None])
            # about the projector's middle line, so neither term dwarfs the sum
            coef = np.concatenate([a + self._centre * b, b, den_a + self._centre * den_b, den_b], axis=1) * scale
            self._coef[top:top + chunk_rows] = coef.reshape(-1, w, 8)

    def __call__(self, proj_map: ArrayLike, valid: ArrayLike | None = None) -> NDArray[np.float32]:
        """World points ``(H, W, 3)`` float32 of a projector-coordinate map; as `triangulate`."""
        proj_map = _check_proj_map("proj_map", proj_map, self.shape)
        mask = np.isfinite(proj_map)
        if valid is not None:
            valid = np.asarray(valid)
            if valid.dtype != np.bool_ or valid.shape != self.shape:
                raise InputError(f"valid must be a bool array of shape {self.shape} (H, W), got {valid.dtype} "
                                 f"{valid.shape}")
            mask &= valid
        xyz_w = np.empty((*self.shape, 3), dtype=np.float32)
        values = np.ascontiguousarray(proj_map if proj_map.dtype.kind == "f" else proj_map.astype(np.float64))
        over_rows(lambda rows: _evaluate_rows(self._coef, self._centre, values, mask, self._quad, rows, xyz_w),
                  self.shape[0], self.workers)
        return xyz_w


def triangulate(proj_map: ArrayLike, calibration: Calibration, *, orientation: str = "rows",
                valid: ArrayLike | None = None, chunk_rows: int = 64) -> NDArray[np.float32]:
    """World point seen by every camera pixel (thesis eqs. 4.13-4.22).

    Builds a `Triangulator` for the rig and applies it; keep one to triangulate many maps.

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
        Camera rows prepared together; bounds the temporary memory (a few hundred bytes per pixel).

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
    return Triangulator(calibration, orientation, chunk_rows=chunk_rows)(proj_map, valid)


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
