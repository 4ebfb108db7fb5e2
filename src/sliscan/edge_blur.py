"""The camera's blur, measured on the albedo edges of one composite-pattern capture.

A reflectance edge is as sharp as the camera's optics and pixels blur it, so its profile in
the capture tells the blur, whatever the pattern: within one code the pattern repeats every
demodulation window ``T`` along a line, so the capture divided by itself one window earlier,
``exp(g(u)) = I(u) / I(u - T)``, is 1 before an albedo step at ``e`` and the step's ratio
``r`` after it, and in between the step blurred by the camera.  Each profile is fitted with
``b + (a - b) Phi((u - e) / sigma)`` (the model the albedo-step detector renders its soft
steps with, `sliscan.demodulate._soften_steps`: pixel centres sampling a Gaussian-blurred
edge, the pixels' own aperture included in `sigma`), and the blur is the median of the
fitted `sigma` over the steps the fit explains.

Measured on the virtual rig (docs/accuracy.md, "A camera blurrier than assumed"): cameras
blurred by a Gaussian of 0.5 / 1 / 2 px measure 0.54 / 1.03-1.06 / 1.96 px (the pixel aperture
adds ``1 / 12`` to the variance: 0.58 / 1.04 / 2.02), on every pattern, scene and camera size
with a checker; the shared real captures' camera (a chessboard's white frames, 1280x1024)
0.73-0.88 px, as erf fits to the same edges.  A smooth albedo has too few steps to tell (fewer
than `BLUR_STEPS`), and its steep flanks, which the detector may take for steps, are no edges
of one blur: too few of them fit an edge, or their blurs spread too wide (`BLUR_SHARE`,
`BLUR_SPREAD`).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.special
from numpy.typing import NDArray

#: Pixels of each step's profile on either side of it: the fit sees the plateaus of an edge
#: blurred by up to about 3 px (``Phi(8 / 3) = 0.996``).
BLUR_REACH = 8
#: Only steps of at least this log height are measured (a reflectance ratio of 1.65): a lower
#: one's profile is mostly noise.
BLUR_HEIGHT = 0.5
#: Fewer well-fitted steps than this and the capture does not tell its blur (a smooth albedo
#: gives about a hundred, none of them an edge).
BLUR_STEPS = 200
#: At most this many steps are fitted (evenly spaced among those found): the median moves by
#: under 0.006 px against 20,000 of them, at a twentieth of the time (15 ms).
BLUR_SAMPLE = 1000
#: A fit explains its profile when its RMS residual is under this share of the step.
BLUR_MISFIT = 0.1
#: The capture tells its blur only where at least this share of the fits explain their profile
#: ...
BLUR_SHARE = 0.75
#: ... and their sigmas' interquartile range is at most this share of their median.  Measured
#: (fiftieth session): checkers seen by cameras of 1-2 px, 81-95 % fitted well, range 0.17-0.26
#: of the median (0.5 px: 70-84 %, 0.29-0.41); the shared real captures 80-98 %, 0.21-0.44; a
#: smooth albedo's steep flanks, which are no edges, 30-70 % at 1296x972 and 5 MP (the objects'
#: 79-81 %, their range 0.28 at a median of 1.05 px and 0.61 at 1.35 px).  Until then a smooth
#: albedo at 5 MP measured 1.2-1.7 px from its flanks, and the steps were found again for that
#: blur (the phase pattern's smooth sphere 2.29 -> 2.50 mm RMS).
BLUR_SPREAD = 0.5
#: Gauss-Newton iterations of the fit (the median within 0.001 px of 12 iterations' on the
#: virtual rig's steps).
BLUR_ITERATIONS = 8


def step_profiles(img: NDArray[np.float32], windows: NDArray[np.intp], steps: NDArray[np.bool_],
                  floor: float) -> NDArray[np.float64]:
    """The ratio ``I(u) / I(u - T)`` around each step, ``(N, 2 * BLUR_REACH)``.

    Parameters
    ----------
    img : (H, W) float32 array
        The capture, lines along axis 1.
    windows : (H,) int array
        Each line's window ``T`` (camera pixels).
    steps : (H, W) bool array
        The pixels where a step to measure lies (between pixel ``x - 1`` and ``x``).
    floor : float
        Intensities below it count as it (the detector's floor).

    Returns
    -------
    (N, 2 * BLUR_REACH) float64 array
        Row ``k`` at pixels ``x - BLUR_REACH .. x + BLUR_REACH - 1`` of its step, each divided by
        the mean of its first three (about 1 before the step); the steps whose profile and its
        window-earlier copy lie on the line, at most `BLUR_SAMPLE` of them.
    """
    rows, cols = np.nonzero(steps)
    t = np.asarray(windows, dtype=np.intp)[rows]
    inside = (cols - BLUR_REACH - t >= 0) & (cols + BLUR_REACH <= img.shape[1])
    rows, cols, t = rows[inside], cols[inside], t[inside]
    if rows.size > BLUR_SAMPLE:
        pick = np.linspace(0, rows.size - 1, BLUR_SAMPLE).astype(np.intp)
        rows, cols, t = rows[pick], cols[pick], t[pick]
    u = cols[:, None] + np.arange(-BLUR_REACH, BLUR_REACH)
    line = rows[:, None]
    here = np.maximum(img[line, u], floor).astype(np.float64)
    before = np.maximum(img[line, u - t[:, None]], floor).astype(np.float64)
    ratio = here / before
    return ratio / ratio[:, :3].mean(axis=1, keepdims=True)


def fit_blurred_edges(profiles: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64],
                                                              NDArray[np.float64]]:
    """Fit ``b + (a - b) Phi((u - e) / sigma)`` to each profile of `step_profiles`.

    ``u`` is measured from the step's nominal middle, half a pixel before its pixel.  Gauss-Newton
    on all profiles at once; `e` kept within 3 px and `sigma` within 0.2-5 px.

    Returns
    -------
    (sigma, centre, misfit) : three (N,) float64 arrays
        The blur (px), the edge's middle relative to the nominal one (px), and the fit's RMS
        residual as a share of the step ``|a - b|``.
    """
    n, m = profiles.shape
    u = np.arange(m) - m // 2 + 0.5
    low, high = profiles[:, :3].mean(axis=1), profiles[:, -3:].mean(axis=1)
    centre, sigma = np.zeros(n), np.ones(n)
    residual = np.zeros_like(profiles)
    for _ in range(BLUR_ITERATIONS):
        z = (u - centre[:, None]) / sigma[:, None]
        cdf, pdf = scipy.special.ndtr(z), np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)
        rise = (high - low)[:, None]
        residual = profiles - (low[:, None] + rise * cdf)
        jacobian = np.stack([1 - cdf, cdf, -rise * pdf / sigma[:, None], -rise * pdf * z / sigma[:, None]], axis=-1)
        normal = np.einsum("nki,nkj->nij", jacobian, jacobian) + 1e-9 * np.eye(4)
        step = np.linalg.solve(normal, np.einsum("nki,nk->ni", jacobian, residual)[..., None])[..., 0]
        low, high = low + step[:, 0], high + step[:, 1]
        centre, sigma = np.clip(centre + step[:, 2], -3, 3), np.clip(sigma + step[:, 3], 0.2, 5)
    misfit = np.sqrt(np.mean(residual**2, axis=1)) / np.maximum(np.abs(high - low), 1e-12)
    return sigma, centre, misfit


def edge_blur(img: NDArray[np.float32], windows: NDArray[np.intp], steps: NDArray[np.bool_],
              floor: float) -> float | None:
    """The camera's blur (Gaussian sigma, camera pixels, the pixels' aperture included) measured
    on the albedo steps at `steps` (as in `step_profiles`): the median of the fits that explain
    their profile (`BLUR_MISFIT`).  None where they are fewer than `BLUR_STEPS` or `BLUR_SHARE`
    of the fits, or spread wider than `BLUR_SPREAD`: steps that are no edges of one blur."""
    profiles = step_profiles(img, windows, steps, floor)
    if len(profiles) < BLUR_STEPS:
        return None
    sigma, centre, misfit = fit_blurred_edges(profiles)
    good = (misfit < BLUR_MISFIT) & (np.abs(centre) < 2) & (sigma > 0.2) & (sigma < 5)
    if good.sum() < max(BLUR_STEPS, BLUR_SHARE * len(profiles)):
        return None
    low, median, high = np.percentile(sigma[good], [25, 50, 75])
    return float(median) if high - low <= BLUR_SPREAD * median else None
