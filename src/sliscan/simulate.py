"""Virtual projector-camera rig: scenes, physically based captures, and the thesis's views.

The simulator stands in for a real scanner in tests and benchmarks, so it models what a real
capture suffers (thesis eq. 3.2 and chapter 5), in this order:

1. projector drive ``d`` -> linear light ``black + (1 - black) * d**gamma``;
2. projector optical blur: a Gaussian in projector pixels, light spreading past the image edge;
   with a depth of field (`Conditions.projector_focus_mm`) its sigma grows with each lit point's
   distance from the focal plane (thin lens), blended between blurs `DEFOCUS_STEP_PX` apart;
3. for every camera sub-pixel ray: the nearest surface hit ``X``, its projector coordinates
   ``(xp, yp)`` by the projector matrix, the blurred light sampled bilinearly there (none
   outside the projector's frustum), a shadow ray from ``X`` to the projector centre,
   Lambert's ``cos(incidence)`` on the surface normal and, optionally, inverse-square falloff;
4. camera signal ``exposure * albedo(X) * (light * cos * falloff + ambient)`` (eq. 3.2:
   ``I_c = alpha (I_p + beta)``); ambient light is diffuse: never shadowed, never foreshortened;
5. the mean of the sub-pixels (the pixel's box aperture), then camera optical blur (Gaussian in
   camera pixels; with `Conditions.camera_focus_mm`, each pixel's by the depth its centre sees);
6. shot noise (Poisson in electrons), read noise (Gaussian), saturation and quantisation.

Conventions (DESIGN.md): the world frame is the camera frame of `virtual_rig`, in millimetres,
``x`` right, ``y`` down, ``z`` forward (OpenCV); pixel centres at integers; images ``(H, W)``
float32 in [0, 1].  Every rig is built from a `Calibration` (two 3x4 pinhole matrices, no lens
distortion), so a real scanner's calibration can drive the simulator too.

Scenes are surfaces with one vectorised method, ``intersect(origins, dirs) -> (t, normal)``,
used for camera rays and shadow rays alike.  `Plane`, `Sphere`, `Box` and `Cylinder` are analytic;
`Union` keeps the nearest hit; `Mat5Surface` triangulates a scanned point grid (chapter 5) and
intersects rays exactly with its triangles, found through a perspective bin grid (see its
docstring).

`projector_view` and `camera_view` are vectorised versions of the thesis's simulation program
(appendix 1.1-1.3): a mat5 point grid splatted into projector and camera pixels.

References
----------
P. Gupta, "Gray Code Composite Pattern Structured Light Illumination", MS thesis, University of
Kentucky, 2007, https://uknowledge.uky.edu/gradschool_theses/438: eq. 3.2 (capture model),
section 4.2 (rig), chapter 5 and appendix 1.1-1.3 (simulation program).
T. Möller and B. Trumbore, "Fast, minimum storage ray-triangle intersection", Journal of
Graphics Tools 2(1), 1997. :doi:`10.1080/10867651.1997.10487468`
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol, cast

import numpy as np
import scipy.linalg
import scipy.ndimage
import scipy.special
import scipy.spatial
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, check_finite_matrix, check_image
from sliscan.lens import distort, has_distortion, undistort
from sliscan.targets import Board, CircleTarget
from sliscan.types import Calibration, Device

__all__ = [
    "BoardAlbedo",
    "Box",
    "Capture",
    "CheckerAlbedo",
    "Conditions",
    "DiscAlbedo",
    "GroundTruth",
    "Mat5Surface",
    "Pinhole",
    "Plane",
    "Rig",
    "SequenceCapture",
    "SmoothAlbedo",
    "Sphere",
    "Surface",
    "TracedScene",
    "UniformAlbedo",
    "Union",
    "board_scene",
    "calibration_poses",
    "camera_view",
    "circle_grid_scene",
    "circle_target_scene",
    "plane_scene",
    "projector_rows",
    "projector_view",
    "render",
    "render_sequence",
    "sphere_scene",
    "steps_scene",
    "tilted_plane_scene",
    "virtual_rig",
]

#: Smallest accepted ray parameter (in units of the ray direction's length): no self-hits.
_T_MIN = 1e-9
#: Shadow rays start this far (mm) off the surface, along its normal, toward the light.
_SHADOW_OFFSET_MM = 1e-3
#: Ray samples traced at once; bounds memory to a few hundred MB per chunk.
_CHUNK_SAMPLES = 1 << 19


# --------------------------------------------------------------------------------------------
# Devices and the rig
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Pinhole:
    """A pinhole device (camera or projector): ``x ~ K [R | t] [Xw, Yw, Zw, 1]``, optionally
    behind a lens that distorts (`sliscan.lens`).

    Attributes
    ----------
    K : (3, 3) float64 array
        Intrinsics: focal lengths and principal point in pixels, ``K[2] = [0, 0, 1]``.
    R : (3, 3) float64 array
        World -> device rotation (rows: the device's x, y, z axes in world coordinates).
    t : (3,) float64 array
        World -> device translation in mm.
    size : (W, H) tuple of int
        Image size in pixels.
    distortion : (5,) float64 array or None
        OpenCV lens distortion ``k1, k2, p1, p2, k3`` relative to `K`; None (or all zeros,
        stored as None) for an ideal pinhole.  `project` then returns the distorted pixel and
        `rays` undistorts the pixel first.
    """

    K: NDArray[np.float64]
    R: NDArray[np.float64]
    t: NDArray[np.float64]
    size: tuple[int, int]
    distortion: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        K = check_finite_matrix("K", self.K, (3, 3))
        R = check_finite_matrix("R", self.R, (3, 3))
        t = check_finite_matrix("t", np.ravel(self.t), (3,))
        if not (K[0, 0] > 0 and K[1, 1] > 0 and np.array_equal(K[2], [0.0, 0.0, 1.0]) and K[1, 0] == 0):
            raise InputError(
                f"K must be upper triangular with positive focal lengths and K[2] = [0, 0, 1], got {K.tolist()}"
            )
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0):
            raise InputError("R must be a rotation matrix (orthonormal, determinant +1)")
        w, h = (int(v) for v in self.size)
        if w < 2 or h < 2:
            raise InputError(f"size must be at least 2x2 (W, H), got {self.size}")
        dist = None
        if self.distortion is not None:
            dist = check_finite_matrix("distortion", np.ravel(self.distortion), (5,))
            dist = dist if has_distortion(dist) else None
        for name, arr in (("K", K), ("R", R), ("t", t), ("distortion", dist)):
            if arr is not None:
                arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "size", (w, h))

    @classmethod
    def from_matrix(cls, matrix: ArrayLike, size: tuple[int, int]) -> Pinhole:
        """Split a 3x4 projection matrix (any scale or sign) into ``K``, ``R``, ``t`` (RQ), no lens.

        Raises
        ------
        InputError
            If the left 3x3 block is singular (not a pinhole projection).
        """
        P = check_finite_matrix("matrix", matrix, (3, 4))
        det = np.linalg.det(P[:, :3])
        if abs(det) <= 1e-12 * np.abs(P[:, :3]).max() ** 3:
            raise InputError("matrix is not a pinhole projection (its left 3x3 block is singular)")
        P = P * np.sign(det)  # points in front of the device then have positive depth
        K, R = scipy.linalg.rq(P[:, :3])
        flip = np.diag(np.sign(np.diag(K)))
        K, R = K @ flip, flip @ R
        scale = K[2, 2]
        K = K / scale
        K[1, 0] = K[2, 0] = K[2, 1] = 0.0
        return cls(K=K, R=R, t=np.linalg.solve(K, P[:, 3]) / scale, size=size)

    @property
    def matrix(self) -> NDArray[np.float64]:
        """``(3, 4)`` projection matrix ``K [R | t]``, world (mm) -> pixel."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def centre(self) -> NDArray[np.float64]:
        """``(3,)`` optical centre in world coordinates (mm)."""
        return -self.R.T @ self.t

    @property
    def axis(self) -> NDArray[np.float64]:
        """``(3,)`` unit optical axis (viewing direction) in world coordinates."""
        return self.R[2].copy()

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)`` of the device's images."""
        return (self.size[1], self.size[0])

    def project(self, xyz: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixel coordinates of world points.

        Parameters
        ----------
        xyz : (..., 3) array
            World points in mm.

        Returns
        -------
        xy : (..., 2) float64 array
            Pixel ``(x, y)`` (through the lens, with `distortion`); only meaningful where
            `depth` > 0.
        depth : (...) float64 array
            Distance in front of the device along its axis, in mm.
        """
        cam = (np.asarray(xyz, dtype=np.float64) - self.centre) @ self.R.T
        depth = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            xy = cam[..., :2] / depth[..., None] @ self.K[:2, :2].T + self.K[:2, 2]
            if self.distortion is not None:
                xy = distort(xy, self.K, self.distortion)
        return xy, depth

    def rays(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.float64]:
        """World directions of the rays through pixel positions ``(x, y)``, scaled to unit depth.

        A point at ray parameter ``s`` lies ``s`` mm in front of the device, along its axis.

        Parameters
        ----------
        x, y : (N,) arrays
            Pixel coordinates (centres at integers), as observed: with `distortion` they are
            undistorted first (`sliscan.lens.undistort`, ~1e-7 px).

        Returns
        -------
        dirs : (N, 3) float64 array
        """
        pix = np.stack([np.asarray(x, np.float64), np.asarray(y, np.float64), np.ones(np.shape(x))], axis=-1)
        if self.distortion is not None:
            pix[..., :2] = undistort(pix[..., :2], self.K, self.distortion)
        return pix @ np.linalg.inv(self.K).T @ self.R


@dataclass(frozen=True, eq=False)
class Rig:
    """A camera and a projector: the `Calibration` plus its pinhole decomposition.

    Parameters
    ----------
    calibration : Calibration
        Camera and projector 3x4 world (mm) -> pixel matrices and image sizes.  A device with
        lens distortion must carry its intrinsics, with ``matrix = intrinsics @ [R | t]``: the
        camera's rays leave through undistorted pixel positions, and the projector lights a
        point from its distorted pixel (the ground truth's `proj` is that pixel, what a decoder
        measures).
    working_distance_mm : float, optional
        Depth along the camera axis at which the rig is set up: the reference distance of the
        inverse-square falloff (there `Conditions.exposure` holds exactly).  Default: where the
        camera and projector optical axes pass closest.

    Attributes
    ----------
    camera, projector : Pinhole
        ``K``, ``R``, ``t``, ``centre`` (mm), ``axis`` of each device.

    Raises
    ------
    InputError
        If a device has lens distortion without matching intrinsics, a matrix is not a pinhole
        projection, or no working distance is given while the optical axes are parallel.
    """

    calibration: Calibration
    working_distance_mm: float | None = None
    camera: Pinhole = field(init=False, repr=False)
    projector: Pinhole = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("camera", "projector"):
            device: Device = getattr(self.calibration, name)
            pinhole = Pinhole.from_matrix(device.matrix, device.size)
            if has_distortion(device.distortion):
                if device.intrinsics is None or not np.allclose(pinhole.K, device.intrinsics, rtol=1e-6,
                                                                               atol=1e-9 * pinhole.K[0, 0]):
                    raise InputError(f"{name}: lens distortion needs the intrinsics K it goes with, and matrix = "
                                     "K [R | t]")
                pinhole = replace(pinhole, distortion=device.distortion)
            object.__setattr__(self, name, pinhole)
        wd = self.working_distance_mm
        if wd is None:
            wd = _axes_crossing_depth(self.camera, self.projector)
        if not (math.isfinite(wd) and wd > 0):
            raise InputError(f"working_distance_mm must be positive, got {wd}")
        object.__setattr__(self, "working_distance_mm", float(wd))

    @property
    def working_point(self) -> NDArray[np.float64]:
        """``(3,)`` world point on the camera axis at the working distance (mm)."""
        return self.camera.centre + cast(float, self.working_distance_mm) * self.camera.axis

    @property
    def projector_distance_mm(self) -> float:
        """Distance from the projector centre to `working_point`: the falloff reference (mm)."""
        return float(np.linalg.norm(self.working_point - self.projector.centre))


def _axes_crossing_depth(camera: Pinhole, projector: Pinhole) -> float:
    """Depth along the camera axis of the closest approach of the two optical axes (mm)."""
    a, b = camera.axis, projector.axis
    cos = float(a @ b)
    if 1 - cos**2 < math.sin(math.radians(0.1)) ** 2:
        raise InputError("camera and projector optical axes are parallel; give working_distance_mm")
    w = camera.centre - projector.centre
    return float((cos * (b @ w) - a @ w) / (1 - cos**2))


def virtual_rig(
    *,
    camera_size: tuple[int, int] = (2592, 1944),
    projector_size: tuple[int, int] = (1024, 768),
    distance_mm: float = 800.0,
    baseline_mm: float = 200.0,
    camera_fov_deg: float = 30.0,
    projector_fov_deg: float | None = None,
    projector_above: bool = True,
    baseline_axis: str = "vertical",
    margin: float = 0.05,
    camera_distortion: ArrayLike | None = None,
    projector_distortion: ArrayLike | None = None,
    projector_roll_deg: float = 0.0,
    projector_offset_mm: float = 0.0,
) -> Rig:
    """The thesis's rig (section 4.2): a projector displaced vertically from the camera.

    The camera sits at the world origin looking along +Z.  The projector's centre is
    `baseline_mm` above (``y = -baseline_mm``) or below it, pitched about the x axis so that
    its optical axis crosses the camera's at `distance_mm`; that crossing point projects to
    the centre of both images.  Both devices have square pixels and centred principal points.
    With ``baseline_axis="horizontal"`` the projector sits beside the camera instead (left
    for `projector_above`, ``x = -baseline_mm``), turned about the y axis: the rig for
    patterns whose stripes code projector columns (``orientation="columns"``).

    Parameters
    ----------
    camera_size, projector_size : (W, H) tuple of int
        Image sizes in pixels (thesis: a 2592x1944 camera and a 1024x768 projector).
    distance_mm : float
        Working distance: where the optical axes cross, in mm.
    baseline_mm : float
        Vertical distance between the optical centres, in mm.
    camera_fov_deg : float
        Camera field of view across its width, in degrees.  The default 30 degrees sees
        429 x 322 mm at 800 mm, which a 245 mm sphere (the thesis's target) fills well.
    projector_fov_deg : float, optional
        Projector field of view across its width, in degrees.  Default: the narrowest one
        whose image covers the camera's whole view of the plane ``Z = distance_mm``, with
        `margin` to spare on the tighter side.
    projector_above : bool
        Projector above the camera (the thesis's set-up) or below it; left or right of it
        with a horizontal baseline.
    baseline_axis : {"vertical", "horizontal"}
        Direction of the baseline in the camera's image.
    margin : float
        Relative spare coverage for the default projector field of view.
    camera_distortion, projector_distortion : (5,) arrays, optional
        Lens distortion ``k1, k2, p1, p2, k3`` (OpenCV's model, `sliscan.lens`) of each device,
        relative to its intrinsics; default none.  The default projector field of view then
        covers the camera's view through both lenses.
    projector_roll_deg : float
        The projector turned about its own optical axis by this angle (degrees; positive turns
        its image clockwise as the camera sees it), as a real rig's mounting leaves it: the
        stripes then cross the camera's lines obliquely everywhere.  The default field of view
        still covers the camera's view.
    projector_offset_mm : float
        The projector moved this far across the baseline (to the camera's right, +x, for a
        vertical baseline; down, +y, for a horizontal one), still aimed at the working point: a
        rig whose baseline is not straight along the camera's columns (rows), so that depth
        moves the carriers.

    Returns
    -------
    Rig
        Its `calibration` carries both matrices ``K [R | t]`` with ``intrinsics`` set.

    Examples
    --------
    >>> rig = virtual_rig(camera_size=(320, 240), projector_size=(128, 96))
    >>> rig.projector.centre.round(6).tolist()
    [0.0, -200.0, 0.0]
    >>> xy, _ = rig.projector.project([0.0, 0.0, 800.0])
    >>> xy.round(6).tolist()
    [63.5, 47.5]
    """
    for name, value in (("distance_mm", distance_mm), ("baseline_mm", baseline_mm)):
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"{name} must be positive, got {value}")
    for name, fov in (("camera_fov_deg", camera_fov_deg), ("projector_fov_deg", projector_fov_deg)):
        if fov is not None and not 0 < fov < 180:
            raise InputError(f"{name} must lie in (0, 180), got {fov}")
    if not 0 <= margin < 1:
        raise InputError(f"margin must lie in [0, 1), got {margin}")
    if not (math.isfinite(projector_roll_deg) and abs(projector_roll_deg) < 45):
        raise InputError(f"projector_roll_deg must lie in (-45, 45), got {projector_roll_deg}")
    if not math.isfinite(projector_offset_mm):
        raise InputError(f"projector_offset_mm must be finite, got {projector_offset_mm}")
    (wc, hc), (wp, hp) = camera_size, projector_size
    camera = Pinhole(K=_intrinsics(_focal(wc, camera_fov_deg), wc, hc), R=np.eye(3), t=np.zeros(3), size=(wc, hc),
                     distortion=None if camera_distortion is None else np.asarray(camera_distortion, np.float64))
    lens_p = None if projector_distortion is None else np.asarray(projector_distortion, np.float64)

    if baseline_axis not in ("vertical", "horizontal"):
        raise InputError(f"baseline_axis must be 'vertical' or 'horizontal', got {baseline_axis!r}")
    sign = -1.0 if projector_above else 1.0
    vertical = baseline_axis == "vertical"
    centre = np.array([projector_offset_mm, sign * baseline_mm, 0.0] if vertical
                      else [sign * baseline_mm, projector_offset_mm, 0.0])
    z_axis = np.array([0.0, 0.0, distance_mm]) - centre
    z_axis /= np.linalg.norm(z_axis)
    kept = 0 if vertical else 1  # the camera axis across the baseline, made square to the projector's axis
    across = np.eye(3)[kept] - z_axis[kept] * z_axis
    across /= np.linalg.norm(across)
    R = (np.stack([across, np.cross(z_axis, across), z_axis]) if vertical
         else np.stack([np.cross(across, z_axis), across, z_axis]))
    cos, sin = math.cos(math.radians(projector_roll_deg)), math.sin(math.radians(projector_roll_deg))
    R = np.array([[cos, sin, 0.0], [-sin, cos, 0.0], [0.0, 0.0, 1.0]]) @ R  # about the projector's own axis
    if projector_fov_deg is None:
        corners = np.array([[-0.5, -0.5], [wc - 0.5, -0.5], [-0.5, hc - 0.5], [wc - 0.5, hc - 0.5]])
        world = distance_mm * camera.rays(corners[:, 0], corners[:, 1])
        local = (world - centre) @ R.T
        normalised = local[:, :2] / local[:, 2:]
        if lens_p is not None:  # where the projector's lens puts the corners, in focal lengths
            normalised = distort(normalised, np.eye(3), lens_p)
        reach = np.abs(normalised).max(axis=0)
        focal = min(wp / 2 / reach[0], hp / 2 / reach[1]) / (1 + margin)
    else:
        focal = _focal(wp, projector_fov_deg)
    projector = Pinhole(K=_intrinsics(focal, wp, hp), R=R, t=-R @ centre, size=(wp, hp), distortion=lens_p)

    calibration = Calibration(
        camera=Device(camera.matrix, camera.size, intrinsics=camera.K, distortion=camera.distortion),
        projector=Device(projector.matrix, projector.size, intrinsics=projector.K, distortion=projector.distortion),
        extra={"source": "sliscan.simulate.virtual_rig", "distance_mm": distance_mm, "baseline_mm": baseline_mm,
               "baseline_axis": baseline_axis},
    )
    return Rig(calibration, working_distance_mm=distance_mm)


def _focal(width: int, fov_deg: float) -> float:
    """Focal length in pixels for a field of view `fov_deg` across `width` pixels."""
    return width / 2 / math.tan(math.radians(fov_deg) / 2)


def _intrinsics(focal: float, width: int, height: int) -> NDArray[np.float64]:
    """Square-pixel ``K`` with the principal point at the image centre."""
    return np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------------------------
# Surfaces
# --------------------------------------------------------------------------------------------


class Surface(Protocol):
    """Anything a ray can hit."""

    def intersect(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Nearest hit along each ray ``origins + t * dirs`` with ``t > 0``.

        Parameters
        ----------
        origins, dirs : (N, 3) arrays
            Ray origins (mm) and directions (any non-zero length).

        Returns
        -------
        t : (N,) float64 array
            Ray parameter of the hit, in units of ``|dirs|``; ``inf`` where the ray misses.
        normal : (N, 3) float64 array
            Unit surface normal at the hit, facing the ray's origin (``normal . dirs <= 0``).
        """
        ...


def _vec3(name: str, value: ArrayLike) -> tuple[float, float, float]:
    arr = check_finite_matrix(name, np.ravel(value), (3,))
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _as_rays(origins: ArrayLike, dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or o.shape != d.shape:
        raise InputError(f"origins and dirs must both have shape (N, 3), got {o.shape} and {d.shape}")
    return o, d


def _dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise dot products of (N, 3) arrays."""
    return np.einsum("ij,ij->i", a, b)


def _facing(normal: NDArray[np.float64], d: NDArray[np.float64]) -> NDArray[np.float64]:
    """`normal` (N, 3) flipped where needed so that it faces against the ray directions."""
    return np.where((_dot(normal, d) > 0)[:, None], -normal, normal)


def _first_positive(*roots: NDArray[np.float64]) -> NDArray[np.float64]:
    """Element-wise the first root (in the order given) above `_T_MIN`; ``inf`` if none."""
    t = np.full(roots[0].shape, np.inf)
    for r in reversed(roots):
        t = np.where(r > _T_MIN, r, t)
    return t


@dataclass(frozen=True)
class Plane:
    """An infinite plane through `point` with normal `normal` (normalised on creation).

    Examples
    --------
    >>> t, n = Plane.at_z(500.0).intersect([[0.0, 0.0, 0.0]], [[0.1, 0.0, 1.0]])
    >>> float(t[0]), n[0].tolist()
    (500.0, [0.0, 0.0, -1.0])
    """

    point: tuple[float, float, float]
    normal: tuple[float, float, float]

    def __post_init__(self) -> None:
        n = np.array(_vec3("normal", self.normal))
        length = np.linalg.norm(n)
        if length == 0:
            raise InputError("normal must be non-zero")
        object.__setattr__(self, "point", _vec3("point", self.point))
        object.__setattr__(self, "normal", tuple(float(v) for v in n / length))

    @classmethod
    def at_z(cls, z_mm: float) -> Plane:
        """The fronto-parallel plane ``Z = z_mm`` (mm)."""
        return cls((0.0, 0.0, float(z_mm)), (0.0, 0.0, -1.0))

    def intersect(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """See `Surface.intersect`."""
        o, d = _as_rays(origins, dirs)
        n = np.array(self.normal)
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((np.array(self.point) - o) @ n) / denom
        return _first_positive(t), _facing(np.broadcast_to(n, d.shape), d)


@dataclass(frozen=True)
class Sphere:
    """A sphere of `radius` (mm) around `center` (mm)."""

    center: tuple[float, float, float]
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3("center", self.center))
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise InputError(f"radius must be positive, got {self.radius}")
        object.__setattr__(self, "radius", float(self.radius))

    def intersect(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """See `Surface.intersect`."""
        o, d = _as_rays(origins, dirs)
        rel = o - np.array(self.center)
        a = _dot(d, d)
        half_b = _dot(d, rel)
        c = _dot(rel, rel) - self.radius**2
        disc = half_b**2 - a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        near, far = (-half_b - root) / a, (-half_b + root) / a
        t = np.where(disc >= 0, _first_positive(near, far), np.inf)
        with np.errstate(invalid="ignore"):
            normal = (rel + np.where(np.isfinite(t), t, 0.0)[:, None] * d) / self.radius
        return t, _facing(normal, d)


@dataclass(frozen=True)
class Cylinder:
    """A closed circular cylinder of `radius` (mm) and `height` (mm), centred on `center` (mm),
    its axis along the world's `axis` (``"y"``: upright, the camera's down direction; ``"x"``:
    lying along the rows).  Its two end caps are flat discs.

    Examples
    --------
    >>> t, n = Cylinder((0.0, 0.0, 800.0), 100.0, 300.0).intersect([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    >>> float(t[0]), n[0].tolist()
    (700.0, [0.0, 0.0, -1.0])
    >>> float(Cylinder((0.0, 0.0, 800.0), 100.0, 300.0).intersect([[0.0, 0.0, 0.0]], [[0.0, 1.0, 1.0]])[0][0])
    inf
    """

    center: tuple[float, float, float]
    radius: float
    height: float
    axis: str = "y"

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3("center", self.center))
        if not (math.isfinite(self.radius) and self.radius > 0 and math.isfinite(self.height) and self.height > 0):
            raise InputError(f"radius and height must be positive, got {self.radius} and {self.height}")
        if self.axis not in ("x", "y"):
            raise InputError(f"axis must be 'x' or 'y', got {self.axis!r}")
        object.__setattr__(self, "radius", float(self.radius))
        object.__setattr__(self, "height", float(self.height))

    def intersect(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """See `Surface.intersect`: the side's two roots within the height, and both caps."""
        o, d = _as_rays(origins, dirs)
        along = 0 if self.axis == "x" else 1
        across = [k for k in range(3) if k != along]
        rel = o - np.array(self.center)
        ra, da = rel[:, across], d[:, across]
        a = _dot(da, da)
        half_b = _dot(da, ra)
        c = _dot(ra, ra) - self.radius**2
        disc = half_b**2 - a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        half = self.height / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            side = [np.where((disc >= 0) & (a > 0) & (np.abs(rel[:, along] + t * d[:, along]) <= half), t, np.nan)
                    for t in ((-half_b - root) / a, (-half_b + root) / a)]
            caps = []
            for end in (-half, half):
                t = (end - rel[:, along]) / d[:, along]
                hit = rel + np.where(np.isfinite(t), t, 0.0)[:, None] * d
                caps.append(np.where(_dot(hit[:, across], hit[:, across]) <= self.radius**2, t, np.nan))
        roots = np.stack(side + caps)
        roots = np.where(roots > _T_MIN, roots, np.inf)  # NaN (no hit) compares false
        first = np.argmin(roots, axis=0)  # 0, 1: the side; 2, 3: the caps
        t = roots[first, np.arange(len(d))]
        point = rel + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        normal = point.copy()
        normal[:, along] = 0.0
        normal /= self.radius
        on_cap = first >= 2
        normal[on_cap] = 0.0
        normal[on_cap, along] = np.where(first[on_cap] == 2, -1.0, 1.0)
        return t, _facing(normal, d)


@dataclass(frozen=True)
class Box:
    """An axis-aligned box between corners `lo` and `hi` (mm)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def __post_init__(self) -> None:
        lo, hi = _vec3("lo", self.lo), _vec3("hi", self.hi)
        if not all(a < b for a, b in zip(lo, hi)):
            raise InputError(f"lo must be below hi on every axis, got {lo} and {hi}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    def intersect(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """See `Surface.intersect` (slab method)."""
        o, d = _as_rays(origins, dirs)
        safe = np.where(d == 0, 1e-300, d)  # a ray parallel to a slab: +-huge, never NaN
        t1, t2 = (np.array(self.lo) - o) / safe, (np.array(self.hi) - o) / safe
        t_in, t_out = np.minimum(t1, t2), np.maximum(t1, t2)
        near, far = t_in.max(axis=1), t_out.min(axis=1)
        t = np.where(near <= far, _first_positive(near, far), np.inf)
        entering = near > _T_MIN
        axis = np.where(entering, t_in.argmax(axis=1), t_out.argmin(axis=1))
        rows = np.arange(len(d))
        normal = np.zeros_like(d)
        normal[rows, axis] = -np.sign(d[rows, axis])
        return t, normal


@dataclass(frozen=True, init=False)
class Union:
    """Several surfaces; each ray hits the nearest of them.

    Examples
    --------
    >>> scene = Union(Plane.at_z(900.0), Sphere((0.0, 0.0, 800.0), 50.0))
    >>> float(scene.intersect([[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])[0][0])
    750.0
    """

    surfaces: tuple[Surface, ...]

    def __init__(self, *surfaces: Surface) -> None:
        if not surfaces or not all(callable(getattr(s, "intersect", None)) for s in surfaces):
            raise InputError("Union needs one or more surfaces (objects with an intersect method)")
        object.__setattr__(self, "surfaces", tuple(surfaces))

    def intersect(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """See `Surface.intersect`."""
        o, d = _as_rays(origins, dirs)
        hits = [s.intersect(o, d) for s in self.surfaces]
        ts = np.stack([h[0] for h in hits])
        nearest = ts.argmin(axis=0)
        rows = np.arange(len(d))
        return ts[nearest, rows], np.stack([h[1] for h in hits])[nearest, rows]


@dataclass(frozen=True, eq=False)
class _BinGrid:
    """Triangles binned by their central projection from a point (see `Mat5Surface`).

    ``(u, v)`` are the tangents of a direction from `centre` in the frame `basis`; each
    triangle is listed in every cell its ``(u, v)`` bounding box (`bounds`) overlaps.
    """

    centre: NDArray[np.float64]
    basis: NDArray[np.float64]  # rows e1, e2, axis
    origin: tuple[float, float]
    cell: float
    nu: int
    nv: int
    bounds: NDArray[np.float32]  # (T, 4): u_lo, v_lo, u_hi, v_hi, widened by a rounding slack
    start: NDArray[np.int64]  # (nu * nv + 1,) CSR offsets into `triangles`
    triangles: NDArray[np.int32]

    @classmethod
    def build(
        cls, vertices: NDArray[np.float64], triangles: NDArray[np.int32], centre: NDArray[np.float64]
    ) -> _BinGrid:
        rel = vertices - centre
        axis = rel.mean(axis=0)
        axis /= np.linalg.norm(axis)
        e1 = np.cross(axis, np.eye(3)[np.argmin(np.abs(axis))])
        e1 /= np.linalg.norm(e1)
        basis = np.stack([e1, np.cross(axis, e1), axis])
        local = rel @ basis.T
        if local[:, 2].min() <= 1e-9 * np.abs(local[:, 2]).max():
            raise InputError("Mat5Surface: all points must lie on one side of the rays' common point")
        uv = local[:, :2] / local[:, 2:]
        slack = 1e-6 * np.abs(uv).max()  # covers float32 rounding of the bounds
        bounds = np.empty((len(triangles), 4), dtype=np.float32)
        for k in range(2):
            corner = uv[:, k][triangles]  # (T, 3)
            bounds[:, k] = corner.min(axis=1) - slack
            bounds[:, k + 2] = corner.max(axis=1) + slack
        origin = bounds[:, :2].min(axis=0).astype(np.float64)
        extent = bounds[:, 2:].max(axis=0) - origin
        cell = max(float(np.median((bounds[:, 2:] - bounds[:, :2]).max(axis=1))), float(extent.max()) / 4096, 1e-12)
        while True:  # coarsen until the binning stays within a few entries per triangle
            i0 = np.floor((bounds[:, :2] - origin) / cell).astype(np.int32)
            span = np.floor((bounds[:, 2:] - origin) / cell).astype(np.int32) - i0 + 1
            counts = span[:, 0].astype(np.int64) * span[:, 1]
            if counts.sum() <= 8 * len(triangles) + 1024:
                break
            cell *= 2
        nu, nv = (int(v) for v in np.floor(extent / cell).astype(np.int64) + 1)
        cells = np.empty(int(counts.sum()), dtype=np.int32 if nu * nv < 2**31 else np.int64)
        done = 0
        for part in np.array_split(np.arange(len(triangles)), max(1, len(triangles) >> 20)):
            n = counts[part]
            k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)  # entry within its triangle
            width = np.repeat(span[part, 0], n)
            row, col = np.repeat(i0[part, 1], n) + k // width, np.repeat(i0[part, 0], n) + k % width
            cells[done : done + len(k)] = row * nu + col
            done += len(k)
        order = np.argsort(cells, kind="stable")
        start = np.concatenate([[0], np.cumsum(np.bincount(cells, minlength=nu * nv))])
        tris = np.repeat(np.arange(len(triangles), dtype=np.int32), counts)[order]
        return cls(centre, basis, (float(origin[0]), float(origin[1])), cell, nu, nv, bounds, start, tris)

    def pairs(self, d: NDArray[np.float64], budget: int) -> Iterator[tuple[NDArray[np.int64], NDArray[np.int32]]]:
        """(ray index, candidate triangle) pairs for rays whose lines pass through `centre`.

        Candidates are the triangles of the ray's cell whose bounds contain the ray's
        ``(u, v)``; yielded in chunks of at most about `budget` cell entries.
        """
        local = d @ self.basis.T
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = local[:, :2] / local[:, 2:]
            iu = np.floor((uv[:, 0] - self.origin[0]) / self.cell)
            iv = np.floor((uv[:, 1] - self.origin[1]) / self.cell)
        inside = (iu >= 0) & (iu < self.nu) & (iv >= 0) & (iv < self.nv)  # NaN (d . axis = 0): outside
        rays = np.flatnonzero(inside)
        cells = iv[inside].astype(np.int64) * self.nu + iu[inside].astype(np.int64)
        first, counts = self.start[cells], self.start[cells + 1] - self.start[cells]
        ends = np.cumsum(counts)
        bounds = np.searchsorted(ends, np.arange(budget, ends[-1] if len(ends) else 0, budget), side="right")
        for a, b in zip(np.r_[0, bounds], np.r_[bounds, len(rays)]):
            n = counts[a:b]
            ray = np.repeat(rays[a:b], n)
            tri = self.triangles[np.repeat(first[a:b], n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)]
            box = self.bounds[tri]
            u, v = uv[ray, 0], uv[ray, 1]
            keep = (u >= box[:, 0]) & (v >= box[:, 1]) & (u <= box[:, 2]) & (v <= box[:, 3])
            yield ray[keep], tri[keep]


@dataclass(frozen=True, eq=False)
class Mat5Surface:
    """A scanned surface: a grid of points (mat5, chapter 5) meshed into triangles.

    The two triangles of every grid square, ``(i, j), (i, j+1), (i+1, j)`` and
    ``(i, j+1), (i+1, j+1), (i+1, j)``, are kept when their three vertices are valid and
    no edge is longer than `max_edge_mm`, which drops the "curtains" a naive mesh would hang
    across depth jumps (leaving a gap up to one grid cell wide there).  Normals are per
    triangle (flat shading).

    Ray intersection is exact (Möller-Trumbore) on candidate triangles found through a
    perspective bin grid: every bundle of rays the renderer casts shares one point (camera
    rays start at the camera centre, shadow rays aim at the projector centre), and a line
    through that point crosses a triangle only if its direction falls inside the triangle's
    central projection from that point.  So the triangles are binned once per common point
    (cached) by the bounding boxes of their projections, and each ray tests only the
    triangles of its one bin; no traversal, no Python loop over rays.  Bundles of rays without
    a common point raise `InputError`.

    Parameters
    ----------
    points : (H, W, 3) float array
        World coordinates in mm; NaN where invalid (as ``formats.mat5.read_mat5`` returns).
    valid : (H, W) bool array
        Points to use (further restricted to finite points).
    max_edge_mm : float, optional
        Longest triangle edge kept, in mm.  Default: 8 times the median distance between
        valid grid neighbours.
    """

    points: NDArray[np.float64]
    valid: NDArray[np.bool_]
    max_edge_mm: float | None = None
    _vertices: NDArray[np.float64] = field(init=False, repr=False)
    _triangles: NDArray[np.int32] = field(init=False, repr=False)
    _grids: dict[tuple[float, ...], _BinGrid] = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self) -> None:
        points, valid = _check_grid(self.points, self.valid)
        masked = np.where(valid[..., None], points, np.nan)  # NaN gaps: never "short"
        across = _gaps(masked[:, :-1], masked[:, 1:])  # (H, W-1)
        down = _gaps(masked[:-1], masked[1:])  # (H-1, W)
        diagonal = _gaps(masked[:-1, 1:], masked[1:, :-1])  # (H-1, W-1), shared by both triangles
        max_edge = self.max_edge_mm
        if max_edge is None:
            grid_gaps = np.concatenate([across[np.isfinite(across)], down[np.isfinite(down)]])
            max_edge = 8 * float(np.median(grid_gaps)) if len(grid_gaps) else 0.0
        elif not max_edge > 0:
            raise InputError(f"max_edge_mm must be positive, got {max_edge}")
        with np.errstate(invalid="ignore"):
            upper = (across[:-1] <= max_edge) & (down[:, :-1] <= max_edge) & (diagonal <= max_edge)
            lower = (down[:, 1:] <= max_edge) & (across[1:] <= max_edge) & (diagonal <= max_edge)
        index = np.full(valid.shape, -1, dtype=np.int64)
        index[valid] = np.arange(int(valid.sum()))
        a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
        tris = np.concatenate(
            [np.stack([a[upper], b[upper], c[upper]], -1), np.stack([b[lower], d[lower], c[lower]], -1)]
        )
        if len(tris) == 0:
            raise InputError("Mat5Surface: no triangle can be formed from the valid points")
        vertices = points[valid]
        vertices.setflags(write=False)
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "max_edge_mm", float(max_edge))
        object.__setattr__(self, "_vertices", vertices)
        object.__setattr__(self, "_triangles", tris.astype(np.int32))

    @property
    def triangles(self) -> NDArray[np.float64]:
        """``(T, 3, 3)`` the mesh's triangles: three vertices (mm) each."""
        return self._vertices[self._triangles]

    def intersect(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """See `Surface.intersect`; the rays' lines must share a common point.

        Raises
        ------
        InputError
            If the rays' lines do not pass through one common point, or the surface is not
            entirely on one side of it.
        """
        o, d = _as_rays(origins, dirs)
        t_best = np.full(len(d), np.inf)
        tri_best = np.full(len(d), -1, dtype=np.int64)
        if len(d) == 0:
            return t_best, np.zeros_like(d)
        grid = self._grid(_common_point(o, d))
        for ray, tri in grid.pairs(d, budget=_CHUNK_SAMPLES):
            t = _moller_trumbore(o[ray], d[ray], self._vertices[self._triangles[tri]])
            hit = np.isfinite(t)
            ray, tri, t = ray[hit], tri[hit], t[hit]
            np.minimum.at(t_best, ray, t)
            win = t == t_best[ray]
            tri_best[ray[win]] = tri[win]
        normal = np.zeros_like(d)
        hit = tri_best >= 0
        v = self._vertices[self._triangles[tri_best[hit]]]
        n = _cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        normal[hit] = _facing(n / np.linalg.norm(n, axis=1, keepdims=True), d[hit])
        return t_best, normal

    def _grid(self, centre: NDArray[np.float64]) -> _BinGrid:
        key = tuple(np.round(centre, 6).tolist())
        grid = self._grids.get(key)
        if grid is None:
            grid = _BinGrid.build(self._vertices, self._triangles, centre)
            if len(self._grids) >= 4:
                self._grids.pop(next(iter(self._grids)))
            self._grids[key] = grid
        return grid


def _gaps(p: NDArray[np.float64], q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distances (mm) between corresponding points of two (..., 3) grids; NaN where either is."""
    diff = p - q
    return np.sqrt(np.einsum("...k,...k->...", diff, diff))


def _common_point(o: NDArray[np.float64], d: NDArray[np.float64]) -> NDArray[np.float64]:
    """The point all ray lines pass through (least squares); `InputError` if there is none."""
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    A = len(d) * np.eye(3) - dn.T @ dn
    b = o.sum(axis=0) - dn.T @ _dot(dn, o)
    centre = np.linalg.lstsq(A, b, rcond=None)[0]
    rel = o - centre
    off = rel - _dot(rel, dn)[:, None] * dn
    if np.abs(off).max() > 1e-6 * (1 + np.abs(rel).max()):
        raise InputError("Mat5Surface.intersect needs rays whose lines share one point (a camera or projector centre)")
    return centre


def _cross(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise cross products of (N, 3) arrays (faster than `np.cross` for tall arrays)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _moller_trumbore(o: NDArray[np.float64], d: NDArray[np.float64], tri: NDArray[np.float64]) -> NDArray[np.float64]:
    """Ray parameter of the hit of rays ``o + t d`` (N, 3) with triangles (N, 3, 3); inf if none."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = _cross(d, e2)
    det = _dot(e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - tri[:, 0]
        u = _dot(s, p) * inv
        q = _cross(s, e1)
        v = _dot(d, q) * inv
        t = _dot(e2, q) * inv
        ok = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > _T_MIN)
    return np.where(ok, t, np.inf)


def plane_scene(*, distance_mm: float = 800.0) -> Plane:
    """A fronto-parallel plane at `distance_mm` (mm): the flat-wall reference scene."""
    return Plane.at_z(distance_mm)


def tilted_plane_scene(tilt_deg: float = 30.0, *, distance_mm: float = 800.0, axis: str = "x") -> Plane:
    """A plane through ``(0, 0, distance_mm)`` turned by `tilt_deg` degrees about `axis`.

    ``axis="x"`` (the default) tilts the depth along the projector's phase direction ``y``:
    the plane's top recedes, ``Z = distance_mm - Y tan(tilt)``.  ``axis="y"``: its left side
    recedes, ``Z = distance_mm - X tan(tilt)``.
    """
    if axis not in ("x", "y"):
        raise InputError(f"axis must be 'x' or 'y', got {axis!r}")
    if not -90 < tilt_deg < 90:
        raise InputError(f"tilt_deg must lie in (-90, 90), got {tilt_deg}")
    s, c = math.sin(math.radians(tilt_deg)), math.cos(math.radians(tilt_deg))
    normal = (0.0, -s, -c) if axis == "x" else (-s, 0.0, -c)
    return Plane((0.0, 0.0, distance_mm), normal)


def sphere_scene(
    *, radius_mm: float = 122.555, distance_mm: float = 800.0, background_mm: float | None = 200.0
) -> Surface:
    """The thesis's target: a 9.65 in (245.11 mm) sphere in front of a wall.

    Parameters
    ----------
    radius_mm : float
        Sphere radius in mm (the thesis's 4.825 in).
    distance_mm : float
        Depth of the sphere's centre, on the camera axis, in mm.
    background_mm : float or None
        The wall (a fronto-parallel plane) lies this far behind the sphere's centre, in mm;
        None for no wall.  The default leaves a 77 mm gap, so the sphere casts a visible shadow.
    """
    sphere = Sphere((0.0, 0.0, distance_mm), radius_mm)
    if background_mm is None:
        return sphere
    if not background_mm > radius_mm:
        raise InputError(f"background_mm must exceed radius_mm ({radius_mm}), got {background_mm}")
    return Union(sphere, Plane.at_z(distance_mm + background_mm))


def steps_scene(
    *,
    distance_mm: float = 800.0,
    step_mm: float = 40.0,
    count: int = 4,
    width_mm: float = 80.0,
    height_mm: float = 160.0,
    background_mm: float = 100.0,
) -> Surface:
    """Blocks standing out of a wall by different amounts: sharp depth steps and cast shadows.

    `count` boxes of `width_mm` x `height_mm` (mm) sit side by side along ``x``, centred on the
    camera axis, each reaching back to the wall at ``distance_mm + background_mm``.  Box ``k``
    (from the left) has its front face at ``distance_mm - k * step_mm``.  Each box's lower edge
    throws a shadow band onto the wall below it (the projector is above the camera), wider for
    nearer boxes; its side edges are depth steps.
    """
    if count < 1 or not (step_mm >= 0 and width_mm > 0 and height_mm > 0 and background_mm > 0):
        raise InputError("steps_scene needs count >= 1, step_mm >= 0 and positive sizes")
    if distance_mm - (count - 1) * step_mm <= 0:
        raise InputError("steps_scene: the nearest box would reach the camera; reduce step_mm or count")
    wall = distance_mm + background_mm
    left = -count * width_mm / 2
    boxes = [
        Box(
            (left + k * width_mm, -height_mm / 2, distance_mm - k * step_mm),
            (left + (k + 1) * width_mm, height_mm / 2, wall),
        )
        for k in range(count)
    ]
    return Union(*boxes, Plane.at_z(wall))


def cylinder_scene(
    *, radius_mm: float = 100.0, height_mm: float = 320.0, distance_mm: float = 800.0, background_mm: float = 200.0
) -> Surface:
    """An upright cylinder (a can, a pipe) in front of a wall: a surface curved across the
    carriers only, its sides turning away from camera and projector alike.

    Parameters
    ----------
    radius_mm, height_mm : float
        The cylinder's size in mm.
    distance_mm : float
        Depth of its axis, on the camera axis, in mm.
    background_mm : float
        The wall (a fronto-parallel plane) lies this far behind the axis, in mm.
    """
    if not background_mm > radius_mm:
        raise InputError(f"background_mm must exceed radius_mm ({radius_mm}), got {background_mm}")
    return Union(Cylinder((0.0, 0.0, distance_mm), radius_mm, height_mm), Plane.at_z(distance_mm + background_mm))


def objects_scene(*, distance_mm: float = 800.0) -> Surface:
    """A cluttered table-top: two spheres (radii 70 and 50 mm), a box, and a cylinder lying
    along the rows, at different depths around `distance_mm` (mm) in front of a wall 200 mm
    behind it.  Many depth edges, occlusions and cast shadows of several widths, and none of the
    other scenes' sizes: the scene for measuring what a decoder tuned on those does elsewhere.
    """
    z = distance_mm
    return Union(Sphere((-95.0, 25.0, z - 40.0), 70.0), Sphere((85.0, -45.0, z + 30.0), 50.0),
                 Box((30.0, 40.0, z - 40.0), (150.0, 150.0, z + 200.0)),
                 Cylinder((-60.0, -110.0, z + 60.0), 35.0, 220.0, axis="x"), Plane.at_z(z + 200.0))


def circle_target_scene(
    *, distance_mm: float = 800.0, opening_deg: float = 90.0, rows: int = 3, columns: int = 3,
    spacing_mm: float = 60.0, radius_mm: float = 12.0
) -> tuple[Surface, DiscAlbedo, CircleTarget]:
    """The thesis's 3-D calibration target (fig. 4.1): dark circles on two planes at an angle.

    Two planes meet at a vertical fold through ``(0, 0, distance_mm)`` and open toward the
    camera by `opening_deg` (an open book, spine away).  Each face carries `rows` x `columns`
    circles of `radius_mm` in a grid `spacing_mm` apart, the first column `spacing_mm` from the
    fold; on the right face every second row is shifted half a spacing away from the fold, so
    its columns are not straight and no projective map takes the target onto itself (its
    circles can be told apart).  Default: 18 circles.

    Returns
    -------
    scene : Surface
        The two (infinite) faces.
    albedo : DiscAlbedo
        Circles at albedo 0.1 on a 0.9 face.
    target : CircleTarget
        Centres, normals and radius: what a user's target file holds.
    """
    if not (0 < opening_deg < 180 and rows >= 1 and columns >= 1 and 0 < 2 * radius_mm < spacing_mm):
        raise InputError("circle_target_scene needs 0 < opening_deg < 180, rows and columns >= 1 and "
                         "0 < 2 radius_mm < spacing_mm")
    half = math.radians(opening_deg) / 2
    fold = np.array([0.0, 0.0, distance_mm])
    up = np.array([0.0, 1.0, 0.0])
    faces, centres, normals = [], [], []
    for side in (-1.0, 1.0):
        along = np.array([side * math.sin(half), 0.0, -math.cos(half)])
        normal = np.cross(along, up)
        faces.append(Plane(tuple(fold), tuple(normal)))
        r, c = np.mgrid[0:rows, 0:columns]
        y = spacing_mm * (r.ravel() - (rows - 1) / 2)
        s = spacing_mm * (c.ravel() + 1 + (side > 0) * (r.ravel() % 2) / 2)
        centres.append(fold + s[:, None] * along + y[:, None] * up)
        normals.append(np.broadcast_to(normal / np.linalg.norm(normal), (rows * columns, 3)))
    target = CircleTarget(np.vstack(centres), np.vstack(normals), radius_mm)
    return Union(*faces), DiscAlbedo(target.centres, radius_mm), target


def _board_pose(tilt_deg: tuple[float, float], distance_mm: float,
                offset_mm: tuple[float, float]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Centre ``(3,)`` (mm) and rotation ``(3, 3)`` (columns: the board's x, y axes and normal)
    of a board at ``(offset_x, offset_y, distance_mm)`` turned by `tilt_deg` (degrees about the
    x axis, then about the y axis)."""
    ax, ay = (math.radians(a) for a in tilt_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    return np.array([offset_mm[0], offset_mm[1], distance_mm], dtype=np.float64), ry @ rx


def board_scene(
    *, tilt_deg: tuple[float, float] = (0.0, 0.0), distance_mm: float = 800.0,
    inner_corners: tuple[int, int] = (9, 7), square_mm: float = 30.0, offset_mm: tuple[float, float] = (0.0, 0.0)
) -> tuple[Plane, BoardAlbedo]:
    """A flat chessboard centred at ``(offset_mm, distance_mm)`` (by default on the camera axis
    at `distance_mm`), turned by `tilt_deg` (degrees about the x axis, then about the y axis).

    Returns
    -------
    scene : Plane
    albedo : BoardAlbedo
        The board printed on it (its `corners` are the inner corners in mm).
    """
    centre, rotation = _board_pose(tilt_deg, distance_mm, offset_mm)
    x_axis, y_axis = rotation[:, 0], rotation[:, 1]
    cols, rows = inner_corners
    origin = centre - square_mm * ((cols - 1) / 2 * x_axis + (rows - 1) / 2 * y_axis)
    albedo = BoardAlbedo(origin, x_axis, y_axis, inner_corners, square_mm)
    return Plane(tuple(centre), tuple(rotation[:, 2])), albedo


Pose = tuple[tuple[float, float], tuple[float, float]]


def calibration_poses(count: int, *, tilt_deg: float = 20.0,
                      offset_mm: tuple[float, float] = (30.0, 20.0)) -> list[Pose]:
    """Board poses that pin down a lens: ``(tilt_deg, offset_mm)`` pairs for `board_scene` and
    `circle_grid_scene`.

    Pose ``k`` tilts the board by `tilt_deg` towards direction ``2 pi k / count`` (about the x
    and y axes) and moves its centre by `offset_mm` around an ellipse (a radian further on).
    The tilt pins the focal lengths down; the principal point of a narrow lens is pinned by how
    far into the image corners the board's points reach and by how many there are, not by the
    tilt (the 30-degree lens of benchmarks/distortion.py, exact points plus noise: OpenCV's
    standard deviation of the principal point per pixel of point error falls from 29 to 8 going
    from a 4x11 grid of 20 mm to a view-filling 15x11 one, 12 poses either way, and rises by
    about 15 % from 15 to 35 degrees of tilt).  So the defaults suit a board that fills most of the view at the working distance:
    a moderate tilt, small offsets that keep it inside the view.

    Examples
    --------
    >>> [(tuple(round(a) for a in t), tuple(round(o) for o in off)) for t, off in calibration_poses(4)][:2]
    [((20, 0), (16, 17)), ((0, 20), (-25, 11))]
    """
    if count < 1 or not 0 <= tilt_deg < 90:
        raise InputError(f"calibration_poses needs count >= 1 and tilt_deg in [0, 90), got {count}, {tilt_deg}")
    angles = 2 * np.pi * np.arange(count) / count
    return [((tilt_deg * math.cos(a), tilt_deg * math.sin(a)),
             (offset_mm[0] * math.cos(a + 1), offset_mm[1] * math.sin(a + 1))) for a in angles]


def circle_grid_scene(
    board: Board, *, tilt_deg: tuple[float, float] = (0.0, 0.0), distance_mm: float = 800.0,
    offset_mm: tuple[float, float] = (0.0, 0.0)
) -> tuple[Plane, DiscAlbedo, NDArray[np.float64]]:
    """A flat circle grid (`sliscan.targets.Board`, symmetric or asymmetric, with its radius)
    printed on an endless white plane, its layout centred at ``(offset_mm, distance_mm)`` and
    turned by `tilt_deg` as in `board_scene`.

    Returns
    -------
    scene : Plane
    albedo : DiscAlbedo
        The circles (albedo 0.1 on 0.9).
    centres : (N, 3) float64 array
        The circle centres in mm, in OpenCV's order (`Board.points`).

    Raises
    ------
    InputError
        If `board` is not a circle grid with a radius.
    """
    if not board.circles or board.radius is None:
        raise InputError(f"a circle grid scene needs a circle grid with its radius, got a {board.describe()} "
                         f"with radius {board.radius}")
    centre, rotation = _board_pose(tilt_deg, distance_mm, offset_mm)
    layout = board.points().astype(np.float64)
    centres = centre + (layout - layout.mean(axis=0)) @ rotation.T
    return Plane(tuple(centre), tuple(rotation[:, 2])), DiscAlbedo(centres, board.radius), centres


# --------------------------------------------------------------------------------------------
# Albedo (texture) and conditions
# --------------------------------------------------------------------------------------------


def _check_xyz(xyz: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(xyz, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"xyz must have shape (N, 3), got {arr.shape}")
    return arr


def _check_unit_range(**values: float) -> None:
    for name, v in values.items():
        if not 0 <= v <= 1:
            raise InputError(f"{name} must lie in [0, 1], got {v}")


def _check_footprint(footprint: ArrayLike, count: int) -> NDArray[np.float64]:
    out = np.asarray(footprint, dtype=np.float64)
    if out.shape != (count, 2, 3):
        raise InputError(f"footprint must have shape ({count}, 2, 3), got {out.shape}")
    return out


def _box_sum_cdf(z: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """``P(A + B < z)`` for independent ``A ~ U(-a/2, a/2)``, ``B ~ U(-b/2, b/2)`` (widths >= 0).

    How the area of a parallelogram footprint spreads along one direction: its two edge
    vectors project onto the direction with lengths `a` and `b`, so the share of its area
    below offset `z` from its centre is this trapezoid's CDF.  Zero widths give the step
    ``z > 0`` (a point sample).  All arguments broadcast; any one length unit.

    Examples
    --------
    >>> [round(float(_box_sum_cdf(np.array(z), np.array(2.0), np.array(1.0))), 4) for z in (-1.5, -0.5, 0.0, 1.0)]
    [0.0, 0.25, 0.5, 0.9375]
    """
    wide, narrow = np.maximum(a, b), np.minimum(a, b)
    half_sum, half_diff = (wide + narrow) / 2, (wide - narrow) / 2

    def ramp2(x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.square(np.maximum(x, 0.0))

    with np.errstate(divide="ignore", invalid="ignore"):
        trapezoid = (ramp2(z + half_sum) - ramp2(z + half_diff) - ramp2(z - half_diff) + ramp2(z - half_sum)) / (
            2 * wide * narrow)
        ramp = np.clip(z / wide + 0.5, 0.0, 1.0)
    return np.where(narrow > 1e-6 * wide, trapezoid, np.where(wide > 0, ramp, (z > 0).astype(np.float64)))


def _widths(footprint: NDArray[np.float64], direction: ArrayLike, unit: float) -> tuple[NDArray[np.float64], ...]:
    """Lengths (in `unit` mm) of a footprint's two edge vectors ``(N, 2, 3)`` along `direction`
    (unit vectors, ``(3,)`` or ``(N, 3)``)."""
    along = np.abs(np.einsum("nek,nk->ne", footprint, np.broadcast_to(direction, (len(footprint), 3)))) / unit
    return along[:, 0], along[:, 1]


def _cell_mean(value: Callable[[NDArray[np.float64]], NDArray[np.float64]], u: NDArray[np.float64],
               a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Mean of a function ``value(k)`` that is constant on unit cells ``[k, k + 1)`` over
    footprints centred at `u` with projected widths `a`, `b` (cell units, capped at one cell,
    so a footprint reaches no further than the neighbouring cells)."""
    a, b = np.minimum(a, 1.0), np.minimum(b, 1.0)
    k = np.floor(u)
    below = _box_sum_cdf(k - u, a, b)
    above = 1.0 - _box_sum_cdf(k + 1 - u, a, b)
    return (1 - below - above) * value(k) + below * value(k - 1) + above * value(k + 1)


def _on_board(k: NDArray[np.float64], count: int) -> NDArray[np.float64]:
    """1 for the cells ``-1 <= k <= count - 1`` of a board with `count` inner corners along an axis."""
    return ((k >= -1) & (k <= count - 1)).astype(np.float64)


def _parity_sign(k: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(-1) ** k`` of whole numbers stored as floats."""
    return 1.0 - 2.0 * np.mod(k, 2.0)


@dataclass(frozen=True)
class UniformAlbedo:
    """The same reflectance `value` in [0, 1] everywhere."""

    value: float = 1.0

    def __post_init__(self) -> None:
        _check_unit_range(value=self.value)

    def __call__(self, xyz: ArrayLike) -> NDArray[np.float32]:
        """Albedo ``(N,)`` float32 at world points ``xyz`` ``(N, 3)`` in mm."""
        return np.full(len(_check_xyz(xyz)), self.value, dtype=np.float32)


@dataclass(frozen=True)
class SmoothAlbedo:
    """A smooth random texture: `terms` plane waves of period about `scale_mm` (mm) in 3-D.

    The sum of waves (unit variance, nearly Gaussian) goes through the normal CDF, so the
    albedo spreads roughly uniformly over [`low`, `high`].  The field depends only on `seed`.

    Examples
    --------
    >>> a = SmoothAlbedo(seed=1)(np.random.default_rng(0).uniform(-200, 200, (1000, 3)))
    >>> bool(a.min() >= 0.15 and a.max() <= 1.0 and a.std() > 0.15)
    True
    """

    low: float = 0.15
    high: float = 1.0
    scale_mm: float = 60.0
    seed: int = 0
    terms: int = 8

    def __post_init__(self) -> None:
        _check_unit_range(low=self.low, high=self.high)
        if not (self.low <= self.high and self.scale_mm > 0 and self.terms >= 1):
            raise InputError("SmoothAlbedo needs low <= high, scale_mm > 0 and terms >= 1")

    def __call__(self, xyz: ArrayLike) -> NDArray[np.float32]:
        """Albedo ``(N,)`` float32 at world points ``xyz`` ``(N, 3)`` in mm."""
        xyz = _check_xyz(xyz)
        rng = np.random.default_rng(self.seed)
        dirs = rng.normal(size=(self.terms, 3))
        magnitude = rng.uniform(0.7, 1.4, (self.terms, 1)) / self.scale_mm  # cycles per mm
        freqs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * magnitude
        phases = rng.uniform(0, 2 * np.pi, self.terms)
        field_ = np.cos(2 * np.pi * xyz @ freqs.T + phases).sum(axis=1) / math.sqrt(self.terms / 2)
        return (self.low + (self.high - self.low) * scipy.special.ndtr(field_)).astype(np.float32)


@dataclass(frozen=True)
class CheckerAlbedo:
    """A 3-D checkerboard of cubes of side `square_mm` (mm), centred on the world origin."""

    square_mm: float = 40.0
    low: float = 0.25
    high: float = 0.9

    def __post_init__(self) -> None:
        _check_unit_range(low=self.low, high=self.high)
        if not self.square_mm > 0:
            raise InputError(f"square_mm must be positive, got {self.square_mm}")

    def __call__(self, xyz: ArrayLike) -> NDArray[np.float32]:
        """Albedo ``(N,)`` float32 at world points ``xyz`` ``(N, 3)`` in mm."""
        parity = np.floor(_check_xyz(xyz) / self.square_mm + 0.5).astype(np.int64).sum(axis=1) % 2
        return np.where(parity == 0, self.high, self.low).astype(np.float32)

    def area_mean(self, xyz: ArrayLike, footprint: ArrayLike) -> NDArray[np.float32]:
        """Mean albedo ``(N,)`` over the parallelograms ``xyz + s f[:, 0] + t f[:, 1]``,
        ``s, t in [-1/2, 1/2]`` (`footprint` ``f`` ``(N, 2, 3)`` in mm): the sign ``(-1)**parity``
        averaged along each axis, the axes taken as independent (exact for footprints aligned
        with the cubes, and much finer than a cube)."""
        xyz = _check_xyz(xyz)
        footprint = _check_footprint(footprint, len(xyz))
        sign = np.ones(len(xyz))
        for axis in range(3):
            a, b = _widths(footprint, np.eye(3)[axis], self.square_mm)
            sign *= _cell_mean(_parity_sign, xyz[:, axis] / self.square_mm + 0.5, a, b)
        return (self.low + (self.high - self.low) * (1 + sign) / 2).astype(np.float32)


@dataclass(frozen=True, eq=False)
class DiscAlbedo:
    """Dark discs of `radius_mm` around `centres` (mm) on a bright surface: printed circles.

    A point is dark (`low`) within `radius_mm` of a centre; on a plane through the centre that
    is a disc.  Everything else is `high`.
    """

    centres: NDArray[np.float64]
    radius_mm: float
    low: float = 0.1
    high: float = 0.9

    def __post_init__(self) -> None:
        _check_unit_range(low=self.low, high=self.high)
        object.__setattr__(self, "centres", _check_xyz(self.centres))
        if not self.radius_mm > 0:
            raise InputError(f"radius_mm must be positive, got {self.radius_mm}")

    def __call__(self, xyz: ArrayLike) -> NDArray[np.float32]:
        """Albedo ``(N,)`` float32 at world points ``xyz`` ``(N, 3)`` in mm."""
        distance, _ = scipy.spatial.cKDTree(self.centres).query(_check_xyz(xyz))
        return np.where(distance < self.radius_mm, self.low, self.high).astype(np.float32)

    def area_mean(self, xyz: ArrayLike, footprint: ArrayLike) -> NDArray[np.float32]:
        """Mean albedo ``(N,)`` over the parallelograms ``xyz + s f[:, 0] + t f[:, 1]``,
        ``s, t in [-1/2, 1/2]`` (`footprint` ``f`` ``(N, 2, 3)`` in mm): the nearest circle's
        edge taken as straight across each footprint (its curvature is second order)."""
        xyz = _check_xyz(xyz)
        footprint = _check_footprint(footprint, len(xyz))
        distance, nearest = scipy.spatial.cKDTree(self.centres).query(xyz)
        with np.errstate(divide="ignore", invalid="ignore"):
            radial = np.nan_to_num((xyz - self.centres[nearest]) / distance[:, None])
        a, b = _widths(footprint, radial, 1.0)
        dark = _box_sum_cdf(self.radius_mm - distance, np.minimum(a, self.radius_mm), np.minimum(b, self.radius_mm))
        return (self.high + (self.low - self.high) * dark).astype(np.float32)


@dataclass(frozen=True, eq=False)
class BoardAlbedo:
    """A printed chessboard on a plane: `inner_corners` (columns, rows) inner corners, squares
    of `square_mm` (mm), a white (`high`) margin around it.

    Inner corner ``(i, j)`` lies at ``origin + square_mm * (i * x_axis + j * y_axis)``; the
    squares cover ``-1 <= i <= columns``, ``-1 <= j <= rows`` (in squares).
    """

    origin: NDArray[np.float64]
    x_axis: NDArray[np.float64]
    y_axis: NDArray[np.float64]
    inner_corners: tuple[int, int] = (9, 7)
    square_mm: float = 30.0
    low: float = 0.1
    high: float = 0.9

    def __post_init__(self) -> None:
        _check_unit_range(low=self.low, high=self.high)
        for name in ("origin", "x_axis", "y_axis"):
            object.__setattr__(self, name, np.array(_vec3(name, getattr(self, name))))
        if not (self.square_mm > 0 and min(self.inner_corners) >= 1):
            raise InputError("BoardAlbedo needs square_mm > 0 and at least 1x1 inner corners")

    @property
    def corners(self) -> NDArray[np.float64]:
        """``(rows * columns, 3)`` inner corners in mm, along a board row first."""
        cols, rows = self.inner_corners
        j, i = np.mgrid[0:rows, 0:cols]
        return self.origin + self.square_mm * (i.reshape(-1, 1) * self.x_axis + j.reshape(-1, 1) * self.y_axis)

    def __call__(self, xyz: ArrayLike) -> NDArray[np.float32]:
        """Albedo ``(N,)`` float32 at world points ``xyz`` ``(N, 3)`` in mm."""
        rel = _check_xyz(xyz) - self.origin
        u, v = np.floor(rel @ self.x_axis / self.square_mm), np.floor(rel @ self.y_axis / self.square_mm)
        cols, rows = self.inner_corners
        on_board = (u >= -1) & (u <= cols - 1) & (v >= -1) & (v <= rows - 1)
        dark = on_board & ((u + v) % 2 == 0)
        return np.where(dark, self.low, self.high).astype(np.float32)

    def area_mean(self, xyz: ArrayLike, footprint: ArrayLike) -> NDArray[np.float32]:
        """Mean albedo ``(N,)`` over the parallelograms ``xyz + s f[:, 0] + t f[:, 1]``,
        ``s, t in [-1/2, 1/2]`` (`footprint` ``f`` ``(N, 2, 3)`` in mm).  A square is dark where
        ``on_u on_v (1 + q_u q_v) / 2`` is 1 (``on``: within the board along that axis, ``q``: the
        square's sign ``(-1)**k``); each factor is averaged along its own axis, the axes taken as
        independent (exact for footprints aligned with the squares)."""
        xyz = _check_xyz(xyz)
        footprint = _check_footprint(footprint, len(xyz))
        rel = xyz - self.origin
        means = []
        for axis, count in ((self.x_axis, self.inner_corners[0]), (self.y_axis, self.inner_corners[1])):
            u = rel @ axis / self.square_mm
            a, b = _widths(footprint, axis, self.square_mm)
            on = functools.partial(_on_board, count=count)
            means.append((_cell_mean(on, u, a, b), _cell_mean(lambda k: on(k) * _parity_sign(k), u, a, b)))
        (on_u, signed_u), (on_v, signed_v) = means
        dark = (on_u * on_v + signed_u * signed_v) / 2
        return (self.high + (self.low - self.high) * dark).astype(np.float32)


@dataclass(frozen=True)
class Conditions:
    """The physics of a capture (defaults: a good real scanner; see each attribute).

    Attributes
    ----------
    albedo : callable
        Reflectance in [0, 1] of world points, ``(N, 3) -> (N,)``.  Default 0.8 everywhere
        (matte white paint).
    ambient : float
        Ambient irradiance beta of eq. 3.2, as a fraction of the projector's full-white
        irradiance at the working distance and normal incidence.  Default 0.1 (a dim room).
    projector_gamma : float
        Projected linear light = drive ** gamma.  Default 2.2 (sRGB-like; table 3.2 finds 2-3.5).
    projector_black : float
        Light leaked at drive 0, as a fraction of full white.  Default 0.005 (200:1 contrast).
    projector_blur_px : float
        Gaussian sigma of the projector optics, in projector pixels.  Default 1.0: the carriers
        at 128 cycles per 1024 px keep 73 % of their amplitude (the roll-off of fig. 3.11).
    camera_blur_px : float
        Gaussian sigma of the camera optics, in camera pixels (after the pixel aperture).
        Default 1.0.
    projector_focus_mm, camera_focus_mm : float or None
        Depth of field: the distance along the device's optical axis of the plane its lens
        focuses on, in mm.  A point at depth ``z`` spreads into a disc of diameter
        ``c = f D |1/z - 1/focus|`` pixels (thin lens; ``f`` the focal length in pixels, ``D``
        the aperture), blurred as a Gaussian of the disc's standard deviation ``c / 4`` added
        in quadrature to the in-focus `projector_blur_px` / `camera_blur_px`.  The projector
        blurs each surface point's light by that point's depth; the camera blurs each pixel by
        the depth of the surface its centre sees (a gather: a defocused foreground does not
        spread over the background beside it).  Default None: in focus at every depth.
    projector_aperture_mm, camera_aperture_mm : float
        The lens's aperture (entrance pupil) diameter, in mm, with a focus.  Defaults 8.0 (a
        20 mm projector lens at f/2.5) and 3.0 (a 12 mm camera lens at f/4).
    exposure : float
        Camera signal (full scale = 1) for albedo 1 under full white at normal incidence at the
        working distance.  Default 0.8: headroom for the brightest points of the default scenes.
    full_well_e : float or None
        Electrons at full scale: shot noise is Poisson in these electrons.  Default 10000 (a
        small-pixel CMOS sensor).  None: a noise-free sensor (no shot and no read noise).
    read_noise_e : float
        Gaussian read noise in electrons.  Default 8.
    bit_depth : int or None
        Output quantisation (levels ``2**bit_depth - 1``).  Default 8.  None: float output.
        The output is always clipped to [0, 1] (saturation).
    supersample : int
        Sub-pixels per camera pixel per axis, averaged (the pixel's box aperture), so depth,
        shadow and albedo edges mix within a pixel.  Default 3.
    inverse_square : bool
        Projector irradiance falls as ``(r0 / r)**2`` with the distance ``r`` from the projector
        centre, ``r0 = Rig.projector_distance_mm``.  Default True.
    seed : int or None
        Seed of the noise generator when `render` gets no `rng`.  Default None (fresh noise).
    """

    albedo: Callable[[NDArray[np.float64]], NDArray[np.floating]] = field(default_factory=lambda: UniformAlbedo(0.8))
    ambient: float = 0.1
    projector_gamma: float = 2.2
    projector_black: float = 0.005
    projector_blur_px: float = 1.0
    camera_blur_px: float = 1.0
    projector_focus_mm: float | None = None
    projector_aperture_mm: float = 8.0
    camera_focus_mm: float | None = None
    camera_aperture_mm: float = 3.0
    exposure: float = 0.8
    full_well_e: float | None = 10000.0
    read_noise_e: float = 8.0
    bit_depth: int | None = 8
    supersample: int = 3
    inverse_square: bool = True
    seed: int | None = None

    def __post_init__(self) -> None:
        if not callable(self.albedo):
            raise InputError("albedo must be callable: (N, 3) world points -> (N,) values in [0, 1]")
        checks = {
            "ambient": self.ambient >= 0,
            "projector_gamma": self.projector_gamma > 0,
            "projector_black": 0 <= self.projector_black < 1,
            "projector_blur_px": self.projector_blur_px >= 0,
            "camera_blur_px": self.camera_blur_px >= 0,
            "projector_focus_mm": self.projector_focus_mm is None or self.projector_focus_mm > 0,
            "projector_aperture_mm": self.projector_aperture_mm > 0,
            "camera_focus_mm": self.camera_focus_mm is None or self.camera_focus_mm > 0,
            "camera_aperture_mm": self.camera_aperture_mm > 0,
            "exposure": self.exposure > 0,
            "full_well_e": self.full_well_e is None or self.full_well_e > 0,
            "read_noise_e": self.read_noise_e >= 0,
            "bit_depth": self.bit_depth is None or (isinstance(self.bit_depth, int) and 1 <= self.bit_depth <= 16),
            "supersample": isinstance(self.supersample, int) and self.supersample >= 1,
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not ok or (isinstance(value, float) and not math.isfinite(value)):
                raise InputError(f"invalid Conditions.{name}: {value!r}")

    @classmethod
    def ideal(cls) -> Conditions:
        """No blur, no noise, albedo 1, no ambient, gamma 1, no black level, float output,
        one sample per pixel, no falloff, exposure 1: the image is ``drive(xp, yp) * cos``."""
        return cls(
            albedo=UniformAlbedo(1.0), ambient=0.0, projector_gamma=1.0, projector_black=0.0,
            projector_blur_px=0.0, camera_blur_px=0.0, exposure=1.0, full_well_e=None,
            read_noise_e=0.0, bit_depth=None, supersample=1, inverse_square=False,
        )

    def with_(self, **changes: object) -> Conditions:
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)  # type: ignore[arg-type]


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What the camera sees at each pixel CENTRE ray.

    Attributes
    ----------
    points : (H, W, 3) float32 array
        World point in mm; NaN where the ray hits no surface.
    proj : (H, W, 2) float32 array
        Projector ``(xp, yp)`` of that point, in projector pixels; NaN where no surface (or
        behind the projector).
    lit : (H, W) bool array
        Surface hit, inside the projector image, not shadowed and facing the projector.
    surface : (H, W) bool array
        The ray hits a surface.
    albedo : (H, W) float32 array
        Albedo at the point; NaN where no surface.
    edge : (H, W) bool array
        The pixel's sub-pixels disagree: some hit a surface and some do not, some are lit and
        some not, or they lie on different planes (a depth step); see `render`.
    """

    points: NDArray[np.float32]
    proj: NDArray[np.float32]
    lit: NDArray[np.bool_]
    surface: NDArray[np.bool_]
    albedo: NDArray[np.float32]
    edge: NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class Capture:
    """A simulated camera frame and its ground truth.

    Attributes
    ----------
    image : (H, W) float32 array
        The camera frame in [0, 1].
    truth : GroundTruth
    """

    image: NDArray[np.float32]
    truth: GroundTruth


@dataclass(frozen=True, eq=False)
class SequenceCapture:
    """Simulated camera frames of a sequence of projected images on one scene, and their
    common ground truth.

    Attributes
    ----------
    images : (K, H, W) float32 array
        One camera frame in [0, 1] per projected image, in the same order; each has its own
        sensor noise.
    truth : GroundTruth
        The same for every frame (the scene and the rig do not move).
    """

    images: NDArray[np.float32]
    truth: GroundTruth


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Hits:
    """Per ray sample: what the camera ray hit and how the projector sees it."""

    points: NDArray[np.float64]  # (N, 3), NaN where no surface
    normal: NDArray[np.float64]  # (N, 3), facing the camera
    surface: NDArray[np.bool_]
    proj: NDArray[np.float64]  # (N, 2)
    cos: NDArray[np.float64]  # cos(incidence) of projector light
    dist: NDArray[np.float64]  # distance to the projector centre, mm
    depth: NDArray[np.float64]  # depth along the projector's axis, mm
    reached: NDArray[np.bool_]  # projector light can reach it (within the padded frustum)
    inside: NDArray[np.bool_]  # within the nominal projector image
    pixel: NDArray[np.float64]  # (N, 2) the sample's camera pixel position (x, y)


def _trace(rig: Rig, scene: Surface, xc: NDArray[np.float64], yc: NDArray[np.float64], pad: int) -> _Hits:
    """Cast camera rays through pixel positions and shadow rays to the projector.

    `pad` widens the projector frustum by that many projector pixels on every side (where
    blurred light spills); `inside` is about the nominal image.
    """
    dirs = rig.camera.rays(xc, yc)
    origins = np.broadcast_to(rig.camera.centre, dirs.shape)
    t, normal = scene.intersect(origins, dirs)
    surface = np.isfinite(t)
    points = origins + np.where(surface, t, np.nan)[:, None] * dirs
    proj, depth = rig.projector.project(points)
    proj[~(depth > 0)] = np.nan  # behind the projector: no projector coordinates
    to_light = rig.projector.centre - points
    dist = np.sqrt(_dot(to_light, to_light))
    cos = np.where(surface, _dot(normal, to_light) / dist, 0.0)
    wp, hp = rig.projector.size

    def within(margin: float) -> NDArray[np.bool_]:
        x, y = proj[:, 0], proj[:, 1]
        inside_x = (x >= -0.5 - margin) & (x <= wp - 0.5 + margin)
        return (depth > 0) & inside_x & (y >= -0.5 - margin) & (y <= hp - 0.5 + margin)

    reached = surface & within(pad) & (cos > 0)
    if reached.any():
        start = points[reached] + _SHADOW_OFFSET_MM * normal[reached]
        blocked, _ = scene.intersect(start, rig.projector.centre - start)
        reached[reached] = ~(blocked < 1.0)
    return _Hits(points, normal, surface, proj, cos, dist, depth, reached, within(0.0), np.stack([xc, yc], axis=-1))


def defocus_blur(depth: ArrayLike, *, in_focus_px: float, focus_mm: float | None, aperture_mm: float,
                 focal_px: float) -> NDArray[np.float64]:
    """Gaussian sigma (pixels) of a lens's blur at each depth (mm along its axis).

    The in-focus blur in quadrature with a quarter of the thin lens's circle of confusion,
    ``focal_px * aperture_mm * |1/depth - 1/focus_mm|`` pixels across (a uniform disc's standard
    deviation is a quarter of its diameter).  `focus_mm` None: `in_focus_px` everywhere.

    >>> [round(float(s), 3) for s in defocus_blur([800.0, 400.0], in_focus_px=1.0, focus_mm=800.0,
    ...                                            aperture_mm=8.0, focal_px=1600.0)]
    [1.0, 4.123]
    """
    depth = np.asarray(depth, dtype=np.float64)
    if focus_mm is None:
        return np.full(depth.shape, float(in_focus_px))
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = focal_px * aperture_mm * np.abs(1.0 / depth - 1.0 / focus_mm)
    return np.hypot(in_focus_px, disc / 4)


#: Blurs that vary with depth are rendered as blends of the light blurred at multiples of this
#: sigma (pixels), linearly between the two that bracket each point's blur.
DEFOCUS_STEP_PX = 0.125


def _blend_weights(sigma: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float32]]:
    """The lower `DEFOCUS_STEP_PX` level below each sigma and the weight of the one above it."""
    level = np.maximum(sigma, 0) / DEFOCUS_STEP_PX
    low = np.floor(level).astype(np.intp)
    return low, (level - low).astype(np.float32)


def _projector_pad(conditions: Conditions, focal_px: float) -> int:
    """Projector pixels that blurred light spreads past the image edge (4 sigma; with a depth of
    field, of the blur at half or twice the focus distance)."""
    focus, sigma = conditions.projector_focus_mm, conditions.projector_blur_px
    if focus is not None:
        sigma = float(defocus_blur(focus / 2, in_focus_px=sigma, focus_mm=focus,
                                   aperture_mm=conditions.projector_aperture_mm, focal_px=focal_px))
    return math.ceil(4 * sigma)


class _ProjectorLight:
    """Linear projector light on a zero-padded canvas, blurred as the projector's optics blur it
    at the depth of each point it falls on (`Conditions.projector_focus_mm`).

    The canvases blurred at each `DEFOCUS_STEP_PX` level a depth asks for are made once and kept.
    """

    def __init__(self, drive: NDArray[np.float32], conditions: Conditions, focal_px: float) -> None:
        black = conditions.projector_black
        light = (black + (1 - black) * drive.astype(np.float64) ** conditions.projector_gamma).astype(np.float32)
        self.conditions, self.focal_px = conditions, focal_px
        self.pad = _projector_pad(conditions, focal_px)
        self._linear = np.pad(light, self.pad)
        self._canvases: dict[float, NDArray[np.float32]] = {}

    def canvas(self, sigma: float) -> NDArray[np.float32]:
        """The light blurred by a Gaussian of `sigma` projector pixels (kept for the next call)."""
        if sigma not in self._canvases:
            self._canvases[sigma] = self._linear if sigma <= 0 else scipy.ndimage.gaussian_filter(
                self._linear, sigma, mode="constant", truncate=4.0)
        return self._canvases[sigma]

    def sample(self, xp: NDArray[np.float64], yp: NDArray[np.float64],
               depth: NDArray[np.float64]) -> NDArray[np.float32]:
        """Irradiance (before shading) at projector pixels ``(xp, yp)`` of points at `depth` mm
        along the projector's axis: ``(N,)``."""
        x, y, cond = xp + self.pad, yp + self.pad, self.conditions
        if cond.projector_focus_mm is None:
            return _bilinear(self.canvas(cond.projector_blur_px), x, y)
        sigma = defocus_blur(depth, in_focus_px=cond.projector_blur_px, focus_mm=cond.projector_focus_mm,
                             aperture_mm=cond.projector_aperture_mm, focal_px=self.focal_px)
        low, upper = _blend_weights(sigma)
        out = np.empty(len(x), dtype=np.float32)
        for level in np.unique(low):
            at = low == level
            below = _bilinear(self.canvas(level * DEFOCUS_STEP_PX), x[at], y[at])
            above = _bilinear(self.canvas((level + 1) * DEFOCUS_STEP_PX), x[at], y[at])
            out[at] = below + upper[at] * (above - below)
        return out


def _bilinear(image: NDArray[np.float32], x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float32]:
    """Bilinear samples of `image` at ``(x, y)`` (pixel centres at integers; edges clamped)."""
    h, w = image.shape
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _subpixel_offsets(supersample: int) -> tuple[NDArray[np.float64], int]:
    """``(S, 2)`` sample offsets (x, y) from the pixel centre, and the index of the centre.

    The first ``supersample**2`` samples tile the pixel; for even `supersample` the centre
    itself is appended (for the ground truth only).
    """
    k = (np.arange(supersample) + 0.5) / supersample - 0.5
    grid = np.stack(np.meshgrid(k, k, indexing="xy"), axis=-1).reshape(-1, 2)
    if supersample % 2:
        return grid, len(grid) // 2
    return np.vstack([grid, [[0.0, 0.0]]]), len(grid)


def _row_chunks(rig: Rig, samples: int) -> Iterator[slice]:
    h, w = rig.camera.shape
    step = max(1, _CHUNK_SAMPLES // (w * samples))
    for r in range(0, h, step):
        yield slice(r, min(r + step, h))


def _trace_rows(rig: Rig, scene: Surface, rows: slice, offsets: NDArray[np.float64], pad: int) -> _Hits:
    """Trace every sample offset of every pixel of camera rows `rows`; sample-fastest order."""
    w = rig.camera.size[0]
    y, x = np.mgrid[rows, 0:w]
    xc = (x[..., None] + offsets[:, 0]).ravel()
    yc = (y[..., None] + offsets[:, 1]).ravel()
    return _trace(rig, scene, xc, yc, pad)


def _check_drive(projected: object, rig: Rig, name: str = "projected") -> NDArray[np.float32]:
    drive = check_image(name, projected, shape=rig.projector.shape)
    if drive.min() < 0 or drive.max() > 1:
        raise InputError(f"{name} values must lie in [0, 1], got [{drive.min():g}, {drive.max():g}]")
    return drive


def render(
    rig: Rig,
    scene: Surface,
    projected: ArrayLike,
    conditions: Conditions | None = None,
    *,
    rng: np.random.Generator | int | None = None,
) -> Capture:
    """Simulate one camera frame of a projected image on a scene (module docstring: the model).

    Parameters
    ----------
    rig : Rig
        Camera and projector.
    scene : Surface
        What the camera looks at (`Plane`, `Sphere`, `Union`, `Mat5Surface`, ...).
    projected : (Hp, Wp) array
        Projector drive image in [0, 1] (uint8 / uint16 are scaled), the projector's shape.
    conditions : Conditions, optional
        The physics; default `Conditions()`.
    rng : numpy Generator or int, optional
        Source (or seed) of the sensor noise.  Default: ``conditions.seed``.

    Returns
    -------
    Capture
        ``image`` (H, W) float32 in [0, 1] and its `GroundTruth`.  A pixel is marked
        ``edge`` where its sub-pixels disagree on hitting a surface or being lit, or where one
        lies off the centre's tangent plane by more than half a pixel footprint.

    Raises
    ------
    InputError
        If `projected` has the wrong shape, non-finite values or values outside [0, 1], or
        the albedo gives values outside [0, 1].

    Notes
    -----
    Camera rows are traced in chunks of about 2**19 ray samples (float64 geometry, float32
    shading), so memory stays near 0.5 GB at any image size.  With even `supersample` the
    pixel centres are traced once more for the ground truth.  A 2592x1944 frame of
    `sphere_scene` at ``supersample=2`` takes about 15 s on one core.

    Examples
    --------
    >>> rig = virtual_rig(camera_size=(65, 49), projector_size=(32, 24))
    >>> cap = render(rig, plane_scene(), np.full((24, 32), 0.5), Conditions.ideal())
    >>> round(float(cap.image[24, 32]), 4)  # the working point: drive 0.5 times cos(incidence) 0.9701
    0.4851
    """
    cond = Conditions() if conditions is None else conditions
    drive = _check_drive(projected, rig)
    generator = np.random.default_rng(cond.seed if rng is None else rng)
    signals, truth = _render_signals(rig, scene, [drive], cond)
    return Capture(image=_sensor(signals[0], cond, generator), truth=truth)


def render_sequence(
    rig: Rig,
    scene: Surface,
    projected: Sequence[ArrayLike],
    conditions: Conditions | None = None,
    *,
    rng: np.random.Generator | int | None = None,
) -> SequenceCapture:
    """Simulate the camera frames of a sequence of projected images (PMP, Gray code) on one scene.

    The scene is traced once and shaded under each projected image, so the frames share the
    geometry, the albedo and the ground truth exactly; each frame gets its own sensor noise, drawn
    in frame order from one generator.  Frame ``k`` equals ``render(rig, scene, projected[k],
    conditions).image`` up to the noise.

    Parameters
    ----------
    rig, scene, conditions
        As for `render`.
    projected : sequence of (Hp, Wp) arrays, or a (K, Hp, Wp) array
        Projector drive images in [0, 1] (uint8 / uint16 are scaled), in projection order.
    rng : numpy Generator or int, optional
        Source (or seed) of the sensor noise of all frames.  Default: ``conditions.seed``.

    Returns
    -------
    SequenceCapture
        ``images`` (K, H, W) float32 and the common `GroundTruth`.

    Raises
    ------
    InputError
        As `render`, naming the bad image (``projected[3]``), or if `projected` is empty.

    Examples
    --------
    >>> rig = virtual_rig(camera_size=(65, 49), projector_size=(32, 24))
    >>> seq = render_sequence(rig, plane_scene(), [np.full((24, 32), v) for v in (0.25, 0.5)],
    ...                       Conditions.ideal())
    >>> seq.images.shape, round(float(seq.images[1, 24, 32] / seq.images[0, 24, 32]), 4)
    ((2, 49, 65), 2.0)
    """
    cond = Conditions() if conditions is None else conditions
    drives = [_check_drive(p, rig, f"projected[{k}]") for k, p in enumerate(projected)]
    if not drives:
        raise InputError("projected must hold at least one image")
    generator = np.random.default_rng(cond.seed if rng is None else rng)
    signals, truth = _render_signals(rig, scene, drives, cond)
    return SequenceCapture(images=np.stack([_sensor(signal, cond, generator) for signal in signals]), truth=truth)


class TracedScene:
    """A still scene traced once through a rig, then photographed under any projected image.

    What a virtual camera needs (`sliscan.devices.VirtualCamera`): many captures of one scene
    under different projector images, each as `render` would make it, without tracing the scene
    again.  ``TracedScene(rig, scene, conditions).capture(image, rng)`` equals
    ``render(rig, scene, image, conditions, rng=rng).image`` exactly (the same arithmetic).

    Parameters
    ----------
    rig, scene, conditions
        As for `render`.

    Notes
    -----
    Every ray sample's hit is kept: about 100 bytes a sample, so 30 MB for a 640x480 camera at
    ``supersample=1`` and 2.5 GB for 2592x1944 at 3; meant for small virtual cameras.

    Examples
    --------
    >>> rig = virtual_rig(camera_size=(65, 49), projector_size=(32, 24))
    >>> traced = TracedScene(rig, plane_scene(), Conditions.ideal())
    >>> drive = np.full((24, 32), 0.5)
    >>> bool(np.array_equal(traced.capture(drive), render(rig, plane_scene(), drive, Conditions.ideal()).image))
    True
    """

    def __init__(self, rig: Rig, scene: Surface, conditions: Conditions | None = None) -> None:
        self.rig = rig
        self.scene = scene
        self.conditions = Conditions() if conditions is None else conditions
        offsets, centre = _subpixel_offsets(self.conditions.supersample)
        self._samples = len(offsets)
        pad = _projector_pad(self.conditions, float(rig.projector.K[0, 0]))
        self._chunks = []
        self._depth = np.empty(rig.camera.shape)
        for rows in _row_chunks(rig, self._samples):
            hits = _trace_rows(rig, scene, rows, offsets, pad)
            self._chunks.append((rows, hits, _albedo(rig.camera, hits, self.conditions)))
            self._depth[rows] = _centre_depths(rig.camera, hits, self._samples, centre).reshape(-1, rig.camera.size[0])

    def signal(self, projected: ArrayLike) -> NDArray[np.float32]:
        """Camera signal ``(H, W)`` float32 (full scale 1) before the sensor: no noise, no clipping."""
        light = _ProjectorLight(_check_drive(projected, self.rig), self.conditions, float(self.rig.projector.K[0, 0]))
        signal = np.empty(self.rig.camera.shape, dtype=np.float32)
        for rows, hits, albedo in self._chunks:
            signal[rows] = _pixel_signal(self.rig, hits, albedo, light, self.conditions, self._samples)
        return _camera_blur(signal, self.conditions, self.rig.camera, self._depth)

    def capture(self, projected: ArrayLike, rng: np.random.Generator | int | None = None) -> NDArray[np.float32]:
        """A camera frame ``(H, W)`` float32 in [0, 1] of `projected` (Hp, Wp) in [0, 1]: `signal`
        through the sensor, with noise from `rng` (a Generator or seed; default the conditions' seed)."""
        generator = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(
            self.conditions.seed if rng is None else rng)
        return _sensor(self.signal(projected), self.conditions, generator)


def _render_signals(
    rig: Rig, scene: Surface, drives: Sequence[NDArray[np.float32]], cond: Conditions
) -> tuple[list[NDArray[np.float32]], GroundTruth]:
    """Camera signal before the sensor (one ``(H, W)`` float32 per drive image) and the truth.

    Traces every chunk of camera rows once and shades it under each drive image.
    """
    lights = [_ProjectorLight(drive, cond, float(rig.projector.K[0, 0])) for drive in drives]
    pad = lights[0].pad
    offsets, centre = _subpixel_offsets(cond.supersample)
    shape = rig.camera.shape
    signals = [np.empty(shape, dtype=np.float32) for _ in drives]
    points = np.empty((*shape, 3), dtype=np.float32)
    proj = np.empty((*shape, 2), dtype=np.float32)
    albedo = np.empty(shape, dtype=np.float32)
    lit, surface, edge = (np.empty(shape, dtype=bool) for _ in range(3))
    focal = rig.camera.K[0, 0]

    for rows in _row_chunks(rig, len(offsets)):
        hits = _trace_rows(rig, scene, rows, offsets, pad)
        alb = _albedo(rig.camera, hits, cond)
        n_pix = len(hits.surface) // len(offsets)
        per_pixel = (n_pix, len(offsets))
        for signal, light in zip(signals, lights):
            signal[rows] = _pixel_signal(rig, hits, alb, light, cond, len(offsets))
        sub_lit = (hits.reached & hits.inside).reshape(per_pixel)
        sub_surface = hits.surface.reshape(per_pixel)
        sub_points = hits.points.reshape(*per_pixel, 3)
        c_points = sub_points[:, centre]
        c_normal = hits.normal.reshape(*per_pixel, 3)[:, centre]
        off_plane = np.abs(np.einsum("psk,pk->ps", sub_points - c_points[:, None], c_normal))
        footprint = (c_points - rig.camera.centre) @ rig.camera.axis / focal
        stepped = (np.where(np.isnan(off_plane), 0.0, off_plane) > 0.5 * footprint[:, None]).any(axis=1)
        mixed = (sub_lit.any(axis=1) != sub_lit.all(axis=1)) | (sub_surface.any(axis=1) != sub_surface.all(axis=1))

        block = (rows.stop - rows.start, shape[1])
        points[rows] = c_points.reshape(*block, 3)
        proj[rows] = hits.proj.reshape(*per_pixel, 2)[:, centre].reshape(*block, 2)
        lit[rows] = sub_lit[:, centre].reshape(block)
        surface[rows] = sub_surface[:, centre].reshape(block)
        albedo[rows] = np.where(sub_surface[:, centre], alb.reshape(per_pixel)[:, centre], np.nan).reshape(block)
        edge[rows] = (mixed | stepped).reshape(block)

    depth = (points.astype(np.float64) - rig.camera.centre) @ rig.camera.axis
    signals = [_camera_blur(signal, cond, rig.camera, depth) for signal in signals]
    return signals, GroundTruth(points=points, proj=proj, lit=lit, surface=surface, albedo=albedo, edge=edge)


def _pixel_signal(rig: Rig, hits: _Hits, albedo: NDArray[np.float32], light: _ProjectorLight, cond: Conditions,
                  samples: int) -> NDArray[np.float32]:
    """Camera signal of a chunk of whole camera rows ``(rows, W)``: `_shade` of its ray samples
    (`samples` per pixel, sample-fastest) averaged over the pixel's aperture samples."""
    value = _shade(hits, albedo, light, cond, rig.projector_distance_mm)
    n_sub = cond.supersample**2
    return value.reshape(-1, samples)[:, :n_sub].mean(axis=1).reshape(-1, rig.camera.size[0])


def _camera_blur(signal: NDArray[np.float32], cond: Conditions, camera: Pinhole,
                 depth: NDArray[np.float64]) -> NDArray[np.float32]:
    """The camera optics' Gaussian blur (`Conditions.camera_blur_px`), if any; with a focus
    (`Conditions.camera_focus_mm`) each pixel's by the `depth` (mm along the camera's axis,
    ``(H, W)``, NaN where no surface: blurred as in focus) its centre sees, blended between the
    signal blurred at the two `DEFOCUS_STEP_PX` levels around it."""

    def blurred(sigma: float) -> NDArray[np.float32]:
        return signal if sigma <= 0 else scipy.ndimage.gaussian_filter(signal, sigma, mode="nearest", truncate=4.0)

    if cond.camera_focus_mm is None:
        return blurred(cond.camera_blur_px)
    sigma = defocus_blur(depth, in_focus_px=cond.camera_blur_px, focus_mm=cond.camera_focus_mm,
                         aperture_mm=cond.camera_aperture_mm, focal_px=float(camera.K[0, 0]))
    low, upper = _blend_weights(np.where(np.isfinite(sigma), sigma, cond.camera_blur_px))
    out = np.zeros_like(signal)
    for level in range(int(low.min()), int(low.max()) + 2):
        weight = np.where(low == level, 1 - upper, 0) + np.where(low == level - 1, upper, 0)
        if weight.any():
            out += weight * blurred(level * DEFOCUS_STEP_PX)
    return out


def _centre_depths(camera: Pinhole, hits: _Hits, samples: int, centre: int) -> NDArray[np.float64]:
    """Depth along the camera's axis (mm) of the surface each pixel centre of a chunk sees
    (NaN where none), ``(n_pixels,)``."""
    points = hits.points.reshape(-1, samples, 3)[:, centre]
    return (points - camera.centre) @ camera.axis


def _albedo(camera: Pinhole, hits: _Hits, conditions: Conditions) -> NDArray[np.float32]:
    """Albedo of each ray sample (0 where no surface), checked to lie in [0, 1].

    An albedo with sharp edges that has an ``area_mean(xyz, footprint)`` method gives its mean
    over the sample's footprint (`_footprints`), so an edge covers a pixel by area, as light
    does on a sensor; others give their value at the hit point.
    """
    albedo = np.zeros(len(hits.surface), dtype=np.float32)
    on = hits.surface
    texture = conditions.albedo
    if hasattr(texture, "area_mean"):
        footprint = _footprints(camera, hits.points[on], hits.normal[on], hits.pixel[on], 1 / conditions.supersample)
        albedo[on] = texture.area_mean(hits.points[on], footprint)
    else:
        albedo[on] = texture(hits.points[on])
    if albedo.min(initial=0) < 0 or albedo.max(initial=0) > 1:
        raise InputError(f"albedo values must lie in [0, 1], got [{albedo.min():g}, {albedo.max():g}]")
    return albedo


def _footprints(camera: Pinhole, points: NDArray[np.float64], normals: NDArray[np.float64],
                pixels: NDArray[np.float64], step: float) -> NDArray[np.float64]:
    """Where each sample's square of side `step` camera pixels lands on the surface.

    Parameters
    ----------
    camera : Pinhole
    points, normals : (N, 3) float64 arrays
        The samples' hit points (mm) and surface normals.
    pixels : (N, 2) float64 array
        The samples' pixel positions ``(x, y)``.
    step : float
        The side of a sample's square, in pixels (``1 / supersample``).

    Returns
    -------
    footprint : (N, 2, 3) float64 array
        The square's edge vectors along image x and y on the tangent plane at each point, in
        mm: from the point to where the ray `step` pixels further along x (or y) meets that
        plane, through the camera's lens (a forward difference: the footprint's size only
        shapes the ramp of coverage across an edge, not where the edge lies).  Zero where the
        plane is seen edge-on.
    """
    centre = camera.centre
    reach = _dot(normals, points - centre)
    footprint = np.empty((len(points), 2, 3))
    for axis in range(2):
        moved = pixels + step * np.eye(2)[axis]
        rays = camera.rays(moved[:, 0], moved[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            footprint[:, axis] = centre + rays * (reach / _dot(normals, rays))[:, None] - points
    footprint[~np.isfinite(footprint).all(axis=(1, 2))] = 0.0
    return footprint


def _shade(hits: _Hits, albedo: NDArray[np.float32], light: _ProjectorLight, conditions: Conditions,
           falloff_mm: float) -> NDArray[np.float32]:
    """Camera signal (full scale = 1) of each ray sample, before the sensor.

    `albedo` is `_albedo` of the samples; the inverse-square falloff is 1 at `falloff_mm` from
    the projector centre.
    """
    on = hits.reached
    irradiance = np.zeros(len(on), dtype=np.float32)
    irradiance[on] = light.sample(hits.proj[on, 0], hits.proj[on, 1], hits.depth[on]) * hits.cos[on]
    if conditions.inverse_square:
        irradiance[on] *= (falloff_mm / hits.dist[on]) ** 2
    return conditions.exposure * albedo * (irradiance + np.float32(conditions.ambient))


def _sensor(signal: NDArray[np.float32], conditions: Conditions, rng: np.random.Generator) -> NDArray[np.float32]:
    """Shot and read noise (electrons), saturation at full scale, quantisation."""
    out = signal
    if conditions.full_well_e is not None:
        full = conditions.full_well_e
        electrons = rng.poisson(np.maximum(signal, 0).astype(np.float64) * full).astype(np.float64)
        electrons += rng.normal(0.0, conditions.read_noise_e, signal.shape)
        out = (electrons / full).astype(np.float32)
    out = np.clip(out, 0.0, 1.0)
    if conditions.bit_depth is not None:
        levels = np.float32(2**conditions.bit_depth - 1)
        out = np.round(out * levels) / levels
    return out.astype(np.float32, copy=False)


def projector_rows(rig: Rig, scene: Surface) -> NDArray[np.float32]:
    """Ground-truth projector row ``yp`` seen by each camera pixel centre.

    Parameters
    ----------
    rig : Rig
    scene : Surface

    Returns
    -------
    yp_map : (H, W) float32 array
        Projector row in projector pixels; NaN where the pixel's point is not lit (no surface,
        shadowed, outside the projector image or facing away from it).

    Examples
    --------
    >>> rig = virtual_rig(camera_size=(65, 49), projector_size=(32, 24))
    >>> float(projector_rows(rig, plane_scene())[24, 32].round(3))  # the working point
    11.5
    """
    offsets, _ = _subpixel_offsets(1)
    yp = np.empty(rig.camera.shape, dtype=np.float32)
    for rows in _row_chunks(rig, 1):
        hits = _trace_rows(rig, scene, rows, offsets, 0)
        yp[rows] = np.where(hits.reached & hits.inside, hits.proj[:, 1], np.nan).reshape(-1, yp.shape[1])
    return yp


# --------------------------------------------------------------------------------------------
# Thesis chapter 5: projector and camera views of a mat5 target
# --------------------------------------------------------------------------------------------


def _check_grid(points: ArrayLike, valid: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """A mat5 point grid as float64 ``(H, W, 3)`` and its mask ``(H, W)``, finite points only."""
    pts = np.array(points, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise InputError(f"points must have shape (H, W, 3), got {pts.shape}")
    mask = np.asarray(valid)
    if mask.shape != pts.shape[:2]:
        raise InputError(f"valid must have shape {pts.shape[:2]} (H, W), got {mask.shape}")
    if mask.dtype != np.bool_:
        raise InputError(f"valid must be a bool array, got {mask.dtype}")
    return pts, mask & np.isfinite(pts).all(axis=2)


def _nearest_pixel(device: Pinhole, xyz: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Flat index of the pixel nearest each point's image (-1 outside the image) and its depth."""
    xy, depth = device.project(xyz)
    w, h = device.size
    with np.errstate(invalid="ignore"):
        ij = np.floor(xy + 0.5)
        inside = (depth > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    flat = np.where(inside, ij[:, 1] * w + ij[:, 0], -1.0).astype(np.int64)
    return flat, depth


def _splat(
    flat: NDArray[np.int64], depth: NDArray[np.float64], value: NDArray[np.float32], shape: tuple[int, int]
) -> NDArray[np.float32]:
    """Z-buffered splat: each pixel (flat index; -1 = none) takes the value of its nearest point."""
    keep = flat >= 0
    flat, depth, value = flat[keep], depth[keep], value[keep]
    order = np.lexsort((depth, flat))
    flat, value = flat[order], value[order]
    first = np.r_[True, flat[1:] != flat[:-1]]
    image = np.zeros(shape[0] * shape[1], dtype=np.float32)
    image[flat[first]] = value[first]
    return image.reshape(shape)


def _lit_texture(
    rig: Rig, points: ArrayLike, valid: ArrayLike, texture: ArrayLike, projected: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float32]]:
    """Valid points (N, 3), their projector pixel and depth, and texture times pattern there."""
    pts, ok = _check_grid(points, valid)
    tex = check_image("texture", texture, shape=ok.shape)
    drive = _check_drive(projected, rig)
    xyz = pts[ok]
    flat, depth = _nearest_pixel(rig.projector, xyz)
    pattern = np.where(flat >= 0, drive.ravel()[np.maximum(flat, 0)], 0.0)
    return xyz, flat, depth, (tex[ok] * pattern).astype(np.float32)


def projector_view(
    rig: Rig, points: ArrayLike, valid: ArrayLike, texture: ArrayLike, projected: ArrayLike
) -> NDArray[np.float32]:
    """What the projector "sees": the target's texture times the pattern, in projector pixels.

    The vectorised form of the thesis's ``sim_prog_proj`` (appendix 1.2, fig. 5.1): every valid
    mat5 point goes to its nearest projector pixel and carries ``texture * projected`` there.
    Two deliberate differences from the MATLAB loop: where several points land on one pixel
    the one nearest the projector wins (a z-buffer; MATLAB kept the last written), and points
    outside the projector image are dropped (MATLAB clamped them onto the border).

    Parameters
    ----------
    rig : Rig
    points : (H, W, 3) float array
        The target's mat5 points, in mm; NaN where invalid.
    valid : (H, W) bool array
    texture : (H, W) array
        The target's texture C0 in [0, 1].
    projected : (Hp, Wp) array
        Projector drive image in [0, 1].

    Returns
    -------
    view : (Hp, Wp) float32 array
        0 where no point lands.
    """
    _, flat, depth, value = _lit_texture(rig, points, valid, texture, projected)
    return _splat(flat, depth, value, rig.projector.shape)


def camera_view(
    rig: Rig, points: ArrayLike, valid: ArrayLike, texture: ArrayLike, projected: ArrayLike
) -> NDArray[np.float32]:
    """The simulated camera image of a mat5 target under a projected pattern (fig. 5.2).

    The vectorised form of the thesis's ``sim_prog_cam`` (appendix 1.3): each valid point
    takes ``texture * projected`` at its nearest projector pixel (0 outside the projector
    image) and is splatted into its nearest camera pixel, the point nearest the camera winning
    (MATLAB: the last written).  Like the thesis, this ignores cast shadows, shading, blur and
    noise; for a physically based capture of the same target use
    ``render(rig, Mat5Surface(points, valid), projected, conditions)``.

    Parameters
    ----------
    rig, points, valid, texture, projected
        As for `projector_view`.

    Returns
    -------
    view : (H, W) float32 array
        Camera image; 0 where no point lands.
    """
    xyz, _, _, value = _lit_texture(rig, points, valid, texture, projected)
    flat, depth = _nearest_pixel(rig.camera, xyz)
    return _splat(flat, depth, value, rig.camera.shape)
