"""Calibration files: sliscan's JSON and the thesis's ``cam.txt`` / ``proj.txt``.

``cam.txt`` and ``proj.txt`` (appendix 1.6) each hold one 3x4 world (mm) -> pixel projection
matrix as three lines of four numbers.  They carry no image size, so loading a pair needs the
camera and projector sizes; the JSON (`Calibration.save` / `Calibration.load`) has everything.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, atomic_write_text, check_finite_matrix
from sliscan.formats.premat5 import _read_text_rows
from sliscan.types import Calibration, Device

PathLike = str | os.PathLike


def read_matrix_txt(path: PathLike) -> NDArray[np.float64]:
    """Read a 3x4 projection matrix from the thesis's text form (``cam.txt`` / ``proj.txt``).

    Parameters
    ----------
    path : path
        Three lines of four numbers (whitespace or commas between them); blank lines and ``#``
        comments are skipped.

    Returns
    -------
    matrix : (3, 4) float64 array
        World (mm) -> pixel, ``x ~ matrix @ [Xw, Yw, Zw, 1]``.

    Raises
    ------
    InputError
        If the file cannot be read, is not exactly 3 lines of 4 numbers, or has non-finite
        values; the message names the file.
    """
    p = Path(path)
    rows = _read_text_rows(p, 4)
    if rows.shape[0] != 3:
        raise InputError(f"{p}: expected 3 lines of 4 numbers, got {rows.shape[0]} lines")
    try:
        return check_finite_matrix("matrix", rows, (3, 4))
    except InputError as exc:
        raise InputError(f"{p}: {exc}") from None


def write_matrix_txt(path: PathLike, matrix: ArrayLike) -> Path:
    """Write a 3x4 projection matrix as three lines of four numbers (``%.10g``), atomically.

    Ten significant digits round-trip the matrix to a relative 1e-10, far below what a
    calibration resolves.

    Parameters
    ----------
    path : path
        Destination (``cam.txt`` or ``proj.txt``).
    matrix : (3, 4) array
        Finite projection matrix.

    Returns
    -------
    path : Path
        The file written.
    """
    matrix = check_finite_matrix("matrix", matrix, (3, 4))
    text = "".join(" ".join(f"{v:.10g}" for v in row) + "\n" for row in matrix)
    return atomic_write_text(path, text)


def load_calibration(source: PathLike | Sequence[PathLike], *,
                     camera_size: tuple[int, int] | None = None,
                     projector_size: tuple[int, int] | None = None) -> Calibration:
    """Load a calibration from sliscan's JSON or from a ``(cam.txt, proj.txt)`` pair.

    Parameters
    ----------
    source : path or (path, path)
        A calibration JSON file (DESIGN.md), or the camera and projector matrix text files.
    camera_size, projector_size : (W, H) tuple of int, optional
        Image sizes in pixels.  Required with a text pair; with a JSON file, if given, they
        must match the sizes in the file.

    Returns
    -------
    calibration : Calibration

    Raises
    ------
    InputError
        Unreadable or malformed files, missing sizes for a text pair, or sizes that disagree
        with the JSON file.
    """
    if isinstance(source, (str, os.PathLike)):
        calibration = Calibration.load(source)
        for name, device, size in (("camera", calibration.camera, camera_size),
                                   ("projector", calibration.projector, projector_size)):
            if size is not None and tuple(size) != device.size:
                raise InputError(f"{source}: {name} size {device.size[0]}x{device.size[1]} differs from the "
                                 f"requested {size[0]}x{size[1]}")
        return calibration
    paths = list(source)
    if len(paths) != 2:
        raise InputError(f"expected a calibration JSON or a (cam.txt, proj.txt) pair, got {len(paths)} paths")
    if camera_size is None or projector_size is None:
        raise InputError("camera_size and projector_size (W, H) are required with cam.txt/proj.txt files")
    cam, proj = paths
    return Calibration(Device(read_matrix_txt(cam), camera_size), Device(read_matrix_txt(proj), projector_size))
