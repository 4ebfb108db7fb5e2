"""One frame to a point cloud: demodulate -> decode -> reconstruct (thesis section 6.1).

`Scanner` holds what does not change from frame to frame (the pattern, the calibration, the
carriers once found) so a stream of frames from one rig pays for it once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, check_image
from sliscan.decode import decode
from sliscan.demodulate import Carriers, Demodulated, demodulate
from sliscan.reconstruct import triangulate
from sliscan.types import Calibration, PatternSpec, ScanResult


def texture_from_dc(dc: NDArray[np.floating]) -> NDArray[np.float32]:
    """Texture in [0, 1] from the local mean: scaled so the 99.5th percentile is white."""
    top = float(np.percentile(dc[::4, ::4], 99.5)) if dc.size else 1.0
    return np.clip(dc / max(top, 1e-6), 0, 1).astype(np.float32)


def inside_projector(points: NDArray[np.floating], calibration: Calibration, spec: PatternSpec) -> NDArray[np.bool_]:
    """Which points the projector can light: finite, in front of camera and projector, and
    projecting inside the projector's image along the direction the stripes do not code.

    A wrong stripe on a pixel the projector never reached (above its frustum, in shadow)
    otherwise triangulates to a point metres away, where the camera ray meets that stripe's
    plane outside the projector's image.

    Parameters
    ----------
    points : (H, W, 3) array
        World points in mm, NaN where invalid.
    """
    finite = np.all(np.isfinite(points), axis=-1)
    xyz = np.where(finite[..., None], points, 0).astype(np.float64)
    ok = finite.copy()
    for device in (calibration.camera, calibration.projector):
        m = device.matrix / np.linalg.norm(device.matrix[2, :3])
        sign = np.sign(np.linalg.det(device.matrix[:, :3]))
        ok &= sign * (xyz @ m[2, :3] + m[2, 3]) > 0  # depth > 0
    xp = calibration.projector.project(xyz)
    w, h = calibration.projector.size
    across, lines = (xp[..., 0], w) if spec.orientation == "rows" else (xp[..., 1], h)
    margin = 0.02 * lines
    return ok & (across > -0.5 - margin) & (across < lines - 0.5 + margin)


def device_centre(matrix: NDArray[np.floating]) -> NDArray[np.float64]:
    """Optical centre (mm) of a 3x4 projection matrix: its right null vector."""
    _, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    return vt[-1, :3] / vt[-1, 3]


def triangulation_angle(points: NDArray[np.floating], calibration: Calibration) -> NDArray[np.float64]:
    """Angle (degrees) between the camera's and the projector's rays at each point.

    Depth precision falls with this angle, and a wrong stripe on a ray almost parallel to its
    plane lands metres away: points under a few degrees are not measurements.
    """
    a = points - device_centre(calibration.camera.matrix)
    b = points - device_centre(calibration.projector.matrix)
    cos = np.sum(a * b, axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


@dataclass
class Scanner:
    """A reusable single-shot scanner for one pattern and one calibrated rig.

    Parameters
    ----------
    spec : PatternSpec
        The projected composite pattern.
    calibration : Calibration
        Camera and projector matrices; the capture must have the camera's size.
    method : {"window", "bandpass"}
        Demodulator (see `sliscan.demodulate`).
    decode_options : dict
        Keyword arguments for `sliscan.decode.decode` (thresholds).
    reuse_carriers : bool
        Detect the carriers in the first frame and reuse them for later frames.
    min_angle_deg : float
        Points whose camera and projector rays meet at less than this angle are dropped
        (`triangulation_angle`).

    Examples
    --------
    >>> from sliscan import simulate, patterns
    >>> rig = simulate.virtual_rig(camera_size=(640, 480), projector_size=(1024, 768))
    >>> spec = patterns.default_spec((1024, 768))
    >>> capture = simulate.render(rig, simulate.plane_scene(), patterns.render_pattern(spec),
    ...                           simulate.Conditions(seed=1))
    >>> result = Scanner(spec, rig.calibration).scan(capture.image)
    >>> bool(abs(np.nanmedian(result.points[..., 2]) - 800) < 20)
    True
    """

    spec: PatternSpec
    calibration: Calibration
    method: str = "window"
    decode_options: dict[str, Any] = field(default_factory=dict)
    reuse_carriers: bool = False
    min_angle_deg: float = 2.0
    _carriers: Carriers | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.method not in ("window", "bandpass"):
            raise InputError(f"method must be 'window' or 'bandpass', got {self.method!r}")
        if tuple(self.calibration.projector.size) != tuple(self.spec.projector_size):
            w, h = self.calibration.projector.size
            pw, ph = self.spec.projector_size
            raise InputError(f"pattern is for a {pw}x{ph} projector but the calibration's projector is {w}x{h}")

    def demodulate(self, image: ArrayLike) -> tuple[Demodulated, Carriers]:
        """Carrier envelopes of one frame (checked against the camera size)."""
        img = check_image("capture", image, shape=self.calibration.camera.shape)
        carriers = self._carriers if self.reuse_carriers else None
        demod, found = demodulate(img, self.spec, method=self.method, carriers=carriers)
        if self.reuse_carriers:
            self._carriers = found
        return demod, found

    def scan(self, image: ArrayLike) -> ScanResult:
        """Point cloud of one camera frame of the composite pattern.

        Parameters
        ----------
        image : (H, W) array
            uint8, uint16 or float in [0, 1], of the calibrated camera's size; not modified.

        Returns
        -------
        ScanResult
        """
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        demod, _ = self.demodulate(image)
        t1 = time.perf_counter()
        decoded = decode(demod, self.spec, **self.decode_options)
        t2 = time.perf_counter()
        points = triangulate(decoded.proj_map, self.calibration, orientation=self.spec.orientation,
                             valid=decoded.valid)
        valid = decoded.valid & inside_projector(points, self.calibration, self.spec)
        with np.errstate(invalid="ignore"):
            valid &= triangulation_angle(points, self.calibration) >= self.min_angle_deg
        points[~valid] = np.nan
        t3 = time.perf_counter()
        timings.update(demodulate=t1 - t0, decode=t2 - t1, triangulate=t3 - t2, total=t3 - t0)
        return ScanResult(points=points, valid=valid, texture=texture_from_dc(demod.dc),
                          proj_map=np.where(valid, decoded.proj_map, np.nan).astype(np.float32),
                          stripe=np.where(valid, decoded.stripe, -1).astype(np.int16),
                          confidence=decoded.confidence, timings=timings)


def scan(image: ArrayLike, spec: PatternSpec, calibration: Calibration, **options: Any) -> ScanResult:
    """Scan one frame: ``Scanner(spec, calibration, **options).scan(image)``."""
    return Scanner(spec, calibration, **options).scan(image)
