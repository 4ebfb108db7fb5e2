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

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan import lens
from sliscan._validate import InputError
from sliscan._threads import default_workers, over_rows
from sliscan.lens import _model as _lens_model
from sliscan.lens import has_distortion
from sliscan.types import ORIENTATIONS, Calibration, Device

# |det C| / (|c1| |c2| |c3|) is the volume spanned by the three unit plane normals (1 when they
# are orthogonal, 0 when the camera ray lies in the projector plane).  Below this the point is
# reported as NaN: it is ~1e6 times more sensitive to the projector coordinate than a right angle.
MIN_PLANE_SINE = 1e-6


def _check_setup(calibration: Calibration, orientation: str) -> None:
    if orientation not in ORIENTATIONS:
        raise InputError(f"orientation must be one of {ORIENTATIONS}, got {orientation!r}")
    for name in ("camera", "projector"):
        device = getattr(calibration, name)
        if has_distortion(device.distortion) and device.intrinsics is None:
            raise InputError(f"the {name} has lens distortion but no intrinsics (K) to undistort with")


def _undistort(camera: Device, xc: NDArray[np.float64], yc: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """Observed camera pixels -> pixels of the ideal pinhole ``K [R | t]`` (`sliscan.lens.undistort`)."""
    if not has_distortion(camera.distortion) or xc.size == 0:
        return xc, yc
    ideal = lens.undistort(np.stack([xc, yc], axis=-1), camera.intrinsics, camera.distortion)
    return ideal[..., 0], ideal[..., 1]


# --- projector lens distortion (issue 5) ------------------------------------------------------
# A decoded projector coordinate is an observed (distorted) pixel; the 3x3 system below needs the
# ideal pinhole one.  With both projector coordinates the point is undistorted exactly
# (`sliscan.lens.undistort`); with one, the ideal point lies on the camera ray's epipolar line in
# the projector, ``across = a + b * along`` (ideal pixels; along = the decoded coordinate's axis),
# and `sliscan.lens.solve_on_lines` finds where on it the observed coordinate is matched.


def _epipolar_lines(calibration: Calibration, orientation: str, xc: NDArray[np.float64],
                    yc: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(..., 2)`` coefficients ``(a, b)`` of the ideal projector epipolar line of observed camera
    pixels ``xc, yc``: ``xp = a + b yp`` (rows) or ``yp = a + b xp`` (columns), ideal pixels.

    The line is ``F (xc, yc, 1)`` with the fundamental matrix ``F = [e]_x Mp[:, :3] Mc[:, :3]^-1``
    (``e`` the epipole, the camera centre seen by the projector) on the undistorted camera pixel.
    Infinite or NaN where the line runs along the decoded axis (no intersection: ill-posed).
    """
    xc, yc = _undistort(calibration.camera, xc, yc)
    mc, mp = calibration.camera.matrix, calibration.projector.matrix
    centre = -np.linalg.solve(mc[:, :3], mc[:, 3])
    e = mp @ np.append(centre, 1.0)
    cross = np.array([[0.0, -e[2], e[1]], [e[2], 0.0, -e[0]], [-e[1], e[0], 0.0]])
    f = cross @ mp[:, :3] @ np.linalg.inv(mc[:, :3])
    line = [f[i, 0] * xc + f[i, 1] * yc + f[i, 2] for i in range(3)]
    k = 1 if orientation == "rows" else 0
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.stack([-line[2] / line[1 - k], -line[k] / line[1 - k]], axis=-1)


def _ideal_projector(calibration: Calibration, orientation: str, proj: NDArray[np.float64],
                     lines: NDArray[np.float64], other: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """Ideal (pinhole) projector coordinate ``(N,)`` of decoded ones ``(N,)`` along `orientation`.

    `lines` ``(N, 2)`` from `_epipolar_lines`; `other` ``(N,)``, optional: the other decoded
    projector coordinate (``xp`` for rows), NaN where unknown.  Where both are known the point is
    undistorted exactly, elsewhere solved on the epipolar line; NaN where `proj` is NaN or unsolved.
    """
    projector = calibration.projector
    k = 1 if orientation == "rows" else 0
    both = np.flatnonzero(np.isfinite(proj) & np.isfinite(other)) if other is not None else np.empty(0, np.intp)
    one = proj.copy()
    one[both] = np.nan
    ideal = lens.solve_on_lines(one, k, lines, projector.intrinsics, projector.distortion)
    if both.size:
        observed = np.stack([other[both], proj[both]][::1 if k else -1], axis=-1)
        ideal[both] = lens.undistort(observed, projector.intrinsics, projector.distortion)[:, k]
    return ideal


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


def device_centre(matrix: NDArray[np.floating]) -> NDArray[np.float64]:
    """Optical centre (mm) of a 3x4 projection matrix: its right null vector."""
    _, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    return vt[-1, :3] / vt[-1, 3]


#: `MeasurableTest.args`: ``(depth (2, 4), projector (3, 4), lens (10,) or (0,), across, low,
#: high, centres (2, 3), max_cos)``, all float64 but `across` (int).
TestArgs = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], int, float, float,
                 NDArray[np.float64], float]


@dataclass(frozen=True, eq=False)
class MeasurableTest:
    """The per-point test of `sliscan.pipeline.measurable` for one rig and coded direction,
    prepared once (`of`) and applied by compiled kernels (`is_measurable`).

    Attributes
    ----------
    depth : (2, 4) float64 array
        The camera's and the projector's depth rows (matrix row 2 scaled to a unit normal,
        signed so that points in front are positive): ``depth . (X, Y, Z, 1) > 0``.
    projector : (3, 4) float64 array
        The projector's matrix.
    lens : (10,) or (0,) float64 array
        The projector's ``fx, s, cx, fy, cy, k1, k2, p1, p2, k3``; empty without distortion.
    across : int
        The projector coordinate the stripes do not code: 0 (x, coding rows) or 1 (y).
    low, high : float
        Its open range (projector pixels, the image plus a margin of 2 % of its lines).
    centres : (2, 3) float64 array
        The camera's and the projector's centre (mm).
    max_cos : float
        Largest cosine of the angle between the camera and the projector ray: the cosine of
        the smallest angle (``inf`` for none, ``-inf`` beyond 180 degrees).
    """

    depth: NDArray[np.float64]
    projector: NDArray[np.float64]
    lens: NDArray[np.float64]
    across: int
    low: float
    high: float
    centres: NDArray[np.float64]
    max_cos: float

    @classmethod
    def of(cls, calibration: Calibration, direction: str, min_angle_deg: float) -> MeasurableTest:
        """The test of `sliscan.pipeline.measurable` for `direction` (``"rows"`` or
        ``"columns"``, the coded projector coordinate) and `min_angle_deg` (degrees)."""
        depth = []
        for device in (calibration.camera, calibration.projector):
            m = device.matrix / np.linalg.norm(device.matrix[2, :3])
            depth.append(np.sign(np.linalg.det(device.matrix[:, :3])) * m[2])
        w, h = calibration.projector.size
        across, lines = (0, w) if direction == "rows" else (1, h)
        margin = 0.02 * lines
        projector = calibration.projector
        lens = (np.concatenate([projector.intrinsics[[0, 0, 0, 1, 1], [0, 1, 2, 1, 2]], projector.distortion])
                if has_distortion(projector.distortion) else np.empty(0))
        angle = float(min_angle_deg)
        max_cos = np.inf if angle <= 0 else -np.inf if angle > 180 else float(np.cos(np.radians(angle)))
        return cls(depth=np.array(depth), projector=np.ascontiguousarray(projector.matrix, dtype=np.float64),
                   lens=lens.astype(np.float64), across=across, low=-0.5 - margin, high=lines - 0.5 + margin,
                   centres=np.array([device_centre(calibration.camera.matrix),
                                     device_centre(calibration.projector.matrix)]), max_cos=max_cos)

    @property
    def args(self) -> TestArgs:
        """The fields as one tuple, for `is_measurable`."""
        return (self.depth, self.projector, self.lens, self.across, self.low, self.high, self.centres, self.max_cos)


@numba.njit(cache=True, inline="always")
def is_measurable(x: float, y: float, z: float, test: TestArgs) -> bool:
    """Whether world point ``(x, y, z)`` (mm) passes `test` (`MeasurableTest.args`): finite, in
    front of both devices, inside the projector's image across the coded direction (through
    its lens, if any), and seen by rays meeting at the smallest angle or more."""
    depth, m, lens, across, low, high, centres, max_cos = test
    if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
        return False
    for device in range(2):
        if not depth[device, 0] * x + depth[device, 1] * y + depth[device, 2] * z + depth[device, 3] > 0:
            return False
    hw = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3]
    if lens.size:  # the pixel the projector's lens sends that ray through
        xp = (m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3]) / hw
        yp = (m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3]) / hw
        fx, skew, cx, fy, cy = lens[0], lens[1], lens[2], lens[3], lens[4]
        v = (yp - cy) / fy
        u = (xp - cx - skew * v) / fx
        ud, vd, _, _, _ = _lens_model(u, v, lens[5:])
        coordinate = fx * ud + skew * vd + cx if across == 0 else fy * vd + cy
    else:
        coordinate = (m[across, 0] * x + m[across, 1] * y + m[across, 2] * z + m[across, 3]) / hw
    if not low < coordinate < high:
        return False
    ab = aa = bb = 0.0
    for j, p in enumerate((x, y, z)):
        a, b = p - centres[0, j], p - centres[1, j]
        ab, aa, bb = ab + a * b, aa + a * a, bb + b * b
    return ab / (np.sqrt(aa) * np.sqrt(bb)) <= max_cos


@numba.njit(cache=True, nogil=True)
def _evaluate_rows(coef: NDArray[np.float64], affine: NDArray[np.float64], norm_c1: NDArray[np.float64],
                   norm_c2: NDArray[np.float64], centre: float, proj_map: NDArray, mask: NDArray[np.bool_],
                   quad: NDArray[np.float64], test: TestArgs | None, rows: NDArray[np.intp], out: NDArray[np.float32],
                   measured: NDArray[np.bool_] | None) -> None:
    """``out[y, x] = (a + b q) / (c + d q)``, ``q = p - centre``, for the given rows (see
    `Triangulator`), NaN where `mask` is false, ``p`` is NaN or the system is ill-posed:
    ``|c + d p| <= MIN_PLANE_SINE |c3(p)|`` with ``|c3(p)|**2 = quad[0] + quad[1] p + quad[2] p**2``.
    With a `test` (`MeasurableTest.args`) the points that fail it (`is_measurable`, on the
    float32 point) are NaN too, and `measured` ``(H, W)`` says which points are left.

    The pixel's eight coefficients come from `coef` ``(H, W, 8)`` when it has rows, else from
    the row's `affine` ``(H, 2, 8)`` terms ``A + B x`` divided by ``|c1(x)| |c2|``, `norm_c1`
    ``(W,)`` and `norm_c2` ``(H,)``."""
    tabled = coef.shape[0] > 0
    for y in rows:
        for x in range(proj_map.shape[1]):
            p = np.float64(proj_map[y, x])
            ok = mask[y, x] and np.isfinite(p)
            if ok:
                scale = 1.0 if tabled else 1.0 / (norm_c1[x] * norm_c2[y])
                q = p - centre
                den = _coefficient(coef, affine, scale, y, x, 6) + _coefficient(coef, affine, scale, y, x, 7) * q
                ok = not abs(den) <= MIN_PLANE_SINE * np.sqrt(quad[0] + quad[1] * p + quad[2] * p * p)
            if ok:
                px = np.float32((_coefficient(coef, affine, scale, y, x, 0)
                                 + _coefficient(coef, affine, scale, y, x, 3) * q) / den)
                py = np.float32((_coefficient(coef, affine, scale, y, x, 1)
                                 + _coefficient(coef, affine, scale, y, x, 4) * q) / den)
                pz = np.float32((_coefficient(coef, affine, scale, y, x, 2)
                                 + _coefficient(coef, affine, scale, y, x, 5) * q) / den)
                if test is not None:
                    ok = is_measurable(np.float64(px), np.float64(py), np.float64(pz), test)
            if ok:
                out[y, x, 0], out[y, x, 1], out[y, x, 2] = px, py, pz
            else:
                out[y, x, 0] = out[y, x, 1] = out[y, x, 2] = np.nan
            if measured is not None:
                measured[y, x] = ok


@numba.njit(cache=True, inline="always")
def _coefficient(coef: NDArray[np.float64], affine: NDArray[np.float64], scale: float, y: int, x: int, j: int) -> float:
    """Coefficient `j` of pixel ``(y, x)`` (`_evaluate_rows`): tabled in `coef`, or the row's
    affine terms of `affine` times `scale`."""
    return coef[y, x, j] if coef.shape[0] > 0 else (affine[y, 0, j] + affine[y, 1, j] * x) * scale


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
    |u - p v|``) and re-expanded about the projector's middle line.  Along a row of a pinhole
    camera the unscaled coefficients are affine in ``x`` (``c1`` and ``d1`` are, the rest is
    fixed), so a row needs only ``2 x 8`` numbers and the kernel forms each pixel's from them,
    ``|c1(x)|`` (one a column) and ``|c2|`` (one a row); with camera distortion the grid is undistorted once, here, and every pixel's
    coefficients are kept (``(H, W, 8)``, 64 bytes a pixel).  All float64 (float32 coefficients
    lose up to 0.02 mm where the projector coordinate is ill-conditioned, as for columns on a
    vertical baseline); the points agree with `_solve`'s to float32 rounding.  With projector distortion each pixel's epipolar line in the projector is found
    once too (`_ProjectorLens`, 16 more bytes a pixel), and every call first undistorts the
    decoded coordinates (`_ideal_projector`).

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
        if has_distortion(calibration.camera.distortion):
            # undistorted, a row of the camera grid is no line: every pixel's coefficients, once
            self._coef = np.empty((h, w, 8), dtype=np.float64)
            for top in range(0, h, chunk_rows):
                yc, xc = np.mgrid[top:min(top + chunk_rows, h), 0:w].astype(np.float64)
                xc, yc = _undistort(calibration.camera, xc.ravel(), yc.ravel())
                coef, scale = self._coefficients(mc, u, u3, v, v3, xc, yc)
                self._coef[top:top + chunk_rows] = (coef * scale[:, None]).reshape(-1, w, 8)
            self._affine, self._norm_c1, self._norm_c2 = np.empty((0, 2, 8)), np.empty(0), np.empty(0)
        else:
            # along a pinhole camera's row the unscaled coefficients are affine in x: 2 x 8 a row
            self._coef = np.empty((0, 0, 8))
            y = np.arange(h, dtype=np.float64)
            at0, _ = self._coefficients(mc, u, u3, v, v3, np.zeros(h), y)
            at1, _ = self._coefficients(mc, u, u3, v, v3, np.ones(h), y)
            self._affine = np.stack([at0, at1 - at0], axis=1)
            self._norm_c2 = np.linalg.norm(np.outer(-y, mc[2, :3]) + mc[1, :3], axis=1)
            x = np.arange(w, dtype=np.float64)
            # |c1(x)| of every column, summed as a compiled loop would (the same float64 value)
            squares = [(mc[0, j] - x * mc[2, j]) ** 2 for j in range(3)]
            self._norm_c1 = np.sqrt(squares[0] + squares[1] + squares[2])
        self._lens = _ProjectorLens(calibration, orientation, chunk_rows) if has_distortion(
            calibration.projector.distortion) else None

    def _coefficients(self, mc: NDArray[np.float64], u: NDArray[np.float64], u3: float, v: NDArray[np.float64],
                      v3: float, xc: NDArray[np.float64], yc: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        """Unscaled coefficients ``(N, 8)`` of ideal camera pixels ``xc, yc`` ``(N,)`` (expanded
        about the projector's middle line) and their scale ``1 / (|c1| |c2|)`` ``(N,)``."""
        c1 = np.outer(-xc, mc[2, :3]) + mc[0, :3]
        c2 = np.outer(-yc, mc[2, :3]) + mc[1, :3]
        d1 = (xc * mc[2, 3] - mc[0, 3])[:, None]
        d2 = (yc * mc[2, 3] - mc[1, 3])[:, None]
        n = np.cross(c1, c2)
        a = d1 * np.cross(c2, u) + d2 * np.cross(u, c1) - u3 * n
        b = -d1 * np.cross(c2, v) - d2 * np.cross(v, c1) + v3 * n
        den_a, den_b = n @ u[:, None], -(n @ v[:, None])
        # about the projector's middle line, so neither term dwarfs the sum
        coef = np.concatenate([a + self._centre * b, b, den_a + self._centre * den_b, den_b], axis=1)
        return coef, 1.0 / (np.linalg.norm(c1, axis=1) * np.linalg.norm(c2, axis=1))

    def __call__(self, proj_map: ArrayLike, valid: ArrayLike | None = None, *,
                 other: ArrayLike | None = None) -> NDArray[np.float32]:
        """World points ``(H, W, 3)`` float32 of a projector-coordinate map (and, optionally, of
        the `other` projector coordinate, for an exact projector undistortion); as `triangulate`."""
        return self._evaluate(proj_map, valid, other, None)[0]

    @property
    def row_affine(self) -> bool:
        """Whether every camera row's points are ratios of functions affine in ``x`` (a pinhole
        camera and projector: `line_table` applies)."""
        return self._coef.shape[0] == 0 and self._lens is None

    def line_table(self, values: ArrayLike) -> NDArray[np.float64]:
        """For every camera row ``y`` and projector coordinate ``values[k]`` ``(K,)``, the point
        of each pixel ``x`` of the row as a ratio of affine functions of ``x``::

            P_j(x) = (t[y, k, j] + t[y, k, 3 + j] x) / (t[y, k, 6] + t[y, k, 7] x),   j = 0, 1, 2

        ``(H, K, 8)`` float64 (mm).  For a pattern of stripes the projector coordinate takes a
        few values only, so a compiled loop triangulates a pixel with 4 multiply-adds and one
        division (`sliscan.fastscan`).  The points equal `__call__`'s to float32 rounding.

        Raises
        ------
        InputError
            If the rig has lens distortion (`row_affine` is false).
        """
        if not self.row_affine:
            raise InputError("a rig with lens distortion has no per-row triangulation table: its rows are not lines")
        q = np.asarray(values, dtype=np.float64)[None, :, None] - self._centre
        at0, slope = self._affine[:, None, 0, :], self._affine[:, None, 1, :]  # (H, 1, 8): A + B x, unscaled
        table = np.empty((self.shape[0], q.shape[1], 8))
        for part, terms in ((0, at0), (3, slope)):
            table[..., part:part + 3] = terms[..., 0:3] + terms[..., 3:6] * q
        table[..., 6:7] = at0[..., 6:7] + at0[..., 7:8] * q
        table[..., 7:8] = slope[..., 6:7] + slope[..., 7:8] * q
        return table

    def measure(self, proj_map: ArrayLike, valid: ArrayLike | None, test: MeasurableTest, *,
                other: ArrayLike | None = None) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """`__call__` and `sliscan.pipeline.measurable` in one pass: the world points ``(H, W, 3)``
        float32 (mm), NaN but where measured, and the ``(H, W)`` bool mask of the measured ones
        (in `valid`, well-posed and passing `test`)."""
        points, measured = self._evaluate(proj_map, valid, other, test)
        assert measured is not None
        return points, measured

    def _evaluate(self, proj_map: ArrayLike, valid: ArrayLike | None, other: ArrayLike | None,
                  test: MeasurableTest | None) -> tuple[NDArray[np.float32], NDArray[np.bool_] | None]:
        """The points of `__call__` and, with a `test`, the mask of `measure` (else None)."""
        proj_map = _check_proj_map("proj_map", proj_map, self.shape)
        if valid is None:
            mask = np.ones(self.shape, dtype=bool)
        else:
            mask = np.ascontiguousarray(valid)
            if mask.dtype != np.bool_ or mask.shape != self.shape:
                raise InputError(f"valid must be a bool array of shape {self.shape} (H, W), got {mask.dtype} "
                                 f"{mask.shape}")
        xyz_w = np.empty((*self.shape, 3), dtype=np.float32)
        measured = None if test is None else np.empty(self.shape, dtype=bool)
        values = np.ascontiguousarray(proj_map if proj_map.dtype.kind == "f" else proj_map.astype(np.float64))
        if self._lens is not None:
            values = self._lens.ideal_map(values, mask, None if other is None else _check_proj_map(
                "other", other, self.shape))
        args = None if test is None else test.args
        over_rows(lambda rows: _evaluate_rows(self._coef, self._affine, self._norm_c1, self._norm_c2, self._centre,
                                              values, mask, self._quad, args, rows, xyz_w, measured),
                  self.shape[0], self.workers)
        return xyz_w, measured


class _ProjectorLens:
    """`Triangulator`'s undistortion of decoded projector coordinates: the epipolar line of every
    camera pixel (`_epipolar_lines`, ``(H, W, 2)`` float64, 16 bytes a pixel), computed once."""

    def __init__(self, calibration: Calibration, orientation: str, chunk_rows: int) -> None:
        self.calibration, self.orientation = calibration, orientation
        h, w = calibration.camera.shape
        self.lines = np.empty((h, w, 2), dtype=np.float64)
        for top in range(0, h, chunk_rows):
            yc, xc = np.mgrid[top:min(top + chunk_rows, h), 0:w].astype(np.float64)
            self.lines[top:top + chunk_rows] = _epipolar_lines(calibration, orientation, xc, yc)

    def ideal_map(self, proj_map: NDArray[np.floating], mask: NDArray[np.bool_],
                  other: NDArray | None) -> NDArray[np.float64]:
        """Ideal projector coordinates ``(H, W)`` of the decoded ones where `mask`; NaN elsewhere."""
        proj = np.where(mask, proj_map, np.nan).astype(np.float64, copy=False).ravel()
        ideal = _ideal_projector(self.calibration, self.orientation, proj, self.lines.reshape(-1, 2),
                                 None if other is None else np.asarray(other, dtype=np.float64).ravel())
        return ideal.reshape(mask.shape)


def triangulate(proj_map: ArrayLike, calibration: Calibration, *, orientation: str = "rows",
                valid: ArrayLike | None = None, chunk_rows: int = 64,
                other: ArrayLike | None = None) -> NDArray[np.float32]:
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
        coefficients, the camera pixel grid is first undistorted (`sliscan.lens.undistort`)
        into the ideal pinhole ``K [R | t]`` that `matrix` describes.  If the projector has
        distortion, each decoded coordinate (an observed, distorted projector pixel) is
        undistorted too: exactly where `other` gives the other coordinate, else by Newton's
        method along the pixel's epipolar line in the projector (`sliscan.lens.solve_on_lines`,
        to 1e-6 px; pixels where it does not converge are invalid).
    orientation : {"rows", "columns"}
        Which projector coordinate `proj_map` holds; selects the projector matrix's second
        (eq. 4.20) or first (eq. 4.11) row for the third equation.
    valid : (H, W) bool array, optional
        Pixels to triangulate.  Default: where `proj_map` is finite.
    chunk_rows : int
        Camera rows prepared together; bounds the temporary memory (a few hundred bytes per pixel).
    other : (H, W) float array, optional
        The other projector coordinate (`xp` for ``rows``, `yp` for ``columns``), NaN where
        undecoded, from a sequence coding both directions.  Used only to undistort the
        projector exactly when it has lens distortion (with a pinhole projector the other
        coordinate adds nothing to the three equations).

    Returns
    -------
    xyz_w : (H, W, 3) float32 array
        Xw, Yw, Zw in mm; NaN where invalid, undecoded, or where the camera ray is (nearly)
        parallel to the projector plane (see `MIN_PLANE_SINE`).  The scan's valid mask is
        ``np.isfinite(xyz_w[..., 0])``.

    Raises
    ------
    InputError
        If `proj_map`, `valid` or `other` is not (H, W) of the camera, `orientation` is unknown,
        or a device has distortion coefficients but no intrinsics.

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
    return Triangulator(calibration, orientation, chunk_rows=chunk_rows)(proj_map, valid, other=other)


def triangulate_points(xc: ArrayLike, yc: ArrayLike, proj: ArrayLike, calibration: Calibration, *,
                       orientation: str = "rows", other: ArrayLike | None = None) -> NDArray[np.float64]:
    """World points of scattered camera pixels and their projector coordinates.

    The same solver as `triangulate`, for points that are not a full camera grid.

    Parameters
    ----------
    xc, yc : (N,) float arrays
        Camera pixel coordinates (x = column, y = row, as observed: undistorted here if the
        camera has distortion coefficients); finite.
    proj : (N,) float array
        Projector row `yp` (``rows``) or column `xp` (``columns``) in pixels, as observed
        (undistorted here if the projector has distortion coefficients); NaN allowed.
    calibration : Calibration
    orientation : {"rows", "columns"}
    other : (N,) float array, optional
        The other projector coordinate of each point (`xp` for ``rows``), NaN where unknown:
        with projector distortion, the points that have it are undistorted exactly (see
        `triangulate`).

    Returns
    -------
    xyz_w : (N, 3) float64 array
        Xw, Yw, Zw in mm; NaN where `proj` is NaN, the projector undistortion does not
        converge, or the system is ill-conditioned.

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
    arrays = [np.asarray(v, dtype=np.float64) for v in (xc, yc, proj, *(() if other is None else (other,)))]
    shapes = [a.shape for a in arrays]
    names = "xc, yc and proj" if other is None else "xc, yc, proj and other"
    if any(a.ndim != 1 for a in arrays) or len(set(shapes)) != 1:
        raise InputError(f"{names} must be 1-D arrays of one length, got shapes {shapes}")
    if not (np.all(np.isfinite(arrays[0])) and np.all(np.isfinite(arrays[1]))):
        raise InputError("xc and yc must be finite")
    if any(np.any(np.isinf(a)) for a in arrays[2:]):
        raise InputError("proj and other must not have infinite values (use NaN for undecoded points)")
    if has_distortion(calibration.projector.distortion):
        lines = _epipolar_lines(calibration, orientation, arrays[0], arrays[1])
        arrays[2] = _ideal_projector(calibration, orientation, arrays[2], lines, None if other is None else arrays[3])
    return _solve(*arrays[:3], calibration, orientation)
