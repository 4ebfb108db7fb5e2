"""Property-based fuzzing of every file reader and of the CLI on broken files (issue 7, item 3).

Whatever the bytes (random, truncated, flipped, NaN/inf, wrong JSON types, huge declared
sizes), a reader either returns a well-formed value or raises `InputError` with one line that
names the file: never another exception, a hang or a huge allocation.  The CLI cases run
`sliscan.cli.main` in-process (`click.testing.CliRunner`) and check exit status 2, a single
``error:`` line and no output left behind.  Every test is seeded (``derandomize``) and small.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sliscan import patterns, simulate
from sliscan._validate import MAX_IMAGE_PIXELS, InputError, read_image
from sliscan.cli import main
from sliscan.formats import mat5, npz, premat5
from sliscan.formats.calibration import read_matrix_txt, write_matrix_txt
from sliscan.types import Calibration, PatternSpec, ScanResult

FUZZ = settings(derandomize=True, max_examples=60, suppress_health_check=[HealthCheck.function_scoped_fixture])
CLI_FUZZ = settings(derandomize=True, max_examples=8, suppress_health_check=[HealthCheck.function_scoped_fixture])

CAMERA = (640, 480)
PROJECTOR = (1024, 768)


# --------------------------------------------------------------------------------------------
# Strategies
# --------------------------------------------------------------------------------------------


def mangled(valid: bytes) -> st.SearchStrategy[bytes]:
    """Broken variants of a valid file: random bytes, a truncation, flipped bytes, junk appended."""
    n = len(valid)
    truncated = st.integers(0, n - 1).map(lambda k: valid[:k])
    flipped = st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=8).map(
        lambda edits: bytes(_edit(bytearray(valid), edits)))
    appended = st.binary(min_size=1, max_size=64).map(lambda junk: valid + junk)
    return st.one_of(st.binary(max_size=2 * n), truncated, flipped, appended)


def _edit(data: bytearray, edits: list[tuple[int, int]]) -> bytearray:
    for pos, value in edits:
        data[pos] = value
    return data


#: Any JSON value, with the numbers a broken file may hold (NaN, inf, huge, negative).
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.sampled_from([0, -1, 10**12, 2**31, 1e400, -1e400, math.nan, 0.5, 1e-300])
    | st.integers(-10**6, 10**6) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12,
)


#: Values that look almost right: NaN, inf, a bool, a number as a string, a fraction.
BAD_SCALARS = st.sampled_from([math.nan, math.inf, 1e400, True, "4", 2.5, -3, None, [], {}])


def _paths(d: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path into nested dicts and lists of `d`."""
    items = d.items() if isinstance(d, dict) else enumerate(d) if isinstance(d, list) else ()
    out = []
    for key, value in items:
        out.append((*prefix, key))
        out += _paths(value, (*prefix, key))
    return out


@st.composite
def mutated_json(draw: st.DrawFn, valid: dict[str, Any]) -> str:
    """`valid` with one value replaced by any JSON value (or a huge size), or a key deleted."""
    d = json.loads(json.dumps(valid))
    path = draw(st.sampled_from(_paths(d)))
    *parents, key = path
    node = d
    for p in parents:
        node = node[p]
    action = draw(st.sampled_from(["replace", "delete", "huge"]))
    if action == "delete" and isinstance(node, dict):
        del node[key]
    elif action == "huge":
        node[key] = draw(st.sampled_from([[10**12, 10**12], [2**31, 8], [65536, 65536], 10**12, "1" * 5000]))
    else:
        node[key] = draw(BAD_SCALARS | JSON_VALUES)
    return json.dumps(d, allow_nan=True)


def json_files(valid: dict[str, Any]) -> st.SearchStrategy[bytes]:
    """Broken JSON files: mutated values, broken bytes, deep nesting, a huge number."""
    text = json.dumps(valid, indent=2).encode()
    special = st.sampled_from([b"[" * 100_000, b"1" * 5000, b"[]", b"null", b"\xff\xfe{}", b""])
    return st.one_of(mutated_json(valid).map(str.encode), mangled(text), special)


# --------------------------------------------------------------------------------------------
# Valid sample files
# --------------------------------------------------------------------------------------------


def encode(suffix: str, image: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(suffix, image)
    assert ok
    return buf.tobytes()


GREY = (np.arange(16 * 12, dtype=np.uint16).reshape(12, 16) * 300)
IMAGES = {
    ".png": encode(".png", (GREY // 256).astype(np.uint8)),
    ".tif": encode(".tif", GREY),
    ".bmp": encode(".bmp", (GREY // 256).astype(np.uint8)),
}


def png_of_size(width: int, height: int) -> bytes:
    """A valid 8x8 PNG whose header claims `width` x `height` (CRC fixed, data too short)."""
    data = bytearray(IMAGES[".png"])
    data[16:24] = struct.pack(">II", width & 0xFFFFFFFF, height & 0xFFFFFFFF)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    return bytes(data)


def bmp_of_size(width: int, height: int) -> bytes:
    """A valid BMP whose header claims `width` x `height`."""
    data = bytearray(IMAGES[".bmp"])
    data[18:26] = struct.pack("<ii", width, height)
    return bytes(data)


HUGE_SIZES = st.sampled_from([(2**20, 2**20), (30000, 30000), (1, 2**28), (2**31 - 1, 1), (0, 0), (-8, 8)])


@pytest.fixture(scope="module")
def rig() -> simulate.Rig:
    return simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR)


def sample_specs() -> dict[str, dict[str, Any]]:
    """JSON of a composite, a modified composite and a PMP spec."""
    best = patterns.default_spec(PROJECTOR)
    return {"composite": best.to_dict(),
            "modified": patterns.thesis_spec(PROJECTOR).with_(kind="modified_composite",
                                                               modified_amplitude=0.05).to_dict(),
            "pmp": PatternSpec(kind="pmp", projector_size=PROJECTOR, steps=3, frequencies=(1.0, 16.0)).to_dict()}


def g_rows(rig: simulate.Rig) -> np.ndarray:
    """A calibration grid of `rig`: 20 world points, their camera pixels and projector phases."""
    world = np.random.default_rng(0).uniform([-150.0, -100.0, 700.0], [150.0, 100.0, 900.0], (20, 3))
    proj = rig.calibration.projector.project(world)
    phases = np.c_[premat5.pixel_to_phase(proj[:, 0], PROJECTOR[0]), premat5.pixel_to_phase(proj[:, 1], PROJECTOR[1])]
    return np.c_[world, rig.calibration.camera.project(world), phases]


# --------------------------------------------------------------------------------------------
# The property every reader must have
# --------------------------------------------------------------------------------------------


def read_or_input_error(read: Callable[[Path], Any], path: Path) -> Any:
    """`read(path)`, or None if it raised an `InputError` of one line naming `path`."""
    try:
        return read(path)
    except InputError as exc:
        message = str(exc)
        assert "\n" not in message and str(path) in message, message
        return None


# --------------------------------------------------------------------------------------------
# Readers
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", sorted(IMAGES))
@FUZZ
@given(data=st.data())
def test_image_reader(tmp_path: Path, suffix: str, data: st.DataObject) -> None:
    path = tmp_path / f"capture{suffix}"
    path.write_bytes(data.draw(mangled(IMAGES[suffix])))
    image = read_or_input_error(read_image, path)
    if image is not None:
        assert image.ndim == 2 and image.dtype == np.float32 and np.all(np.isfinite(image))


@FUZZ
@given(size=HUGE_SIZES, kind=st.sampled_from(["png", "bmp"]))
def test_image_reader_huge_declared_size(tmp_path: Path, size: tuple[int, int], kind: str) -> None:
    path = tmp_path / f"huge.{kind}"
    path.write_bytes(png_of_size(*size) if kind == "png" else bmp_of_size(*size))
    assert read_or_input_error(read_image, path) is None


def test_image_reader_rejects_nan_and_out_of_range_floats(tmp_path: Path) -> None:
    for name, values in (("nan", np.full((8, 8), np.nan, np.float32)), ("big", np.full((8, 8), 7.0, np.float32))):
        path = tmp_path / f"{name}.tif"
        path.write_bytes(encode(".tif", values))
        assert read_or_input_error(read_image, path) is None


@pytest.mark.parametrize("kind", sorted(sample_specs()))
@FUZZ
@given(data=st.data())
def test_pattern_spec_reader(tmp_path: Path, kind: str, data: st.DataObject) -> None:
    path = tmp_path / "cp.json"
    path.write_bytes(data.draw(json_files(sample_specs()[kind])))
    spec = read_or_input_error(PatternSpec.load, path)
    if spec is not None:
        w, h = spec.projector_size
        assert w * h <= MAX_IMAGE_PIXELS
        assert all(math.isfinite(v) for v in (*spec.all_carriers, *spec.all_weights, spec.a_p, spec.b_p))


@FUZZ
@given(data=st.data())
def test_calibration_reader(tmp_path: Path, rig: simulate.Rig, data: st.DataObject) -> None:
    path = tmp_path / "rig.json"
    path.write_bytes(data.draw(json_files(rig.calibration.to_dict())))
    calib = read_or_input_error(Calibration.load, path)
    if calib is not None:
        for device in (calib.camera, calib.projector):
            assert device.size[0] * device.size[1] <= MAX_IMAGE_PIXELS
            assert np.all(np.isfinite(device.matrix))


@FUZZ
@given(data=st.data())
def test_matrix_text_reader(tmp_path: Path, rig: simulate.Rig, data: st.DataObject) -> None:
    valid = write_matrix_txt(tmp_path / "valid.txt", rig.calibration.camera.matrix).read_bytes()
    path = tmp_path / "cam.txt"
    special = st.sampled_from([b"nan 1 2 3\n" * 3, b"1e999 1 2 3\n" * 3, b"1 2 3 4\n" * 2, b"1 2 3\n" * 4])
    path.write_bytes(data.draw(mangled(valid) | special))
    matrix = read_or_input_error(read_matrix_txt, path)
    if matrix is not None:
        assert matrix.shape == (3, 4) and np.all(np.isfinite(matrix))


@pytest.mark.parametrize("name", ["G.byt", "G.txt"])
@FUZZ
@given(data=st.data())
def test_g_reader(tmp_path: Path, rig: simulate.Rig, name: str, data: st.DataObject) -> None:
    rows = g_rows(rig)
    valid = premat5.write_g(tmp_path / f"valid_{name}", rows).read_bytes()
    rows[2, 3] = np.nan
    nan = premat5.write_byt(tmp_path / "nan.byt", rows).read_bytes() if name.endswith(".byt") else b"1 2 3 4 5 6 inf\n"
    path = tmp_path / name
    path.write_bytes(data.draw(mangled(valid) | st.just(nan)))
    rows = read_or_input_error(premat5.read_g, path)
    if rows is not None:
        assert rows.ndim == 2 and rows.shape[1] == 7 and np.all(np.isfinite(rows))


@pytest.mark.parametrize("name, shape", [("A.byt", (4, 4)), ("XP.byt", (12, 16)), ("YP.byt", (12, 16))])
@FUZZ
@given(data=st.data())
def test_byt_readers(tmp_path: Path, name: str, shape: tuple[int, int], data: st.DataObject) -> None:
    valid = np.random.default_rng(1).uniform(0, 6, shape).astype("<f4").tobytes()
    path = tmp_path / name
    path.write_bytes(data.draw(mangled(valid)))
    read = premat5.read_a if name == "A.byt" else (lambda p: premat5.read_byt(p, shape))
    values = read_or_input_error(read, path)
    if values is not None:
        assert values.shape == shape


@pytest.mark.parametrize("suffix", mat5.SUFFIXES)
@FUZZ
@given(data=st.data())
def test_mat5_reader(tmp_path: Path, suffix: str, data: st.DataObject) -> None:
    valid = np.random.default_rng(2).uniform(size=(12, 16)) > 0.3
    points = np.random.default_rng(3).uniform(-50, 50, (12, 16, 3))
    prefix = tmp_path / "scan"
    paths = mat5.write_mat5(prefix, points, valid, np.full((12, 16), 0.5))
    broken = paths[mat5.SUFFIXES.index(suffix)]
    broken.write_bytes(data.draw(mangled(broken.read_bytes())))
    try:
        mat5.read_mat5(prefix)
    except InputError as exc:
        assert "\n" not in str(exc) and str(tmp_path) in str(exc)


@FUZZ
@given(data=st.data())
def test_npz_reader(tmp_path: Path, data: st.DataObject) -> None:
    shape = (6, 8)
    result = ScanResult(points=np.zeros((*shape, 3), np.float32), valid=np.ones(shape, bool),
                        texture=np.zeros(shape, np.float32), proj_map=np.zeros(shape, np.float32),
                        stripe=np.zeros(shape, np.int16), confidence=np.ones(shape, np.float32))
    valid = npz.write_scan_npz(tmp_path / "valid.npz", result).read_bytes()
    path = tmp_path / "scan.npz"
    path.write_bytes(data.draw(mangled(valid)))
    read_or_input_error(npz.read_scan_npz, path)


# --------------------------------------------------------------------------------------------
# The CLI on fuzzed files: exit 2, one `error:` line, nothing written
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cli_inputs(tmp_path_factory: pytest.TempPathFactory, rig: simulate.Rig) -> dict[str, bytes]:
    """Valid inputs of scan, calibrate and simulate on the small rig, by file name."""
    folder = tmp_path_factory.mktemp("cli_inputs")
    spec = patterns.default_spec(PROJECTOR)
    capture = simulate.render(rig, simulate.plane_scene(), patterns.render_pattern(spec),
                              simulate.Conditions(seed=0, supersample=1))
    spec.save(folder / "cp.json")
    rig.calibration.save(folder / "rig.json")
    premat5.write_g(folder / "G.byt", g_rows(rig))
    files = {p.name: p.read_bytes() for p in folder.iterdir()}
    return {**files, "capture.png": encode(".png", (capture.image * 255).astype(np.uint8))}


def run_cli(folder: Path, args: list[str], monkeypatch: pytest.MonkeyPatch) -> tuple[int, str, str]:
    """`sliscan ARGS` in-process in `folder`: exit status, stdout, stderr."""
    monkeypatch.chdir(folder)
    with CliRunner().isolation() as (out, err, _):
        try:
            main(args)
            code = 0
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue().decode(), err.getvalue().decode()


CLI_CASES: dict[str, tuple[str, list[str], list[str]]] = {
    "scan, broken capture": ("capture.png", ["scan", "capture.png", "--pattern", "cp.json", "--calibration",
                                             "rig.json", "--ply", "out/s.ply", "--mat5", "out/s"],
                             ["out"]),
    "scan, broken pattern": ("cp.json", ["scan", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json",
                                         "--npz", "out/s.npz"], ["out"]),
    "scan, broken calibration": ("rig.json", ["scan", "capture.png", "--pattern", "cp.json", "--calibration",
                                              "rig.json", "--npz", "out/s.npz"], ["out"]),
    "calibrate, broken G file": ("G.byt", ["calibrate", "G.byt", "--camera-size", "640x480", "--projector",
                                           "1024x768", "-o", "out/rig.json", "--cam-txt", "out/cam.txt"], ["out"]),
    "simulate, broken pattern": ("cp.json", ["simulate", "--pattern", "cp.json", "--calibration", "rig.json",
                                             "--supersample", "1", "-o", "out/c.png"], ["out"]),
    "simulate, broken calibration": ("rig.json", ["simulate", "--pattern", "cp.json", "--calibration", "rig.json",
                                                  "--supersample", "1", "-o", "out/c.png"], ["out"]),
}


def test_cli_cases_pass_on_valid_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                       cli_inputs: dict[str, bytes]) -> None:
    """The fuzz cases below start from files that work."""
    for case, (_, args, outputs) in CLI_CASES.items():
        folder = tmp_path / case.replace(",", "").replace(" ", "_")
        folder.mkdir()
        for name, content in cli_inputs.items():
            (folder / name).write_bytes(content)
        code, _, err = run_cli(folder, args, monkeypatch)
        assert code == 0 and all((folder / o).exists() for o in outputs), (case, err)


@pytest.mark.parametrize("case", CLI_CASES)
@CLI_FUZZ
@given(data=st.data())
def test_cli_on_broken_files(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch,
                             cli_inputs: dict[str, bytes], case: str, data: st.DataObject) -> None:
    broken, args, outputs = CLI_CASES[case]
    valid = cli_inputs[broken]
    content = data.draw(json_files(json.loads(valid)) if broken.endswith(".json") else mangled(valid))
    folder = tmp_path_factory.mktemp("cli")
    for name, file_content in {**cli_inputs, broken: content}.items():
        (folder / name).write_bytes(file_content)
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    code, out, err = run_cli(folder, args, monkeypatch)
    if code == 0:  # the mutation happened to leave a usable file
        assert all((folder / o).exists() for o in outputs)
        return
    lines = err.splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
    assert out == ""
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before  # no output, no temporary, inputs intact
