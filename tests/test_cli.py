"""The ``sliscan`` command as a user runs it: one subprocess per command (DESIGN.md, "The command line").

Everything runs on a small virtual rig (a 640x480 camera, the thesis's 1024x768 projector) so
each command takes a few seconds.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from sliscan import patterns, sequences, simulate
from sliscan._validate import read_image
from sliscan.formats import mat5, npz, ply, premat5
from sliscan.formats.calibration import read_matrix_txt, write_matrix_txt
from sliscan.outliers import default_max_jump, remove_run_ends
from sliscan.pipeline import Scanner, stripe_tilt_deg
from sliscan.reconstruct import triangulate_points
from sliscan.types import Calibration, PatternSpec

CAMERA = (640, 480)
PROJECTOR = (1024, 768)
CAMERA_ARG = "640x480"
PROJECTOR_ARG = "1024x768"


def sliscan(*args: object, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run ``python -m sliscan ARGS`` in `cwd`, no stdin, capturing its output."""
    return subprocess.run([sys.executable, "-m", "sliscan", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, stdin=subprocess.DEVNULL, timeout=300)


def ok(*args: object, cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run a command that must succeed with a one-line summary on stdout."""
    result = sliscan(*args, cwd=cwd)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip(), "a command prints a summary of what it wrote"
    return result


def read_png(path: Path) -> np.ndarray:
    """An image file as stored (8-bit stays uint8)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, f"{path} is not an image"
    return image


def listing(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` and its content."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def plane(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """pattern -> simulate (writing the rig) -> scan of the plane scene; the folder and scan's stdout."""
    folder = tmp_path_factory.mktemp("plane")
    ok("pattern", "composite", "--projector", PROJECTOR_ARG, "-o", "cp.png", cwd=folder)
    ok("simulate", "--pattern", "cp.json", "--scene", "plane", "--camera", CAMERA_ARG, "--supersample", "1",
       "--write-rig", "rig.json", "--truth", "truth.npz", "-o", "capture.png", cwd=folder)
    scan = ok("scan", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json", "--mat5", "out/plane",
              "--ply", "out/plane.ply", "--npz", "out/plane.npz", cwd=folder)
    return folder, scan.stdout


def test_pattern_with_only_the_projector_is_the_default_spec(plane: tuple[Path, str]) -> None:
    folder, _ = plane
    spec = PatternSpec.load(folder / "cp.json")
    assert spec == patterns.default_spec(PROJECTOR).with_(image="cp.png")
    image = read_png(folder / "cp.png")
    np.testing.assert_array_equal(image, np.round(patterns.render_pattern(spec) * 255).astype(np.uint8))


def test_pattern_thesis_flag_and_thesis_carriers_agree(tmp_path: Path) -> None:
    ok("pattern", "composite", "--projector", PROJECTOR_ARG, "--thesis", "-o", "a.png", cwd=tmp_path)
    ok("pattern", "composite", "--projector", PROJECTOR_ARG, "--bits", "4", "--carriers", "32,64,96,128",
       "-o", "b.png", cwd=tmp_path)
    thesis = patterns.thesis_spec(PROJECTOR)
    assert PatternSpec.load(tmp_path / "a.json") == thesis.with_(image="a.png")
    assert PatternSpec.load(tmp_path / "b.json") == thesis.with_(image="b.png")


def test_pattern_modified_stays_in_range(tmp_path: Path) -> None:
    ok("pattern", "modified", "--projector", PROJECTOR_ARG, "--thesis", "-o", "m.png", cwd=tmp_path)
    spec = PatternSpec.load(tmp_path / "m.json")
    assert spec.kind == "modified_composite" and spec.modified_amplitude > 0
    low, high = patterns.pattern_range(spec)
    assert low >= 0 and high <= 1 + 1e-12


def test_scan_of_the_plane(plane: tuple[Path, str]) -> None:
    folder, stdout = plane
    points, valid, _ = mat5.read_mat5(folder / "out/plane")
    assert valid.shape == CAMERA[::-1]
    n_valid = int(valid.sum())
    assert n_valid > 0.5 * valid.size
    assert f"{n_valid} points" in stdout and len(stdout.splitlines()) == 1
    ply_points, _ = ply.read_point_cloud(folder / "out/plane.ply")
    assert len(ply_points) == n_valid
    result = npz.read_scan_npz(folder / "out/plane.npz")
    np.testing.assert_array_equal(result.valid, valid)

    # The plane lies at the rig's working distance (800 mm).  A decoded pixel is triangulated
    # from its stripe's centre row, so it lies at most half a stripe's depth from the plane:
    # measure that depth along the central camera ray, between the two rows bounding its stripe.
    spec = PatternSpec.load(folder / "cp.json")
    calibration = Calibration.load(folder / "rig.json")
    xc, yc = (CAMERA[0] - 1) / 2, (CAMERA[1] - 1) / 2
    yp = simulate.Rig(calibration).projector.project([0.0, 0.0, 800.0])[0][1]
    stripe = patterns.stripe_of_line(yp, spec)
    edges = (stripe + np.array([0.0, 1.0])) * spec.phase_lines / spec.stripes - 0.5
    z_edges = triangulate_points([xc, xc], [yc, yc], edges, calibration)[:, 2]
    half_stripe_mm = abs(z_edges[1] - z_edges[0]) / 2
    assert 1 < half_stripe_mm < 100
    assert abs(float(np.median(points[valid][:, 2])) - 800.0) < half_stripe_mm


def test_a_rolled_projector_is_simulated_and_its_scan_warns(plane: tuple[Path, str], tmp_path: Path) -> None:
    """`simulate --projector-roll 5` turns the virtual rig's projector (its rows then cross the
    camera's at 5.1 degrees: `pipeline.stripe_tilt_deg`), and `scan` with that rig says so on
    stderr, once, and still writes the points; the unturned rig of the module's scan said
    nothing; `--projector-offset 80` moves it sideways, which `scan` names too."""
    folder, _ = plane
    ok("simulate", "--pattern", folder / "cp.json", "--scene", "plane", "--camera", CAMERA_ARG, "--supersample", "1",
       "--projector-roll", "5", "--write-rig", "rig.json", "-o", "capture.png", cwd=tmp_path)
    assert 5.0 < stripe_tilt_deg(Calibration.load(tmp_path / "rig.json")) < 5.3
    scan = ok("scan", "capture.png", "--pattern", folder / "cp.json", "--calibration", "rig.json", "--npz", "out.npz",
              cwd=tmp_path)
    assert scan.stderr.count("warning:") == 1 and "5.1 degrees" in scan.stderr
    assert npz.read_scan_npz(tmp_path / "out.npz").valid.mean() > 0.5
    quiet = sliscan("scan", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json", cwd=folder)
    assert quiet.returncode == 0 and "warning" not in quiet.stderr
    ok("simulate", "--pattern", folder / "cp.json", "--scene", "plane", "--camera", CAMERA_ARG, "--supersample", "1",
       "--projector-offset", "80", "--write-rig", "aside.json", "-o", "aside.png", cwd=tmp_path)
    aside = ok("scan", "aside.png", "--pattern", folder / "cp.json", "--calibration", "aside.json", cwd=tmp_path)
    assert "sits 22 degrees off straight above or below the camera" in aside.stderr  # atan(80 / 200)


def test_a_pattern_coding_the_lines_along_the_baseline_is_told_which_to_code(plane: tuple[Path, str],
                                                                              tmp_path: Path) -> None:
    """With the camera beside the projector the projector's rows do not move with depth: a rows
    pattern scanned there gets a warning naming the orientation to use (before whatever the
    scan makes of it: here its carriers, running along the baseline, smear with depth and are
    not found); the columns pattern the warning asks for scans that rig without one."""
    folder, _ = plane
    simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR,
                         baseline_axis="horizontal").calibration.save(tmp_path / "side.json")
    ok("pattern", "composite", "--projector", PROJECTOR_ARG, "--orientation", "columns", "-o", "cols.png", cwd=tmp_path)
    for pattern in (folder / "cp.json", "cols.json"):
        ok("simulate", "--pattern", pattern, "--scene", "plane", "--calibration", "side.json", "--supersample", "1",
           "-o", "capture.png", "--overwrite", cwd=tmp_path)
        scan = sliscan("scan", "capture.png", "--pattern", pattern, "--calibration", "side.json", cwd=tmp_path)
        if pattern == "cols.json":
            assert scan.returncode == 0 and "warning" not in scan.stderr
        else:
            first = scan.stderr.splitlines()[0]
            assert first.startswith("warning: ") and "make the pattern with --orientation columns" in first


def test_a_pattern_made_for_a_calibration_fits_its_rig(plane: tuple[Path, str], tmp_path: Path) -> None:
    """`pattern composite --calibration` takes the projector's size and the orientation the
    rig's baseline needs (columns with the camera beside the projector), and warns when the
    rig's camera will not resolve the pattern: the phase channel's finest carrier, 224 cycles
    per 1024 px, spans 2.8 camera px per period at 640x480 (`pipeline.carrier_period_px`;
    under `MIN_CARRIER_PERIOD_PX`); the default pattern's 128 cycles, 4.9, does not warn."""
    folder, _ = plane
    simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR,
                         baseline_axis="horizontal").calibration.save(tmp_path / "beside.json")
    made = ok("pattern", "composite", "--calibration", "beside.json", "-o", "side.png", cwd=tmp_path)
    assert "warning" not in made.stderr
    side = PatternSpec.load(tmp_path / "side.json")
    assert side.orientation == "columns" and side.projector_size == PROJECTOR
    assert side == patterns.default_spec(PROJECTOR, orientation="columns").with_(image="side.png")
    phase = ok("pattern", "composite", "--calibration", folder / "rig.json", "--phase", "-o", "phase.png", cwd=tmp_path)
    assert phase.stderr.count("warning:") == 1 and "spans 2.8 camera px per period" in phase.stderr
    assert PatternSpec.load(tmp_path / "phase.json").orientation == "rows"
    simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR,
                         projector_offset_mm=80.0).calibration.save(tmp_path / "offset-rig.json")
    aside = ok("pattern", "composite", "--calibration", "offset-rig.json", "-o", "aside.png", cwd=tmp_path)
    assert "sits 22 degrees off straight above or below the camera" in aside.stderr  # atan(80 / 200)
    usage = sliscan("pattern", "composite", "-o", "none.png", cwd=tmp_path)
    assert usage.returncode == 2 and "--projector WxH, or --calibration" in usage.stderr
    assert not (tmp_path / "none.png").exists()


def test_simulate_writes_the_ground_truth(plane: tuple[Path, str]) -> None:
    folder, _ = plane
    with np.load(folder / "truth.npz") as truth:
        assert {"points", "proj", "lit", "surface"} <= set(truth.files)
        assert truth["points"].shape == (*CAMERA[::-1], 3)
        np.testing.assert_allclose(truth["points"][truth["surface"]][:, 2], 800.0, rtol=0, atol=1e-3)  # float32 mm
    capture = read_png(folder / "capture.png")
    assert capture.dtype == np.uint8 and capture.shape == CAMERA[::-1]


def test_simulate_depth_of_field_reaches_the_render(tmp_path: Path) -> None:
    ok("pattern", "composite", "--projector", "256x192", "-o", "cp.png", cwd=tmp_path)
    common = ("simulate", "--pattern", "cp.json", "--scene", "plane", "--camera", "160x120", "--supersample", "1",
              "--no-noise")
    ok(*common, "--projector-focus", 400, "--projector-aperture", 30, "--camera-focus", 500, "--camera-aperture", 20,
       "-o", "dof.png", cwd=tmp_path)
    ok(*common, "-o", "sharp.png", cwd=tmp_path)
    conditions = simulate.Conditions(ambient=0.1, projector_gamma=2.2, supersample=1, seed=0, full_well_e=None,
                                     projector_focus_mm=400.0, projector_aperture_mm=30.0, camera_focus_mm=500.0,
                                     camera_aperture_mm=20.0)
    rig = simulate.virtual_rig(camera_size=(160, 120), projector_size=(256, 192))
    spec = PatternSpec.load(tmp_path / "cp.json")
    expected = simulate.render(rig, simulate.plane_scene(), patterns.render_pattern(spec), conditions).image
    np.testing.assert_array_equal(read_png(tmp_path / "dof.png"), np.round(expected * 255).astype(np.uint8))
    # out of focus the carriers lose contrast
    contrast = {name: np.std(read_png(tmp_path / f"{name}.png").astype(float)) for name in ("dof", "sharp")}
    assert contrast["dof"] < 0.9 * contrast["sharp"]
    bad = sliscan(*common, "--projector-focus", 0, "-o", "bad.png", cwd=tmp_path)
    assert bad.returncode == 2 and "--projector-focus" in bad.stderr and not (tmp_path / "bad.png").exists()


def test_scan_timings_prints_every_stage(plane: tuple[Path, str]) -> None:
    folder, _ = plane
    stdout = ok("scan", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json", "--timings",
                cwd=folder).stdout.splitlines()
    stages = [line.split()[0] for line in stdout[1:]]
    assert stages == ["read", "demodulate", "decode", "triangulate", "write", "total"]
    assert all(line.endswith(" ms") and float(line.split()[1]) >= 0 for line in stdout[1:])


def test_scan_with_text_matrices_matches_the_json(plane: tuple[Path, str], tmp_path: Path) -> None:
    folder, _ = plane
    calibration = Calibration.load(folder / "rig.json")
    write_matrix_txt(tmp_path / "cam.txt", calibration.camera.matrix)
    write_matrix_txt(tmp_path / "proj.txt", calibration.projector.matrix)
    ok("scan", folder / "capture.png", "--pattern", folder / "cp.json", "--camera-matrix", "cam.txt",
       "--projector-matrix", "proj.txt", "--npz", "scan.npz", cwd=tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cam.txt", "proj.txt", "scan.npz"]
    from_text = npz.read_scan_npz(tmp_path / "scan.npz")
    from_json = npz.read_scan_npz(folder / "out/plane.npz")
    np.testing.assert_array_equal(from_text.valid, from_json.valid)
    # cam.txt keeps 10 significant digits: points agree far below a micrometre
    np.testing.assert_allclose(from_text.points, from_json.points, rtol=0, atol=1e-3, equal_nan=True)


@pytest.mark.parametrize("decisions", ["pixel", "order"])
def test_scan_decisions_are_the_decoders_of_the_python_api(plane: tuple[Path, str], tmp_path: Path,
                                                           decisions: str) -> None:
    folder, _ = plane
    ok("scan", folder / "capture.png", "--pattern", folder / "cp.json", "--calibration", folder / "rig.json",
       "--decisions", decisions, "--npz", "scan.npz", cwd=tmp_path)
    from_cli = npz.read_scan_npz(tmp_path / "scan.npz")
    scanner = Scanner(PatternSpec.load(folder / "cp.json"), Calibration.load(folder / "rig.json"),
                      decode_options=dict(order=decisions == "order"))
    expected = scanner.scan(read_image(folder / "capture.png"))
    np.testing.assert_array_equal(from_cli.valid, expected.valid)
    np.testing.assert_array_equal(from_cli.stripe, expected.stripe)
    np.testing.assert_allclose(from_cli.points, expected.points, rtol=0, atol=1e-4, equal_nan=True)


def test_scan_method_baseband_is_the_real_time_path_of_the_python_api(plane: tuple[Path, str],
                                                                     tmp_path: Path) -> None:
    folder, _ = plane
    stdout = ok("scan", folder / "capture.png", "--pattern", folder / "cp.json", "--calibration", folder / "rig.json",
                "--method", "baseband", "--npz", "scan.npz", "--timings", cwd=tmp_path).stdout.splitlines()
    assert [line.split()[0] for line in stdout[1:]] == ["read", "demodulate", "decode", "triangulate", "write",
                                                         "total"]
    from_cli = npz.read_scan_npz(tmp_path / "scan.npz")
    expected = Scanner(PatternSpec.load(folder / "cp.json"), Calibration.load(folder / "rig.json"),
                       method="baseband").scan(read_image(folder / "capture.png"))
    np.testing.assert_array_equal(from_cli.valid, expected.valid)
    assert from_cli.valid.mean() > 0.5
    np.testing.assert_allclose(from_cli.points, expected.points, rtol=0, atol=1e-4, equal_nan=True)
    fails_cleanly(("scan", str(folder / "capture.png"), "--pattern", str(folder / "cp.json"), "--calibration",
                   str(folder / "rig.json"), "--method", "baseband", "--decisions", "order", "--npz", "o.npz"),
                  "baseband", tmp_path)


def test_scan_without_albedo_steps_is_the_scanner_without_them(plane: tuple[Path, str], tmp_path: Path) -> None:
    """--no-albedo-steps reaches the scanner: the baseband scan equals ``Scanner(albedo=None)``'s,
    which differs from the default's (the flat field divides even a uniform plane's capture)."""
    folder, _ = plane
    ok("scan", folder / "capture.png", "--pattern", folder / "cp.json", "--calibration", folder / "rig.json",
       "--method", "baseband", "--no-albedo-steps", "--npz", "scan.npz", cwd=tmp_path)
    from_cli = npz.read_scan_npz(tmp_path / "scan.npz")
    spec, calibration = PatternSpec.load(folder / "cp.json"), Calibration.load(folder / "rig.json")
    image = read_image(folder / "capture.png")
    plain, steps = (Scanner(spec, calibration, method="baseband", albedo=albedo).scan(image)
                    for albedo in (None, "steps"))
    assert not np.array_equal(plain.confidence, steps.confidence)
    np.testing.assert_array_equal(from_cli.valid, plain.valid)
    np.testing.assert_array_equal(from_cli.confidence, plain.confidence)


def test_scan_trim_edges_trims_the_run_ends_as_the_scanner_does(plane: tuple[Path, str], tmp_path: Path) -> None:
    """--trim-edges reaches the scanner (``Scanner(trim_edges=)``): the plane's scan less the
    pixels within the margin of each run's ends along the carriers (here the frame's edges and
    the projected area's)."""
    folder, _ = plane
    ok("scan", folder / "capture.png", "--pattern", folder / "cp.json", "--calibration", folder / "rig.json",
       "--trim-edges", "4", "--npz", "trimmed.npz", cwd=tmp_path)
    trimmed = npz.read_scan_npz(tmp_path / "trimmed.npz")
    full = npz.read_scan_npz(folder / "out" / "plane.npz")
    spec = PatternSpec.load(folder / "cp.json")
    expected = remove_run_ends(full.proj_map, full.valid, margin=4, max_jump=default_max_jump(spec, "rows"))
    np.testing.assert_array_equal(trimmed.valid, expected)
    assert 0 < full.valid.sum() - trimmed.valid.sum() < 0.1 * full.valid.sum()
    bad = sliscan("scan", folder / "capture.png", "--pattern", folder / "cp.json", "--calibration", folder / "rig.json",
              "--trim-edges", "-1", "--npz", "bad.npz", cwd=tmp_path)
    assert bad.returncode == 2 and not (tmp_path / "bad.npz").exists()


def test_scan_camera_blur_reaches_the_scanner(plane: tuple[Path, str], tmp_path: Path) -> None:
    """--camera-blur reaches the scanner (``Scanner(camera_blur=)``): a checkered plane scanned
    for a 2.5 px camera equals the Python API's, and differs from the default's (the blur
    measured on the capture: 1 px here); 0 is refused, nothing written."""
    folder, _ = plane
    ok("simulate", "--pattern", folder / "cp.json", "--scene", "plane", "--calibration", folder / "rig.json",
       "--albedo", "checker", "--supersample", "1", "-o", "checker.png", cwd=tmp_path)
    ok("scan", "checker.png", "--pattern", folder / "cp.json", "--calibration", folder / "rig.json",
       "--camera-blur", "2.5", "--npz", "blurred.npz", cwd=tmp_path)
    from_cli = npz.read_scan_npz(tmp_path / "blurred.npz")
    spec, calibration = PatternSpec.load(folder / "cp.json"), Calibration.load(folder / "rig.json")
    image = read_image(tmp_path / "checker.png")
    blurred, measured = (Scanner(spec, calibration, camera_blur=blur).scan(image) for blur in (2.5, None))
    assert not np.array_equal(blurred.confidence, measured.confidence)
    np.testing.assert_array_equal(from_cli.valid, blurred.valid)
    np.testing.assert_array_equal(from_cli.confidence, blurred.confidence)
    bad = sliscan("scan", "checker.png", "--pattern", folder / "cp.json", "--calibration", folder / "rig.json",
                  "--camera-blur", "0", "--npz", "bad.npz", cwd=tmp_path)
    assert bad.returncode == 2 and not (tmp_path / "bad.npz").exists()


def test_scan_stripe_centres_are_the_staircase_the_stripe_lines_remove(plane: tuple[Path, str],
                                                                        tmp_path: Path) -> None:
    """--stripe-centres reaches the scanner (``Scanner(interpolate_stripes=False)``): one line per
    stripe, its centre, so on the plane the median line error is a quarter of a stripe (uniform
    within each stripe); the default lines between the located borders are within a line."""
    folder, _ = plane
    for flag in ("--stripe-centres", "--stripe-lines"):
        ok("scan", folder / "capture.png", "--pattern", folder / "cp.json", "--calibration", folder / "rig.json",
           flag, "--npz", f"{flag[2:]}.npz", cwd=tmp_path)
    centres, lines = (npz.read_scan_npz(tmp_path / name) for name in ("stripe-centres.npz", "stripe-lines.npz"))
    spec, calibration = PatternSpec.load(folder / "cp.json"), Calibration.load(folder / "rig.json")
    expected = Scanner(spec, calibration, interpolate_stripes=False).scan(read_image(folder / "capture.png"))
    np.testing.assert_array_equal(centres.proj_map, expected.proj_map)
    valid = centres.valid
    stripes = np.unique(centres.stripe[valid])
    assert all(np.unique(centres.proj_map[valid & (centres.stripe == k)]).size == 1 for k in stripes)
    with np.load(folder / "truth.npz") as truth:
        true_line = truth["proj"][..., 1]
    stripe_lines = spec.projector_size[1] / 2 ** spec.bits
    centre_error = np.median(np.abs(centres.proj_map - true_line)[valid])
    assert 0.2 * stripe_lines < centre_error < 0.3 * stripe_lines, centre_error
    assert np.median(np.abs(lines.proj_map - true_line)[lines.valid]) < 1.0


@pytest.mark.parametrize("method", ["svd", "lstsq"])
def test_calibrate_recovers_the_rig(tmp_path: Path, method: str) -> None:
    rig = simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR)
    rng = np.random.default_rng(0)
    volume = ([-150.0, -100.0, 700.0], [150.0, 100.0, 900.0])
    world = rng.uniform(*volume, (60, 3))
    cam = rig.calibration.camera.project(world)
    proj = rig.calibration.projector.project(world)
    phases = np.c_[premat5.pixel_to_phase(proj[:, 0], PROJECTOR[0]), premat5.pixel_to_phase(proj[:, 1], PROJECTOR[1])]
    premat5.write_g(tmp_path / "G.byt", np.c_[world, cam, phases])
    result = ok("calibrate", "G.byt", "--camera-size", CAMERA_ARG, "--projector", PROJECTOR_ARG, "--method", method,
                "-o", "rig.json", "--cam-txt", "cam.txt", "--proj-txt", "proj.txt", cwd=tmp_path)
    assert "RMS" in result.stdout and len(result.stdout.splitlines()) == 1
    calibration = Calibration.load(tmp_path / "rig.json")
    # G.byt stores float32: about 1e-4 px of rounding in every coordinate, so residuals stay
    # far below a thousandth of a pixel and fresh points reproject within 1e-2 px.
    for name, truth in (("camera", rig.calibration.camera), ("projector", rig.calibration.projector)):
        assert calibration.extra["residuals"][name]["rms_px"] < 1e-3
        device = getattr(calibration, name)
        fresh = rng.uniform(*volume, (100, 3))
        np.testing.assert_allclose(device.project(fresh), truth.project(fresh), rtol=0, atol=1e-2)
    np.testing.assert_allclose(read_matrix_txt(tmp_path / "cam.txt"), calibration.camera.matrix, rtol=1e-9)
    np.testing.assert_allclose(read_matrix_txt(tmp_path / "proj.txt"), calibration.projector.matrix, rtol=1e-9)


def test_demo_runs_end_to_end(tmp_path: Path) -> None:
    result = ok("demo", "--camera", CAMERA_ARG, "--out", "demo", cwd=tmp_path)
    assert "stripe accuracy" in result.stdout and "thesis" in result.stdout and "best" in result.stdout
    out = tmp_path / "demo"
    assert (out / "rig.json").is_file()
    mat5_files = [p.name for p in mat5.mat5_paths("sphere")]
    for name in ("thesis", "best"):
        for file in ["pattern.png", "pattern.json", "capture.png", "sphere.ply", *mat5_files]:
            assert (out / name / file).is_file(), f"{name}/{file}"
    # the best pattern's capture through the real-time path too, its column last
    header = next(line for line in result.stdout.splitlines() if "thesis" in line)
    assert header.rstrip(" ┃│").endswith("best, baseband")
    for file in ["sphere.ply", *mat5_files]:
        assert (out / "baseband" / file).is_file(), f"baseband/{file}"
    ok("demo", "--camera", CAMERA_ARG, "--out", "demo", "--pattern", "best", cwd=tmp_path)  # again: replaces its files


def test_demo_scans_the_phase_pattern_where_the_camera_resolves_it(tmp_path: Path) -> None:
    coarse = ok("demo", "--camera", CAMERA_ARG, "--out", "demo", cwd=tmp_path)
    assert "phase: left out" in coarse.stderr and not (tmp_path / "demo" / "phase").exists()
    result = ok("demo", "--camera", CAMERA_ARG, "--projector", "512x384", "--out", "demo2", cwd=tmp_path)
    header = next(line for line in result.stdout.splitlines() if "thesis" in line)
    assert "phase" in header
    median = next(line for line in result.stdout.splitlines() if line.lstrip("│ ").startswith("median error"))
    thesis, best, phase = (float(v) for v in median.split("│")[2:5])
    assert phase < 0.3 * best  # sub-stripe depth: measured 4 mm against 34 (the staircase's 27)
    assert (tmp_path / "demo2" / "phase" / "pattern.json").is_file()


def test_pattern_with_a_phase_channel(tmp_path: Path) -> None:
    result = ok("pattern", "composite", "--projector", "1024x768", "--phase", "-o", "cp.png", cwd=tmp_path)
    assert "3-step phase channel" in result.stdout
    spec = PatternSpec.load(tmp_path / "cp.json")
    # an equal share of the drive per carrier, stretched over 0.2-1 (patterns.PHASE_DRIVE): as phase_spec
    assert spec.phase_carriers == (160.0, 192.0, 224.0) and spec.b_p == pytest.approx(0.5 / 7 * 1.244, rel=1e-3)
    assert patterns.pattern_range(spec) == pytest.approx(patterns.PHASE_DRIVE) and spec == patterns.phase_spec(
        (1024, 768), image="cp.png")
    ok("pattern", "composite", "--projector", "1024x768", "--phase", "--bp", "0.05", "-o", "low.png", cwd=tmp_path)
    assert PatternSpec.load(tmp_path / "low.json").b_p == 0.05 and PatternSpec.load(tmp_path / "low.json").a_p == 0.5
    bad = sliscan("pattern", "composite", "--projector", "1024x768", "--phase-carriers", "150,170", "-o", "x.png",
              cwd=tmp_path)
    assert bad.returncode == 2 and "at least 3 phase carriers" in bad.stderr and not (tmp_path / "x.png").exists()


def test_pattern_drive_range(tmp_path: Path) -> None:
    """--drive fits A_p and B_p to the pattern's own extremes (0.24-1 for sliscan's stripe
    pattern, which never projects the all-zero code): 0.2,1 gives 1.05 times its modulation; the
    image spans the range to a grey level."""
    ok("pattern", "composite", "--projector", "1024x768", "--drive", "0.2,1", "-o", "cp.png", cwd=tmp_path)
    spec = PatternSpec.load(tmp_path / "cp.json")
    assert patterns.pattern_range(spec) == pytest.approx((0.2, 1.0))
    stripes = patterns.default_spec((1024, 768))
    low, high = patterns.pattern_range(stripes)
    assert spec.b_p == pytest.approx(stripes.b_p * 0.8 / (high - low), rel=1e-9)
    image = read_image(tmp_path / "cp.png")
    assert abs(image.min() - 0.2) <= 0.5 / 255 and image.max() == 1.0
    for args, message in ((("--drive", "0.2,1", "--bp", "0.1"), "leave out --ap and --bp"),
                          (("--drive", "0.2,0.5,1"), "takes LOW,HIGH"),
                          (("--drive", "0.6,0.4"), "0 <= low < high <= 1")):
        bad = sliscan("pattern", "composite", "--projector", "1024x768", *args, "-o", "x.png", cwd=tmp_path)
        assert bad.returncode == 2 and message in bad.stderr and not (tmp_path / "x.png").exists(), bad.stderr


def test_a_precorrected_pattern_spans_the_whole_light_range(tmp_path: Path) -> None:
    """--gamma pre-corrects the composite pattern and stretches it over the light's 0-1
    (`patterns.PRECORRECTED_DRIVE`: B_p 0.165 against 0.125, A_p 0.34), unless --ap, --bp or
    --drive say otherwise; the image is the stretched pattern through 1 / gamma."""
    ok("pattern", "composite", "--projector", "1024x768", "--gamma", "2.2", "-o", "cp.png", cwd=tmp_path)
    spec = PatternSpec.load(tmp_path / "cp.json")
    assert spec.gamma == 2.2 and patterns.pattern_range(spec) == pytest.approx((0.0, 1.0), abs=1e-12)
    assert spec.b_p == pytest.approx(0.165, abs=5e-4) and spec.a_p == pytest.approx(0.341, abs=5e-4)
    image = read_image(tmp_path / "cp.png")
    assert image.min() <= 0.5 / 255 and image.max() == 1.0
    np.testing.assert_allclose(image, patterns.linear_pattern(spec) ** (1 / 2.2), atol=0.5 / 255 + 1e-6)
    ok("pattern", "composite", "--projector", "1024x768", "--gamma", "2.2", "--ap", "0.5", "-o", "kept.png",
       cwd=tmp_path)
    kept = PatternSpec.load(tmp_path / "kept.json")
    assert (kept.a_p, kept.b_p) == (0.5, 0.125)
    ok("pattern", "composite", "--projector", "1024x768", "-o", "plain.png", cwd=tmp_path)
    assert PatternSpec.load(tmp_path / "plain.json") == patterns.default_spec((1024, 768), image="plain.png")


def test_existing_outputs_are_replaced_only_with_overwrite(plane: tuple[Path, str], tmp_path: Path) -> None:
    source, _ = plane
    for name in ("cp.json", "rig.json", "capture.png"):
        shutil.copy(source / name, tmp_path / name)
    (tmp_path / "old.ply").write_text("not replaced")
    (tmp_path / "old.json").write_text("not replaced")
    for args, name in ((scan_args("capture.png", "cp.json", "rig.json", "--ply", "old.ply"), "old.ply"),
                       (("pattern", "composite", "--projector", PROJECTOR_ARG, "-o", "old.png"), "old.json")):
        before = listing(tmp_path)
        result = sliscan(*args, cwd=tmp_path)
        assert result.returncode == 2 and result.stderr == f"error: {name} exists (use --overwrite)\n"
        assert listing(tmp_path) == before
        ok(*args, "--overwrite", cwd=tmp_path)
    assert (tmp_path / "old.ply").read_bytes().startswith(b"ply")
    result = sliscan(*scan_args("capture.png", "cp.json", "rig.json", "--npz", "rig.json"), "--overwrite", cwd=tmp_path)
    assert result.returncode == 2 and "refusing to overwrite the input file" in result.stderr  # never an input


@pytest.mark.parametrize("command", [[], ["pattern", "composite"], ["pattern", "carrier-only"], ["pattern", "modified"],
                                     ["pattern", "pmp"], ["pattern", "graycode"], ["simulate"], ["scan"], ["calibrate"],
                                     ["demo"]])
def test_help_has_examples(tmp_path: Path, command: list[str]) -> None:
    result = sliscan(*command, "--help", cwd=tmp_path)
    assert result.returncode == 0 and "Examples:" in result.stdout


# --------------------------------------------------------------------------------------------
# Bad input: exit 2, one line on stderr naming the file, nothing written
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bad_inputs(plane: tuple[Path, str], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with the plane run's good inputs and one broken file per failure mode."""
    source, _ = plane
    folder = tmp_path_factory.mktemp("bad")
    for name in ("cp.json", "cp.png", "rig.json", "capture.png"):
        shutil.copy(source / name, folder / name)
    capture = read_png(folder / "capture.png")
    cv2.imwrite(str(folder / "small.png"), cv2.resize(capture, (CAMERA[0] // 2, CAMERA[1] // 2)))
    flat = np.random.default_rng(0).normal(128, 2, capture.shape).clip(0, 255).astype(np.uint8)
    cv2.imwrite(str(folder / "flat.png"), flat)  # a capture without any carrier
    rig = json.loads((folder / "rig.json").read_text())
    rig["camera"]["matrix"][1][2] = float("nan")
    (folder / "nan.json").write_text(json.dumps(rig))
    rig = json.loads((folder / "rig.json").read_text())
    rig["projector"]["matrix"] = [row[:3] for row in rig["projector"]["matrix"]]
    (folder / "shape.json").write_text(json.dumps(rig))
    PatternSpec.load(folder / "cp.json").with_(projector_size=(800, 600)).save(folder / "cp800.json")
    premat5.write_g(folder / "G.byt", np.ones((10, 7)))
    (folder / "short.byt").write_bytes((folder / "G.byt").read_bytes()[:-5])
    return folder


def scan_args(capture: str = "capture.png", pattern: str = "cp.json", calibration: str = "rig.json",
              *outputs: str) -> tuple[str, ...]:
    """Arguments of ``sliscan scan`` (writing a PLY unless `outputs` are given)."""
    return ("scan", capture, "--pattern", pattern, "--calibration", calibration, *(outputs or ("--ply", "o.ply")))


BAD_CASES: dict[str, tuple[tuple[str, ...], str]] = {
    "capture size differs from the camera": (scan_args("small.png"), "small.png"),
    "no carriers in the capture": (scan_args("flat.png"), "flat.png"),
    "pattern for another projector": (scan_args(pattern="cp800.json"), "cp800.json"),
    "calibration with NaN": (scan_args(calibration="nan.json"), "nan.json"),
    "calibration matrix of the wrong shape": (scan_args("capture.png", "cp.json", "shape.json", "--mat5", "o/scan"),
                                              "shape.json"),
    "missing capture": (scan_args("missing.png"), "missing.png"),
    "output onto the capture": (scan_args("capture.png", "cp.json", "rig.json", "--npz", "capture.png"), "capture.png"),
    "simulate onto its calibration": (("simulate", "--pattern", "cp.json", "--calibration", "rig.json",
                                       "--write-rig", "rig.json", "-o", "o.png"), "rig.json"),
    "simulate with a NaN calibration": (("simulate", "--pattern", "cp.json", "--calibration", "nan.json",
                                         "-o", "o.png"), "nan.json"),
    "truncated G file": (("calibrate", "short.byt", "--camera-size", CAMERA_ARG, "--projector", PROJECTOR_ARG,
                          "-o", "o.json"), "short.byt"),
    "bad WxH": (("pattern", "composite", "--projector", "1024by768", "-o", "o.png"), "--projector"),
    "unknown scene": (("simulate", "--pattern", "cp.json", "--scene", "sphre", "-o", "o.png"), "sphre"),
    "pattern for another projector than the calibration's": (("pattern", "composite", "--calibration", "rig.json",
                                                               "--projector", "800x600", "-o", "o.png"), "rig.json"),
    "pattern with a NaN calibration": (("pattern", "composite", "--calibration", "nan.json", "-o", "o.png"),
                                       "nan.json"),
}


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_input_is_one_line_and_writes_nothing(bad_inputs: Path, tmp_path: Path, case: str) -> None:
    folder = tmp_path / "run"
    shutil.copytree(bad_inputs, folder)
    fails_cleanly(*BAD_CASES[case], folder)


def fails_cleanly(args: tuple[str, ...], name: str, folder: Path) -> None:
    """Run a command on bad input in `folder`: it must exit with status 2 and one line ``error:
    ...`` naming `name` on stderr, print nothing on stdout, and leave `folder` as it was."""
    before = listing(folder)
    result = sliscan(*args, cwd=folder)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and name in lines[0], result.stderr
    assert result.stdout == ""
    assert listing(folder) == before  # nothing written, no input touched, no temporary left behind



# --------------------------------------------------------------------------------------------
# Multi-frame patterns: pattern -> simulate a sequence -> scan a folder, a glob or a list
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pmp_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-step dual-frequency PMP sequence of the plane, simulated into cap/pmp_00.png .. cap/pmp_05.png."""
    folder = tmp_path_factory.mktemp("pmp")
    ok("pattern", "pmp", "--projector", PROJECTOR_ARG, "--steps", "3", "--frequencies", "1,16", "--gamma", "2.2",
       "-o", "pat/pmp.json", cwd=folder)
    ok("simulate", "--pattern", "pat/pmp.json", "--scene", "plane", "--camera", CAMERA_ARG, "--supersample", "1",
       "--write-rig", "rig.json", "--truth", "truth.npz", "-o", "cap/pmp.png", cwd=folder)
    return folder


def test_pattern_pmp_writes_its_frames_and_lists_them(pmp_run: Path) -> None:
    spec = PatternSpec.load(pmp_run / "pat/pmp.json")
    assert spec.kind == "pmp" and spec.frames == tuple(f"pmp_{k:02d}.png" for k in range(6))
    frames = np.stack([read_png(pmp_run / "pat" / name) for name in spec.frames])
    np.testing.assert_array_equal(frames, np.round(sequences.render_frames(spec) * 255).astype(np.uint8))
    assert sorted(p.name for p in (pmp_run / "cap").iterdir()) == [f"pmp_{k:02d}.png" for k in range(6)]


def test_pattern_graycode_defaults_to_opencvs_sequence(tmp_path: Path) -> None:
    result = ok("pattern", "graycode", "--projector", PROJECTOR_ARG, "-o", "gc.json", cwd=tmp_path)
    assert "42 frames" in result.stdout
    spec = PatternSpec.load(tmp_path / "gc.json")
    assert spec == PatternSpec(kind="graycode", projector_size=PROJECTOR, orientation="both", b_p=0.5,
                               frames=tuple(f"gc_{k:02d}.png" for k in range(42)))
    assert np.array_equal(read_png(tmp_path / "gc_40.png"), np.full(PROJECTOR[::-1], 255, np.uint8))


def test_scan_refuses_decisions_for_a_sequence(pmp_run: Path) -> None:
    fails_cleanly(("scan", "cap", "--pattern", "pat/pmp.json", "--calibration", "rig.json", "--decisions", "pixel",
                   "--npz", "x.npz"), "pat/pmp.json", pmp_run)


@pytest.mark.parametrize("captures", [["cap"], ["cap/pmp_*.png"], [f"cap/pmp_{k:02d}.png" for k in range(6)]])
def test_scan_takes_a_folder_a_glob_or_a_list(pmp_run: Path, tmp_path: Path, captures: list[str]) -> None:
    out = tmp_path / "plane.npz"
    stdout = ok("scan", *captures, "--pattern", "pat/pmp.json", "--calibration", "rig.json", "--npz", out,
                cwd=pmp_run).stdout
    result = npz.read_scan_npz(out)
    assert f"{int(result.valid.sum())} points" in stdout
    assert result.valid.mean() > 0.9
    # sub-pixel rows: one projector row is ~2.7 mm of depth at 800 mm (a 4-bit stripe of 48 rows ~128 mm); 3 steps
    # of period 48 rows under noise: every point well within a row of the plane, RMS a fraction of a row
    dz = result.points[result.valid][:, 2] - 800
    assert np.abs(dz).max() < 2.5 and np.sqrt(np.mean(dz**2)) < 0.6


@pytest.fixture()
def pmp_bad(pmp_run: Path, tmp_path: Path) -> Path:
    folder = tmp_path / "run"
    shutil.copytree(pmp_run, folder)
    frame = read_png(folder / "cap/pmp_00.png")
    cv2.imwrite(str(folder / "pmp_small.png"), cv2.resize(frame, (CAMERA[0] // 2, CAMERA[1] // 2)))
    return folder


PMP_BAD: dict[str, tuple[tuple[str, ...], str]] = {
    "a frame missing": (("cap/pmp_0[0-4].png",), "needs 6 frames (1 direction x 2 frequencies x 3 steps), got 5"),
    "a frame of another size": (("cap/pmp_0[0-4].png", "pmp_small.png"), "pmp_small.png: the frame is 320x240"),
    "an empty glob": (("cap/none_*.png",), "matches no files"),
    "a composite pattern with many captures and --ply": (("cap",), "a batch writes into --out DIR"),
}


@pytest.mark.parametrize("case", PMP_BAD)
def test_bad_sequences_are_one_line_and_write_nothing(pmp_bad: Path, case: str) -> None:
    captures, message = PMP_BAD[case]
    pattern = "pat/pmp.json"
    if case.startswith("a composite"):
        ok("pattern", "composite", "--projector", PROJECTOR_ARG, "-o", "cp.png", cwd=pmp_bad)
        pattern = "cp.json"
    before = listing(pmp_bad)
    result = sliscan("scan", *captures, "--pattern", pattern, "--calibration", "rig.json", "--ply", "o/out.ply",
                     cwd=pmp_bad)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], result.stderr
    assert listing(pmp_bad) == before


def test_bad_sequence_pattern_writes_nothing(tmp_path: Path) -> None:
    result = sliscan("pattern", "graycode", "--projector", PROJECTOR_ARG, "--phase-steps", "2", "-o", "gc.json",
                     cwd=tmp_path)
    assert result.returncode == 2 and "steps >= 3" in result.stderr and len(result.stderr.splitlines()) == 1
    assert listing(tmp_path) == {}


# --------------------------------------------------------------------------------------------
# sliscan characterize: gamma -> pre-corrected carrier-only -> roll-off -> compensated pattern
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def characterized(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The characterisation workflow of the README, on the virtual rig's plane (gamma 2.2)."""
    folder = tmp_path_factory.mktemp("characterize")
    capture = ("--scene", "plane", "--camera", CAMERA_ARG, "--supersample", "1")
    ok("pattern", "sine", "--projector", PROJECTOR_ARG, "-o", "sine.png", cwd=folder)
    ok("simulate", "--pattern", "sine.json", *capture, "-o", "sine-capture.png", cwd=folder)
    ok("characterize", "gamma", "sine-capture.png", "--pattern", "sine.json", "-o", "gamma.json", cwd=folder)
    ok("pattern", "carrier-only", "--projector", PROJECTOR_ARG, "--thesis", "--from-characterization", "gamma.json",
       "-o", "carriers.png", cwd=folder)
    ok("simulate", "--pattern", "carriers.json", *capture, "-o", "carriers-capture.png", cwd=folder)
    ok("characterize", "rolloff", "carriers-capture.png", "--pattern", "carriers.json", "--characterization",
       "gamma.json", "-o", "rig-char.json", cwd=folder)
    ok("pattern", "composite", "--projector", PROJECTOR_ARG, "--from-characterization", "rig-char.json",
       "-o", "cp.png", cwd=folder)
    return folder


def test_characterize_gamma_prints_the_table_and_writes_the_response(characterized: Path) -> None:
    char = json.loads((characterized / "gamma.json").read_text())
    assert abs(char["gamma"]["gamma"] - 2.2) < 0.05 and char["rolloff"] is None
    assert [row[0] for row in char["gamma"]["table"]] == [2.0, 2.4, 2.5, 3.0, 3.5]
    assert PatternSpec.load(characterized / "carriers.json").response == tuple(char["gamma"]["response"])


def test_pattern_from_characterization_is_compensated_and_decodes(characterized: Path) -> None:
    char = json.loads((characterized / "rig-char.json").read_text())
    assert char["gamma"] == json.loads((characterized / "gamma.json").read_text())["gamma"]
    spec = PatternSpec.load(characterized / "cp.json")
    default = patterns.default_spec(PROJECTOR)
    assert spec.carriers == default.carriers and spec.response is not None
    assert spec.weights[0] > 1.4 * spec.weights[-1]  # the highest carrier (bit 0) boosted against roll-off
    assert sum(spec.weights) == pytest.approx(sum(default.weights))
    assert patterns.pattern_range(spec) == pytest.approx((0.0, 1.0), abs=1e-12)  # pre-corrected: the whole range


def test_characterize_bad_input_is_one_line(characterized: Path, tmp_path: Path) -> None:
    folder = tmp_path / "run"
    shutil.copytree(characterized, folder)
    flat = np.full((CAMERA[1], CAMERA[0]), 128, np.uint8)
    cv2.imwrite(str(folder / "flat.png"), flat)
    before = listing(folder)
    cases = {("characterize", "gamma", "flat.png", "--pattern", "sine.json", "-o", "o.json"): "flat.png",
             ("characterize", "gamma", "carriers-capture.png", "--pattern", "sine.json"): "carriers-capture.png",
             ("characterize", "rolloff", "flat.png", "--pattern", "carriers.json", "-o", "o.json"): "flat.png",
             ("characterize", "rolloff", "carriers-capture.png", "--pattern", "carriers.json", "--characterization",
              "gamma.json", "-o", "gamma.json"): "gamma.json",
             ("pattern", "composite", "--projector", PROJECTOR_ARG, "--thesis", "--gamma", "2.2",
              "--from-characterization", "gamma.json", "-o", "o.png"): "--gamma"}
    for args, name in cases.items():
        result = sliscan(*args, cwd=folder)
        lines = result.stderr.splitlines()
        assert result.returncode == 2 and len(lines) == 1 and name in lines[0], (args, result.stderr)
    assert listing(folder) == before


@pytest.mark.parametrize("command", [["pattern", "sine"], ["characterize", "gamma"], ["characterize", "rolloff"]])
def test_characterize_help_has_examples(tmp_path: Path, command: list[str]) -> None:
    result = sliscan(*command, "--help", cwd=tmp_path)
    assert result.returncode == 0 and "Examples:" in result.stdout
