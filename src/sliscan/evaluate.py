"""Accuracy of a scan against the virtual rig's ground truth.

The figures every accuracy claim in sliscan rests on:

* **stripe accuracy**: of the pixels the projector lights, the fraction decoded to exactly the
  stripe the ground-truth projector row lies in;
* **far off**: of the lit pixels, the fraction with a valid point whose stripe is more than
  one stripe from the true one (issue 8's "wrong stripe": a neighbouring stripe along a
  border is a blurred border, two stripes off is a wrong code);
* **completeness**: the fraction of lit pixels that got a valid point;
* **3D error**: distance between each valid point and the true surface point of that pixel
  (mm): RMS, median, 95th percentile;
* **outliers**: valid points farther from the truth than one stripe's depth at that pixel
  (`stripe_depth`: a wrong stripe by more than one), or where the camera sees no surface;
* **gross outliers**: valid points whose projector coordinate (the point projected into the
  projector) is more than three stripes from the true one, or where the camera sees no
  surface: a wrong high bit, a point off in space rather than a blurred stripe border;
* **oracle**: the same errors for triangulating the ground-truth stripe (the staircase of the
  code itself): what a perfect decoder of this pattern would get;
* **fitted sphere**: centre and radius of the sphere that best fits the scan's points on a
  known sphere (the thesis's 122.555 mm target), as a metrologist would check a scanner.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass

import numpy as np
import scipy.ndimage
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from sliscan._validate import InputError
from sliscan.patterns import stripe_center, stripe_of_line
from sliscan.reconstruct import triangulate
from sliscan.simulate import Conditions, GroundTruth
from sliscan.types import Calibration, PatternSpec, ScanResult


@dataclass(frozen=True)
class Accuracy:
    """Scan accuracy figures (see the module docstring); lengths in mm, fractions in [0, 1]."""

    lit_pixels: int
    valid_pixels: int
    completeness: float
    stripe_accuracy: float
    wrong_stripe: float
    far_stripe: float
    outliers: float
    gross_outliers: float
    rms_mm: float
    median_mm: float
    p95_mm: float
    oracle_rms_mm: float
    oracle_median_mm: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def true_proj_line(truth: GroundTruth, spec: PatternSpec) -> NDArray[np.float64]:
    """Ground-truth projector line along the phase direction per camera pixel (NaN unlit)."""
    line = truth.proj[..., 1] if spec.orientation == "rows" else truth.proj[..., 0]
    return np.where(truth.lit, line, np.nan)


def true_stripes(truth: GroundTruth, spec: PatternSpec) -> NDArray[np.int64]:
    """Ground-truth stripe index per camera pixel, -1 where the projector does not light it."""
    return np.where(truth.lit, stripe_of_line(true_proj_line(truth, spec), spec), -1)


def _errors(points: NDArray[np.floating], truth: GroundTruth, mask: NDArray[np.bool_]) -> NDArray[np.float64]:
    diff = points[mask].astype(np.float64) - truth.points[mask].astype(np.float64)
    return np.linalg.norm(diff, axis=-1)


def error_map(result: ScanResult, truth: GroundTruth) -> NDArray[np.float32]:
    """3D error (mm) of every valid point that lies on a true surface, NaN elsewhere: the
    comparisons `surface_accuracy` takes its RMS, median and 95th percentile from.

    Returns
    -------
    (H, W) float32 array
        Distance between the scan's point and the true point of the pixel.
    """
    on_surface = result.valid & truth.surface
    errors = np.full(on_surface.shape, np.nan, dtype=np.float32)
    errors[on_surface] = _errors(result.points, truth, on_surface)
    return errors


#: The arrays of a ground-truth npz (``sliscan simulate --truth``) and their dtypes.
TRUTH_DTYPES = {"points": np.float32, "proj": np.float32, "lit": np.bool_, "surface": np.bool_,
                "albedo": np.float32, "edge": np.bool_}


def read_truth(path: str | os.PathLike, *, shape: tuple[int, int] | None = None) -> GroundTruth:
    """Read the ground truth written by ``sliscan simulate --truth`` (an npz of `GroundTruth`).

    Parameters
    ----------
    path : path
    shape : (H, W), optional
        The camera's image shape the truth must have.

    Raises
    ------
    InputError
        If the file is not such an npz, or its arrays do not share one ``(H, W)`` (or `shape`).
    """
    from sliscan.formats.npz import read_npz_arrays

    arrays = read_npz_arrays(path, TRUTH_DTYPES, what="a ground truth (sliscan simulate --truth)")
    want = shape if shape is not None else arrays["lit"].shape
    for name, arr in arrays.items():
        expected = (*want, 3 if name == "points" else 2) if name in ("points", "proj") else tuple(want)
        if arr.shape != expected:
            raise InputError(f"{path}: {name} has shape {arr.shape}, expected {expected} (the camera's H, W)")
    return GroundTruth(**arrays)


def _stats(errors: NDArray[np.float64]) -> tuple[float, float, float]:
    if errors.size == 0:
        return float("nan"), float("nan"), float("nan")
    return (float(np.sqrt(np.mean(errors**2))), float(np.median(errors)), float(np.percentile(errors, 95)))


def stripe_depth(truth: GroundTruth, spec: PatternSpec, calibration: Calibration) -> NDArray[np.float32]:
    """Length (mm) of each camera ray inside one stripe: the band of projector lines one
    stripe wide centred on the pixel's true projector line; the yardstick of the outliers.

    Defined on every pixel whose true point the projector's lines reach (`GroundTruth.proj`
    is finite: lit pixels, and those in shadow or at a blurred shadow border, where a scan
    may still return a point); 0 elsewhere, so any point there is an outlier.
    """
    line = (truth.proj[..., 1] if spec.orientation == "rows" else truth.proj[..., 0]).astype(np.float64)
    known = truth.surface & np.isfinite(line)
    half = 0.5 * spec.phase_lines / spec.stripes
    near = triangulate(line - half, calibration, orientation=spec.orientation, valid=known)
    far = triangulate(line + half, calibration, orientation=spec.orientation, valid=known)
    return np.nan_to_num(np.linalg.norm(far - near, axis=-1), nan=0.0).astype(np.float32)


def oracle_points(truth: GroundTruth, spec: PatternSpec, calibration: Calibration) -> NDArray[np.float32]:
    """Triangulation of the ground-truth stripe centre: a perfect decoder's points."""
    stripe = true_stripes(truth, spec)
    return triangulate(stripe_center(stripe, spec), calibration, orientation=spec.orientation, valid=stripe >= 0)


@dataclass(frozen=True)
class SurfaceAccuracy:
    """3D figures of any scan (any pattern kind) against the true surface; mm and fractions."""

    lit_pixels: int
    valid_pixels: int
    completeness: float
    outliers: float
    rms_mm: float
    median_mm: float
    p95_mm: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def surface_accuracy(result: ScanResult, truth: GroundTruth, quantum_mm: float | NDArray[np.floating]) -> SurfaceAccuracy:
    """Completeness, outliers and 3D error of a scan against the virtual rig's ground truth.

    Parameters
    ----------
    result : ScanResult
        The scan of a rendered capture (single- or multi-frame).
    truth : GroundTruth
        From `sliscan.simulate.render` / `render_sequence` for that capture.
    quantum_mm : float or (H, W) array
        A valid point farther than this from its pixel's true surface point is an outlier (so
        is any valid point where the camera sees no surface).  `accuracy` passes one stripe's
        depth of the composite pattern (`stripe_depth`); comparisons across pattern kinds pass
        one yardstick for all of them.
    """
    lit, valid = truth.lit, result.valid
    on_surface = valid & truth.surface
    errors = _errors(result.points, truth, on_surface)
    quantum = np.broadcast_to(np.asarray(quantum_mm, dtype=np.float64), valid.shape)[on_surface]
    off_surface = int((valid & ~truth.surface).sum())
    n_lit, n_valid = int(lit.sum()), int(valid.sum())
    rms, med, p95 = _stats(errors)
    return SurfaceAccuracy(lit_pixels=n_lit, valid_pixels=n_valid,
                           completeness=float((valid & lit).sum() / max(n_lit, 1)),
                           outliers=float((int((errors > quantum).sum()) + off_surface) / max(n_valid, 1)),
                           rms_mm=rms, median_mm=med, p95_mm=p95)


def gross_outliers(result: ScanResult, truth: GroundTruth, spec: PatternSpec, calibration: Calibration, *,
                   stripes: float = 3.0) -> float:
    """Share of the valid points that are more than `stripes` stripes of `spec` off: projected
    into the projector, the point's coordinate along the phase direction is farther than that
    from the true point's, or the camera sees no surface (or none the projector's lines reach)
    at its pixel.

    A point on its pixel's camera ray (as every scanned point is) is off by exactly its
    decoding error in projector lines, so this counts wrong codes by how wrong they are,
    whatever the stripes' depth there (which varies along the phase direction).
    """
    valid = result.valid
    axis = 1 if spec.orientation == "rows" else 0
    true_line = truth.proj[..., axis].astype(np.float64)
    known = valid & truth.surface & np.isfinite(true_line)
    scanned_line = calibration.projector.project(result.points[known])[:, axis]
    off = np.abs(scanned_line - true_line[known]) > stripes * spec.phase_lines / spec.stripes
    return float((int(off.sum()) + int((valid & ~known).sum())) / max(int(valid.sum()), 1))


def accuracy(result: ScanResult, truth: GroundTruth, spec: PatternSpec, calibration: Calibration) -> Accuracy:
    """Compare a composite-pattern scan with the virtual rig's ground truth.

    Parameters
    ----------
    result : ScanResult
        The scan of a rendered capture.
    truth : GroundTruth
        From `sliscan.simulate.render` for that capture.
    spec, calibration
        The pattern and the rig's calibration the scan used.
    """
    stripes = true_stripes(truth, spec)
    lit = stripes >= 0
    valid = result.valid
    correct = valid & lit & (result.stripe == stripes)
    surface = surface_accuracy(result, truth, stripe_depth(truth, spec, calibration))
    gross = gross_outliers(result, truth, spec, calibration)
    oracle = oracle_points(truth, spec, calibration)
    oracle_err = _errors(oracle, truth, lit & np.all(np.isfinite(oracle), axis=-1))
    orms, omed, _ = _stats(oracle_err)
    return Accuracy(lit_pixels=surface.lit_pixels, valid_pixels=surface.valid_pixels,
                    completeness=surface.completeness,
                    stripe_accuracy=float(correct.sum() / max(surface.lit_pixels, 1)),
                    wrong_stripe=float((valid & lit & ~correct).sum() / max(surface.valid_pixels, 1)),
                    far_stripe=float((valid & lit & (np.abs(result.stripe - stripes) > 1)).sum()
                                     / max(surface.lit_pixels, 1)),
                    outliers=surface.outliers, gross_outliers=gross, rms_mm=surface.rms_mm, median_mm=surface.median_mm,
                    p95_mm=surface.p95_mm, oracle_rms_mm=orms, oracle_median_mm=omed)


def fit_sphere(points: NDArray[np.floating]) -> tuple[NDArray[np.float64], float, float]:
    """Least-squares sphere through 3D points (mm).

    The algebraic fit (``|p|^2 = 2 c.p + k``, linear in the centre ``c`` and ``k``) starts a
    geometric fit that minimises the points' distances to the sphere.

    Parameters
    ----------
    points : (N, 3) array, N >= 4, not all on one plane

    Returns
    -------
    centre : (3,) float64, radius : float, rms : float
        Centre and radius in mm, and the RMS distance (mm) of the points to the sphere.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> d = rng.normal(size=(500, 3)); d /= np.linalg.norm(d, axis=1, keepdims=True)
    >>> centre, radius, rms = fit_sphere([10, -5, 800] + 122.555 * d)
    >>> round(radius, 3), bool(rms < 1e-6)
    (122.555, True)
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    a = np.c_[2 * p, np.ones(len(p))]
    solution = np.linalg.lstsq(a, np.sum(p**2, axis=1), rcond=None)[0]
    start = np.r_[solution[:3], np.sqrt(max(solution[3] + solution[:3] @ solution[:3], 0.0))]
    fit = least_squares(lambda v: np.linalg.norm(p - v[:3], axis=1) - v[3], start)
    return fit.x[:3], float(fit.x[3]), float(np.sqrt(np.mean(fit.fun**2)))


def robust_sphere(points: NDArray[np.floating], *, rounds: int = 5,
                  cut: float = 3.0) -> tuple[NDArray[np.float64], float, float, NDArray[np.bool_]]:
    """Sphere fit with outlier rejection, as metrology software fits a probed sphere.

    Fits all points (`fit_sphere`), then repeatedly refits the points whose distance to the
    sphere lies within `cut` robust standard deviations (1.4826 x the median absolute
    deviation) of the median distance.

    Returns
    -------
    centre : (3,) float64, radius : float, rms : float, inliers : (N,) bool
        Centre and radius (mm), RMS distance of the inliers to the sphere (mm), and which
        points were kept.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    keep = np.ones(len(p), bool)
    for _ in range(rounds):
        centre, radius, rms = fit_sphere(p[keep])
        distance = np.linalg.norm(p - centre, axis=1) - radius
        middle = np.median(distance[keep])
        sigma = 1.4826 * np.median(np.abs(distance[keep] - middle))
        inside = np.abs(distance - middle) <= cut * max(sigma, 1e-9)
        if np.array_equal(inside, keep) or inside.sum() < 4:
            break
        keep = inside
    return centre, radius, rms, keep


def sphere_fit(result: ScanResult, truth: GroundTruth, centre: ArrayLike, radius: float) -> tuple[float, float]:
    """Radius (mm) of the sphere fitted (`robust_sphere`) to the scan's valid points whose true
    point lies on the sphere of `centre` and `radius` (mm), and the fraction of those points the
    fit rejected as outliers.

    NaN, NaN when fewer than 100 such points exist.
    """
    true_distance = np.linalg.norm(truth.points - np.asarray(centre, dtype=np.float32), axis=-1)
    on_sphere = result.valid & truth.surface & (np.abs(true_distance - radius) < 1.0)
    if on_sphere.sum() < 100:
        return float("nan"), float("nan")
    _, fitted, _, inliers = robust_sphere(result.points[on_sphere])
    return fitted, float(1 - inliers.mean())


def carrier_transfer(spec: PatternSpec, conditions: Conditions, truth: GroundTruth) -> NDArray[np.float64]:
    """The virtual rig's true optical transfer of each carrier, relative to the largest (1).

    Closed form of `sliscan.simulate.render`'s linear chain at the median magnification of
    the lit pixels: the projector's Gaussian blur, its bilinear sampling of projector pixels
    (``sinc**2``), the camera pixel's box aperture (the mean of the sub-pixel samples) and the
    camera's Gaussian blur.  Exact for a fronto-parallel plane up to the spread of the
    magnification over the frame.

    Parameters
    ----------
    spec : PatternSpec
        The projected pattern (its `all_carriers`, cycles per projector width).
    conditions : Conditions
        The capture's blur and supersampling.
    truth : GroundTruth
        Its ground truth (for the projector pixels per camera pixel along the carriers).

    Returns
    -------
    (C,) float64 array
        Parallel to ``spec.all_carriers``.
    """
    axis = 0 if spec.orientation == "rows" else 1
    step = np.diff(truth.proj[..., axis], axis=1 - axis)
    lit = truth.lit[:, 1:] & truth.lit[:, :-1] if axis == 0 else truth.lit[1:] & truth.lit[:-1]
    scale = float(np.median(np.abs(step[lit & np.isfinite(step)])))
    fp = np.asarray(spec.all_carriers, dtype=np.float64) / spec.orthogonal_lines  # cycles per projector px
    fc = fp * scale  # cycles per camera px
    offsets = (np.arange(conditions.supersample) + 0.5) / conditions.supersample - 0.5
    transfer = (np.exp(-2 * np.pi**2 * conditions.projector_blur_px**2 * fp**2) * np.sinc(fp) ** 2
                * np.mean(np.cos(2 * np.pi * np.outer(fc, offsets)), axis=1)
                * np.exp(-2 * np.pi**2 * conditions.camera_blur_px**2 * fc**2))
    return transfer / transfer.max()


def clean_pixels(truth: GroundTruth, *, margin_px: int = 3, max_slope: float = 2.0) -> NDArray[np.bool_]:
    """Pixels whose ground truth a scan can fairly be held to, for comparing calibrations.

    Lit, not an `GroundTruth.edge`, at least `margin_px` pixels from any pixel that is not (the
    camera's blur mixes a depth or shadow edge into its neighbours: 3 px is 3 sigma of the
    default 1 px blur), and where one camera pixel spans at most `max_slope` projector pixels
    in either coordinate (on steeper, grazing surfaces the fringes alias within a pixel and a
    decoder's error is not the calibration's).

    Returns
    -------
    (H, W) bool array
    """
    clean = truth.lit & ~truth.edge
    if margin_px > 0:
        clean = scipy.ndimage.binary_erosion(clean, iterations=margin_px)
    slope = np.zeros(clean.shape)
    for k in range(2):
        gy, gx = np.gradient(truth.proj[..., k].astype(np.float64))
        slope = np.fmax(slope, np.hypot(gx, gy))
    return clean & (slope < max_slope)


def rigid_alignment(points: ArrayLike, truth: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The rotation and translation that best map `points` onto `truth` (least squares; Kabsch).

    A board calibration's world is its own estimate of the camera frame, whose orientation rests
    on the camera's principal point (uncertain by about a pixel for a narrow lens: a rotation of
    about 1 mrad): comparing shapes, not that frame, means comparing after this alignment.

    Parameters
    ----------
    points, truth : (N, 3) arrays
        Corresponding points (mm), N >= 3, not collinear.

    Returns
    -------
    rotation : (3, 3) float64 array
    translation : (3,) float64 array
        ``truth ~ points @ rotation.T + translation``.

    Examples
    --------
    >>> p = np.random.default_rng(0).normal(size=(10, 3))
    >>> turn = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    >>> r, t = rigid_alignment(p, p @ turn.T + [1, 2, 3])
    >>> bool(np.allclose(r, turn) and np.allclose(t, [1, 2, 3]))
    True
    """
    a, b = np.asarray(points, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape or len(a) < 3:
        raise InputError(f"points and truth must be (N, 3) arrays of one shape with N >= 3, got {a.shape}, {b.shape}")
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = (u @ flip @ vt).T
    return rotation, cb - ca @ rotation.T
