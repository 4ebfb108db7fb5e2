"""The mat5 scan format (thesis section 4.1, MATLAB ``mat5write``/``mat5read``, appendix 1.4-1.5).

For a prefix ``P`` a scan is five files:

- ``PX.byt``, ``PY.byt``, ``PZ.byt``: world coordinates in mm, raw little-endian float32,
  ``H*W`` values row by row (MATLAB writes ``reshape(xw', 1, my*nx)``, i.e. row-major);
- ``PC.bmp``: the texture, 8-bit grey;
- ``PI.bmp``: the indicator, 8-bit, 255 where the point is valid and 0 elsewhere (any nonzero
  value counts as valid when reading).

The ``.byt`` files carry no size: it comes from ``PI.bmp``.  Invalid points are stored as 0 in
all three coordinates (the thesis's tools set ``Z = 0`` where ``I == 0``) and read back as NaN.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, atomic_path, check_image, read_image, to_uint8
from sliscan.formats.premat5 import read_byt

#: Suffixes of the five files, in the order `write_mat5` returns them.
SUFFIXES = ("X.byt", "Y.byt", "Z.byt", "C.bmp", "I.bmp")


def mat5_paths(prefix: str | os.PathLike) -> list[Path]:
    """The five file names of the mat5 scan `prefix` (``PX.byt`` ... ``PI.bmp``).

    Examples
    --------
    >>> [p.name for p in mat5_paths("out/sphere")]
    ['sphereX.byt', 'sphereY.byt', 'sphereZ.byt', 'sphereC.bmp', 'sphereI.bmp']
    """
    return [Path(f"{os.fspath(prefix)}{suffix}") for suffix in SUFFIXES]


def write_mat5(prefix: str | os.PathLike, points: ArrayLike, valid: ArrayLike, texture: ArrayLike) -> list[Path]:
    """Write a scan as mat5 files; invalid points are stored as 0.

    All five files are written to temporary names first and renamed only when every one is
    complete, so a failure leaves no partial scan behind.  Missing folders in `prefix` are
    created.

    Parameters
    ----------
    prefix : path
        File prefix, possibly with folders: ``out/sphere`` writes ``out/sphereX.byt`` etc.
    points : (H, W, 3) float array
        Xw, Yw, Zw in mm; must be finite where `valid` (anything is allowed elsewhere).
    valid : (H, W) bool array
        Valid points; written as 255 in the indicator image, the rest as 0.
    texture : (H, W) array
        Grey texture, float in [0, 1] (or uint8 / uint16), quantised to 8 bits.

    Returns
    -------
    paths : list of Path
        ``PX.byt, PY.byt, PZ.byt, PC.bmp, PI.bmp``.

    Raises
    ------
    InputError
        On shapes that disagree or non-finite valid points.
    """
    valid = np.asarray(valid)
    if valid.dtype != np.bool_ or valid.ndim != 2:
        raise InputError(f"valid must be a 2-D (H, W) bool array, got {valid.dtype} with shape {valid.shape}")
    shape = valid.shape
    points = np.asarray(points, dtype=np.float64)
    if points.shape != (*shape, 3):
        raise InputError(f"points must have shape {(*shape, 3)} (H, W, 3), got {points.shape}")
    texture = check_image("texture", texture, shape=shape)
    bad = int(np.count_nonzero(valid & ~np.all(np.isfinite(points), axis=-1)))
    if bad:
        raise InputError(f"points are non-finite at {bad} of {np.count_nonzero(valid)} valid pixels")
    stored = np.where(valid[..., None], points, 0.0).astype("<f4")
    contents = [np.ascontiguousarray(stored[..., k]).tobytes() for k in range(3)]
    contents += [_encode_bmp(to_uint8(texture)), _encode_bmp(np.where(valid, 255, 0).astype(np.uint8))]
    paths = mat5_paths(prefix)
    with contextlib.ExitStack() as stack:
        for path, data in zip(paths, contents):
            stack.enter_context(atomic_path(path)).write_bytes(data)
    return paths


def _encode_bmp(image: NDArray[np.uint8]) -> bytes:
    ok, buf = cv2.imencode(".bmp", image)
    if not ok:  # pragma: no cover - OpenCV always encodes 8-bit grey BMP
        raise InputError("cannot encode a BMP image")
    return buf.tobytes()


def read_mat5(prefix: str | os.PathLike) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.float32]]:
    """Read a mat5 scan written by `write_mat5` or by the thesis's tools.

    Parameters
    ----------
    prefix : path
        File prefix (``out/sphere`` reads ``out/sphereX.byt`` ...).

    Returns
    -------
    points : (H, W, 3) float32 array
        Xw, Yw, Zw in mm; NaN where the indicator is 0.
    valid : (H, W) bool array
        Where the indicator image is nonzero.
    texture : (H, W) float32 array
        The C image in [0, 1].

    Raises
    ------
    InputError
        A missing or unreadable file, a texture whose size differs from the indicator's, or a
        ``.byt`` file whose byte count is not ``4*H*W``; the message names the file.
    """
    px, py, pz, pc, pi = mat5_paths(prefix)
    valid = read_image(pi) > 0
    shape = valid.shape
    texture = read_image(pc)
    if texture.shape != shape:
        raise InputError(f"{pc}: size {texture.shape[1]}x{texture.shape[0]} differs from the indicator's "
                         f"{shape[1]}x{shape[0]} ({pi})")
    points = np.stack([read_byt(p, shape) for p in (px, py, pz)], axis=-1)
    points[~valid] = np.nan
    return points, valid, texture
