"""Shared input checks, image I/O at the file boundary, and atomic writes.

Every check raises `InputError` (a `ValueError`) with a one-line message that names what is
wrong: ``yp_map must have shape (480, 640) (H, W), got (640, 480)``.  File readers put the file
name first: ``scan.png: not an image (cannot decode)``.
"""

from __future__ import annotations

import contextlib
import numbers
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray


class InputError(ValueError):
    """Bad input: a file, an array or a parameter the library cannot use (one-line message)."""


#: Largest image or device size accepted (pixels per side, pixels in all): a bound that keeps a
#: broken file's declared size from turning into a huge allocation.
MAX_IMAGE_SIDE = 1 << 16
MAX_IMAGE_PIXELS = 1 << 28


def check_size(name: str, size: object, *, minimum: int = 1) -> tuple[int, int]:
    """`size` as a ``(W, H)`` tuple of int: two whole numbers of at least `minimum`, at most
    `MAX_IMAGE_SIDE` a side and `MAX_IMAGE_PIXELS` in all (what a broken file may declare)."""
    try:
        w, h = size  # type: ignore[misc]
    except (TypeError, ValueError):
        raise InputError(f"{name} must be (W, H), got {size!r}") from None
    if not all(_is_whole(v) for v in (w, h)):
        raise InputError(f"{name} must be two whole numbers (W, H), got {size!r}")
    w, h = int(w), int(h)
    if w < minimum or h < minimum:
        raise InputError(f"{name} must be at least {minimum}x{minimum}, got {w}x{h}")
    if max(w, h) > MAX_IMAGE_SIDE or w * h > MAX_IMAGE_PIXELS:
        raise InputError(f"{name} {w}x{h} is too large (at most {MAX_IMAGE_SIDE} px a side and "
                         f"{MAX_IMAGE_PIXELS} px in all)")
    return w, h


def _is_whole(value: object) -> bool:
    """An integer (not a bool), or a float with an integral value."""
    if isinstance(value, bool):
        return False
    return isinstance(value, numbers.Integral) or (isinstance(value, float) and value.is_integer())


def check_finite_matrix(name: str, value: object, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """`value` as a float64 array of exactly `shape` with only finite entries."""
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be numeric with shape {shape}") from None
    if arr.shape != shape:
        raise InputError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} has non-finite entries (NaN or inf)")
    return arr


def check_image(name: str, image: object, *, shape: tuple[int, int] | None = None,
                copy: bool = True) -> NDArray[np.float32]:
    """A 2-D image as float32 in [0, 1] (uint8 / uint16 are scaled), never the caller's array
    unless `copy` is false and it is float32 already (for a caller that only reads it).

    Parameters
    ----------
    name : str
        Used in the error message.
    image : (H, W) array
        uint8, uint16, bool or float (floats are taken as already in [0, 1]).
    shape : (H, W), optional
        Required shape.
    copy : bool
        False: return a float32 `image` itself (checked) instead of a copy.
    """
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        raise InputError(f"{name} must be a grey (H, W) image, got colour shape {arr.shape}")
    if arr.ndim != 2:
        raise InputError(f"{name} must be a 2-D (H, W) image, got shape {arr.shape}")
    if shape is not None and arr.shape != tuple(shape):
        raise InputError(f"{name} must have shape {tuple(shape)} (H, W), got {arr.shape}")
    if arr.dtype in (np.uint8, np.uint16):  # one pass, the values of astype then divide
        return np.divide(arr, np.float32(np.iinfo(arr.dtype).max), dtype=np.float32)
    if arr.dtype == np.bool_:
        return arr.astype(np.float32)
    if not np.issubdtype(arr.dtype, np.floating):
        raise InputError(f"{name} must be uint8, uint16 or float, got {arr.dtype}")
    out = arr.astype(np.float32, copy=copy)
    if not np.all(np.isfinite(out)):
        raise InputError(f"{name} has non-finite pixels (NaN or inf)")
    return out


def read_image(path: str | os.PathLike) -> NDArray[np.float32]:
    """Read a grey image file (PNG, BMP, TIFF, ...) as ``(H, W)`` float32 in [0, 1].

    Colour images are converted to grey (OpenCV's luma weights); 16-bit files keep their depth.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    return decode_image(np.fromfile(p, dtype=np.uint8), str(p))


def decode_image(data: bytes | NDArray[np.uint8], name: str) -> NDArray[np.float32]:
    """`read_image` of an image file's bytes (PNG, BMP, TIFF, ...); `name` labels errors."""
    import cv2

    buf = np.frombuffer(data, dtype=np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    except cv2.error:  # OpenCV refuses some broken headers (e.g. a huge declared size) by raising
        img = None
    if img is None:
        raise InputError(f"{name}: not an image (cannot decode)")
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.dtype not in (np.uint8, np.uint16):
        img = img.astype(np.float32)
        if img.max(initial=0) > 1:
            raise InputError(f"{name}: float image values must lie in [0, 1]")
    return check_image(name, img)


def to_uint8(image: NDArray[np.floating]) -> NDArray[np.uint8]:
    """Quantise a [0, 1] float image to 8 bits (round half up, clipped)."""
    return np.clip(np.floor(np.asarray(image, dtype=np.float64) * 255 + 0.5), 0, 255).astype(np.uint8)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, inputs: tuple[str | os.PathLike, ...] = ()) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success rename it onto `path`, else delete it.

    Creates the parent folder.  Refuses to write onto any of `inputs` (never overwrite an input).
    The temporary name keeps the suffix of `path` so writers that look at it (OpenCV) work.
    """
    target = Path(path)
    for src in inputs:
        if Path(src).exists() and target.exists() and os.path.samefile(src, target):
            raise InputError(f"{target}: refusing to overwrite an input file")
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=f".tmp{target.suffix}", dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp makes 0600; a written file should not be
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_paths(paths: list[Path], *, inputs: tuple[str | os.PathLike, ...] = ()) -> Iterator[list[Path]]:
    """`atomic_path` for several files at once: yields their temporary paths; on success all are
    renamed onto `paths`, on failure every temporary file is deleted and none is written."""
    with contextlib.ExitStack() as stack:
        yield [stack.enter_context(atomic_path(p, inputs=inputs)) for p in paths]


def write_images(paths: list[Path], images: NDArray, *, inputs: tuple[str | os.PathLike, ...] = ()) -> list[Path]:
    """Write several grey images (as `write_image`) all or none: ``images[k]`` to ``paths[k]``."""
    import cv2

    with atomic_paths(paths, inputs=inputs) as tmps:
        for path, tmp, image in zip(paths, tmps, images):
            arr = np.asarray(image)
            if not cv2.imwrite(str(tmp), arr if arr.dtype in (np.uint8, np.uint16) else to_uint8(arr)):
                raise InputError(f"{path}: cannot write an image with this file extension")
    return list(paths)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` through a temporary file and a rename."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write `text` (UTF-8) to `path` through a temporary file and a rename."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def write_image(path: str | os.PathLike, image: NDArray, *, inputs: tuple[str | os.PathLike, ...] = ()) -> Path:
    """Write an 8-bit (or uint16) grey image atomically; float images are quantised to 8 bits."""
    import cv2

    arr = np.asarray(image)
    if arr.dtype not in (np.uint8, np.uint16):
        arr = to_uint8(arr)
    with atomic_path(path, inputs=inputs) as tmp:
        if not cv2.imwrite(str(tmp), arr):
            raise InputError(f"{path}: cannot write an image with this file extension")
    return Path(path)
