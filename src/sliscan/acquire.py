"""Acquisition with a projector and a camera: show, settle, grab, check the frame is fresh.

`Session` drives any `sliscan.devices` display and camera (real or virtual).  For every
projected image it shows the image, waits the settle delay, grabs K frames (averaged), and
checks that the capture shows this image and not the one before it; if not, it shows the image
again, waits twice as long as the last time, and grabs again, up to R retakes.  The captures
and a JSON record (`write_record`: the pattern spec, the frames in order, the camera settings,
timestamps and every retake) go into one folder, which `sliscan scan RECORD.json` reads
directly (`read_record`).

**Is a capture fresh?**  A camera can deliver a frame exposed before the display switched: the
display or projector lags (a late or missed refresh), or the driver hands out an old buffer.
Such a frame looks like a capture of the previous image.  `Session.start` first takes two
references, the camera's view of the projector's black and of its white (each the mean of two
grabs whose mean levels agree, so a frame grabbed mid-change is not used; black, white, then
black again to confirm the black was not stale).  They give the pixels the projector lights
and the sensor noise at black and at white, hence a noise threshold for every pixel at its
level (`Reference.threshold`).  Two captures *differ* when at least `MIN_CHANGED` of the lit
pixels moved by more than `NOISE_SIGMAS` noise deviations of a difference: two exposures of
one image differ in a negligible fraction (a 5-sigma tail), a new pattern in tens of per cent.

* ``change`` (the default): frame k is fresh when it differs from the capture of the image
  shown before it.  When it does not, it is either stale or the camera cannot see the
  difference between the two images (the finest Gray code bits under blur), and the
  flash-and-detect check decides.
* ``flash``: the flash-and-detect check on every frame.  Show a *flash*, the projector's black
  or white (whichever is farther from the frame's mean drive), wait, grab, and check that the
  grab does not differ from that reference (the display has caught up); then show the frame,
  wait, grab, and check that it differs from the flash.  The stale image is now known (the
  flash), and every pattern differs from black or from white over most lit pixels, so the check
  is conclusive for any pattern, at the cost of a second image per frame.
* ``none``: no check.

With K > 1 grabs averaged, the first and the last must not differ (the display changed during
the averaging).  `Session.measure_latency` times the display-to-camera delay with the same
references, to choose the settle delay.

`run_live` is the live loop of `sliscan live`: project one single-shot pattern, then scan
every frame as it arrives and hand it to a sink (a window, a counter in tests).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan._validate import InputError, atomic_write_text, check_image, write_images
from sliscan.devices import Camera, Clock, DeviceError, Display, RealClock, display_image
from sliscan.pipeline import Scanner
from sliscan.sequences import indexed_paths
from sliscan.types import PatternSpec, ScanResult

#: Freshness checks (`Session`): none, change (flash when inconclusive), flash on every frame.
VERIFY_MODES = ("none", "change", "flash")

#: Two captures differ when at least this fraction of the lit pixels changed beyond the noise.
MIN_CHANGED = 0.01

#: Noise deviations (of the difference of two captures) a pixel must move to count as changed.
NOISE_SIGMAS = 5.0

#: Added to every pixel's threshold: 1.5 grey levels of an 8-bit camera (quantisation, flicker).
THRESHOLD_FLOOR = 1.5 / 255

#: The projector must light at least this fraction of the camera's view.
MIN_LIT = 0.01

#: Retakes wait at least twice this (seconds), even after a settle delay of 0.
MIN_RETAKE_WAIT_S = 0.05

#: Two grabs of one image agree in mean level within this (in full scale): 1.3 grey levels.
LEVEL_TOLERANCE = 0.005

#: Reasons of rejected captures: a capture like the previous frame's (stale, or the camera cannot
#: see the difference: the flash check decides), and signs of a stale frame.
_AMBIGUOUS = "no change from the previous frame"
_STALE = "stale"

#: File name of the record in an acquisition folder.
RECORD_NAME = "acquisition.json"

#: ``"format"`` key of a record.
RECORD_FORMAT = "sliscan-acquisition"


def pair_sigma(a: NDArray[np.floating], b: NDArray[np.floating]) -> float:
    """Noise deviation of one capture from two exposures `a`, `b` of one image (any shape): the
    RMS of their difference over sqrt(2).  (Not a median: on 8-bit frames with noise of about
    one grey level the median difference is stuck at 0 or 1 level.)

    >>> rng = np.random.default_rng(0)
    >>> a, b = rng.normal(0.5, 0.01, (2, 100_000))
    >>> round(pair_sigma(a, b), 3)
    0.01
    """
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    return float(np.sqrt(np.mean(d**2) / 2)) if d.size else 0.0


@dataclass(frozen=True, eq=False)
class Reference:
    """The camera's view of the projector's black and white: the basis of the freshness checks.

    Attributes
    ----------
    black, white : (H, W) float32 arrays
        Captures of the projector's black and white, in [0, 1].
    sigma_black, sigma_white : float
        Sensor noise deviation of one capture at the black and at the white level (full scale 1).
    lit : (H, W) bool array
        Pixels the projector lights: white above black by 10 noise deviations and 2 % of full
        scale.
    """

    black: NDArray[np.float32]
    white: NDArray[np.float32]
    sigma_black: float
    sigma_white: float
    lit: NDArray[np.bool_]

    @classmethod
    def measure(cls, blacks: tuple[NDArray[np.float32], NDArray[np.float32]],
                whites: tuple[NDArray[np.float32], NDArray[np.float32]]) -> Reference:
        """From two captures of black and two of white (float32 (H, W) in [0, 1])."""
        black, white = (blacks[0] + blacks[1]) / 2, (whites[0] + whites[1]) / 2
        rough = (white - black) > 0.02
        pick = rough if rough.any() else np.ones_like(rough)
        sigma_b, sigma_w = pair_sigma(blacks[0][pick], blacks[1][pick]), pair_sigma(whites[0][pick], whites[1][pick])
        lit = (white - black) > max(0.02, 10 * max(sigma_b, sigma_w))
        return cls(black.astype(np.float32), white.astype(np.float32), sigma_b, sigma_w, lit)

    @property
    def lit_fraction(self) -> float:
        """Fraction of the camera's pixels the projector lights."""
        return float(self.lit.mean())

    def threshold(self, a: NDArray[np.float32], b: NDArray[np.float32]) -> NDArray[np.float32]:
        """Per pixel, how far two captures may differ by noise alone (full scale 1): `NOISE_SIGMAS`
        deviations of the difference at the pixel's level (the noise variance interpolated
        between black and white), plus `THRESHOLD_FLOOR`."""
        span = np.maximum(self.white - self.black, 1e-6)
        level = np.clip((np.maximum(a, b) - self.black) / span, 0, 1)
        variance = self.sigma_black**2 + (self.sigma_white**2 - self.sigma_black**2) * level
        return (NOISE_SIGMAS * np.sqrt(2 * variance) + THRESHOLD_FLOOR).astype(np.float32)

    def changed(self, a: NDArray[np.float32], b: NDArray[np.float32]) -> float:
        """Fraction of the lit pixels where captures `a` and `b` ((H, W) float32) differ beyond
        the noise."""
        moved = np.abs(a - b) > self.threshold(a, b)
        return float(moved[self.lit].mean()) if self.lit.any() else 0.0

    def differ(self, a: NDArray[np.float32], b: NDArray[np.float32]) -> bool:
        """Whether `a` and `b` are captures of different images (`MIN_CHANGED` of the lit pixels)."""
        return self.changed(a, b) >= MIN_CHANGED

    def summary(self) -> dict[str, float]:
        """Numbers for the acquisition record."""
        contrast = (self.white - self.black)[self.lit]
        return {"noise_black": self.sigma_black, "noise_white": self.sigma_white, "lit_fraction": self.lit_fraction,
                "contrast_median": float(np.median(contrast)) if contrast.size else 0.0}


@dataclass(frozen=True, eq=False)
class Shot:
    """One accepted capture of one projected image.

    Attributes
    ----------
    raw : (H, W) uint8 or uint16 array
        What is saved: the camera's frame, or the mean of K frames in 16 bits.
    image : (H, W) float32 array
        `raw` in [0, 1].
    log : dict
        For the record: times, attempts, retakes (with reasons), whether a flash was used.
    """

    raw: NDArray[Any]
    image: NDArray[np.float32]
    log: dict[str, Any]


def _mean_frame(frames: Sequence[NDArray[Any]]) -> NDArray[Any]:
    """One frame as is; several as their mean in 16 bits (uint16, full scale 65535)."""
    if len(frames) == 1:
        return frames[0]
    mean = np.mean([check_image("frame", f) for f in frames], axis=0, dtype=np.float64)
    return np.round(mean * 65535).astype(np.uint16)


class Session:
    """Acquisition on one display and one camera (module docstring: the checks).

    Parameters
    ----------
    display : Display
    camera : Camera
    clock : Clock, optional
        Default the machine's clock; the virtual devices bring their own.
    settle_s : float
        Seconds from showing an image to grabbing (doubled on each retake).
    average : int
        Frames grabbed and averaged per capture.
    verify : {"change", "flash", "none"}
    retakes : int
        Retakes allowed per image before giving up.

    Raises
    ------
    InputError
        On a bad setting.
    """

    def __init__(self, display: Display, camera: Camera, *, clock: Clock | None = None, settle_s: float = 0.2,
                 average: int = 1, verify: str = "change", retakes: int = 3) -> None:
        if not (math.isfinite(settle_s) and settle_s >= 0):
            raise InputError(f"settle_s must be a non-negative number of seconds, got {settle_s!r}")
        if not (isinstance(average, int) and average >= 1):
            raise InputError(f"average must be a positive whole number of frames, got {average!r}")
        if verify not in VERIFY_MODES:
            raise InputError(f"verify must be one of {', '.join(VERIFY_MODES)}, got {verify!r}")
        if not (isinstance(retakes, int) and retakes >= 0):
            raise InputError(f"retakes must be a whole number >= 0, got {retakes!r}")
        self.display, self.camera = display, camera
        self.clock: Clock = RealClock() if clock is None else clock
        self.settle_s, self.average, self.verify, self.retakes = float(settle_s), average, verify, retakes
        self.started = datetime.now(timezone.utc).isoformat(timespec="seconds")
        self._t0 = self.clock.now()
        self.reference: Reference | None = None
        self.wait_s = self.settle_s
        self._black = self._white = np.zeros(0, np.uint8)
        self._in_flight: list[NDArray[np.float32]] = []

    def wait_for(self, attempt: int) -> float:
        """Seconds to wait before grabbing at attempt `attempt` (0 the first): the settle delay,
        doubled at each retake (from at least `MIN_RETAKE_WAIT_S`, so a zero delay grows too)."""
        return self.wait_s if attempt == 0 else max(self.wait_s, MIN_RETAKE_WAIT_S) * 2**attempt

    def elapsed(self) -> float:
        """Seconds on the session's clock since it began."""
        return round(self.clock.now() - self._t0, 6)

    def _grab(self, count: int) -> list[NDArray[Any]]:
        return [self.camera.grab() for _ in range(count)]

    def _show_and_grab(self, image: NDArray[np.uint8], wait_s: float, count: int) -> tuple[list[NDArray[Any]], float]:
        """Show `image`, wait, grab `count` frames; returns them and when the image was shown."""
        self.display.show(image)
        shown = self.elapsed()
        self.clock.sleep(wait_s)
        return self._grab(count), shown

    # ---- references ------------------------------------------------------------------------

    def _settled_pair(self, image: NDArray[np.uint8], wait_s: float, what: str) -> tuple[NDArray[np.float32], ...]:
        """Two consecutive grabs of `image` whose mean levels agree (`LEVEL_TOLERANCE`)."""
        frames, _ = self._show_and_grab(image, wait_s, 1)
        a = check_image("frame", frames[0])
        for _ in range(self.retakes + 2):
            b = check_image("frame", self.camera.grab())
            if abs(float(a.mean()) - float(b.mean())) <= LEVEL_TOLERANCE:
                return a, b
            a = b
        raise DeviceError(f"the camera's view of the projector's {what} does not settle (consecutive frames differ "
                          f"in brightness): switch the camera's auto-exposure off and keep the room light steady")

    def start(self) -> Reference:
        """Take the black and white references (black, white, black again to confirm), waiting
        longer on each retake; the display is left showing black.

        Raises
        ------
        DeviceError
            If the camera does not see the projector (white and black alike over all but
            `MIN_LIT` of the frame) or the references do not settle.
        """
        w, h = self.display.size
        self._black, self._white = np.zeros((h, w), np.uint8), np.full((h, w), 255, np.uint8)
        self._in_flight = []
        problem = ""
        for attempt in range(self.retakes + 1):
            wait = self.wait_for(attempt)
            blacks = self._settled_pair(self._black, wait, "black")
            whites = self._settled_pair(self._white, wait, "white")
            reference = Reference.measure(blacks, whites)
            if reference.lit_fraction < MIN_LIT:
                problem = (f"the camera does not see the projector: its white and black captures differ in "
                           f"{reference.lit_fraction:.1%} of the frame")
                continue
            again = self._settled_pair(self._black, wait, "black")
            if not reference.differ(again[1], reference.black):
                self.reference = reference
                return reference
            problem = "the projector's black looks different each time it is shown"
        raise DeviceError(f"{problem}; point the camera at the projected area, check --screen, or lengthen --settle")

    def _require_reference(self) -> Reference:
        if self.reference is None:
            self.start()
        assert self.reference is not None
        return self.reference

    # ---- one image -------------------------------------------------------------------------

    def _flash_for(self, target: NDArray[np.uint8],
                   previous: NDArray[np.float32]) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """The flash for `target`: black or white, one whose look differs from `previous` (the
        image that may still be on the display), the farther from the target's mean drive first;
        with its reference capture."""
        reference = self._require_reference()
        flashes = [(self._black, reference.black), (self._white, reference.white)]
        if float(target.mean()) < 127.5:
            flashes.reverse()
        return next((f for f in flashes if reference.differ(f[1], previous)), flashes[0])

    def _grab_capture(self, image: NDArray[np.uint8], wait_s: float) -> tuple[NDArray[Any], NDArray[np.float32], float] | str:
        """Show `image`, wait, grab and average: ``(raw, capture, time shown)``, or why not."""
        frames, shown = self._show_and_grab(image, wait_s, self.average)
        raw = _mean_frame(frames)
        if self.average > 1 and self.verify != "none" and self._require_reference().differ(
                check_image("frame", frames[0]), check_image("frame", frames[-1])):
            return "the averaged frames disagree (the image changed while grabbing)"
        return raw, check_image("frame", raw), shown

    def _try_plain(self, target: NDArray[np.uint8], avoid: Sequence[NDArray[np.float32]],
                   wait_s: float) -> tuple[NDArray[Any], NDArray[np.float32], float] | str:
        """Show the target and grab: the capture, or why it is not (yet) accepted.  It must
        differ from every look in `avoid` (the previous frame, flashes maybe still in flight)."""
        got = self._grab_capture(target, wait_s)
        if isinstance(got, str) or self.verify == "none":
            return got
        changed = min(self._require_reference().changed(got[1], look) for look in avoid)
        return got if changed >= MIN_CHANGED else f"{_AMBIGUOUS} ({changed:.2%} of lit pixels)"

    def _try_flash(self, target: NDArray[np.uint8], previous: NDArray[np.float32],
                   wait_s: float) -> tuple[NDArray[Any], NDArray[np.float32], float] | str:
        """The flash-and-detect check: show the flash, check it is seen, show the target, check
        the capture differs from the flash.  A uniform target equal to the flash is accepted
        once the flash is seen."""
        reference = self._require_reference()
        flash, look = self._flash_for(target, previous)
        seen, _ = self._show_and_grab(flash, wait_s, 1)
        if reference.differ(check_image("frame", seen[0]), look):
            return f"{_STALE}: the flash was not seen"
        got = self._grab_capture(target, wait_s)
        if isinstance(got, str) or np.array_equal(flash, target):
            return got
        changed = reference.changed(got[1], look)
        return got if changed >= MIN_CHANGED else f"{_STALE}: no change from the flash ({changed:.2%} of lit pixels)"

    def capture(self, image: ArrayLike, previous: NDArray[np.float32] | None = None, *, index: int = 0) -> Shot:
        """Show `image` ((H, W) of the display: uint8 or float in [0, 1]) and take a fresh capture.

        In the ``change`` mode a capture that does not differ from `previous` goes to the flash
        check at once (in the same attempt); if the capture then differs from `previous`, the
        first one was stale (a dropped or repeated frame), else the camera cannot tell the two
        images apart.  Signs of a display lagging behind the wait (the flash not seen, or still
        seen after the target was shown) make the session wait longer from then on (the wait
        that worked), and the capture is confirmed by another grab one wait later.  Every
        rejected capture is logged with its reason under ``"rejected"``.

        Parameters
        ----------
        image : (H, W) array
        previous : (H, W) float32 array, optional
            The capture of the image shown before (for the ``change`` check); default the
            black reference (what `start` leaves on the display).
        index : int
            Frame number, for messages and the log.

        Raises
        ------
        DeviceError
            When no fresh capture came after `retakes` retakes, with the last reason.
        """
        reference = self._require_reference()
        target = display_image(image, self.display.size, f"frame {index}")
        previous = reference.black if previous is None else previous
        avoid = [previous, *self._in_flight]
        flash = self.verify == "flash"
        rejected: list[dict[str, Any]] = []
        lagging = False
        for attempt in range(self.retakes + 1):
            wait = self.wait_for(attempt)
            got = self._try_flash(target, previous, wait) if flash else self._try_plain(target, avoid, wait)
            if isinstance(got, str) and got.startswith(_AMBIGUOUS) and self.verify == "change":
                rejected.append({"attempt": attempt, "reason": f"{got}: flash check"})
                flash = True
                got = self._try_flash(target, previous, wait)
            if not isinstance(got, str) and lagging:
                self.clock.sleep(wait)
                if reference.differ(check_image("frame", self.camera.grab()), got[1]):
                    got = f"{_STALE}: the display changed after the capture (an image still in flight)"
            if isinstance(got, str):
                rejected.append({"attempt": attempt, "reason": got})
                lagging |= got.startswith(_STALE)
                continue
            raw, capture, shown = got
            if lagging and wait > self.wait_s:
                self.wait_s = wait
            self._in_flight = [self._flash_for(target, previous)[1]] if flash else []
            changed = reference.changed(capture, previous)
            stale = [r for r in rejected if not r["reason"].startswith(_AMBIGUOUS)]
            stale_first = len(stale) < len(rejected) and changed >= MIN_CHANGED  # it did change: a stale frame
            log = {"frame": index, "shown_s": shown, "grabbed_s": self.elapsed(), "wait_s": wait,
                   "retakes": len(stale) + stale_first, "flash": flash, "changed": round(changed, 4),
                   "rejected": rejected}
            return Shot(raw, capture, log)
        raise DeviceError(f"frame {index}: no fresh capture after {self.retakes + 1} tries (last: "
                          f"{rejected[-1]['reason']}); lengthen --settle (measure it with --measure-settle) or check "
                          f"that the camera sees the projector")

    def sequence(self, images: ArrayLike, *, progress: Callable[[int], None] | None = None) -> list[Shot]:
        """`capture` every image of ``(K, H, W)`` `images` in order, each checked against the one
        before; `progress(k)` is called as frame k starts."""
        self._require_reference()
        shots: list[Shot] = []
        previous = None
        for k, image in enumerate(images):  # type: ignore[arg-type]
            if progress is not None:
                progress(k)
            shots.append(self.capture(image, previous, index=k))
            previous = shots[-1].image
        return shots

    def measure_latency(self, *, repeats: int = 3, timeout_s: float = 5.0) -> list[float]:
        """Seconds from showing white (after a settled black) until a grab shows it, `repeats`
        times: the display-to-camera latency, including one grab's duration.

        Raises
        ------
        DeviceError
            If the white is not seen within `timeout_s`.
        """
        reference = self._require_reference()
        latencies = []
        for _ in range(repeats):
            self._settled_pair(self._black, max(self.settle_s, 0.5), "black")
            self.display.show(self._white)
            t0 = self.clock.now()
            while not reference.differ(check_image("frame", self.camera.grab()), reference.black):
                if self.clock.now() - t0 > timeout_s:
                    raise DeviceError(f"the projector's white was not seen within {timeout_s:g} s of showing it")
            latencies.append(round(self.clock.now() - t0, 6))
        return latencies

    def settings(self) -> dict[str, Any]:
        """The session's timing and checks (``wait_s``: the settle delay it ended with, longer
        than ``settle_s`` when the display lagged), and the references' numbers, for the record."""
        out: dict[str, Any] = {"settle_s": self.settle_s, "wait_s": self.wait_s, "average": self.average,
                               "verify": self.verify, "retakes_allowed": self.retakes}
        if self.reference is not None:
            out.update(self.reference.summary())
        return out


def suggested_settle(latencies: Sequence[float]) -> float:
    """A settle delay for measured latencies: 1.5 times the longest, rounded up to 10 ms.

    >>> suggested_settle([0.061, 0.067, 0.064])
    0.11
    """
    return math.ceil(round(150 * max(latencies), 3)) / 100  # rounded to 1e-5 s first: no float noise


# --------------------------------------------------------------------------------------------
# The record
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Record:
    """An acquisition record read back: the pattern, the capture files in order, everything else."""

    path: Path
    spec: PatternSpec
    files: list[Path]
    data: dict[str, Any] = field(repr=False)


def capture_paths(folder: str | os.PathLike, count: int, stem: str = "capture") -> list[Path]:
    """The capture files of an acquisition: ``DIR/capture_00.png`` ... (`indexed_paths`)."""
    return indexed_paths(Path(folder) / f"{stem}.png", count)


def write_record(folder: str | os.PathLike, spec: PatternSpec, raws: Sequence[NDArray[Any]],
                 info: dict[str, Any], *, stem: str = "capture", paths: Sequence[Path] | None = None) -> Path:
    """Write the captures (PNG, all or none) and the record ``DIR/acquisition.json``.

    Parameters
    ----------
    folder : path
    spec : PatternSpec
        Embedded in the record (its own ``frames``, the pattern's image files, dropped).
    raws : sequence of (H, W) uint8 or uint16 arrays
        The captures in projection order (or, live, in time order).
    info : dict
        Everything else the record holds (camera, display, session, captures, ...).
    stem : str
        Capture file names (`capture_paths`), unless `paths` are given (already written).

    Returns
    -------
    Path of the record.
    """
    folder = Path(folder)
    if paths is None:
        paths = capture_paths(folder, len(raws), stem)
        write_images(list(paths), raws)  # type: ignore[arg-type]
    record = {"format": RECORD_FORMAT, "version": 1, "pattern": spec.with_(frames=()).to_dict(),
              "frames": [Path(p).name for p in paths], **info}
    return atomic_write_text(folder / RECORD_NAME, json.dumps(record, indent=2) + "\n")


def is_record(path: str | os.PathLike) -> bool:
    """Whether `path` names a JSON file (then `read_record` reads it as an acquisition record)."""
    return Path(path).suffix.lower() == ".json"


def read_record(path: str | os.PathLike) -> Record:
    """Read an acquisition record: the embedded pattern spec and the capture files (relative to
    the record's folder) in order.

    Raises
    ------
    InputError
        Naming the file: not JSON, not a record, a bad pattern, no frames.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != RECORD_FORMAT:
        raise InputError(f"{path}: not an acquisition record (sliscan acquire writes them; a pattern JSON goes "
                         f"with --pattern)")
    frames = data.get("frames")
    if not (isinstance(frames, list) and frames and all(isinstance(f, str) and f for f in frames)):
        raise InputError(f"{path}: 'frames' must list the capture files")
    if not isinstance(data.get("pattern"), dict):
        raise InputError(f"{path}: 'pattern' must hold the pattern spec")
    spec = PatternSpec.from_dict(data["pattern"], source=f"{path}: pattern")
    return Record(path, spec, [path.parent / f for f in frames], data)


# --------------------------------------------------------------------------------------------
# Live scanning
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class LiveFrame:
    """One frame of the live loop: the camera's frame, its scan, and the rate so far.

    Attributes
    ----------
    index : int
    raw : (H, W) uint8 or uint16 array
    result : ScanResult
    fps : float
        Frames per second over the last `LIVE_FPS_WINDOW` frames (wall clock).
    seconds : float
        Wall-clock seconds since the loop started.
    """

    index: int
    raw: NDArray[Any]
    result: ScanResult
    fps: float
    seconds: float


@dataclass(frozen=True)
class LiveStats:
    """What a live run did: frames scanned, wall-clock seconds, frames per second, and the mean
    fraction of each frame with a valid point."""

    frames: int
    seconds: float
    fps: float
    completeness: float


#: Frames over which `LiveFrame.fps` is measured.
LIVE_FPS_WINDOW = 10

#: A live sink: gets every frame; returning False ends the loop (the window was closed).
Sink = Callable[[LiveFrame], bool]


def run_live(display: Display, camera: Camera, scanner: Scanner, pattern: ArrayLike, *, sink: Sink,
             clock: Clock | None = None, settle_s: float = 0.2, frames: int | None = None,
             seconds: float | None = None) -> LiveStats:
    """Project one single-shot `pattern` ((H, W) of the display), then scan every camera frame.

    Ends after `frames` frames, after `seconds` (wall clock), or when `sink` returns False;
    Ctrl-C ends it too (KeyboardInterrupt propagates).  With the real-time method (``baseband``)
    each frame is scanned into the previous frame's result (`Scanner.scan`'s `out`): a frame's
    result is the sink's until it returns, and must be copied to be kept.
    """
    display.show(display_image(pattern, display.size, "pattern"))
    (RealClock() if clock is None else clock).sleep(settle_s)
    t0 = time.perf_counter()
    recent: deque[float] = deque([t0], maxlen=LIVE_FPS_WINDOW + 1)
    count, valid = 0, 0.0
    result: ScanResult | None = None
    while (frames is None or count < frames) and (seconds is None or time.perf_counter() - t0 < seconds):
        raw = camera.grab()
        result = scanner.scan(raw, out=result if scanner.method == "baseband" else None)
        now = time.perf_counter()
        recent.append(now)
        fps = (len(recent) - 1) / max(recent[-1] - recent[0], 1e-9)
        count += 1
        valid += float(result.valid.mean())
        if not sink(LiveFrame(count - 1, raw, result, fps, now - t0)):
            break
    elapsed = time.perf_counter() - t0
    return LiveStats(count, elapsed, count / elapsed if elapsed > 0 else 0.0, valid / count if count else 0.0)


def depth_preview(result: ScanResult, fps: float) -> NDArray[np.uint8]:
    """An ``(H, W, 3)`` RGB image of a scan's depth for the live window: near red, far blue
    (OpenCV's turbo map over the 2nd-98th percentile of the valid depths), black where no point,
    with the frames per second and the fraction of valid points written on it."""
    import cv2

    z = result.points[..., 2]
    valid = result.valid & np.isfinite(z)
    grey = np.zeros(z.shape, np.uint8)
    if valid.any():
        near, far = np.percentile(z[valid], [2, 98])
        grey[valid] = np.clip(255 * (far - z[valid]) / max(far - near, 1e-6), 0, 255).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(grey, cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[~valid] = 0
    scale = max(z.shape[1] / 640, 0.5)
    cv2.putText(rgb, f"{fps:5.1f} fps  {valid.mean():.0%} valid", (int(10 * scale), int(30 * scale)),
                cv2.FONT_HERSHEY_SIMPLEX, 0.8 * scale, (255, 255, 255), max(1, int(2 * scale)), cv2.LINE_AA)
    return rgb
