"""Hard captures give a specific one-line error, not garbage (issue 7, item 4).

Each case is a capture of the virtual sphere gone wrong: all dark, saturated, defocused, of
another pattern, rotated by 90 degrees, tiny.  `Scanner.scan` raises `InputError` with a message
that says what is wrong; `sliscan scan` prints it as its one ``error:`` line.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sliscan import patterns, sequences, simulate
from sliscan._validate import InputError, to_uint8
from sliscan.cli import main
from sliscan.demodulate import DARK_LEVEL, check_exposure
from sliscan.pipeline import Scanner
from sliscan.types import PatternSpec

PROJECTOR = (1024, 768)
SPEC = patterns.thesis_spec(PROJECTOR)


def capture(rig: simulate.Rig, projected: np.ndarray, **conditions: float) -> np.ndarray:
    """The sphere under `projected`, rendered quickly (no supersampling)."""
    return simulate.render(rig, simulate.sphere_scene(), projected,
                           simulate.Conditions(seed=0, supersample=1, **conditions)).image


@pytest.fixture(scope="module")
def good(small_rig: simulate.Rig) -> np.ndarray:
    return capture(small_rig, patterns.render_pattern(SPEC))


def test_the_good_capture_scans(small_rig: simulate.Rig, good: np.ndarray) -> None:
    assert Scanner(SPEC, small_rig.calibration).scan(good).valid.mean() > 0.5


@pytest.mark.parametrize("case, message", [
    ("dark", "the capture is dark"),
    ("saturated", "the capture is saturated"),
    ("defocused", "carriers near 96, 128 cycles/width not found (only 32, 64): is the capture out of focus"),
    ("pmp frame", "no carriers found near 32, 64, 96, 128 cycles/width: is this a composite-pattern capture?"),
])
def test_hard_capture_has_a_specific_message(small_rig: simulate.Rig, good: np.ndarray, case: str,
                                             message: str) -> None:
    pmp = PatternSpec(kind="pmp", projector_size=PROJECTOR, steps=3, frequencies=(1.0, 16.0))
    images = {
        "dark": lambda: good * 0.02,
        "saturated": lambda: np.clip(good * 20, 0, 1),
        "defocused": lambda: capture(small_rig, patterns.render_pattern(SPEC), projector_blur_px=3, camera_blur_px=3),
        "pmp frame": lambda: capture(small_rig, sequences.render_frames(pmp)[4]),
    }
    with pytest.raises(InputError, match="^" + message.replace("(", r"\(").replace(")", r"\)").replace("?", r"\?")):
        Scanner(SPEC, small_rig.calibration).scan(images[case]())


def test_rotated_capture_is_named() -> None:
    rig = simulate.virtual_rig(camera_size=(640, 640), projector_size=PROJECTOR)
    rotated = np.rot90(capture(rig, patterns.render_pattern(SPEC)))
    with pytest.raises(InputError, match="rotated by 90 degrees"):
        Scanner(SPEC, rig.calibration).scan(rotated)


def test_tiny_capture() -> None:
    rig = simulate.virtual_rig(camera_size=(8, 8), projector_size=PROJECTOR)
    with pytest.raises(InputError, match="capture is 8 px along the carriers: too short to resolve them"):
        Scanner(SPEC, rig.calibration).scan(np.full((8, 8), 0.5, np.float32))


def run_scan(folder: Path, image: np.ndarray, monkeypatch: pytest.MonkeyPatch) -> tuple[int, str, str]:
    """`sliscan scan` of `image` (written as capture.png) in `folder`: status, stdout, stderr."""
    cv2.imwrite(str(folder / "capture.png"), to_uint8(image))
    monkeypatch.chdir(folder)
    with CliRunner().isolation() as (out, err, _):
        try:
            main(["scan", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json", "--ply", "s.ply"])
            code = 0
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue().decode(), err.getvalue().decode()


@pytest.fixture
def scan_folder(tmp_path: Path, small_rig: simulate.Rig) -> Path:
    SPEC.save(tmp_path / "cp.json")
    small_rig.calibration.save(tmp_path / "rig.json")
    return tmp_path


def test_cli_names_a_dark_capture(scan_folder: Path, good: np.ndarray, monkeypatch: pytest.MonkeyPatch) -> None:
    code, out, err = run_scan(scan_folder, good * 0.02, monkeypatch)
    assert code == 2 and out == "" and not (scan_folder / "s.ply").exists()
    assert err.startswith("error: capture.png, pattern cp.json: the capture is dark") and err.count("\n") == 1


def test_cli_names_a_tiny_capture(scan_folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    code, _, err = run_scan(scan_folder, np.full((8, 8), 0.5), monkeypatch)
    assert code == 2 and err == "error: capture.png: the capture is 8x8 but the camera of rig.json is 640x480\n"


def test_cli_warns_when_almost_nothing_decodes(scan_folder: Path, small_rig: simulate.Rig,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    best = patterns.default_spec(PROJECTOR)
    best.save(scan_folder / "cp.json")
    # 0.10 % of the frame decodes (blur 2 px: 1.7 % since the window fit is solved exactly,
    # fortieth session, 0.75 % before; 2.15 px: the finest carrier is no longer found)
    blurred = capture(small_rig, patterns.render_pattern(best), projector_blur_px=2.05, camera_blur_px=2.05)
    code, out, err = run_scan(scan_folder, blurred, monkeypatch)
    assert code == 0 and "points" in out and (scan_folder / "s.ply").exists()
    assert err.startswith("warning: capture.png: only ") and err.count("\n") == 1


def test_exposure_thresholds() -> None:
    """Dark: fewer than 1 % of the pixels reach `DARK_LEVEL`; saturated: more than half at 254."""
    image = np.zeros((100, 100), np.float32)
    image.flat[:99] = DARK_LEVEL  # 0.99 % bright: dark
    with pytest.raises(InputError, match="the capture is dark"):
        check_exposure(image)
    image.flat[:100] = DARK_LEVEL  # 1 %: enough light
    check_exposure(image)
    image.flat[:5001] = 1.0
    with pytest.raises(InputError, match=r"the capture is saturated \(50% of pixels"):
        check_exposure(image)
    image.flat[5000] = 0.5
    check_exposure(image)
