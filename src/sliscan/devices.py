"""Projectors and cameras behind one small interface: real devices and a virtual pair.

A `Display` shows a grey image full-screen (the projector); a `Camera` grabs a grey frame; a
`Clock` tells the time and waits.  `sliscan.acquire` drives any of them:

* `OpenCVCamera`: a camera (or a video file or stream) through OpenCV's ``VideoCapture``, with
  resolution, exposure and gain set and read back (what the driver actually accepted);
* `PygameDisplay`: a borderless full-screen window on display N through SDL2 (pygame, the
  ``sliscan[hardware]`` extra).  OpenCV's own windows (highgui) are not used: the
  ``opencv-python-headless`` wheel sliscan depends on is built without them (its build
  information says ``GUI: NONE``);
* `VirtualDisplay` and `VirtualCamera`: the virtual rig of `sliscan.simulate`.  They share a
  `VirtualStage`: what the display shows becomes visible after a latency, and the camera
  photographs whatever is visible when it grabs, rendered by `simulate.TracedScene`.  A
  `VirtualClock` makes waiting free, so acquisition, synchronisation, stale-frame detection and
  the live loop run end to end in tests.  Faults on demand: the display drops given `show`
  calls (the previous image stays), the camera repeats given grabs (returns its previous frame
  again), as real drivers do.

Frames are ``(H, W)`` grey arrays as the camera delivers them (uint8, or uint16 for deeper
sensors); images to show are ``(H, W)`` (the display's size) uint8, or floats in [0, 1].
Sizes are ``(W, H)``.  Device problems raise `DeviceError` (an `InputError`: one line).
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Iterable, Iterator
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, check_image, to_uint8
from sliscan.motion import Motion, posed_scene
from sliscan.simulate import Conditions, Rig, Surface, TracedScene

#: The command that lists the devices, named in every device error.
LIST_COMMAND = "sliscan acquire --list"

#: Camera indices `list_cameras` probes by default.
PROBED_CAMERAS = 10

#: SDL's ``SDL_WINDOWPOS_CENTERED_DISPLAY(n)``: a window position centred on display n.
_SDL_CENTERED_DISPLAY = 0x2FFF0000


class DeviceError(InputError):
    """A camera or display that cannot be opened, or that fails (one-line message)."""


# --------------------------------------------------------------------------------------------
# The interface
# --------------------------------------------------------------------------------------------


class Clock(Protocol):
    """Time in seconds (any origin) and waiting."""

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


class Display(Protocol):
    """A projector: shows one image at a time, full-screen."""

    @property
    def size(self) -> tuple[int, int]:
        """``(W, H)`` in pixels."""
        ...

    def show(self, image: ArrayLike) -> None:
        """Show an ``(H, W)`` image (uint8, or float in [0, 1]) until the next `show`."""
        ...

    def close(self) -> None: ...


class Camera(Protocol):
    """A camera: grabs grey frames."""

    @property
    def size(self) -> tuple[int, int]:
        """``(W, H)`` of its frames."""
        ...

    def grab(self) -> NDArray[Any]:
        """The next frame, ``(H, W)`` uint8 or uint16."""
        ...

    def settings(self) -> dict[str, Any]:
        """What was asked for and what the device reports (for the acquisition record)."""
        ...

    def close(self) -> None: ...


class RealClock:
    """The machine's monotonic clock."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(max(seconds, 0.0))


class VirtualClock:
    """A clock that only moves when told: `sleep` returns at once, having advanced it.

    >>> clock = VirtualClock()
    >>> clock.sleep(0.25); clock.now()
    0.25
    """

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)

    def now(self) -> float:
        return self._t

    def sleep(self, seconds: float) -> None:
        self._t += max(float(seconds), 0.0)


def display_image(image: ArrayLike, size: tuple[int, int], name: str = "image") -> NDArray[np.uint8]:
    """An image to show, as ``(H, W)`` uint8 of exactly the display's `size` ``(W, H)``.

    Nothing is scaled: a projector shows the pattern pixel for pixel (the pattern must be
    made for its resolution).

    Raises
    ------
    InputError
        Naming both sizes when they differ.
    """
    arr = np.asarray(image)
    w, h = size
    if arr.ndim == 2 and arr.shape != (h, w):
        raise InputError(f"{name} is {arr.shape[1]}x{arr.shape[0]} but the display is {w}x{h} "
                         f"(make the pattern for the projector's native resolution)")
    return arr if arr.dtype == np.uint8 and arr.ndim == 2 else to_uint8(check_image(name, arr, shape=(h, w)))


# --------------------------------------------------------------------------------------------
# OpenCV camera
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def quiet_opencv() -> Iterator[Any]:
    """OpenCV (and its FFmpeg) silenced while devices are opened or probed; yields ``cv2``."""
    import cv2

    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    os.environ.setdefault("OPENCV_VIDEOIO_DEBUG", "0")
    logging = cv2.utils.logging
    level = logging.getLogLevel()
    logging.setLogLevel(logging.LOG_LEVEL_SILENT)
    try:
        yield cv2
    finally:
        logging.setLogLevel(level)


def camera_source(camera: str) -> int | str:
    """A ``--camera`` argument as `VideoCapture` takes it: an index (``"0"`` -> 0) or a path/URL."""
    text = str(camera).strip()
    return int(text) if text.isdigit() else text


def _finite(name: str, value: float | None, *, positive: bool = False) -> float | None:
    """`value` checked to be finite (and > 0 with `positive`); None stays None."""
    if value is None:
        return None
    if not math.isfinite(value) or (positive and value <= 0):
        raise InputError(f"{name} must be a {'positive' if positive else 'finite'} number, got {value!r}")
    return float(value)


class OpenCVCamera:
    """A camera through OpenCV's ``VideoCapture``: an index (USB, ``/dev/videoN``), a device
    path, a stream URL, or a video file (handy to test without a camera).

    Parameters
    ----------
    source : int or str
        What `VideoCapture` opens (`camera_source` of the ``--camera`` argument).
    resolution : (W, H), optional
        Asked of the driver; an error if it delivers another size.
    exposure : float, optional
        Manual exposure in the driver's unit (``CAP_PROP_EXPOSURE``: V4L2 takes 100 us steps,
        DirectShow log2 seconds); auto-exposure is switched off first.
    gain : float, optional
        ``CAP_PROP_GAIN`` in the driver's unit.

    Raises
    ------
    DeviceError
        If it cannot be opened (naming the camera and `LIST_COMMAND`), gives no frame, or gives
        another resolution than asked for.
    """

    def __init__(self, source: int | str, *, resolution: tuple[int, int] | None = None,
                 exposure: float | None = None, gain: float | None = None) -> None:
        self.source = source
        self._requested = {"resolution": None if resolution is None else list(resolution),
                           "exposure": _finite("exposure", exposure), "gain": _finite("gain", gain)}
        with quiet_opencv() as cv2:
            self._capture = cv2.VideoCapture(source)
            if not self._capture.isOpened():
                raise DeviceError(f"camera {source}: cannot open it (no such camera, or it is in use); "
                                  f"list the cameras with '{LIST_COMMAND}'")
            self._apply(cv2, resolution, exposure, gain)
        frame = self.grab()
        self._size = (frame.shape[1], frame.shape[0])
        if resolution is not None and self._size != tuple(resolution):
            self.close()
            raise DeviceError(f"camera {source}: asked for {resolution[0]}x{resolution[1]}, the driver gives "
                              f"{self._size[0]}x{self._size[1]}")

    def _apply(self, cv2: Any, resolution: tuple[int, int] | None, exposure: float | None,
               gain: float | None) -> None:
        """Ask the driver for the settings (what it accepts is read back by `settings`)."""
        cap = self._capture
        if resolution is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, resolution[0])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, resolution[1])
        if exposure is not None:  # manual exposure: V4L2 wants 1, DirectShow and others 0.25
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1 if cap.getBackendName() == "V4L2" else 0.25)
            cap.set(cv2.CAP_PROP_EXPOSURE, exposure)
        if gain is not None:
            cap.set(cv2.CAP_PROP_GAIN, gain)
        cap.set(cv2.CAP_PROP_AUTO_WB, 0)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # where the back end allows it: fewer stale frames queued

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    def grab(self) -> NDArray[Any]:
        import cv2

        ok, frame = self._capture.read()
        if not ok or frame is None:
            raise DeviceError(f"camera {self.source}: gave no frame (disconnected, or the end of a video)")
        if frame.ndim == 3:
            frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2GRAY if frame.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        return frame

    def settings(self) -> dict[str, Any]:
        import cv2

        cap = self._capture
        actual = {"resolution": list(self._size), "exposure": cap.get(cv2.CAP_PROP_EXPOSURE),
                  "gain": cap.get(cv2.CAP_PROP_GAIN), "auto_exposure": cap.get(cv2.CAP_PROP_AUTO_EXPOSURE),
                  "fps": cap.get(cv2.CAP_PROP_FPS)}
        return {"backend": "opencv", "source": str(self.source), "api": cap.getBackendName(),
                "requested": self._requested, "actual": {k: _number(v) for k, v in actual.items()}}

    def close(self) -> None:
        self._capture.release()


def _number(value: Any) -> Any:
    """A JSON-safe number (NaN/inf -> None); lists pass through."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def list_cameras(count: int = PROBED_CAMERAS) -> list[tuple[int, tuple[int, int]]]:
    """The camera indices ``0 .. count-1`` that open, each with its default ``(W, H)``; quietly."""
    found = []
    with quiet_opencv() as cv2:
        for index in range(count):
            capture = cv2.VideoCapture(index)
            try:
                if capture.isOpened():
                    found.append((index, (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)),
                                          int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))))
            finally:
                capture.release()
    return found


# --------------------------------------------------------------------------------------------
# SDL2 (pygame) windows
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Send the process's standard error (file descriptor 2: C libraries' messages) to the null
    device for a while; SDL complains there while it probes for a display."""
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


#: SDL video drivers that show nothing; used only when asked for in ``SDL_VIDEODRIVER`` (tests).
_HEADLESS_DRIVERS = ("offscreen", "dummy")


def require_pygame() -> Any:
    """pygame with its display initialised, or a one-line `DeviceError` naming the extra.

    SDL falls back to an off-screen driver when it finds no display; that is an error unless
    ``SDL_VIDEODRIVER`` asks for it (``dummy`` in tests: nothing is shown).
    """
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    try:
        import pygame
    except ImportError:
        raise DeviceError("showing patterns on a display needs pygame (SDL2): pip install 'sliscan[hardware]'") from None
    try:
        with _quiet_stderr():
            pygame.display.init()
    except pygame.error as exc:
        raise DeviceError(f"no display available ({exc}); without one use --screen virtual") from None
    driver = pygame.display.get_driver()
    if driver in _HEADLESS_DRIVERS and os.environ.get("SDL_VIDEODRIVER") != driver:
        pygame.display.quit()
        raise DeviceError(f"no display found (SDL fell back to its {driver} driver): run on a desktop session with the "
                          f"projector attached, or use --screen virtual")
    return pygame


def list_displays() -> list[tuple[int, int]]:
    """``(W, H)`` of each display SDL2 knows, in its order (0 is the primary)."""
    return [tuple(s) for s in require_pygame().display.get_desktop_sizes()]  # type: ignore[misc]


def _describe_displays(sizes: list[tuple[int, int]]) -> str:
    shown = ", ".join(f"{k}: {w}x{h}" for k, (w, h) in enumerate(sizes))
    return f"{len(sizes)} display{'s' if len(sizes) != 1 else ''}: {shown}" if sizes else "no displays"


class _SDLWindow:
    """A pygame SDL2 window that draws grey or colour images (the common part of the windows)."""

    def __init__(self, title: str, size: tuple[int, int], *, screen: int | None, fullscreen: bool) -> None:
        self._pygame = require_pygame()
        from pygame._sdl2 import video

        self._video = video
        position: Any = (video.WINDOWPOS_CENTERED, video.WINDOWPOS_CENTERED) if screen is None else (
            _SDL_CENTERED_DISPLAY | screen, _SDL_CENTERED_DISPLAY | screen)
        self._window = video.Window(title, size=size, position=position, borderless=fullscreen)
        if fullscreen:
            self._window.set_fullscreen(desktop=True)
        self._renderer = video.Renderer(self._window)

    def draw(self, image: NDArray[np.uint8]) -> None:
        """Draw ``(H, W)`` grey or ``(H, W, 3)`` RGB uint8, stretched to the window."""
        rgb = np.ascontiguousarray(np.repeat(image[..., None], 3, axis=2) if image.ndim == 2 else image)
        surface = self._pygame.image.frombuffer(rgb.tobytes(), (rgb.shape[1], rgb.shape[0]), "RGB")
        texture = self._video.Texture.from_surface(self._renderer, surface)
        self._renderer.clear()
        texture.draw()
        self._renderer.present()

    def closed(self) -> bool:
        """Whether the user closed the window or pressed Esc or q (events are consumed)."""
        pg = self._pygame
        stop = False
        for event in pg.event.get():
            stop |= event.type in (pg.QUIT, pg.WINDOWCLOSE) or (
                event.type == pg.KEYDOWN and event.key in (pg.K_ESCAPE, pg.K_q))
        return stop

    def close(self) -> None:
        self._window.destroy()


class PygameDisplay:
    """A borderless full-screen window on display `screen` (SDL2 through pygame).

    The window is centred on that display at its desktop size and made full-screen there, so
    it covers exactly that display (the projector: extend the desktop to it, at its native
    resolution, with no scaling).  Esc (or closing it) interrupts: `show` raises
    KeyboardInterrupt.

    Raises
    ------
    DeviceError
        If pygame is missing, or there is no display `screen` (naming those there are).
    """

    def __init__(self, screen: int) -> None:
        sizes = list_displays()
        if not 0 <= screen < len(sizes):
            raise DeviceError(f"screen {screen}: no such display ({_describe_displays(sizes)}); "
                              f"list the displays with '{LIST_COMMAND}'")
        self.screen = screen
        self._size = sizes[screen]
        self._window = _SDLWindow(f"sliscan projector (screen {screen})", self._size, screen=screen, fullscreen=True)
        self._window._pygame.mouse.set_visible(False)

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    def show(self, image: ArrayLike) -> None:
        self._window.draw(display_image(image, self._size))
        if self._window.closed():
            raise KeyboardInterrupt

    def close(self) -> None:
        self._window.close()


class PreviewWindow:
    """An ordinary window on the primary display for a live view (`sliscan live`).

    Call it with an ``(H, W, 3)`` RGB uint8 image; it returns False once the user closed it or
    pressed Esc or q.
    """

    def __init__(self, size: tuple[int, int], title: str = "sliscan live") -> None:
        self._window = _SDLWindow(title, size, screen=None, fullscreen=False)

    def __call__(self, image: NDArray[np.uint8]) -> bool:
        self._window.draw(image)
        return not self._window.closed()

    def close(self) -> None:
        self._window.close()


# --------------------------------------------------------------------------------------------
# The virtual pair
# --------------------------------------------------------------------------------------------


class VirtualStage:
    """What a virtual display and camera share: the rig, the scene, the clock, and what the
    display has been asked to show and from when it is visible.

    Parameters
    ----------
    rig : simulate.Rig
        The projector is the display, the camera the camera.
    scene : simulate.Surface
    conditions : simulate.Conditions
        The physics of every capture; its ``bit_depth`` must be 8 or 16 (the camera's frames
        are uint8 or uint16).
    clock : Clock, optional
        Default a new `VirtualClock`.
    latency_s : float
        Time from `VirtualDisplay.show` until the image is visible (the display's and the
        projector's lag).
    frame_period_s : float
        Time one grab takes (1 / the camera's frame rate).
    motion : motion.Motion, optional
        Move the scene's object: grab ``k`` sees pose ``k mod motion.frames``
        (`motion.posed_scene`).

    Initially the display shows black.
    """

    def __init__(self, rig: Rig, scene: Surface, conditions: Conditions, *, clock: Clock | None = None,
                 latency_s: float = 0.0, frame_period_s: float = 1 / 30, motion: Motion | None = None) -> None:
        if conditions.bit_depth not in (8, 16):
            raise InputError(f"a virtual camera delivers 8- or 16-bit frames; Conditions.bit_depth is "
                             f"{conditions.bit_depth!r}")
        for name, value in (("latency_s", latency_s), ("frame_period_s", frame_period_s)):
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"{name} must be a non-negative number of seconds, got {value!r}")
        self.rig = rig
        self.clock: Clock = VirtualClock() if clock is None else clock
        self.latency_s = float(latency_s)
        self.frame_period_s = float(frame_period_s)
        self.motion = motion
        self.scene, self.conditions = scene, conditions
        w, h = rig.projector.size
        self._timeline: list[tuple[float, NDArray[np.uint8]]] = [(-math.inf, np.zeros((h, w), np.uint8))]

    def move(self, scene: Surface, conditions: Conditions | None = None) -> None:
        """Put another scene (a new pose of a calibration target) in front of the rig."""
        self.scene = scene
        if conditions is not None:
            self.conditions = conditions

    def put(self, image: NDArray[np.uint8]) -> None:
        """The display was given `image` now: it becomes visible after the latency."""
        self._timeline.append((self.clock.now() + self.latency_s, image))
        del self._timeline[:-8]  # older images can no longer be visible

    def visible(self, t: float) -> NDArray[np.uint8]:
        """The image on the display at time `t`."""
        return next(image for start, image in reversed(self._timeline) if start <= t)

    def scene_for(self, grab: int) -> tuple[Surface, Conditions]:
        """The scene and conditions the camera's grab number `grab` sees."""
        if self.motion is None:
            return self.scene, self.conditions
        return posed_scene(self.rig, self.scene, self.motion, grab % self.motion.frames, self.conditions)


class VirtualDisplay:
    """The virtual rig's projector as a `Display`.

    Parameters
    ----------
    stage : VirtualStage
    drop_shows : iterable of int
        Numbers (0-based, counting every `show`) of the calls the display drops: the image
        it showed before stays, as when a display misses a refresh.
    """

    def __init__(self, stage: VirtualStage, *, drop_shows: Iterable[int] = ()) -> None:
        self.stage = stage
        self.drop_shows = frozenset(int(k) for k in drop_shows)
        self.shows = 0

    @property
    def size(self) -> tuple[int, int]:
        return self.stage.rig.projector.size

    def show(self, image: ArrayLike) -> None:
        frame = display_image(image, self.size)
        self.shows += 1
        if self.shows - 1 not in self.drop_shows:
            self.stage.put(frame)

    def close(self) -> None:
        pass


class VirtualCamera:
    """The virtual rig's camera as a `Camera`: each grab renders what the display shows at that
    moment (`VirtualStage.visible`) through `simulate.TracedScene`, with fresh sensor noise.

    Parameters
    ----------
    stage : VirtualStage
    exposure, gain : float
        Multiply the conditions' exposure (signal and shot noise scale alike) and the sensor's
        gain (signal, shot and read noise amplified); 1 is the stage's nominal capture.
    repeat_grabs : iterable of int
        Numbers (0-based) of the grabs that return the previous frame again (a driver
        delivering a stale buffer twice).
    seed : int, optional
        Seed of the sensor noise (drawn grab after grab).  Default: the conditions' seed.

    A grab takes `VirtualStage.frame_period_s` of the stage's clock; the scene is traced
    again only when it changes (a new pose, a moving object).
    """

    def __init__(self, stage: VirtualStage, *, exposure: float = 1.0, gain: float = 1.0,
                 repeat_grabs: Iterable[int] = (), seed: int | None = None) -> None:
        for name, value in (("exposure", exposure), ("gain", gain)):
            _finite(name, value, positive=True)
        self.stage = stage
        self.exposure, self.gain = float(exposure), float(gain)
        self.repeat_grabs = frozenset(int(k) for k in repeat_grabs)
        self.grabs = 0
        self._rng = np.random.default_rng(stage.conditions.seed if seed is None else seed)
        self._traced: tuple[Surface, Conditions, TracedScene] | None = None
        self._last: NDArray[Any] | None = None

    @property
    def size(self) -> tuple[int, int]:
        return self.stage.rig.camera.size

    def _camera_conditions(self, conditions: Conditions) -> Conditions:
        """The stage's conditions under this camera's exposure and gain."""
        if self.exposure == 1 and self.gain == 1:
            return conditions
        full = conditions.full_well_e
        return conditions.with_(exposure=conditions.exposure * self.exposure * self.gain,
                                full_well_e=None if full is None else full / self.gain)

    def _traced_scene(self, scene: Surface, conditions: Conditions) -> TracedScene:
        if self._traced is None or self._traced[0] is not scene or self._traced[1] is not conditions:
            self._traced = (scene, conditions, TracedScene(self.stage.rig, scene, self._camera_conditions(conditions)))
        return self._traced[2]

    def grab(self) -> NDArray[Any]:
        k, t = self.grabs, self.stage.clock.now()
        self.grabs += 1
        self.stage.clock.sleep(self.stage.frame_period_s)
        if k in self.repeat_grabs and self._last is not None:
            return self._last.copy()
        traced = self._traced_scene(*self.stage.scene_for(k))
        image = traced.capture(self.stage.visible(t), rng=self._rng)
        if traced.conditions.bit_depth == 8:
            frame: NDArray[Any] = to_uint8(image)
        else:
            frame = np.round(image.astype(np.float64) * 65535).astype(np.uint16)
        self._last = frame
        return frame

    def settings(self) -> dict[str, Any]:
        cond = self.stage.conditions
        return {"backend": "virtual", "source": "virtual",
                "requested": {"resolution": list(self.size), "exposure": self.exposure, "gain": self.gain},
                "actual": {"resolution": list(self.size), "exposure": self.exposure, "gain": self.gain,
                           "fps": 1 / self.stage.frame_period_s if self.stage.frame_period_s else None,
                           "noise": cond.full_well_e is not None, "bit_depth": cond.bit_depth}}

    def close(self) -> None:
        pass


def virtual_devices(rig: Rig, scene: Surface, conditions: Conditions, *, latency_s: float = 0.0,
                    frame_period_s: float = 1 / 30, motion: Motion | None = None, drop_shows: Iterable[int] = (),
                    repeat_grabs: Iterable[int] = (), exposure: float = 1.0, gain: float = 1.0,
                    seed: int | None = None) -> tuple[VirtualDisplay, VirtualCamera, Clock]:
    """A virtual display and camera on one `VirtualStage` (with a `VirtualClock`), and the clock.

    The parameters are those of `VirtualStage`, `VirtualDisplay` and `VirtualCamera`.
    """
    stage = VirtualStage(rig, scene, conditions, latency_s=latency_s, frame_period_s=frame_period_s, motion=motion)
    return (VirtualDisplay(stage, drop_shows=drop_shows),
            VirtualCamera(stage, exposure=exposure, gain=gain, repeat_grabs=repeat_grabs, seed=seed), stage.clock)
