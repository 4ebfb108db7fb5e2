"""Devices (issue 11): the virtual display and camera against the simulator, their faults, the
OpenCV camera on a video file (no camera here), and the SDL2 windows on SDL's dummy driver."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from sliscan import InputError, devices, simulate
from sliscan._validate import to_uint8

CAMERA, PROJECTOR = (160, 120), (128, 96)
NOISE_FREE = simulate.Conditions(albedo=simulate.SmoothAlbedo(seed=1), supersample=1, full_well_e=None)


@pytest.fixture(scope="module")
def rig() -> simulate.Rig:
    return simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR)


def stripes(value: int) -> np.ndarray:
    """A (96, 128) uint8 test image: horizontal bands of `value` and 255 - `value`."""
    image = np.full(PROJECTOR[::-1], value, np.uint8)
    image[::16] = 255 - value
    return image


def test_a_grab_is_what_render_renders(rig):
    """Noise-free, the camera's frame is `render`'s image of what the display shows, quantised to
    8 bits (bit for bit); with noise, its first grab draws the same noise as render with its seed."""
    scene = simulate.sphere_scene()
    display, camera, clock = devices.virtual_devices(rig, scene, NOISE_FREE)
    display.show(stripes(40))
    expected = simulate.render(rig, scene, stripes(40), NOISE_FREE).image
    assert np.array_equal(camera.grab(), to_uint8(expected))
    assert clock.now() == pytest.approx(1 / 30)  # a grab takes one frame period
    noisy = NOISE_FREE.with_(full_well_e=10000.0)
    display, camera, _ = devices.virtual_devices(rig, scene, noisy, seed=7)
    display.show(stripes(40))
    assert np.array_equal(camera.grab(), to_uint8(simulate.render(rig, scene, stripes(40), noisy, rng=7).image))


def test_the_display_shows_after_its_latency(rig):
    display, camera, clock = devices.virtual_devices(rig, simulate.plane_scene(), NOISE_FREE, latency_s=0.09)
    black = camera.grab()
    display.show(np.full(PROJECTOR[::-1], 255, np.uint8))  # at 1/30 s: visible from 0.123 s
    seen = [camera.grab().mean() > black.mean() + 20 for _ in range(5)]  # grabs start at 1/30, 2/30, 3/30, ...
    assert seen == [False, False, False, True, True]


def test_dropped_shows_and_repeated_grabs(rig):
    """A dropped show leaves the previous image; a repeated grab returns the previous frame again."""
    white, grey = np.full(PROJECTOR[::-1], 255, np.uint8), np.full(PROJECTOR[::-1], 128, np.uint8)
    display, camera, _ = devices.virtual_devices(rig, simulate.plane_scene(), NOISE_FREE, drop_shows=[1],
                                                 repeat_grabs=[1])
    display.show(white)
    first = camera.grab()
    display.show(grey)  # show 1: dropped
    repeated = camera.grab()  # grab 1: repeated
    assert np.array_equal(repeated, first) and repeated is not first
    assert np.array_equal(camera.grab(), first)  # still white: the grey was dropped
    display.show(grey)
    assert camera.grab().mean() < first.mean() * 0.7


def test_exposure_and_gain_scale_the_signal(rig):
    """Exposure and gain multiply the signal (noise-free: within a grey level of quantisation)."""
    grey = np.full(PROJECTOR[::-1], 128, np.uint8)
    frames = {}
    for exposure, gain in ((1.0, 1.0), (0.5, 1.0), (0.5, 2.0)):
        display, camera, _ = devices.virtual_devices(rig, simulate.plane_scene(), NOISE_FREE, exposure=exposure,
                                                     gain=gain)
        display.show(grey)
        frames[exposure, gain] = camera.grab().astype(float)
    assert np.abs(frames[0.5, 1.0] - frames[1.0, 1.0] / 2).max() <= 1.0
    assert np.abs(frames[0.5, 2.0] - frames[1.0, 1.0]).max() <= 1.0
    assert camera.settings()["actual"]["gain"] == 2.0


def test_sixteen_bit_virtual_camera(rig):
    display, camera, _ = devices.virtual_devices(rig, simulate.plane_scene(), NOISE_FREE.with_(bit_depth=16))
    display.show(np.full(PROJECTOR[::-1], 200, np.uint8))
    frame = camera.grab()
    assert frame.dtype == np.uint16 and frame.max() > 255


def test_moving_scene_changes_pose_per_grab(rig):
    from sliscan import motion

    stage = devices.VirtualStage(rig, simulate.sphere_scene(), NOISE_FREE, motion=motion.Motion(3, (20.0, 0.0, 0.0)))
    display, camera = devices.VirtualDisplay(stage), devices.VirtualCamera(stage)
    display.show(np.full(PROJECTOR[::-1], 255, np.uint8))
    frames = [camera.grab() for _ in range(4)]
    assert not np.array_equal(frames[0], frames[1])
    assert np.array_equal(frames[0], frames[3])  # pose 3 mod 3 = pose 0


@pytest.mark.parametrize("make, match", [
    (lambda rig: devices.virtual_devices(rig, simulate.plane_scene(), NOISE_FREE, exposure=0.0),
     "exposure must be a positive number"),
    (lambda rig: devices.virtual_devices(rig, simulate.plane_scene(), NOISE_FREE, gain=float("nan")),
     "gain must be a positive number"),
    (lambda rig: devices.virtual_devices(rig, simulate.plane_scene(), NOISE_FREE.with_(bit_depth=None)),
     "8- or 16-bit frames"),
    (lambda rig: devices.virtual_devices(rig, simulate.plane_scene(), NOISE_FREE, latency_s=-1.0),
     "latency_s must be a non-negative"),
])
def test_virtual_devices_refuse_bad_settings(rig, make, match):
    with pytest.raises(InputError, match=match):
        make(rig)


def test_an_image_of_another_size_is_refused(rig):
    display, _, _ = devices.virtual_devices(rig, simulate.plane_scene(), NOISE_FREE)
    with pytest.raises(InputError, match=r"image is 64x48 but the display is 128x96 \(make the pattern"):
        display.show(np.zeros((48, 64), np.uint8))
    with pytest.raises(InputError, match="image must be a grey"):
        display.show(np.zeros((96, 128, 3), np.uint8))


# --- OpenCV camera ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    """A 64x48 MJPG video of 30 grey frames, levels 0, 8, 16, ...: a 'camera' without a camera."""
    path = tmp_path_factory.mktemp("video") / "camera.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (64, 48))
    for k in range(30):
        writer.write(np.full((48, 64, 3), 8 * k, np.uint8))
    writer.release()
    return path


def test_opencv_camera_grabs_grey_frames_and_reports_settings(video):
    camera = devices.OpenCVCamera(str(video))
    try:
        assert camera.size == (64, 48)
        frame = camera.grab()  # the first frame went to learning the size
        assert frame.shape == (48, 64) and frame.dtype == np.uint8 and abs(float(frame.mean()) - 8) < 2
        settings = camera.settings()
        assert settings["backend"] == "opencv" and settings["actual"]["resolution"] == [64, 48]
        assert settings["requested"] == {"resolution": None, "exposure": None, "gain": None}
    finally:
        camera.close()


def test_opencv_camera_errors(video, capfd):
    with pytest.raises(devices.DeviceError, match=r"^camera 97: cannot open it .* list the cameras with "
                                                  r"'sliscan acquire --list'$"):
        devices.OpenCVCamera(97)
    with pytest.raises(devices.DeviceError, match="asked for 640x480, the driver gives 64x48"):
        devices.OpenCVCamera(str(video), resolution=(640, 480))
    with pytest.raises(InputError, match="exposure must be a finite number"):
        devices.OpenCVCamera(str(video), exposure=float("nan"))
    camera = devices.OpenCVCamera(str(video))
    for _ in range(29):
        camera.grab()
    with pytest.raises(devices.DeviceError, match="gave no frame"):
        camera.grab()
    assert devices.camera_source("2") == 2 and devices.camera_source("/dev/video2") == "/dev/video2"
    assert isinstance(devices.list_cameras(3), list)
    out, err = capfd.readouterr()
    assert out == "" and err == ""  # OpenCV's complaints about missing cameras are silenced


# --- SDL2 windows (dummy driver) -------------------------------------------------------------


@pytest.fixture
def sdl(monkeypatch):
    """pygame on SDL's dummy video driver (one 1024x768 display, nothing shown)."""
    pygame = pytest.importorskip("pygame")
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    pygame.display.quit()
    yield pygame
    pygame.display.quit()


def test_pygame_display_shows_full_screen_images(sdl):
    sizes = devices.list_displays()
    assert len(sizes) >= 1
    display = devices.PygameDisplay(0)
    try:
        assert display.size == sizes[0]
        w, h = display.size
        display.show(np.zeros((h, w), np.uint8))
        display.show(np.full((h, w), 0.5, np.float32))
        with pytest.raises(InputError, match=f"image is 10x10 but the display is {w}x{h}"):
            display.show(np.zeros((10, 10), np.uint8))
    finally:
        display.close()
    preview = devices.PreviewWindow((64, 48))
    assert preview(np.zeros((48, 64, 3), np.uint8)) is True
    preview.close()


def test_pygame_display_errors(sdl, monkeypatch):
    with pytest.raises(devices.DeviceError, match=r"^screen 5: no such display \(1 display: 0: \d+x\d+\); list the "
                                                  r"displays with 'sliscan acquire --list'$"):
        devices.PygameDisplay(5)
    monkeypatch.setattr(sdl.display, "get_driver", lambda: "offscreen")  # what SDL falls back to without a screen
    with pytest.raises(devices.DeviceError, match="no display found .* use --screen virtual"):
        devices.list_displays()
    monkeypatch.setitem(sys.modules, "pygame", None)
    with pytest.raises(devices.DeviceError, match=r"needs pygame \(SDL2\): pip install 'sliscan\[hardware\]'"):
        devices.PygameDisplay(0)
