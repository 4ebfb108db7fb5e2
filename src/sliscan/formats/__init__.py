"""File formats at the library's boundary (DESIGN.md, "File formats").

Modules
-------
mat5
    ``PREFIX{X,Y,Z}.byt`` + ``PREFIXC.bmp`` + ``PREFIXI.bmp``: one scan, the thesis's format (4.1).
premat5
    Raw float32 ``.byt`` files: ``G.byt`` calibration grids, ``A.byt`` transforms, phase images,
    and the thesis's phase <-> projector pixel conversion.
calibration
    The thesis's ``cam.txt`` / ``proj.txt`` matrices and a loader for every calibration form.
ply
    Binary PLY point clouds (through `plyfile`).
npz
    A whole `ScanResult` in one compressed ``.npz`` file.

Every writer is atomic (temporary file + rename) and creates missing folders; every reader
raises `sliscan.InputError` with a one-line message that starts with the file name.
"""
