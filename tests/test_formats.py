"""File formats: mat5, pre-mat5 (.byt, G, A), cam.txt/proj.txt, PLY and npz round trips."""

from __future__ import annotations

import dataclasses
import io
import json
import struct
import zipfile

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from plyfile import PlyData

from sliscan import Calibration, Device, InputError, ScanResult, _threads
from sliscan._validate import to_uint8
from sliscan.formats.calibration import load_calibration, read_matrix_txt, write_matrix_txt
from sliscan.formats.mat5 import mat5_paths, read_mat5, write_mat5
from sliscan.formats import npz
from sliscan.formats.npz import ARRAY_DTYPES, read_scan_npz, write_npz_arrays, write_scan_npz
from sliscan.formats.ply import read_point_cloud, write_point_cloud
from sliscan.formats.premat5 import (phase_to_pixel, pixel_to_phase, read_a, read_byt, read_g, write_a, write_byt,
                                     write_g)

# 8-bit texture files: a [0, 1] grey level comes back within half a quantisation step.
ATOL_8BIT = 0.5 / 255


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(2007)


def random_scan(rng: np.random.Generator, shape=(6, 9)):
    valid = rng.random(shape) < 0.6
    points = rng.uniform(-500, 900, size=(*shape, 3)).astype(np.float32)
    points[~valid] = np.nan
    texture = rng.random(shape).astype(np.float32)
    return points, valid, texture


def assert_only(folder, names):
    """`folder` holds exactly `names` (no temporary files left behind)."""
    assert sorted(p.name for p in folder.iterdir()) == sorted(names)


# ------------------------------------------------------------------------------------------ mat5

def test_mat5_round_trip(tmp_path, rng):
    points, valid, texture = random_scan(rng)
    paths = write_mat5(tmp_path / "deep" / "er" / "scan", points, valid, texture)
    assert [p.name for p in paths] == ["scanX.byt", "scanY.byt", "scanZ.byt", "scanC.bmp", "scanI.bmp"]
    assert_only(tmp_path / "deep" / "er", [p.name for p in paths])
    got_points, got_valid, got_texture = read_mat5(tmp_path / "deep" / "er" / "scan")
    np.testing.assert_array_equal(got_valid, valid)
    assert got_points.dtype == np.float32
    np.testing.assert_array_equal(got_points, points)  # float32 exactly, NaN where invalid
    np.testing.assert_allclose(got_texture, texture, rtol=0, atol=ATOL_8BIT)


def test_mat5_invalid_points_are_zero_on_disk_and_indicator_is_255(tmp_path, rng):
    points, valid, texture = random_scan(rng)
    write_mat5(tmp_path / "s", points, valid, texture)
    h, w = valid.shape
    for k, axis in enumerate("XYZ"):
        on_disk = np.fromfile(tmp_path / f"s{axis}.byt", dtype="<f4").reshape(h, w)
        np.testing.assert_array_equal(on_disk[~valid], 0.0)
        np.testing.assert_array_equal(on_disk[valid], points[..., k][valid])
    indicator = cv2.imread(str(tmp_path / "sI.bmp"), cv2.IMREAD_UNCHANGED)
    assert indicator.dtype == np.uint8 and indicator.ndim == 2
    np.testing.assert_array_equal(indicator, np.where(valid, 255, 0))
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "sC.bmp"), cv2.IMREAD_UNCHANGED), to_uint8(texture))


def test_mat5_byte_layout_is_row_major_little_endian_float32(tmp_path):
    # MATLAB's mat5write writes reshape(xw', 1, my*nx): row 0 first, then row 1.
    x = np.array([[1.5, -2.0, 3.25], [4.0, 5.5, -6.75]])
    points = np.stack([x, 10 * x, 100 * x], axis=-1)
    write_mat5(tmp_path / "t", points, np.ones((2, 3), dtype=bool), np.zeros((2, 3)))
    raw = (tmp_path / "tX.byt").read_bytes()
    assert raw == struct.pack("<6f", 1.5, -2.0, 3.25, 4.0, 5.5, -6.75)
    assert (tmp_path / "tZ.byt").read_bytes() == np.array(100 * x, dtype="<f4").tobytes(order="C")


def test_mat5_reads_any_nonzero_indicator_as_valid(tmp_path, rng):
    points, valid, texture = random_scan(rng)
    write_mat5(tmp_path / "s", points, valid, texture)
    cv2.imwrite(str(tmp_path / "sI.bmp"), np.where(valid, 1, 0).astype(np.uint8))  # the thesis's "1 = valid"
    np.testing.assert_array_equal(read_mat5(tmp_path / "s")[1], valid)


def test_mat5_truncated_byt_names_the_file(tmp_path, rng):
    points, valid, texture = random_scan(rng, shape=(2, 3))
    write_mat5(tmp_path / "s", points, valid, texture)
    (tmp_path / "sY.byt").write_bytes(b"\0" * 8)
    with pytest.raises(InputError, match=r"sY\.byt: truncated: expected 24 bytes \(3x2 float32\), got 8$"):
        read_mat5(tmp_path / "s")
    (tmp_path / "sY.byt").write_bytes(b"\0" * 28)
    with pytest.raises(InputError, match=r"sY\.byt: too long: expected 24 bytes \(3x2 float32\), got 28"):
        read_mat5(tmp_path / "s")


def test_mat5_read_errors(tmp_path, rng):
    with pytest.raises(InputError, match=r"nopeI\.bmp: no such file"):
        read_mat5(tmp_path / "nope")
    points, valid, texture = random_scan(rng)
    write_mat5(tmp_path / "s", points, valid, texture)
    cv2.imwrite(str(tmp_path / "sC.bmp"), np.zeros((3, 3), dtype=np.uint8))
    with pytest.raises(InputError, match=r"sC\.bmp: size 3x3 differs from the indicator's 9x6"):
        read_mat5(tmp_path / "s")
    write_mat5(tmp_path / "s", points, valid, texture)
    (tmp_path / "sX.byt").unlink()
    with pytest.raises(InputError, match=r"sX\.byt: cannot read"):
        read_mat5(tmp_path / "s")


def test_mat5_write_errors(tmp_path, rng):
    points, valid, texture = random_scan(rng)
    bad = points.copy()
    bad[valid.nonzero()[0][0], valid.nonzero()[1][0], 2] = np.nan
    with pytest.raises(InputError, match=r"points are non-finite at 1 of \d+ valid pixels"):
        write_mat5(tmp_path / "s", bad, valid, texture)
    with pytest.raises(InputError, match=r"points must have shape \(6, 9, 3\) \(H, W, 3\), got \(9, 6, 3\)"):
        write_mat5(tmp_path / "s", points.transpose(1, 0, 2), valid, texture)
    with pytest.raises(InputError, match="valid must be a 2-D .* bool array"):
        write_mat5(tmp_path / "s", points, valid.astype(np.uint8), texture)
    with pytest.raises(InputError, match=r"texture must have shape \(6, 9\)"):
        write_mat5(tmp_path / "s", points, valid, texture.T)
    assert_only(tmp_path, [])


def test_mat5_failure_leaves_nothing_behind(tmp_path, rng):
    # A folder squats on the indicator's name: renaming onto it fails, and the four other files,
    # complete in their temporary names, must not appear either.
    (tmp_path / "sI.bmp").mkdir()
    with pytest.raises(OSError):
        write_mat5(tmp_path / "s", *random_scan(rng))
    assert_only(tmp_path, ["sI.bmp"])


def test_scan_result_save_methods(tmp_path, rng):
    result = make_result(rng)
    paths = result.save_mat5(tmp_path / "m" / "scan")
    assert paths == mat5_paths(tmp_path / "m" / "scan")
    np.testing.assert_array_equal(read_mat5(tmp_path / "m" / "scan")[0], result.points)
    result.save_ply(tmp_path / "p" / "scan.ply")
    assert read_point_cloud(tmp_path / "p" / "scan.ply")[0].shape == (int(result.valid.sum()), 3)
    result.save_npz(tmp_path / "n" / "scan.npz")
    np.testing.assert_array_equal(read_scan_npz(tmp_path / "n" / "scan.npz").stripe, result.stripe)


# -------------------------------------------------------------------------------------- pre-mat5

def test_byt_round_trip(tmp_path, rng):
    image = rng.normal(size=(5, 7)).astype(np.float32)
    image[1, 2] = np.nan
    write_byt(tmp_path / "YP.byt", image)
    np.testing.assert_array_equal(read_byt(tmp_path / "YP.byt", (5, 7)), image)
    assert read_byt(tmp_path / "YP.byt").shape == (35,)
    (tmp_path / "odd.byt").write_bytes(b"\0" * 7)
    with pytest.raises(InputError, match=r"odd\.byt: size 7 bytes is not a whole number of float32 values"):
        read_byt(tmp_path / "odd.byt")


@pytest.mark.parametrize("name", ["G.txt", "G.csv", "grid.dat"])
def test_g_text_round_trip(tmp_path, rng, name):
    rows = rng.normal(scale=300, size=(12, 7))
    write_g(tmp_path / name, rows)
    np.testing.assert_array_equal(read_g(tmp_path / name), rows)  # shortest round-trip repr: exact


def test_g_binary_round_trip(tmp_path, rng):
    rows = rng.normal(scale=300, size=(12, 7))
    write_g(tmp_path / "G.byt", rows)
    assert (tmp_path / "G.byt").stat().st_size == 12 * 28
    got = read_g(tmp_path / "G.byt")
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, rows.astype(np.float32))  # binary stores float32
    np.testing.assert_array_equal(read_g(tmp_path / "G.byt")[3], np.fromfile(tmp_path / "G.byt", "<f4")[21:28])


def test_g_text_forms(tmp_path):
    (tmp_path / "G.csv").write_text(
        "# Xw, Yw, Zw, xc, yc, xp, yp\n"
        "1, 2, 3, 4, 5, 6, 7   # first point\n"
        "\n"
        "  8\t9 10 11 12 13 14e0\n")
    np.testing.assert_array_equal(read_g(tmp_path / "G.csv"), np.arange(1, 15).reshape(2, 7))


@pytest.mark.parametrize(("name", "content", "message"), [
    ("G.byt", b"\0" * 30, r"G\.byt: size 30 bytes is not a multiple of 28 \(7 float32 per point\)"),
    ("G.byt", b"", r"G\.byt: no calibration points"),
    ("G.txt", b"1 2 3 4 5 6 7\n1 2 3 4 5 6\n", r"G\.txt: line 2: expected 7 numbers, got 6"),
    ("G.txt", b"1 2 3 4 5 6 x7\n", r"G\.txt: line 1: not a number: 'x7'"),
    ("G.txt", b"# only a comment\n", r"G\.txt: no calibration points"),
    ("G.txt", b"1 2 3 4 5 nan 7\n", r"G\.txt: non-finite values \(NaN or inf\) in point 0 \(1 of 1 points\)"),
    ("G.txt", b"\xff\xfe\x00binary", r"G\.txt: cannot read \(not a text file\)"),
])
def test_g_errors(tmp_path, name, content, message):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(InputError, match=message):
        read_g(tmp_path / name)


def test_g_missing_file_and_bad_rows(tmp_path):
    with pytest.raises(InputError, match=r"missing\.byt: cannot read \(No such file or directory\)"):
        read_g(tmp_path / "missing.byt")
    with pytest.raises(InputError, match=r"G\.txt must have shape \(N, 7\)"):
        write_g(tmp_path / "G.txt", np.zeros((3, 6)))
    assert_only(tmp_path, [])


def test_atomic_write_failure_leaves_no_temp_file(tmp_path):
    (tmp_path / "G.byt").mkdir()  # the target is a folder: the final rename fails
    with pytest.raises(OSError):
        write_g(tmp_path / "G.byt", np.ones((2, 7)))
    assert_only(tmp_path, ["G.byt"])


def test_a_round_trip(tmp_path, rng):
    a = rng.normal(size=(4, 4))
    write_a(tmp_path / "A.byt", a)
    assert (tmp_path / "A.byt").stat().st_size == 64
    np.testing.assert_array_equal(read_a(tmp_path / "A.byt"), a.astype(np.float32))
    with pytest.raises(InputError, match=r"A\.byt: the transform must have shape \(4, 4\), got \(3, 3\)"):
        write_a(tmp_path / "A.byt", np.eye(3))
    (tmp_path / "B.byt").write_bytes(b"\0" * 60)
    with pytest.raises(InputError, match=r"B\.byt: truncated: expected 64 bytes \(4x4 float32\), got 60"):
        read_a(tmp_path / "B.byt")


@given(st.floats(-4 * np.pi, 4 * np.pi), st.integers(1, 4096))
def test_phase_pixel_round_trip(phase, size):
    assert pixel_to_phase(phase_to_pixel(phase, size), size) == pytest.approx(phase, rel=1e-12, abs=1e-12)


def test_phase_convention():
    # Appendix 1.6: xp = xpt * 1280 / (2*pi).
    assert phase_to_pixel(2 * np.pi, 1280) == pytest.approx(1280)
    assert phase_to_pixel(0.0, 1280) == 0
    with pytest.raises(InputError, match="size must be a positive number of projector pixels, got 0"):
        phase_to_pixel(1.0, 0)


# ----------------------------------------------------------------------------------- calibration

def test_matrix_txt_round_trip(tmp_path, rng):
    m = rng.normal(size=(3, 4)) * [[1000], [1000], [1]]
    write_matrix_txt(tmp_path / "cam.txt", m)
    assert len((tmp_path / "cam.txt").read_text().splitlines()) == 3
    # %.10g keeps 10 significant digits: relative error <= 5e-10 per entry.
    np.testing.assert_allclose(read_matrix_txt(tmp_path / "cam.txt"), m, rtol=5e-10, atol=0)


def test_matrix_txt_reads_the_thesis_form(tmp_path):
    # fprintf(fp, '%f ', ...) with a trailing space and '\n' after the fourth number.
    (tmp_path / "proj.txt").write_text("1.000000 2.000000 3.000000 4.000000\n"
                                       "5.000000 6.000000 7.000000 8.000000\n"
                                       "0.000000 0.000000 1.000000 -1.000000\n")
    np.testing.assert_array_equal(read_matrix_txt(tmp_path / "proj.txt"),
                                  [[1, 2, 3, 4], [5, 6, 7, 8], [0, 0, 1, -1]])


@pytest.mark.parametrize(("content", "message"), [
    ("1 2 3 4\n5 6 7 8\n", r"cam\.txt: expected 3 lines of 4 numbers, got 2 lines"),
    ("1 2 3 4\n5 6 7 8\n9 10 11\n", r"cam\.txt: line 3: expected 4 numbers, got 3"),
    ("1 2 3 4\n5 6 7 8\n9 10 11 inf\n", r"cam\.txt: matrix has non-finite entries"),
])
def test_matrix_txt_errors(tmp_path, content, message):
    (tmp_path / "cam.txt").write_text(content)
    with pytest.raises(InputError, match=message):
        read_matrix_txt(tmp_path / "cam.txt")


def rig_calibration() -> Calibration:
    k = np.array([[800.0, 0, 319.5], [0, 800, 239.5], [0, 0, 1]])
    proj = np.array([[400.0, 0, 127.5, 0], [0, 400, 95.5, 200 * 400], [0, 0, 1, 0]])
    return Calibration(Device(k @ np.eye(3, 4), (640, 480)), Device(proj, (256, 192)), {"method": "svd"})


def test_load_calibration_json_and_text_pair(tmp_path):
    calibration = rig_calibration()
    calibration.save(tmp_path / "rig.json")
    loaded = load_calibration(tmp_path / "rig.json", camera_size=(640, 480))
    np.testing.assert_array_equal(loaded.projector.matrix, calibration.projector.matrix)
    assert loaded.extra == {"method": "svd"}
    write_matrix_txt(tmp_path / "cam.txt", calibration.camera.matrix)
    write_matrix_txt(tmp_path / "proj.txt", calibration.projector.matrix)
    pair = load_calibration([tmp_path / "cam.txt", str(tmp_path / "proj.txt")], camera_size=(640, 480),
                            projector_size=(256, 192))
    assert pair.camera.size == (640, 480) and pair.projector.size == (256, 192)
    np.testing.assert_allclose(pair.camera.matrix, calibration.camera.matrix, rtol=5e-10)


def test_load_calibration_errors(tmp_path):
    rig_calibration().save(tmp_path / "rig.json")
    with pytest.raises(InputError, match=r"rig\.json: projector size 256x192 differs from the requested 1024x768"):
        load_calibration(tmp_path / "rig.json", projector_size=(1024, 768))
    with pytest.raises(InputError, match=r"camera_size and projector_size \(W, H\) are required"):
        load_calibration([tmp_path / "cam.txt", tmp_path / "proj.txt"], camera_size=(640, 480))
    with pytest.raises(InputError, match="a \\(cam.txt, proj.txt\\) pair, got 3 paths"):
        load_calibration(["a", "b", "c"])
    with pytest.raises(InputError, match=r"cam\.txt: cannot read"):
        load_calibration([tmp_path / "cam.txt", tmp_path / "proj.txt"], camera_size=(640, 480),
                         projector_size=(256, 192))


# ------------------------------------------------------------------------------------------- PLY

def test_ply_round_trip(tmp_path, rng):
    points = rng.uniform(-500, 900, size=(50, 3))
    grey = rng.random(50)
    path = write_point_cloud(tmp_path / "out" / "cloud.ply", points, grey)
    ply = PlyData.read(str(path))
    assert ply.header.splitlines()[1] == "format binary_little_endian 1.0"
    vertex = ply["vertex"].data
    assert vertex.dtype["x"] == np.dtype("<f4") and vertex.dtype["red"] == np.dtype("u1")
    np.testing.assert_array_equal(vertex["red"], vertex["blue"])
    got_points, got_grey = read_point_cloud(path)
    np.testing.assert_array_equal(got_points, points.astype(np.float32))
    np.testing.assert_allclose(got_grey, grey, rtol=0, atol=ATOL_8BIT + 1e-7)  # + float32 rounding
    assert_only(tmp_path / "out", ["cloud.ply"])


def test_ply_without_grey_and_with_normals(tmp_path, rng):
    points = rng.normal(size=(5, 3))
    normals = points / np.linalg.norm(points, axis=1, keepdims=True)
    write_point_cloud(tmp_path / "n.ply", points, normals=normals)
    vertex = PlyData.read(str(tmp_path / "n.ply"))["vertex"].data
    np.testing.assert_allclose(np.stack([vertex["nx"], vertex["ny"], vertex["nz"]], -1), normals, rtol=1e-6)
    got_points, grey = read_point_cloud(tmp_path / "n.ply")
    assert grey is None and got_points.shape == (5, 3)
    write_point_cloud(tmp_path / "empty.ply", np.zeros((0, 3)))
    assert read_point_cloud(tmp_path / "empty.ply")[0].shape == (0, 3)


def test_ply_errors(tmp_path):
    with pytest.raises(InputError, match=r"points must have shape \(N, 3\), got \(3, 4\)"):
        write_point_cloud(tmp_path / "a.ply", np.zeros((3, 4)))
    with pytest.raises(InputError, match=r"grey must have shape \(3,\), got \(2,\)"):
        write_point_cloud(tmp_path / "a.ply", np.zeros((3, 3)), np.zeros(2))
    with pytest.raises(InputError, match="points has non-finite values"):
        write_point_cloud(tmp_path / "a.ply", np.full((3, 3), np.nan))
    (tmp_path / "bad.ply").write_text("not a ply file\n")
    with pytest.raises(InputError, match=r"bad\.ply: not a valid PLY file"):
        read_point_cloud(tmp_path / "bad.ply")
    with pytest.raises(InputError, match=r"none\.ply: cannot read"):
        read_point_cloud(tmp_path / "none.ply")
    assert_only(tmp_path, ["bad.ply"])


# ------------------------------------------------------------------------------------------- npz

def make_result(rng: np.random.Generator) -> ScanResult:
    points, valid, texture = random_scan(rng)
    proj_map = np.where(valid, rng.uniform(0, 192, valid.shape), np.nan).astype(np.float32)
    return ScanResult(points=points, valid=valid, texture=texture, proj_map=proj_map,
                      stripe=np.where(valid, rng.integers(0, 16, valid.shape), -1).astype(np.int16),
                      confidence=rng.random(valid.shape).astype(np.float32),
                      timings={"demodulate": 0.25, "decode": 0.125})


@pytest.mark.parametrize("name", ["scan.npz", "scan.result"])
def test_npz_round_trip(tmp_path, rng, name):
    result = make_result(rng)
    write_scan_npz(tmp_path / name, result)
    assert_only(tmp_path, [name])  # no ".npz" appended, no temporary file
    got = read_scan_npz(tmp_path / name)
    for f in dataclasses.fields(ScanResult):
        a, b = getattr(got, f.name), getattr(result, f.name)
        if f.name == "timings":
            assert a == b
        else:
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    with np.load(tmp_path / name, allow_pickle=False) as data:  # plain numpy can read it
        assert json.loads(str(data["timings"])) == result.timings


def test_npz_covers_every_field():
    assert set(ARRAY_DTYPES) | {"timings"} == {f.name for f in dataclasses.fields(ScanResult)}


def test_npz_errors(tmp_path, rng):
    np.savez(tmp_path / "partial.npz", points=np.zeros((2, 2, 3)))
    with pytest.raises(InputError, match=r"partial\.npz: not a sliscan scan: missing arrays \['confidence'"):
        read_scan_npz(tmp_path / "partial.npz")
    (tmp_path / "junk.npz").write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(InputError, match=r"junk\.npz: not a valid npz file"):
        read_scan_npz(tmp_path / "junk.npz")
    np.save(tmp_path / "single.npy", np.zeros(3))
    with pytest.raises(InputError, match=r"single\.npy: not an npz archive"):
        read_scan_npz(tmp_path / "single.npy")
    result = make_result(rng)
    write_scan_npz(tmp_path / "bad.npz", dataclasses.replace(result, stripe=result.stripe[:2]))
    with pytest.raises(InputError, match=r"bad\.npz: stripe has shape \(2, 9\), expected \(6, 9\) \(H, W\)"):
        read_scan_npz(tmp_path / "bad.npz")
    with pytest.raises(InputError, match=r"missing\.npz: cannot read"):
        read_scan_npz(tmp_path / "missing.npz")


def npy_bytes(array) -> bytes:
    """What `np.lib.format.write_array` writes for `array` (a member of `np.savez`)."""
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asarray(array), allow_pickle=False)
    return buf.getvalue()


def read_npz_arrays_plain(path) -> dict[str, np.ndarray]:
    """Every array of an npz, read by plain numpy."""
    with np.load(path, allow_pickle=False) as data:
        return {name: data[name] for name in data.files}


def odd_arrays(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Arrays of every layout the npz writer must store as numpy does."""
    grid = rng.normal(size=(40, 30)).astype(np.float32)
    grid[::3, ::7] = np.nan
    return {"c": grid, "fortran": np.asfortranarray(grid), "strided": grid[::2, ::-3], "scalar": np.array(2.5),
            "empty": np.zeros((0, 4), np.int16), "text": np.array('{"a": 1}'), "big_endian": grid.astype(">f8"),
            "record": np.zeros(5, dtype=[("x", "<f4"), ("n", "<i2")]), "when": np.arange(3).astype("M8[s]"),
            "flags": rng.random((7, 3)) < 0.5}


def test_npz_plain_numpy_reads_the_scan_nans_included(tmp_path, rng):
    result = make_result(rng)
    assert np.isnan(result.points).any() and np.isnan(result.proj_map).any()
    write_scan_npz(tmp_path / "scan.npz", result)
    with zipfile.ZipFile(tmp_path / "scan.npz") as archive:
        assert archive.testzip() is None
        assert [i.filename for i in archive.infolist()] == [f"{n}.npy" for n in (*ARRAY_DTYPES, "timings")]
        assert all(i.compress_type == zipfile.ZIP_DEFLATED for i in archive.infolist())
    with np.load(tmp_path / "scan.npz", allow_pickle=False) as data:
        for name, dtype in ARRAY_DTYPES.items():
            assert data[name].dtype == dtype
            np.testing.assert_array_equal(data[name], getattr(result, name))  # NaN where NaN


def test_npz_members_are_the_bytes_numpy_writes(tmp_path, rng):
    result = make_result(rng)
    write_scan_npz(tmp_path / "scan.npz", result)
    arrays = odd_arrays(rng)
    write_npz_arrays(tmp_path / "odd.npz", arrays)
    with zipfile.ZipFile(tmp_path / "scan.npz") as archive:
        for name, dtype in ARRAY_DTYPES.items():
            assert archive.read(f"{name}.npy") == npy_bytes(np.asarray(getattr(result, name), dtype=dtype))
        assert archive.read("timings.npy") == npy_bytes(np.array(json.dumps(result.timings)))
    with zipfile.ZipFile(tmp_path / "odd.npz") as archive:
        assert archive.testzip() is None
        for name, array in arrays.items():
            assert archive.read(f"{name}.npy") == npy_bytes(array), name
    with np.load(tmp_path / "odd.npz", allow_pickle=False) as data:
        for name, array in arrays.items():
            assert data[name].dtype == array.dtype
            np.testing.assert_array_equal(data[name], array)
    with pytest.raises(ValueError, match="without pickle"):
        write_npz_arrays(tmp_path / "object.npz", {"o": np.array([None, 1])})
    assert_only(tmp_path, ["scan.npz", "odd.npz"])


def test_npz_member_spanning_many_chunks(tmp_path, rng, monkeypatch):
    monkeypatch.setattr(npz, "_CHUNK_BYTES", 1000)  # under the 32 KiB window: each chunk's dictionary is short
    noise = rng.normal(size=(300, 200)).astype(np.float32)
    arrays = {"noise": noise, "ramp": np.tile(np.arange(200, dtype=np.float32), (300, 1)), "tiny": np.arange(3)}
    write_npz_arrays(tmp_path / "chunks.npz", arrays)
    with zipfile.ZipFile(tmp_path / "chunks.npz") as archive:
        assert archive.testzip() is None
        for name, array in arrays.items():
            assert archive.read(f"{name}.npy") == npy_bytes(array)
        ramp = archive.getinfo("ramp.npy")
        assert ramp.file_size > 200 * npz._CHUNK_BYTES
        assert ramp.compress_size < ramp.file_size / 20  # its matches reach back across chunks
    got = read_npz_arrays_plain(tmp_path / "chunks.npz")
    for name, array in arrays.items():
        np.testing.assert_array_equal(got[name], array)


def test_npz_same_file_with_one_and_two_workers(tmp_path, rng, monkeypatch):
    monkeypatch.setattr(npz, "_CHUNK_BYTES", 4096)
    monkeypatch.setattr(npz, "_dos_timestamp", lambda: (0x6000, 0x5A21))  # both files the same second
    pools = []
    real_pool = _threads.pool
    monkeypatch.setattr(_threads, "pool", lambda workers, group=0: pools.append(workers) or real_pool(workers, group))
    arrays = {**odd_arrays(rng), "noise": rng.normal(size=(100, 120)).astype(np.float32)}
    files = []
    for threads in ("1", "2"):
        monkeypatch.setenv("SLISCAN_THREADS", threads)
        files.append(write_npz_arrays(tmp_path / f"w{threads}.npz", arrays).read_bytes())
    assert pools == [2]  # one worker deflates in this thread, two on the pool
    assert files[0] == files[1]
    with zipfile.ZipFile(io.BytesIO(files[1])) as archive:
        assert archive.testzip() is None


@pytest.mark.parametrize("threads", ["1", "2"])
def test_npz_write_failure_leaves_nothing_behind(tmp_path, rng, monkeypatch, threads):
    monkeypatch.setenv("SLISCAN_THREADS", threads)
    monkeypatch.setattr(npz, "_CHUNK_BYTES", 64)

    def fail(header, data):
        raise OSError("no space left")

    monkeypatch.setattr(npz, "_crc32", fail)
    with pytest.raises(OSError, match="no space left"):
        write_scan_npz(tmp_path / "scan.npz", make_result(rng))
    assert_only(tmp_path, [])


def test_npz_zip64_records(tmp_path, rng, monkeypatch):
    # Every size, offset and count over the limits: the zip64 extra fields and end records.
    monkeypatch.setattr(npz, "_ZIP64_LIMIT", 0)
    monkeypatch.setattr(npz, "_ZIP_FILECOUNT_LIMIT", 0)
    result = make_result(rng)
    write_scan_npz(tmp_path / "scan.npz", result)
    with zipfile.ZipFile(tmp_path / "scan.npz") as archive:
        assert archive.testzip() is None
    got = read_scan_npz(tmp_path / "scan.npz")
    np.testing.assert_array_equal(got.points, result.points)
    assert got.timings == result.timings
    raw = (tmp_path / "scan.npz").read_bytes()
    end64, locator, end = raw[-98:-42], raw[-42:-22], raw[-22:]
    assert end64[:4] == b"PK\x06\x06" and locator[:4] == b"PK\x06\x07" and end[:4] == b"PK\x05\x06"
    count, size, start = struct.unpack("<3Q", end64[32:56])
    assert count == 7 and start + size == len(raw) - 98
    assert struct.unpack("<4H2L", end[4:20]) == (0, 0, count, count, size, start)  # they fit, as zipfile writes
    second = start + 46 + len("points.npy") + 4 + 8 * 2  # after the first record (its offset 0 fits)
    assert raw[second:second + 4] == b"PK\x01\x02"
    assert struct.unpack("<2L", raw[second + 20:second + 28]) == (0xFFFFFFFF, 0xFFFFFFFF)
    assert struct.unpack("<L", raw[second + 42:second + 46]) == (0xFFFFFFFF,)  # offset in the zip64 field
