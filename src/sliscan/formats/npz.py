"""A whole `ScanResult` in one compressed ``.npz`` file.

Every array field is stored under its own name (``points``, ``valid``, ``texture``,
``proj_map``, ``stripe``, ``confidence``) and ``timings`` as a JSON string, so the file opens
with plain ``np.load`` (no pickle): the layout of `numpy.savez_compressed`, at a faster
deflate level (`COMPRESS_LEVEL`).
"""

from __future__ import annotations

import json
import os
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sliscan._validate import InputError, atomic_path
from sliscan.types import ScanResult

#: What numpy and zipfile raise on a corrupt archive (a huge declared array shape: MemoryError).
_CORRUPT = (ValueError, EOFError, KeyError, OSError, MemoryError, struct.error, zlib.error, zipfile.BadZipFile)

#: Deflate level of the archive: 1 writes a 1280x1024 scan in 0.43 s against numpy's
#: `savez_compressed` (level 6) 0.70 s, for a file 1 % larger (float noise hardly compresses).
COMPRESS_LEVEL = 1

#: Array fields of ScanResult and the dtype each is stored and read back with.
ARRAY_DTYPES = {
    "points": np.float32,
    "valid": np.bool_,
    "texture": np.float32,
    "proj_map": np.float32,
    "stripe": np.int16,
    "confidence": np.float32,
}


def write_scan_npz(path: str | os.PathLike, result: ScanResult) -> Path:
    """Write every array of `result`, and its timings as JSON, to a compressed npz, atomically.

    Parameters
    ----------
    path : path
        Destination, written as given (no ``.npz`` is appended); missing folders are created.
    result : ScanResult

    Returns
    -------
    path : Path
        The file written.
    """
    arrays = {name: np.asarray(getattr(result, name), dtype=dtype) for name, dtype in ARRAY_DTYPES.items()}
    arrays["timings"] = np.array(json.dumps({str(k): float(v) for k, v in result.timings.items()}))
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED,
                                                   compresslevel=COMPRESS_LEVEL) as archive:
        for name, array in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, array, allow_pickle=False)
    return Path(path)


def read_npz_arrays(path: str | os.PathLike, dtypes: dict[str, Any], *, what: str) -> dict[str, NDArray]:
    """Read named arrays from an npz file (no pickle), each cast to its dtype.

    Parameters
    ----------
    path : path
        The npz file.
    dtypes : dict of str -> dtype
        The arrays the file must hold and the dtype each is returned with.
    what : str
        What the file should be, for the message on a missing array (``"a sliscan scan"``).

    Raises
    ------
    InputError
        If the file cannot be read, is not an npz archive, or lacks an array; the message names
        the file.
    """
    p = Path(path)
    try:
        f = open(p, "rb")
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    with f:
        try:
            loaded = np.load(f, allow_pickle=False)
        except _CORRUPT as exc:
            raise InputError(f"{p}: not a valid npz file ({exc})") from None
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise InputError(f"{p}: not an npz archive (a single .npy array)")
        with loaded:
            missing = sorted(set(dtypes) - set(loaded.files))
            if missing:
                raise InputError(f"{p}: not {what}: missing arrays {missing}")
            try:
                return {name: loaded[name].astype(dtype) for name, dtype in dtypes.items()}
            except _CORRUPT as exc:
                raise InputError(f"{p}: corrupt npz file ({exc})") from None


def read_scan_npz(path: str | os.PathLike) -> ScanResult:
    """Read a `ScanResult` written by `write_scan_npz`.

    Parameters
    ----------
    path : path
        An npz file with the arrays of a ScanResult and a ``timings`` JSON string.

    Returns
    -------
    result : ScanResult

    Raises
    ------
    InputError
        If the file cannot be read, is not an npz, lacks an array, or its shapes disagree;
        the message names the file.
    """
    p = Path(path)
    arrays = read_npz_arrays(p, {**ARRAY_DTYPES, "timings": str}, what="a sliscan scan")
    try:
        timings = json.loads(str(arrays.pop("timings")))
    except ValueError as exc:
        raise InputError(f"{p}: corrupt npz file ({exc})") from None
    if not isinstance(timings, dict):
        raise InputError(f"{p}: timings must be a JSON object")
    shape = arrays["valid"].shape
    for name, arr in arrays.items():
        want = (*shape, 3) if name == "points" else shape
        if arr.shape != want or len(shape) != 2:
            raise InputError(f"{p}: {name} has shape {arr.shape}, expected {want} (H, W)")
    return ScanResult(timings=timings, **arrays)
