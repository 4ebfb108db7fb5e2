"""A whole `ScanResult` in one compressed ``.npz`` file.

Every array field is stored under its own name (``points``, ``valid``, ``texture``,
``proj_map``, ``stripe``, ``confidence``) and ``timings`` as a JSON string, so the file opens
with plain ``np.load`` (no pickle): the layout of `numpy.savez_compressed`, at a faster
deflate level (`COMPRESS_LEVEL`).
"""

from __future__ import annotations

import functools
import io
import json
import os
import struct
import time
import zipfile
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._threads import results_in_order
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

#: Uncompressed bytes of a member deflated as one task on the thread pool (the members are
#: deflated pigz-style, in chunks that each continue the previous one's stream).  At 4 MiB a
#: 5 MP scan makes about 35 tasks, and the sync-flush marker (5 bytes) and lost matches at the
#: start of each chunk cost nothing measurable.
_CHUNK_BYTES = 4 << 20

#: The deflate window: the bytes before a chunk that its matches may reach back into (32 KiB).
_WINDOW = 1 << 15

#: Sizes and offsets above this go to a zip64 extra field, and member counts above
#: `_ZIP_FILECOUNT_LIMIT` to the zip64 end records, as `zipfile` writes them.
_ZIP64_LIMIT = (1 << 31) - 1
_ZIP_FILECOUNT_LIMIT = (1 << 16) - 1

#: Version 4.5 of the zip format (zip64), needed to extract and stated as the writer's.
_ZIP64_VERSION = 45

_LOCAL = struct.Struct("<4s2B4HL2L2H")  # local file header (30 bytes), then name and extra field
_ZIP64_LOCAL_EXTRA = struct.Struct("<2H2Q")  # zip64 extra field: id 1, length 16, sizes
_CENTRAL = struct.Struct("<4s4B4HL2L5H2L")  # central directory header (46 bytes)
_END64 = struct.Struct("<4sQ2H2L4Q")  # zip64 end of central directory record (56 bytes)
_END64_LOCATOR = struct.Struct("<4sLQL")  # zip64 end of central directory locator (20 bytes)
_END = struct.Struct("<4s4H2LH")  # end of central directory record (22 bytes)


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
    return write_npz_arrays(path, arrays)


def write_npz_arrays(path: str | os.PathLike, arrays: Mapping[str, ArrayLike]) -> Path:
    """Write named arrays to a compressed npz, atomically, deflating on all threads.

    The file is what `numpy.savez_compressed` writes (a zip of ``NAME.npy`` members, each
    the bytes of `numpy.lib.format.write_array`), at deflate level `COMPRESS_LEVEL`: it opens
    with plain ``np.load(path, allow_pickle=False)``.  Each member is deflated in chunks of
    `_CHUNK_BYTES` on the scan's threads (`sliscan._threads.results_in_order`; zlib releases
    the GIL), and its CRC-32 as one more task; the chunks are written in order as they come.
    At 5 MP that takes 1.2 s on 2 cores against 2.4 s for one stream (thirty-fifth session).

    Parameters
    ----------
    path : path
        Destination, written as given (no ``.npz`` is appended); missing folders are created.
    arrays : mapping of str -> array_like
        The arrays, by name (the member ``NAME.npy``); any dtype `numpy.save` stores without
        pickle.

    Returns
    -------
    path : Path
        The file written.

    Raises
    ------
    ValueError
        If an array has object (or another non-numpy) dtype: it could only be pickled.
    """
    members = [(f"{name}.npy", *_npy_bytes(np.asarray(array))) for name, array in arrays.items()]
    tasks: list[Callable[[], Any]] = []
    chunk_counts = []
    for _, header, data in members:
        chunks = _deflate_chunks(header, data)
        tasks += chunks
        tasks.append(functools.partial(_crc32, header, data))
        chunk_counts.append(len(chunks))
    stamp = _dos_timestamp()
    entries: list[_Entry] = []
    results = results_in_order(tasks)
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            for (name, header, data), count in zip(members, chunk_counts):
                offset = f.tell()
                f.write(_local_header(name, stamp, 0, 0, 0))  # CRC and sizes once known
                compressed = 0
                for _ in range(count):
                    block = next(results)
                    f.write(block)
                    compressed += len(block)
                entry = _Entry(name, next(results), len(header) + data.nbytes, compressed, offset)
                end = f.tell()
                f.seek(offset)
                f.write(_local_header(name, stamp, entry.crc, entry.size, entry.compressed))
                f.seek(end)
                entries.append(entry)
            f.write(_central_directory(entries, stamp, start=f.tell()))
    finally:
        results.close()
    return Path(path)


class _Entry(NamedTuple):
    """What the central directory records of a member written."""

    name: str
    crc: int  #: CRC-32 of the uncompressed bytes
    size: int  #: uncompressed bytes
    compressed: int  #: deflated bytes
    offset: int  #: byte offset of the member's local file header in the file


def _npy_bytes(array: NDArray) -> tuple[bytes, NDArray[np.uint8]]:
    """The bytes `numpy.lib.format.write_array` writes for `array`: its ``.npy`` header and data.

    Parameters
    ----------
    array : ndarray
        Any shape and memory layout; not of object dtype.

    Returns
    -------
    header : bytes
        The ``.npy`` header (version 1.0, or 2.0 for a header over 64 KiB), as numpy writes it.
    data : (N,) uint8 array
        The array's bytes in the order the header states (C, or Fortran for a Fortran-only
        contiguous array), N = ``array.nbytes``: a view of `array`'s memory, copied only when
        the array is contiguous neither way.

    Raises
    ------
    ValueError
        If the array has object dtype (or a non-legacy one, such as `numpy.dtypes.StringDType`),
        as `numpy.lib.format.write_array` does without pickle.
    """
    if array.dtype.hasobject or array.dtype.kind not in "biufcmMSUV":
        raise ValueError(f"cannot store an array of dtype {array.dtype} without pickle")
    fields = np.lib.format.header_data_from_array_1_0(array)
    header = io.BytesIO()
    try:
        np.lib.format.write_array_header_1_0(header, fields)
    except ValueError:  # a header over 64 KiB (a very large structured dtype)
        header = io.BytesIO()
        np.lib.format.write_array_header_2_0(header, fields)
    ordered = array.T if fields["fortran_order"] else np.ascontiguousarray(array)
    data = ordered.reshape(-1).view(np.uint8) if array.nbytes else np.empty(0, np.uint8)
    return header.getvalue(), data


def _deflate_chunks(header: bytes, data: NDArray[np.uint8]) -> list[Callable[[], bytes]]:
    """Tasks deflating ``header + data`` in chunks, whose outputs joined are one raw deflate stream.

    Parameters
    ----------
    header : bytes
        The member's first bytes (its ``.npy`` header), deflated with the first chunk of data.
    data : (N,) uint8 array
        The rest of the member, split in chunks of `_CHUNK_BYTES` (at least one, maybe empty).

    Returns
    -------
    tasks : list of callables returning bytes
        One per chunk, in order; each primes its deflate with the `_WINDOW` bytes before its
        chunk (pigz's way: matches may reach back into them as they would in one stream).
    """
    step = _CHUNK_BYTES
    starts = range(0, max(data.nbytes, 1), step)
    view = memoryview(data)
    return [functools.partial(_deflate, (header, view[:step]) if s == 0 else (view[s:s + step],),
                              view[max(0, s - _WINDOW):s], s + step >= data.nbytes)
            for s in starts]


def _deflate(pieces: tuple[bytes | memoryview, ...], window: memoryview, last: bool) -> bytes:
    """Deflate one chunk (`pieces` in turn) at `COMPRESS_LEVEL`, as raw deflate (no zlib header).

    Parameters
    ----------
    pieces : tuple of bytes-like
        The chunk's bytes.
    window : bytes-like
        The stream's bytes just before the chunk (at most 32 KiB; empty for the first chunk),
        as the deflate dictionary.
    last : bool
        The member's last chunk: ends the stream (``Z_FINISH``); else the output ends on a byte
        boundary with an empty stored block (``Z_SYNC_FLUSH``), so that the next chunk's output
        follows it.

    Returns
    -------
    deflated : bytes
    """
    compressor = zlib.compressobj(COMPRESS_LEVEL, zlib.DEFLATED, -zlib.MAX_WBITS, zdict=window)
    out = [compressor.compress(piece) for piece in pieces]
    out.append(compressor.flush(zlib.Z_FINISH if last else zlib.Z_SYNC_FLUSH))
    return b"".join(out)


def _crc32(header: bytes, data: NDArray[np.uint8]) -> int:
    """CRC-32 of ``header + data`` (a member's uncompressed bytes), as zip stores it."""
    return zlib.crc32(data, zlib.crc32(header))


def _dos_timestamp() -> tuple[int, int]:
    """The local time now as zip stores it: (DOS time, DOS date), 2 s steps, years from 1980."""
    year, month, day, hour, minute, second = time.localtime()[:6]
    if year < 1980:
        year, month, day, hour, minute, second = 1980, 1, 1, 0, 0, 0
    return hour << 11 | minute << 5 | second // 2, (year - 1980) << 9 | month << 5 | day


def _encode_name(name: str) -> tuple[bytes, int]:
    """A member name's bytes and general purpose flags: ASCII, else UTF-8 with flag bit 11."""
    try:
        return name.encode("ascii"), 0
    except UnicodeEncodeError:
        return name.encode("utf-8"), 0x800


def _local_header(name: str, stamp: tuple[int, int], crc: int, size: int, compressed: int) -> bytes:
    """A deflated member's local file header, always zip64 (as ``zipfile``'s ``force_zip64``).

    Parameters
    ----------
    name : str
    stamp : (int, int)
        DOS time and date (`_dos_timestamp`).
    crc, size, compressed : int
        CRC-32, uncompressed and compressed bytes.  The sizes go to the zip64 extra field, so
        the header has the same length before they are known (zeros) and after.

    Returns
    -------
    header : bytes
        30 bytes, the name, and the 20-byte zip64 extra field.
    """
    encoded, flags = _encode_name(name)
    extra = _ZIP64_LOCAL_EXTRA.pack(1, 16, size, compressed)
    return _LOCAL.pack(b"PK\x03\x04", _ZIP64_VERSION, 0, flags, zipfile.ZIP_DEFLATED, *stamp, crc,
                       0xFFFFFFFF, 0xFFFFFFFF, len(encoded), len(extra)) + encoded + extra


def _central_directory(entries: list[_Entry], stamp: tuple[int, int], start: int) -> bytes:
    """The central directory and end records of a zip whose members are `entries`.

    A size or offset over `_ZIP64_LIMIT` goes to a zip64 extra field, and the zip64 end
    records are written when the count, size or offset of the directory needs them, as
    ``zipfile`` does: a small file is read by any zip reader.

    Parameters
    ----------
    entries : list of _Entry
        The members written, in order.
    stamp : (int, int)
        DOS time and date of every member (`_dos_timestamp`).
    start : int
        Byte offset of the directory in the file (the end of the last member).

    Returns
    -------
    directory : bytes
        Everything from `start` to the end of the file.
    """
    records = []
    for entry in entries:
        encoded, flags = _encode_name(entry.name)
        sizes, big = (entry.compressed, entry.size), []
        if max(sizes) > _ZIP64_LIMIT:
            big += [entry.size, entry.compressed]
            sizes = (0xFFFFFFFF, 0xFFFFFFFF)
        offset = entry.offset
        if offset > _ZIP64_LIMIT:
            big.append(offset)
            offset = 0xFFFFFFFF
        extra = struct.pack(f"<2H{len(big)}Q", 1, 8 * len(big), *big) if big else b""
        records += [_CENTRAL.pack(b"PK\x01\x02", _ZIP64_VERSION, 3, _ZIP64_VERSION, 0, flags,
                                  zipfile.ZIP_DEFLATED, *stamp, entry.crc, *sizes, len(encoded), len(extra),
                                  0, 0, 0, 0o600 << 16, offset), encoded, extra]
    directory = b"".join(records)
    count, size, end = len(entries), len(directory), start + len(directory)
    if count > _ZIP_FILECOUNT_LIMIT or size > _ZIP64_LIMIT or start > _ZIP64_LIMIT:
        directory += _END64.pack(b"PK\x06\x06", _END64.size - 12, _ZIP64_VERSION, _ZIP64_VERSION, 0, 0,
                                 count, count, size, start)
        directory += _END64_LOCATOR.pack(b"PK\x06\x07", 0, end, 1)
        count, size, start = min(count, 0xFFFF), min(size, 0xFFFFFFFF), min(start, 0xFFFFFFFF)
    return directory + _END.pack(b"PK\x05\x06", 0, 0, count, count, size, start, 0)


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
