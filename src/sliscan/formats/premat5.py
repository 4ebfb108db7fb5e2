"""Pre-mat5 files: raw float32 ``.byt`` arrays, G calibration grids and A transforms.

The thesis's tools (section 4.1, appendix 1.6) keep their inputs as headerless little-endian
float32 files:

- ``G.byt``: the calibration grid, one row of 7 values per point,
  ``Xw Yw Zw xc yc xp_phase yp_phase`` (world in mm, camera in pixels, projector phases in
  radians); a text file with the same 7 columns is accepted wherever a G file is;
- ``A.byt``: a 4x4 transform;
- ``XP.byt`` / ``YP.byt``: projector phase images, ``H*W`` values row by row.

Projector phases convert to projector pixels with `phase_to_pixel` (``x = phase * size / 2pi``).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, atomic_write_bytes, atomic_write_text, check_finite_matrix

#: Columns of a G file, in order.
G_COLUMNS = ("Xw", "Yw", "Zw", "xc", "yc", "xp_phase", "yp_phase")

_FLOAT32_LE = np.dtype("<f4")


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None


def read_byt(path: str | os.PathLike, shape: tuple[int, ...] | None = None) -> NDArray[np.float32]:
    """Read a raw little-endian float32 ``.byt`` file.

    Parameters
    ----------
    path : path
        The file.
    shape : tuple of int, optional
        Expected shape, e.g. ``(H, W)`` for an image (values are stored row by row).  The byte
        count must then be exactly ``4 * prod(shape)``.  Default: a 1-D array of every value.

    Returns
    -------
    values : float32 array of `shape`, or (N,)
        NaN and inf are returned as stored.

    Raises
    ------
    InputError
        If the file cannot be read or its size does not fit (message names the file, the
        expected and the actual byte counts).
    """
    p = Path(path)
    data = _read_bytes(p)
    if shape is None:
        if len(data) % _FLOAT32_LE.itemsize:
            raise InputError(f"{p}: size {len(data)} bytes is not a whole number of float32 values")
        return np.frombuffer(data, dtype=_FLOAT32_LE).astype(np.float32)
    expected = _FLOAT32_LE.itemsize * math.prod(shape)
    if len(data) != expected:
        what = "truncated" if len(data) < expected else "too long"
        dims = "x".join(str(n) for n in (shape[::-1] if len(shape) == 2 else shape))
        raise InputError(f"{p}: {what}: expected {expected} bytes ({dims} float32), got {len(data)}")
    return np.frombuffer(data, dtype=_FLOAT32_LE).reshape(shape).astype(np.float32)


def write_byt(path: str | os.PathLike, array: ArrayLike) -> Path:
    """Write `array` as raw little-endian float32, row by row (C order), atomically.

    This is the layout of MATLAB's ``fwrite(fp, reshape(a', 1, []), 'float32')`` in the thesis's
    ``mat5write`` (appendix 1.4).  Values are rounded to float32.

    Returns
    -------
    path : Path
        The file written.
    """
    data = np.ascontiguousarray(np.asarray(array, dtype=np.float64), dtype=_FLOAT32_LE).tobytes()
    return atomic_write_bytes(path, data)


def _read_text_rows(path: Path, columns: int) -> NDArray[np.float64]:
    """Numbers of a text table: whitespace or commas between values, ``#`` starts a comment."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) else "not a text file"
        raise InputError(f"{path}: cannot read ({reason or exc})") from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].replace(",", " ").split()
        if not fields:
            continue
        if len(fields) != columns:
            raise InputError(f"{path}: line {lineno}: expected {columns} numbers, got {len(fields)}")
        try:
            rows.append([float(v) for v in fields])
        except ValueError:
            bad = next(v for v in fields if not _is_float(v))
            raise InputError(f"{path}: line {lineno}: not a number: {bad!r}") from None
    return np.array(rows, dtype=np.float64).reshape(-1, columns)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _is_binary(path: Path) -> bool:
    return path.suffix.lower() == ".byt"


def check_g(rows: ArrayLike, *, name: str = "G rows") -> NDArray[np.float64]:
    """Check calibration-grid rows: ``(N, 7)`` with ``N >= 1``, all finite.

    Parameters
    ----------
    rows : (N, 7) array
        ``Xw Yw Zw xc yc xp_phase yp_phase``.
    name : str
        What to call `rows` in error messages (a file name, for files).

    Returns
    -------
    rows : (N, 7) float64 array
    """
    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != len(G_COLUMNS):
        raise InputError(f"{name} must have shape (N, 7) ({' '.join(G_COLUMNS)}), got {rows.shape}")
    if rows.shape[0] < 1:
        raise InputError(f"{name}: no calibration points")
    bad = np.flatnonzero(~np.all(np.isfinite(rows), axis=1))
    if bad.size:
        raise InputError(f"{name}: non-finite values (NaN or inf) in point {bad[0]} ({bad.size} of {rows.shape[0]} points)")
    return rows


def read_g(path: str | os.PathLike) -> NDArray[np.float64]:
    """Read a G calibration-grid file: binary ``.byt`` or text.

    Parameters
    ----------
    path : path
        ``*.byt`` (any case): raw little-endian float32, 7 values per point (28 bytes).  Any
        other extension: text, one point per line, 7 numbers separated by whitespace or commas,
        ``#`` starts a comment, blank lines are skipped.

    Returns
    -------
    rows : (N, 7) float64 array
        ``Xw Yw Zw`` (mm), ``xc yc`` (camera pixels), ``xp_phase yp_phase`` (radians; see
        `phase_to_pixel`).

    Raises
    ------
    InputError
        Unreadable file, a byte count that is not a multiple of 28, a line without exactly 7
        numbers, no points, or non-finite values; the message names the file.
    """
    p = Path(path)
    if _is_binary(p):
        data = _read_bytes(p)
        record = len(G_COLUMNS) * _FLOAT32_LE.itemsize
        if len(data) % record:
            raise InputError(f"{p}: size {len(data)} bytes is not a multiple of {record} (7 float32 per point)")
        rows = np.frombuffer(data, dtype=_FLOAT32_LE).reshape(-1, len(G_COLUMNS)).astype(np.float64)
    else:
        rows = _read_text_rows(p, len(G_COLUMNS))
    return check_g(rows, name=str(p))


def write_g(path: str | os.PathLike, rows: ArrayLike) -> Path:
    """Write G calibration rows; ``*.byt`` as float32 binary, any other extension as text.

    Parameters
    ----------
    path : path
        Destination; the extension picks the form, as in `read_g`.
    rows : (N, 7) array
        ``Xw Yw Zw xc yc xp_phase yp_phase``, finite.

    Returns
    -------
    path : Path
        The file written.  Text keeps every float64 digit (shortest round-trip form); binary
        rounds to float32.
    """
    p = Path(path)
    rows = check_g(rows, name=str(p))
    if _is_binary(p):
        return write_byt(p, rows)
    lines = ["# " + " ".join(G_COLUMNS)]
    lines += [" ".join(repr(float(v)) for v in row) for row in rows]
    return atomic_write_text(p, "\n".join(lines) + "\n")


def read_a(path: str | os.PathLike) -> NDArray[np.float64]:
    """Read an ``A.byt`` 4x4 transform (16 little-endian float32, row by row).

    Returns
    -------
    a : (4, 4) float64 array
    """
    p = Path(path)
    a = read_byt(p, (4, 4)).astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise InputError(f"{p}: non-finite values (NaN or inf) in the 4x4 transform")
    return a


def write_a(path: str | os.PathLike, a: ArrayLike) -> Path:
    """Write a 4x4 transform as ``A.byt`` (16 little-endian float32, row by row)."""
    try:
        a = check_finite_matrix("the transform", a, (4, 4))
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    return write_byt(path, a)


def phase_to_pixel(phase: ArrayLike, size: int) -> NDArray[np.float64]:
    """Projector pixel coordinate of a phase, the thesis's convention ``x = phase * size / 2pi``.

    Appendix 1.6 converts G-file phases with ``xp = xpt * 1280 / (2*pi)``: phase 0 is pixel 0
    and one full period spans the `size` projector pixels, with no half-pixel offset.

    Parameters
    ----------
    phase : array_like
        Phase in radians.
    size : int
        Projector pixels along that axis (W for `xp`, H for `yp`).

    Returns
    -------
    pixel : float64 array
        Projector coordinate in pixels.

    Examples
    --------
    >>> float(phase_to_pixel(np.pi, 768))
    384.0
    """
    return np.asarray(phase, dtype=np.float64) * (_check_size(size) / (2 * np.pi))


def pixel_to_phase(pixel: ArrayLike, size: int) -> NDArray[np.float64]:
    """Inverse of `phase_to_pixel`: ``phase = pixel * 2pi / size`` (the thesis's convention).

    Parameters
    ----------
    pixel : array_like
        Projector coordinate in pixels.
    size : int
        Projector pixels along that axis (W for `xp`, H for `yp`).

    Returns
    -------
    phase : float64 array
        Phase in radians.

    Examples
    --------
    >>> float(pixel_to_phase(384, 768) / np.pi)
    1.0
    """
    return np.asarray(pixel, dtype=np.float64) * (2 * np.pi / _check_size(size))


def _check_size(size: int) -> int:
    if int(size) != size or size < 1:
        raise InputError(f"size must be a positive number of projector pixels, got {size}")
    return int(size)
