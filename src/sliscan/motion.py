"""Moving scenes for 3D video: a rigid object translating and rotating in front of the rig.

A single-shot pattern exists so that moving objects can be scanned (thesis, abstract and
section 2.2).  This module moves an object of the virtual rig frame by frame and renders one
capture per frame, each with its own ground truth and its own sensor noise, so batch scanning
(`sliscan.batch`) can be checked frame by frame against the truth.

Conventions: world coordinates in mm (camera frame of the virtual rig); the object's pose at
frame ``k`` maps an object point ``x`` to ``pivot + R_k (x - pivot) + t_k``.  Planes of a scene
(the wall behind the sphere) are the static background; everything else moves.  The texture
(albedo) moves with the object: it is evaluated at the object-frame point.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError
from sliscan.simulate import Capture, Conditions, Plane, Rig, Surface, Union, render


@dataclass(frozen=True)
class Motion:
    """Constant-velocity rigid motion over `frames` frames, centred on the nominal pose.

    Parameters
    ----------
    frames : int
        Number of frames (>= 1).
    velocity_mm : (3,) floats
        Translation per frame, mm (X right, Y down, Z away from the camera).
    spin_deg : float
        Rotation per frame about `axis` through the pivot, degrees.
    axis : (3,) floats
        Rotation axis (normalised on use); default the vertical (Y) axis.

    The middle frame is the nominal pose, so the sequence sweeps evenly around the working
    point: frame ``k`` is displaced by ``(k - (frames - 1) / 2)`` times the per-frame motion.

    Examples
    --------
    >>> m = Motion(frames=3, velocity_mm=(2.0, 0.0, 0.0), spin_deg=90.0)
    >>> rotation, translation = m.pose(2)
    >>> translation.tolist(), np.round(rotation @ [1.0, 0.0, 0.0], 6).tolist()
    ([2.0, 0.0, 0.0], [0.0, 0.0, -1.0])
    """

    frames: int
    velocity_mm: tuple[float, float, float] = (3.0, 0.0, 0.0)
    spin_deg: float = 4.0
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)

    def __post_init__(self) -> None:
        if not (isinstance(self.frames, (int, np.integer)) and self.frames >= 1):
            raise InputError(f"frames must be a positive integer, got {self.frames!r}")
        values = np.array([*self.velocity_mm, self.spin_deg, *self.axis], dtype=np.float64)
        if values.shape != (7,) or not np.all(np.isfinite(values)):
            raise InputError("velocity_mm and axis need 3 finite values each, spin_deg a finite value")
        if np.linalg.norm(self.axis) == 0:
            raise InputError("axis must be non-zero")

    def pose(self, k: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Rotation (3, 3) and translation (3,) mm of frame `k` (Rodrigues' formula)."""
        if not 0 <= k < self.frames:
            raise InputError(f"frame {k} is outside 0..{self.frames - 1}")
        steps = k - (self.frames - 1) / 2
        u = np.asarray(self.axis, dtype=np.float64) / np.linalg.norm(self.axis)
        angle = math.radians(self.spin_deg * steps)
        cross = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
        rotation = np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross
        return rotation, steps * np.asarray(self.velocity_mm, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class Moved:
    """`surface` under a rigid pose: ``world = pivot + rotation @ (object - pivot) + translation``.

    Rays are taken into the object's frame, intersected there and the normals brought back;
    a rotation keeps lengths, so the ray parameter is the same in both frames.
    """

    surface: Surface
    rotation: NDArray[np.float64]
    translation: NDArray[np.float64]
    pivot: NDArray[np.float64]

    def to_object(self, xyz: ArrayLike) -> NDArray[np.float64]:
        """World points ``(N, 3)`` mm in the object's own frame."""
        return (np.asarray(xyz, dtype=np.float64) - self.pivot - self.translation) @ self.rotation + self.pivot

    def intersect(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """See `sliscan.simulate.Surface.intersect`."""
        d = np.asarray(dirs, dtype=np.float64) @ self.rotation
        t, normal = self.surface.intersect(self.to_object(origins), d)
        return t, normal @ self.rotation.T


@dataclass(frozen=True, eq=False)
class MovedAlbedo:
    """An albedo carried by a moving object: points of the object take `base` at their
    object-frame position, points on a static `background` plane at their world position."""

    base: object
    moved: Moved
    background: tuple[Plane, ...] = ()

    def __call__(self, xyz: ArrayLike) -> NDArray[np.float32]:
        """Albedo ``(N,)`` float32 at world points ``xyz`` ``(N, 3)`` in mm."""
        return self._albedo(np.asarray(xyz, dtype=np.float64), None)

    def area_mean(self, xyz: ArrayLike, footprint: ArrayLike) -> NDArray[np.float32]:
        """Mean albedo ``(N,)`` over sample footprints ``(N, 2, 3)`` (mm; see
        `sliscan.simulate.CheckerAlbedo.area_mean`) where `base` has ``area_mean``, else its
        value at the points."""
        return self._albedo(np.asarray(xyz, dtype=np.float64), np.asarray(footprint, dtype=np.float64))

    def _albedo(self, xyz: NDArray[np.float64], footprint: NDArray[np.float64] | None) -> NDArray[np.float32]:
        """`base` at the object-frame points (and footprints) of the object, at the world ones
        on the background."""
        on_background = np.zeros(len(xyz), dtype=bool)
        for plane in self.background:
            on_background |= np.abs((xyz - plane.point) @ np.asarray(plane.normal)) < 1e-6
        turned = None if footprint is None else footprint @ self.moved.rotation
        out = self._base(self.moved.to_object(xyz), turned)
        if on_background.any():
            out[on_background] = self._base(xyz[on_background], None if footprint is None else footprint[on_background])
        return out

    def _base(self, xyz: NDArray[np.float64], footprint: NDArray[np.float64] | None) -> NDArray[np.float32]:
        if footprint is None or not hasattr(self.base, "area_mean"):
            return np.asarray(self.base(xyz), dtype=np.float32)  # type: ignore[operator]
        return np.asarray(self.base.area_mean(xyz, footprint), dtype=np.float32)


def split_background(scene: Surface) -> tuple[Surface, tuple[Plane, ...]]:
    """The moving part of a scene and its static background planes.

    A `Union` keeps its planes still and moves the rest; any other surface (a single plane
    included) moves as a whole.
    """
    if not isinstance(scene, Union):
        return scene, ()
    planes = tuple(s for s in scene.surfaces if isinstance(s, Plane))
    movers = [s for s in scene.surfaces if not isinstance(s, Plane)]
    if not movers:
        return scene, ()
    return (movers[0] if len(movers) == 1 else Union(*movers)), planes


def render_motion(rig: Rig, scene: Surface, projected: ArrayLike, motion: Motion,
                  conditions: Conditions | None = None, *, pivot: ArrayLike | None = None) -> Iterator[Capture]:
    """One capture per frame of `scene` moving by `motion`, lit by the same projected image.

    Parameters
    ----------
    rig : Rig
    scene : Surface
        The scene at its nominal pose; its planes stay still when it is a `Union`
        (`split_background`).
    projected : (Hp, Wp) array
        Projector drive image in [0, 1].
    motion : Motion
    conditions : Conditions, optional
        The physics; frame ``k`` uses seed ``conditions.seed + k`` (its own sensor noise; a
        seed of None stays None: fresh noise).
    pivot : (3,) floats, optional
        Centre of rotation in mm; default the rig's working point.

    Yields
    ------
    Capture
        The frame and its ground truth, frame by frame (nothing is kept: memory does not
        grow with the number of frames).
    """
    cond = Conditions() if conditions is None else conditions
    for k in range(motion.frames):
        frame_scene, frame_cond = posed_scene(rig, scene, motion, k, cond, pivot=pivot)
        yield render(rig, frame_scene, projected, frame_cond)


def posed_scene(rig: Rig, scene: Surface, motion: Motion, k: int, conditions: Conditions, *,
                pivot: ArrayLike | None = None) -> tuple[Surface, Conditions]:
    """Frame `k` of `scene` moving by `motion`: the moved scene and its conditions (the albedo
    carried by the object, seed ``conditions.seed + k``); what `render_motion` renders.

    Parameters are those of `render_motion`.
    """
    centre = rig.working_point if pivot is None else np.asarray(pivot, dtype=np.float64)
    mover, background = split_background(scene)
    rotation, translation = motion.pose(k)
    moved = Moved(mover, rotation, translation, centre)
    frame_scene = Union(moved, *background) if background else moved
    seed = None if conditions.seed is None else conditions.seed + k
    return frame_scene, conditions.with_(albedo=MovedAlbedo(conditions.albedo, moved, background), seed=seed)
