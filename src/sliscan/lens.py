"""OpenCV's lens distortion model on pixel coordinates (issue 5).

A device with intrinsics ``K`` and distortion ``k1, k2, p1, p2, k3`` (OpenCV's order, DESIGN.md)
sees a world point where its pinhole ``K [R | t]`` would put it, moved by the lens: with the
normalised ideal coordinates ``(u, v) = K^-1 (x, y, 1)`` and ``r2 = u**2 + v**2``::

    radial = 1 + k1 r2 + k2 r2**2 + k3 r2**3
    ud = u radial + 2 p1 u v + p2 (r2 + 2 u**2)
    vd = v radial + p1 (r2 + 2 v**2) + 2 p2 u v

and the observed pixel is ``K (ud, vd, 1)``.  For a camera "observed" is the image pixel; for a
projector, calibrated as an inverse camera, it is the projector pixel that lights the point
(what a decoder measures).  The functions here work on pixels, ``(..., 2)`` arrays of ``(x, y)``
with pixel centres at integers; ``K`` may have a skew term (OpenCV's own functions ignore it;
its calibrations have none).

- `distort`: ideal pinhole pixels -> observed pixels (closed form), optionally with the
  Jacobian;
- `undistort`: observed -> ideal (`cv2.undistortPoints`, iterated to 1e-10 in normalised
  coordinates, i.e. ~1e-7 px);
- `solve_on_lines`: where only ONE observed coordinate is known but the ideal point lies on a
  known line (a camera ray's epipolar line in the projector), Newton's method along the line.

The model is written once (`_model`, compiled with numba) and evaluated point by point in
compiled loops: undistorting a 1296x972 map of decoded projector rows takes ~0.07 s this way,
~0.8 s as the same Newton iteration in numpy array expressions (docs/accuracy.md, "Lens distortion").

References
----------
.. [1] D. C. Brown, "Decentering distortion of lenses", Photogrammetric Engineering 32(3),
   444-462 (1966).
.. [2] OpenCV, "Camera calibration and 3D reconstruction" (calib3d), the distortion model.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, check_finite_matrix

FloatArray = NDArray[np.float64]

# cv2.undistortPoints: stop after 100 iterations or when the normalised point moves less than
# 1e-12 (1e-9 px for focal lengths up to 1000 px): far below any decoder's precision.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
#: `solve_on_lines` stops when the observed coordinate is matched to this many pixels ...
SOLVE_TOLERANCE_PX = 1e-6
#: ... or gives up (the point is reported unsolved) after this many Newton steps.  From the
#: pinhole start Newton needs 2-4 steps for |k1| <= 0.3 over a whole image (quadratic convergence).
SOLVE_MAX_ITERATIONS = 20


def has_distortion(distortion: ArrayLike | None) -> bool:
    """Whether distortion coefficients are given and not all zero."""
    return distortion is not None and bool(np.any(np.asarray(distortion) != 0))


def _check_model(intrinsics: ArrayLike, distortion: ArrayLike) -> tuple[FloatArray, FloatArray]:
    k = check_finite_matrix("intrinsics", intrinsics, (3, 3))
    if not (k[0, 0] > 0 and k[1, 1] > 0 and np.array_equal(k[2], [0.0, 0.0, 1.0]) and k[1, 0] == 0):
        raise InputError(f"intrinsics must be upper triangular with positive focal lengths and K[2] = [0, 0, 1], "
                         f"got {k.tolist()}")
    return k, check_finite_matrix("distortion", np.ravel(distortion), (5,))


def _normalise(xy: FloatArray, k: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Pixels ``(..., 2)`` -> normalised ``u, v`` (``K^-1``, skew included)."""
    v = (xy[..., 1] - k[1, 2]) / k[1, 1]
    u = (xy[..., 0] - k[0, 2] - k[0, 1] * v) / k[0, 0]
    return u, v


def _to_pixels(u: FloatArray, v: FloatArray, k: FloatArray) -> FloatArray:
    """Normalised ``u, v`` -> pixels ``(..., 2)`` (``K``)."""
    return np.stack([k[0, 0] * u + k[0, 1] * v + k[0, 2], k[1, 1] * v + k[1, 2]], axis=-1)


@numba.njit(cache=True, nogil=True, inline="always")
def _model(u: float, v: float, d: NDArray[np.float64]) -> tuple[float, float, float, float, float]:
    """The lens model at normalised ``(u, v)``: ``ud, vd`` and the Jacobian's entries
    ``d ud / du``, ``d ud / dv = d vd / du``, ``d vd / dv``."""
    k1, k2, p1, p2, k3 = d[0], d[1], d[2], d[3], d[4]
    r2 = u * u + v * v
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    slope = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))  # d radial / d r2, times 2
    ud = u * radial + 2.0 * p1 * u * v + p2 * (r2 + 2.0 * u * u)
    vd = v * radial + p1 * (r2 + 2.0 * v * v) + 2.0 * p2 * u * v
    cross = slope * u * v + 2.0 * p1 * u + 2.0 * p2 * v
    d_ud_du = radial + slope * u * u + 2.0 * p1 * v + 6.0 * p2 * u
    d_vd_dv = radial + slope * v * v + 6.0 * p1 * v + 2.0 * p2 * u
    return ud, vd, d_ud_du, cross, d_vd_dv


@numba.njit(cache=True, nogil=True)
def _distort_kernel(xy: NDArray[np.float64], k: NDArray[np.float64], d: NDArray[np.float64],
                    observed: NDArray[np.float64], jac: NDArray[np.float64]) -> None:
    """`distort` of ``(N, 2)`` pixels into `observed`, and the pixel Jacobian ``(N, 2, 2)``
    ``A Jn A^-1`` (``A = K[:2, :2]``) into `jac` unless it is empty."""
    fx, s, cx, fy, cy = k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]
    for i in range(xy.shape[0]):
        v = (xy[i, 1] - cy) / fy
        u = (xy[i, 0] - cx - s * v) / fx
        ud, vd, j00, j01, j11 = _model(u, v, d)
        observed[i, 0] = fx * ud + s * vd + cx
        observed[i, 1] = fy * vd + cy
        if jac.shape[0]:
            # rows of A Jn, then times A^-1 = [[1/fx, -s/(fx fy)], [0, 1/fy]]
            a00, a01 = fx * j00 + s * j01, fx * j01 + s * j11
            a10, a11 = fy * j01, fy * j11
            jac[i, 0, 0], jac[i, 0, 1] = a00 / fx, (a01 - a00 * s / fx) / fy
            jac[i, 1, 0], jac[i, 1, 1] = a10 / fx, (a11 - a10 * s / fx) / fy


@numba.njit(cache=True, nogil=True)
def _solve_kernel(observed: NDArray[np.float64], axis: int, lines: NDArray[np.float64], k: NDArray[np.float64],
                  d: NDArray[np.float64], out: NDArray[np.float64]) -> None:
    """`solve_on_lines`: Newton's method per line, NaN where unsolved."""
    fx, s, cx, fy, cy = k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]
    for i in range(observed.shape[0]):
        out[i] = np.nan
        target, a, b = observed[i], lines[i, 0], lines[i, 1]
        if not (np.isfinite(target) and np.isfinite(a) and np.isfinite(b)):
            continue
        # the line's point at t and its derivative, (x, y) = (a + b t, t) or (t, a + b t)
        dx, dy = (b, 1.0) if axis == 1 else (1.0, b)
        dv = dy / fy
        du = (dx - s * dv) / fx
        t = target
        for _ in range(SOLVE_MAX_ITERATIONS + 1):
            x, y = (a + b * t, t) if axis == 1 else (t, a + b * t)
            v = (y - cy) / fy
            u = (x - cx - s * v) / fx
            ud, vd, j00, j01, j11 = _model(u, v, d)
            dud, dvd = j00 * du + j01 * dv, j01 * du + j11 * dv
            if axis == 0:
                error, slope = fx * ud + s * vd + cx - target, fx * dud + s * dvd
            else:
                error, slope = fy * vd + cy - target, fy * dvd
            if not slope > 0:  # the model folds here: no physical solution
                break
            if abs(error) < SOLVE_TOLERANCE_PX:
                out[i] = t
                break
            t -= error / slope


def distort(xy: ArrayLike, intrinsics: ArrayLike, distortion: ArrayLike, *,
            jacobian: bool = False) -> FloatArray | tuple[FloatArray, FloatArray]:
    """Observed pixels of ideal (pinhole) pixels: the lens model of the module docstring.

    Parameters
    ----------
    xy : (..., 2) float array
        Ideal pixel ``(x, y)``: where the pinhole ``K [R | t]`` projects the point.
    intrinsics : (3, 3) array
        ``K``, pixels.
    distortion : (5,) array
        ``k1, k2, p1, p2, k3`` (OpenCV's order).
    jacobian : bool
        Also return the derivatives of the observed pixel by the ideal one.

    Returns
    -------
    observed : (..., 2) float64 array
        Pixel ``(x, y)`` the device sees.  Far outside the image (``r2`` beyond the model's
        monotonic range) the model folds back.
    d_observed : (..., 2, 2) float64 array
        Only with `jacobian`: ``d_observed[..., i, j] = d observed_i / d ideal_j``.

    Examples
    --------
    >>> K = np.array([[1000.0, 0, 320], [0, 1000, 240], [0, 0, 1]])
    >>> distort([[820.0, 240.0]], K, [0.1, 0, 0, 0, 0]).round(6)   # u = 0.5: 0.5 (1 + 0.1 * 0.25)
    array([[832.5, 240. ]])
    """
    k, d = _check_model(intrinsics, distortion)
    xy = np.asarray(xy, dtype=np.float64)
    if xy.shape[-1:] != (2,):
        raise InputError(f"xy must have shape (..., 2) (x, y), got {xy.shape}")
    flat = np.ascontiguousarray(xy.reshape(-1, 2))
    observed = np.empty_like(flat)
    jac = np.empty((len(flat) if jacobian else 0, 2, 2))
    _distort_kernel(flat, k, d, observed, jac)
    if not jacobian:
        return observed.reshape(xy.shape)
    return observed.reshape(xy.shape), jac.reshape(*xy.shape, 2)


def undistort(xy: ArrayLike, intrinsics: ArrayLike, distortion: ArrayLike) -> FloatArray:
    """Ideal (pinhole) pixels of observed ones: the inverse of `distort`.

    `cv2.undistortPoints` (OpenCV's fixed-point iteration) on the normalised coordinates, to
    1e-12 (`_UNDISTORT_CRITERIA`); exact to ~1e-7 px inside the model's monotonic range.

    Parameters
    ----------
    xy : (..., 2) float array
        Observed pixel ``(x, y)``.
    intrinsics, distortion
        As for `distort`.

    Returns
    -------
    ideal : (..., 2) float64 array

    Examples
    --------
    >>> K = np.array([[1000.0, 0, 320], [0, 1000, 240], [0, 0, 1]])
    >>> undistort([[832.5, 240.0]], K, [0.1, 0, 0, 0, 0]).round(6)
    array([[820., 240.]])
    """
    k, d = _check_model(intrinsics, distortion)
    xy = np.asarray(xy, dtype=np.float64)
    if xy.size == 0:
        return xy.reshape(xy.shape).copy()
    u, v = _normalise(xy, k)
    src = np.stack([u.ravel(), v.ravel()], axis=-1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(src, np.eye(3), d, criteria=_UNDISTORT_CRITERIA)[:, 0].astype(np.float64)
    return _to_pixels(ideal[:, 0], ideal[:, 1], k).reshape(xy.shape)


def solve_on_lines(observed: ArrayLike, axis: int, lines: ArrayLike, intrinsics: ArrayLike,
                   distortion: ArrayLike) -> FloatArray:
    """Ideal points on lines whose observed (distorted) pixel has one known coordinate.

    Each line is ``across = a + b * along`` in ideal pixels, ``along`` the coordinate on `axis`
    (``y`` for ``axis=1``: ``x = a + b y``).  Finds the ideal ``t = along`` whose point's observed
    pixel has ``distort(point)[axis] == observed``: Newton's method on ``t`` (a compiled loop)
    from the pinhole start ``t = observed``, until the observed coordinate matches to
    `SOLVE_TOLERANCE_PX` (at most `SOLVE_MAX_ITERATIONS` steps).  This is how a decoded projector
    row (or column) is undistorted when the other projector coordinate is unknown: the ideal
    point lies on the camera ray's epipolar line in the projector.

    Parameters
    ----------
    observed : (N,) float array
        The known observed coordinate (``x`` for ``axis=0``, ``y`` for ``axis=1``), pixels; NaN
        where there is none.
    axis : {0, 1}
    lines : (N, 2) float array
        ``(a, b)`` of each line (``a`` in pixels, ``b`` dimensionless).
    intrinsics, distortion
        As for `distort`.

    Returns
    -------
    t : (N,) float64 array
        The ideal coordinate along `axis`; NaN where `observed` or the line is not finite, Newton
        did not converge, or it reached a point where the model folds (the observed coordinate
        does not grow along the line there: no physical solution).

    Examples
    --------
    >>> K = np.array([[1000.0, 0, 320], [0, 1000, 240], [0, 0, 1]])
    >>> dist = [0.1, 0, 0, 0, 0]
    >>> observed = distort([[500.0, 700.0]], K, dist)   # on the line x = 500 + 0 y
    >>> t = solve_on_lines(observed[:, 1], 1, [[500.0, 0.0]], K, dist)
    >>> bool(abs(t[0] - 700) < 1e-6)
    True
    """
    if axis not in (0, 1):
        raise InputError(f"axis must be 0 (x) or 1 (y), got {axis!r}")
    k, d = _check_model(intrinsics, distortion)
    observed = np.ascontiguousarray(observed, dtype=np.float64).ravel()
    lines = np.ascontiguousarray(lines, dtype=np.float64).reshape(-1, 2)
    if len(lines) != len(observed):
        raise InputError(f"need one line per observed coordinate, got {len(lines)} lines for {len(observed)}")
    out = np.empty(len(observed))
    _solve_kernel(observed, axis, lines, k, d, out)
    return out
