"""PLY point clouds through the `plyfile` library.

Files are binary little endian with one ``vertex`` element: float32 ``x, y, z`` (mm), optional
float32 ``nx, ny, nz`` and uchar ``red, green, blue`` (the grey texture replicated).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from plyfile import PlyData, PlyElement, PlyParseError

from sliscan._validate import InputError, atomic_path, to_uint8

# OpenCV's luma weights, as `sliscan._validate.read_image` uses for colour images.
_LUMA = (0.299, 0.587, 0.114)


def _check_points(name: str, value: ArrayLike, n: int | None) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or (n is not None and arr.shape[0] != n):
        want = "(N, 3)" if n is None else f"({n}, 3)"
        raise InputError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} has non-finite values (NaN or inf)")
    return arr


def write_point_cloud(path: str | os.PathLike, points: ArrayLike, grey: ArrayLike | None = None,
                      normals: ArrayLike | None = None) -> Path:
    """Write a point cloud as a binary little-endian PLY file, atomically.

    Parameters
    ----------
    path : path
        Destination; missing folders are created.
    points : (N, 3) float array
        Xw, Yw, Zw in mm, finite (select the valid points first).
    grey : (N,) float array in [0, 1], optional
        Grey level of each point, stored as equal uchar red, green and blue.
    normals : (N, 3) float array, optional
        Unit normals, stored as float32 ``nx, ny, nz``.

    Returns
    -------
    path : Path
        The file written.

    Raises
    ------
    InputError
        On shapes that disagree or non-finite values.
    """
    points = _check_points("points", points, None)
    n = points.shape[0]
    fields = [(("x", "y", "z"), "<f4", points)]
    if normals is not None:
        fields.append((("nx", "ny", "nz"), "<f4", _check_points("normals", normals, n)))
    if grey is not None:
        grey = np.asarray(grey, dtype=np.float64)
        if grey.shape != (n,):
            raise InputError(f"grey must have shape ({n},), got {grey.shape}")
        if not np.all(np.isfinite(grey)):
            raise InputError("grey has non-finite values (NaN or inf)")
        fields.append((("red", "green", "blue"), "u1", np.repeat(to_uint8(grey)[:, None], 3, axis=1)))
    vertex = np.empty(n, dtype=[(name, dtype) for names, dtype, _ in fields for name in names])
    for names, _, values in fields:
        for k, name in enumerate(names):
            vertex[name] = values[:, k]
    ply = PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        ply.write(f)
    return Path(path)


def read_point_cloud(path: str | os.PathLike) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    """Read the vertices of a PLY file (binary or ASCII).

    Parameters
    ----------
    path : path
        A PLY file with a ``vertex`` element holding ``x, y, z``.

    Returns
    -------
    points : (N, 3) float32 array
        Vertex coordinates (mm for sliscan's files).
    grey : (N,) float32 array in [0, 1], or None
        Grey level from ``red, green, blue`` (luma weights; exact for sliscan's grey files);
        None when the file has no colour.

    Raises
    ------
    InputError
        If the file cannot be read, is not PLY, or has no ``vertex`` element with x, y, z.
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            ply = PlyData.read(f, mmap=False)
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except (PlyParseError, ValueError, IndexError) as exc:
        raise InputError(f"{p}: not a valid PLY file ({exc})") from None
    if "vertex" not in ply:
        raise InputError(f"{p}: no 'vertex' element")
    vertex = ply["vertex"].data
    names = set(vertex.dtype.names or ())
    if not {"x", "y", "z"} <= names:
        raise InputError(f"{p}: vertices lack x, y, z")
    points = np.stack([vertex[c] for c in ("x", "y", "z")], axis=-1).astype(np.float32)
    if not {"red", "green", "blue"} <= names:
        return points, None
    rgb = np.stack([vertex[c] for c in ("red", "green", "blue")], axis=-1).astype(np.float64)
    grey = (rgb @ np.array(_LUMA)) / 255.0
    return points, grey.astype(np.float32)
