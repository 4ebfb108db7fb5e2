"""The ``sliscan acquire`` and ``sliscan live`` commands: scanning with a projector and a camera.

They live beside `sliscan.cli` (which imports this module at its end, registering them on its
command group) and follow its conventions: outputs checked first, inputs read before any
device is touched, one line ``error: ...`` and exit status 2 on bad input or a device that
cannot be opened, a one-line summary of what was written.

The devices: ``--camera`` is an OpenCV camera index, device path or stream URL, ``--screen`` a
display number (SDL2 through pygame, the ``hardware`` extra); ``--camera virtual --screen
virtual`` is the virtual rig of `sliscan.simulate` (`sliscan.devices.VirtualStage`), with a
virtual clock, so the commands run end to end without hardware.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import click
import numpy as np

from sliscan import acquire, devices, motion, patterns, sequences, simulate
from sliscan._validate import InputError, write_image
from sliscan.acquire import RECORD_NAME, Session, capture_paths, write_record
from sliscan.calibrate import MIN_BOARD_VIEWS
from sliscan.cli import (ALBEDOS, FLOATS, INPUT_FILE, OUTPUT_FILE, POSITIVE, SCENES, SIZE, _board,
                         _board_options, _check_outputs, _check_projector, _conditions, _options, _overwrite_option,
                         _progress, _run_calibrate_board, _run_calibrate_target, _scan_choices_options, _sequence_spec,
                         _warn_rig, cli)
from sliscan.formats.calibration import load_calibration
from sliscan.pipeline import METHODS, ScanChoices, Scanner
from sliscan.targets import Board, CircleTarget
from sliscan.types import MULTI_FRAME_KINDS, PatternSpec

#: ``--camera`` / ``--screen`` value of the virtual rig.
VIRTUAL = "virtual"

#: Size of the virtual camera without --resolution or --virtual-rig.
VIRTUAL_CAMERA = (640, 480)

#: Poses of the virtual chessboard (degrees about x, then y), cycled through.
VIRTUAL_BOARD_TILTS = ((20, 0), (-20, 15), (0, 25), (15, -25), (-15, -15), (25, 10), (-10, -25), (10, 20))

#: Default number of chessboard poses.
BOARD_POSES = 4


# --------------------------------------------------------------------------------------------
# Options shared by acquire and live
# --------------------------------------------------------------------------------------------

_device_options = _options(
    click.option("--camera", "camera_id", default="0", show_default=True,
                 help="Camera: an OpenCV index (0, 1, ...), a device path or stream URL, or 'virtual' (the virtual "
                      "rig, with --screen virtual)."),
    click.option("--screen", default="1", show_default=True,
                 help="Display that shows the patterns (0 is the primary; a projector extending the desktop is "
                      "usually 1), or 'virtual'."),
    click.option("--resolution", type=SIZE,
                 help="Camera resolution WxH asked of the driver (an error if it gives another); virtual: the "
                      f"virtual camera's [{VIRTUAL_CAMERA[0]}x{VIRTUAL_CAMERA[1]}]."),
    click.option("--exposure", type=float,
                 help="Manual exposure in the driver's unit (CAP_PROP_EXPOSURE; auto-exposure is switched off); "
                      "virtual: a factor [1]."),
    click.option("--gain", type=float, help="Gain in the driver's unit (CAP_PROP_GAIN); virtual: a factor [1]."),
    click.option("--settle", "settle_s", type=click.FloatRange(min=0), default=0.2, show_default=True,
                 help="Seconds from showing an image to grabbing (measure it: --measure-settle)."),
)

_virtual_options = _options(
    click.option("--scene", type=click.Choice(list(SCENES)), default="sphere", show_default=True,
                 help="Virtual: the scene in front of the rig."),
    click.option("--albedo", type=click.Choice(list(ALBEDOS)), default="smooth", show_default=True,
                 help="Virtual: the surface texture."),
    click.option("--noise/--no-noise", default=True, show_default=True, help="Virtual: shot and read noise."),
    click.option("--seed", type=int, default=0, show_default=True, help="Virtual: seed of the noise and the albedo."),
    click.option("--latency", "latency_s", type=click.FloatRange(min=0), default=0.05, show_default=True,
                 help="Virtual: seconds from showing an image until the camera sees it."),
    click.option("--drop", "drops", type=click.IntRange(min=0), multiple=True,
                 help="Virtual: the display drops its Nth image (0-based, counting every image shown; repeatable)."),
    click.option("--repeat", "repeats", type=click.IntRange(min=0), multiple=True,
                 help="Virtual: the camera's Nth grab returns its previous frame again (repeatable)."),
)


@dataclasses.dataclass
class _Virtual:
    """The ``--scene ... --repeat`` options: how to build the virtual rig's stage."""

    scene: str
    albedo: str
    noise: bool
    seed: int
    latency_s: float
    drops: tuple[int, ...]
    repeats: tuple[int, ...]

    def conditions(self, albedo: Any = None) -> simulate.Conditions:
        """`sliscan simulate`'s default physics at one sample per pixel (fast), with this
        texture (or `albedo`, a calibration target's)."""
        cond = _conditions(albedo=self.albedo, ambient=0.1, gamma=2.2, blur=1.0, noise=self.noise, supersample=1,
                           seed=self.seed)
        return cond if albedo is None else cond.with_(albedo=albedo)

    def record(self) -> dict[str, Any]:
        """For the acquisition record."""
        return {"scene": self.scene, "albedo": self.albedo, "noise": self.noise, "seed": self.seed,
                "latency_s": self.latency_s, "drops": list(self.drops), "repeats": list(self.repeats)}


@dataclasses.dataclass
class _Devices:
    """Opened devices: display, camera, their clock, and the virtual stage (None for real ones)."""

    display: devices.Display
    camera: devices.Camera
    clock: devices.Clock
    stage: devices.VirtualStage | None
    info: dict[str, Any]


def _virtual_rig(virtual_rig: Path | None, resolution: tuple[int, int] | None,
                 projector: tuple[int, int] | None) -> simulate.Rig:
    """The virtual rig: a calibration JSON's, or the built-in one at `resolution` and the
    pattern's `projector` size."""
    if virtual_rig is None:
        return simulate.virtual_rig(camera_size=resolution or VIRTUAL_CAMERA, projector_size=projector or (1024, 768))
    rig = simulate.Rig(load_calibration(virtual_rig))
    if resolution is not None and rig.camera.size != tuple(resolution):
        (w, h), (cw, ch) = resolution, rig.camera.size
        raise InputError(f"--resolution {w}x{h}: the camera of the virtual rig {virtual_rig} is {cw}x{ch}")
    return rig


@contextlib.contextmanager
def _open_devices(camera_id: str, screen: str, *, resolution: tuple[int, int] | None, exposure: float | None,
                  gain: float | None, virtual: _Virtual, rig: simulate.Rig | None, projector: tuple[int, int] | None,
                  motion_: motion.Motion | None = None) -> Iterator[_Devices]:
    """Open the camera, then the display (closing both at the end).

    A real display must have the pattern's `projector` size (when given); a virtual stage uses
    `rig` (its projector must be the pattern's) and `virtual`'s scene and faults.
    """
    if (camera_id == VIRTUAL) != (screen == VIRTUAL):
        raise click.UsageError("--camera virtual and --screen virtual go together (the virtual camera sees the "
                               "virtual display)")
    if camera_id == VIRTUAL:
        assert rig is not None
        if projector is not None and rig.projector.size != tuple(projector):
            (w, h), (pw, ph) = projector, rig.projector.size
            raise InputError(f"the pattern is for a {w}x{h} projector but the virtual rig's is {pw}x{ph}")
        cond = virtual.conditions()
        scene = SCENES[virtual.scene](distance_mm=rig.working_distance_mm)
        stage = devices.VirtualStage(rig, scene, cond, latency_s=virtual.latency_s, motion=motion_)
        camera: devices.Camera = devices.VirtualCamera(stage, exposure=1.0 if exposure is None else exposure,
                                                       gain=1.0 if gain is None else gain, repeat_grabs=virtual.repeats)
        display: devices.Display = devices.VirtualDisplay(stage, drop_shows=virtual.drops)
        yield _Devices(display, camera, stage.clock, stage,
                       {"backend": VIRTUAL, "screen": VIRTUAL, "size": list(display.size), "virtual": virtual.record()})
        return
    try:
        index = int(screen)
    except ValueError:
        raise click.UsageError(f"--screen takes a display number (0, 1, ...) or 'virtual', got {screen!r}") from None
    camera = devices.OpenCVCamera(devices.camera_source(camera_id), resolution=resolution, exposure=exposure, gain=gain)
    try:
        display = devices.PygameDisplay(index)
        try:
            if projector is not None and display.size != tuple(projector):
                (w, h), (pw, ph) = display.size, projector
                raise InputError(f"screen {index} is {w}x{h} but the pattern is for a {pw}x{ph} projector: make the "
                                 f"pattern at the projector's native resolution (sliscan pattern ... --projector {w}x{h})")
            yield _Devices(display, camera, devices.RealClock(), None,
                           {"backend": "pygame", "screen": index, "size": list(display.size)})
        finally:
            display.close()
    finally:
        camera.close()


def _print_devices() -> None:
    """`sliscan acquire --list`: cameras, displays and the virtual pair."""
    cameras = devices.list_cameras()
    click.echo(f"cameras (OpenCV VideoCapture, indices 0-{devices.PROBED_CAMERAS - 1}; --camera N):")
    for index, (w, h) in cameras:
        click.echo(f"  {index}: {w}x{h}")
    if not cameras:
        click.echo("  none found (a device path, stream URL or video file also works as --camera)")
    click.echo("displays (SDL2; --screen N):")
    try:
        for index, (w, h) in enumerate(devices.list_displays()):
            click.echo(f"  {index}: {w}x{h}{' (primary)' if index == 0 else ''}")
    except devices.DeviceError as exc:
        click.echo(f"  {exc}")
    click.echo("virtual: --camera virtual --screen virtual (the virtual rig of sliscan simulate)")


# --------------------------------------------------------------------------------------------
# sliscan acquire
# --------------------------------------------------------------------------------------------


def _pattern_images(spec: PatternSpec) -> np.ndarray:
    """Every image of a pattern in projection order, ``(K, Hp, Wp)`` float32."""
    return sequences.render_frames(spec) if spec.kind in MULTI_FRAME_KINDS else patterns.render_pattern(spec)[None]


def _session(devs: _Devices, *, settle_s: float, average: int, verify: str, retakes: int) -> Session:
    """A `Session` on the opened devices."""
    return Session(devs.display, devs.camera, clock=devs.clock, settle_s=settle_s, average=average, verify=verify,
                   retakes=retakes)


def _take(session: Session, images: np.ndarray, stage: Any, label: str = "") -> list[acquire.Shot]:
    """The references, then every image, with progress stages."""
    stage(f"{label}references")
    session.start()
    return session.sequence(images, progress=lambda k: stage(f"{label}frame {k + 1}/{len(images)}"))


def _record_info(session: Session, devs: _Devices, shots: list[acquire.Shot], paths: list[Path]) -> dict[str, Any]:
    """Everything but the pattern and the frames in a record."""
    captures = [{"file": path.name, **shot.log} for path, shot in zip(paths, shots)]
    return {"started": session.started, "seconds": session.elapsed(),
            "camera": {**devs.camera.settings(), "average": session.average}, "display": devs.info,
            "session": session.settings(), "captures": captures}


def _retake_summary(shots: list[acquire.Shot]) -> str:
    """``"no retakes"`` or ``"2 retakes (frames 3, 7)"``."""
    retaken = [s.log["frame"] for s in shots if s.log["retakes"]]
    total = sum(s.log["retakes"] for s in shots)
    if not total:
        return "no retakes"
    return f"{total} retake{'s' if total > 1 else ''} (frame{'s' if len(retaken) > 1 else ''} " \
           f"{', '.join(map(str, retaken))})"


@cli.command("acquire", epilog="""\b
Examples:
  sliscan acquire --list                                          # cameras and displays
  sliscan acquire --camera 0 --screen 1 --measure-settle          # display-to-camera delay
  sliscan acquire --pattern pmp/pmp.json --camera 0 --screen 1 --exposure 200 --settle 0.15 -o take
  sliscan scan take/acquisition.json --calibration rig.json --ply take.ply
  sliscan acquire --pattern cp.json --camera 0 --screen 1 --average 4 -o cp-take
  sliscan acquire --pattern gc.json --calibration-board 9x7 --square 25 --poses 6 -o cal   # -> cal/rig.json
  sliscan acquire --pattern gc.json --calibration-board 4x11 --circles asymmetric --spacing 20 --poses 8 -o cal
  sliscan acquire --pattern pmp.json --calibration-target target.json -o cal-target
\b
Without hardware (the virtual rig, a virtual clock):
  sliscan acquire --pattern pmp/pmp.json --camera virtual --screen virtual --scene sphere -o vtake
  sliscan acquire --pattern pmp/pmp.json --camera virtual --screen virtual --drop 3 --repeat 9 -o vtake2""")
@click.option("--pattern", "pattern_path", type=INPUT_FILE,
              help="PatternSpec JSON of the pattern to project (any kind; for calibration a pmp or graycode "
                   "sequence with orientation both).")
@_device_options
@click.option("-o", "--output", type=click.Path(file_okay=False, path_type=Path),
              help=f"Folder for the captures (capture_00.png ...) and the record {RECORD_NAME}.")
@click.option("--average", type=click.IntRange(min=1), default=1, show_default=True,
              help="Frames grabbed and averaged per capture (saved in 16 bits when more than 1).")
@click.option("--verify", type=click.Choice(acquire.VERIFY_MODES), default="change", show_default=True,
              help="Freshness check: each capture must differ from the previous one (a flash decides when it does "
                   "not), a flash before every frame, or none.")
@click.option("--retakes", type=click.IntRange(min=0), default=3, show_default=True,
              help="Retakes per frame (each waiting twice as long) before giving up.")
@click.option("--list", "list_", is_flag=True, help="List the cameras and displays, and exit.")
@click.option("--measure-settle", is_flag=True,
              help="Measure the display-to-camera delay (flash and detect) and suggest --settle; writes nothing.")
@click.option("--calibration-target", "target_path", type=INPUT_FILE,
              help="Capture and calibrate with this 3-D circle target (target JSON, as calibrate-target; one pose).")
@click.option("--calibration-board", "board", type=SIZE,
              help="Capture and calibrate with a planar board of OpenCV's pattern size COLUMNSxROWS (as "
                   "calibrate-board: a chessboard's inner corners, or with --circles a circle grid's circles).")
@_board_options
@click.option("--poses", type=click.IntRange(min=1),
              help=f"With --calibration-board: board poses [{BOARD_POSES}], at least {MIN_BOARD_VIEWS}.")
@click.option("--yes", is_flag=True, help="Do not wait for Enter between poses (virtual: the target moves itself).")
@click.option("--projector-distortion/--no-projector-distortion", default=True, show_default=True,
              help="With --calibration-board: estimate the projector's lens distortion, or fix it at 0.")
@click.option("--write-calibration", type=OUTPUT_FILE, help="Calibration JSON to write [OUT/rig.json].")
@click.option("--virtual-rig", type=INPUT_FILE,
              help="Virtual: calibration JSON of the virtual rig [the built-in rig at --resolution and the pattern's "
                   "projector].")
@_virtual_options
@_overwrite_option
def acquire_cmd(pattern_path: Path | None, camera_id: str, screen: str, resolution: tuple[int, int] | None,
                exposure: float | None, gain: float | None, settle_s: float, output: Path | None, average: int,
                verify: str, retakes: int, list_: bool, measure_settle: bool, target_path: Path | None,
                board: tuple[int, int] | None, square: float | None, circles: str | None, spacing: float | None,
                radius: float | None, poses: int | None, yes: bool, projector_distortion: bool,
                write_calibration: Path | None, virtual_rig: Path | None, overwrite: bool, **virtual_args: Any) -> None:
    """Project a pattern with a projector, grab it with a camera, and save the captures.

    Each image of the pattern is shown full-screen on --screen, and after --settle seconds the
    camera grabs --average frames.  Every capture is checked to be fresh (it shows this image,
    not the one before: --verify) and retaken, waiting longer, if not.  OUT gets the captures
    capture_00.png ... in projection order and acquisition.json (the pattern, camera settings,
    timestamps, retakes), which `sliscan scan OUT/acquisition.json --calibration rig.json`
    reads directly.

    With --calibration-board or --calibration-target it runs the calibration workflow instead:
    per pose the whole sequence (both directions) into OUT/pose_00/ ..., asking to move the
    board between poses (Enter), then calibrates (as calibrate-board / calibrate-target).
    """
    if list_:
        _print_devices()
        return
    virtual = _Virtual(**virtual_args)
    spec = None if pattern_path is None else PatternSpec.load(pattern_path)
    projector = None if spec is None else spec.projector_size
    rig = _virtual_rig(virtual_rig, resolution, projector) if camera_id == VIRTUAL else None
    settings = dict(settle_s=settle_s, average=average, verify=verify, retakes=retakes)
    if measure_settle:
        _measure_settle(camera_id, screen, resolution, exposure, gain, virtual, rig, projector, settings)
        return
    if spec is None or output is None:
        raise click.UsageError("give --pattern PATTERN.json and -o DIR (or --list, or --measure-settle)")
    opened = lambda **kw: _open_devices(camera_id, screen, resolution=resolution, exposure=exposure,  # noqa: E731
                                        gain=gain, virtual=virtual, rig=rig, projector=projector, **kw)
    if board is not None or target_path is not None:
        _acquire_calibration(spec, pattern_path, output, opened, settings, virtual=virtual, board=board,
                             board_options=dict(square=square, circles=circles, spacing=spacing, radius=radius),
                             poses=poses, target_path=target_path, yes=yes,
                             projector_distortion=projector_distortion, write_calibration=write_calibration,
                             inputs=[virtual_rig], overwrite=overwrite)
        return
    if any(v is not None for v in (square, circles, spacing, radius, poses, write_calibration)):
        raise click.UsageError("--square, --circles, --spacing, --radius, --poses and --write-calibration go with "
                               "--calibration-board or --calibration-target")
    images = _pattern_images(spec)
    paths = capture_paths(output, len(images))
    _check_outputs([*paths, output / RECORD_NAME], [pattern_path, virtual_rig], overwrite=overwrite)
    with opened() as devs, _progress(len(images) + 1) as stage:
        session = _session(devs, **settings)
        shots = _take(session, images, stage)
        write_record(output, spec, [s.raw for s in shots], _record_info(session, devs, shots, paths))
    w, h = devs.camera.size
    files = paths[0].name if len(paths) == 1 else f"{len(paths)} {w}x{h} captures {paths[0].name} .. {paths[-1].name}"
    files = f"the {w}x{h} capture {files}" if len(paths) == 1 else files
    click.echo(f"wrote {output / RECORD_NAME} and {files}: "
               f"{spec.kind} pattern in {session.elapsed():.2f} s, {_retake_summary(shots)}; scan them with "
               f"'sliscan scan {output / RECORD_NAME} --calibration RIG.json'")


def _measure_settle(camera_id: str, screen: str, resolution: tuple[int, int] | None, exposure: float | None,
                    gain: float | None, virtual: _Virtual, rig: simulate.Rig | None, projector: tuple[int, int] | None,
                    settings: dict[str, Any]) -> None:
    """`sliscan acquire --measure-settle`: time black -> white three times, print a --settle."""
    with _open_devices(camera_id, screen, resolution=resolution, exposure=exposure, gain=gain, virtual=virtual,
                       rig=rig, projector=projector) as devs:
        session = _session(devs, **{**settings, "settle_s": max(settings["settle_s"], 0.5)})
        session.start()
        latencies = session.measure_latency()
    shown = ", ".join(f"{t:.3f}" for t in latencies)
    click.echo(f"display-to-camera delay {max(latencies):.3f} s (measured {shown} s, each including one grab); use "
               f"--settle {acquire.suggested_settle(latencies):g}")


def _acquire_calibration(spec: PatternSpec, pattern_path: Path | None, output: Path, opened: Any,
                         settings: dict[str, Any], *, virtual: _Virtual, board: tuple[int, int] | None,
                         board_options: dict[str, Any], poses: int | None, target_path: Path | None, yes: bool,
                         projector_distortion: bool, write_calibration: Path | None, inputs: list[Path | None],
                         overwrite: bool) -> None:
    """`sliscan acquire --calibration-board/--calibration-target`: capture every pose, then
    calibrate with the code of calibrate-board / calibrate-target."""
    assert pattern_path is not None
    if (board is None) == (target_path is None):
        raise click.UsageError("give --calibration-board or --calibration-target, not both")
    spec = _sequence_spec(pattern_path)
    layout = None
    if board is not None:
        layout = _board(board, **board_options, size_option="--calibration-board")
        poses = BOARD_POSES if poses is None else poses
        if poses < MIN_BOARD_VIEWS:
            raise click.UsageError(f"--poses {poses}: a board calibration needs at least {MIN_BOARD_VIEWS} poses")
        target = None
    else:
        if poses not in (None, 1) or any(v is not None for v in board_options.values()):
            raise click.UsageError("a circle target is calibrated from one pose: leave out --poses, and --square, "
                                   "--circles, --spacing and --radius (they describe a --calibration-board)")
        poses, target = 1, CircleTarget.load(target_path)  # type: ignore[arg-type]
    images = _pattern_images(spec)
    folders = [output / f"pose_{k:02d}" for k in range(poses)]
    pose_files = {folder: capture_paths(folder, len(images)) for folder in folders}
    calibration_out = output / "rig.json" if write_calibration is None else write_calibration
    _check_outputs([*(p for files in pose_files.values() for p in files), *(f / RECORD_NAME for f in folders),
                    calibration_out], [pattern_path, target_path, *inputs], overwrite=overwrite)
    what = "board" if board is not None else "target"
    with opened() as devs:
        session = _session(devs, **settings)
        for k, (folder, paths) in enumerate(pose_files.items()):
            if devs.stage is not None:
                devs.stage.move(*_virtual_pose(devs.stage.rig, virtual, k, layout))
            if not yes:
                click.prompt(f"pose {k + 1} of {poses}: place the {what}"
                             f"{' (turned differently from the last pose)' if k else ''} and press Enter",
                             default="", show_default=False, err=True)
            with _progress(len(images) + 1) as stage:
                shots = _take(session, images, stage, label=f"pose {k + 1}: ")
                write_record(folder, spec, [s.raw for s in shots], _record_info(session, devs, shots, paths))
            click.echo(f"pose {k + 1} of {poses}: wrote {folder}/ ({len(paths)} captures, {_retake_summary(shots)})")
    if board is not None:
        assert layout is not None
        _run_calibrate_board(pose_files, spec, layout, projector_distortion=projector_distortion,
                             output=calibration_out)
    else:
        _run_calibrate_target(pose_files[folders[0]], spec, pattern_path, target, target_path,  # type: ignore[arg-type]
                              method="svd", output=calibration_out)


def _virtual_pose(rig: simulate.Rig, virtual: _Virtual, k: int,
                  board: Board | None) -> tuple[simulate.Surface, simulate.Conditions]:
    """Pose `k` of the virtual calibration target: a board turned by `VIRTUAL_BOARD_TILTS` (a
    circle grid without a radius gets circles a quarter of their distance across), or the
    thesis's circle target (`simulate.circle_target_scene`)."""
    distance = rig.working_distance_mm
    tilt = VIRTUAL_BOARD_TILTS[k % len(VIRTUAL_BOARD_TILTS)]
    if board is None:
        scene, albedo, _ = simulate.circle_target_scene(distance_mm=distance)
    elif board.circles:
        radius = board.radius if board.radius is not None else board.nearest / 4
        scene, albedo, _ = simulate.circle_grid_scene(dataclasses.replace(board, radius=radius), tilt_deg=tilt,
                                                      distance_mm=distance)
    else:
        scene, albedo = simulate.board_scene(tilt_deg=tilt, distance_mm=distance, inner_corners=board.size,
                                             square_mm=board.spacing)
    return scene, virtual.conditions(albedo)


# --------------------------------------------------------------------------------------------
# sliscan live
# --------------------------------------------------------------------------------------------


class _Recorder:
    """A live sink stage that saves every frame as ``DIR/frame_000000.png`` ... (the names of a
    batch's outputs, so `sliscan scan DIR --out ...` scans them in order)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.paths: list[Path] = []
        self.log: list[dict[str, Any]] = []

    def __call__(self, frame: acquire.LiveFrame) -> None:
        path = self.folder / f"frame_{frame.index:06d}.png"
        write_image(path, frame.raw)
        self.paths.append(path)
        self.log.append({"file": path.name, "frame": frame.index, "seconds": round(frame.seconds, 4),
                         "points": int(frame.result.valid.sum()), "completeness": round(float(frame.result.valid.mean()), 4)})


@cli.command("live", epilog="""\b
Examples:
  sliscan live --pattern cp.json --calibration rig.json --camera 0 --screen 1
  sliscan live --pattern cp.json --calibration rig.json --camera 0 --screen 1 --record take --seconds 30
  sliscan scan take/acquisition.json --calibration rig.json --out scans        # the batch, afterwards
  sliscan live --pattern cp.json --calibration rig.json --camera virtual --screen virtual --motion 20 \\
      --no-window --frames 20 --record vtake""")
@click.option("--pattern", "pattern_path", type=INPUT_FILE, required=True,
              help="PatternSpec JSON of a single-shot pattern (sliscan pattern composite).")
@click.option("--calibration", type=INPUT_FILE, required=True, help="Calibration JSON of the rig (and virtual: the rig).")
@_device_options
@click.option("--method", type=click.Choice(list(METHODS)), default="window", show_default=True,
              help="Demodulator (as sliscan scan; baseband: the real-time path, carriers of the first frame kept).")
@_scan_choices_options
@click.option("--frames", type=click.IntRange(min=1), help="Stop after this many frames.")
@click.option("--seconds", type=POSITIVE, help="Stop after this many seconds.")
@click.option("--record", type=click.Path(file_okay=False, path_type=Path),
              help=f"Save every frame into this folder (frame_000000.png ... and {RECORD_NAME}) for batch scanning.")
@click.option("--window/--no-window", default=True, show_default=True,
              help="Show the depth map and frames per second in a window (Esc or q ends).")
@click.option("--motion", "motion_frames", type=click.IntRange(min=1),
              help="Virtual: the scene's object moves, pose after pose, over this many frames (then again).")
@click.option("--velocity", type=FLOATS, default="3,0,0", show_default=True, help="Virtual: mm per frame along X, Y, Z.")
@click.option("--spin", type=float, default=4.0, show_default=True, help="Virtual: degrees per frame about the vertical.")
@_virtual_options
@_overwrite_option
def live_cmd(pattern_path: Path, calibration: Path, camera_id: str, screen: str, resolution: tuple[int, int] | None,
             exposure: float | None, gain: float | None, settle_s: float, method: str, choices: ScanChoices,
             frames: int | None, seconds: float | None, record: Path | None, window: bool,
             motion_frames: int | None, velocity: tuple[float, ...], spin: float, overwrite: bool,
             **virtual_args: Any) -> None:
    """Scan continuously: project one single-shot pattern, then scan every camera frame.

    Shows each frame's depth map and the frames per second in a window; --record saves the
    frames (frame_000000.png ... and acquisition.json) so that `sliscan scan DIR --out ...`
    scans them as a batch afterwards.  Ends after --frames or --seconds, or when the window is
    closed (Esc, q), or on Ctrl-C.  Prints the frames scanned and the rate.
    """
    virtual = _Virtual(**virtual_args)
    spec = PatternSpec.load(pattern_path)
    if spec.kind in MULTI_FRAME_KINDS:
        raise InputError(f"{pattern_path}: live scanning needs a single-shot pattern (sliscan pattern composite), "
                         f"got a {spec.kind} sequence")
    if not window and frames is None and seconds is None:
        raise click.UsageError("--no-window needs --frames or --seconds (else nothing ends the loop)")
    if len(velocity) != 3:
        raise click.UsageError(f"--velocity takes 3 numbers (mm per frame along X, Y, Z), got {len(velocity)}")
    calib = load_calibration(calibration)
    _check_projector(spec, pattern_path, calib, str(calibration))
    _warn_rig(spec, pattern_path, calib, calibration)
    recorder = None
    if record is not None:
        earlier = record.is_dir() and any(record.glob("frame_*"))
        if earlier and not overwrite:
            raise InputError(f"--record {record}: holds frames of an earlier recording (use --overwrite)")
        _check_outputs([record / RECORD_NAME], [pattern_path, calibration], overwrite=overwrite)
        recorder = _Recorder(record)
    rig = simulate.Rig(calib) if camera_id == VIRTUAL else None
    moving = None if motion_frames is None else motion.Motion(motion_frames, (velocity[0], velocity[1], velocity[2]),
                                                               spin)
    with _open_devices(camera_id, screen, resolution=resolution, exposure=exposure, gain=gain, virtual=virtual,
                       rig=rig, projector=spec.projector_size, motion_=moving) as devs:
        if devs.camera.size != calib.camera.size:
            (w, h), (cw, ch) = devs.camera.size, calib.camera.size
            raise InputError(f"camera {camera_id} gives {w}x{h} frames but the camera of {calibration} is {cw}x{ch}")
        # the real-time path keeps the first frame's carriers (the search costs 57 ms at 5 MP)
        scanner = Scanner(spec, calib, method=method, **choices.scanner_options(spec),
                          reuse_carriers=method == "baseband")
        started = datetime.now(timezone.utc).isoformat(timespec="seconds")
        preview = devices.PreviewWindow(devs.camera.size) if window else None
        try:
            def sink(frame: acquire.LiveFrame) -> bool:
                if recorder is not None:
                    recorder(frame)
                return preview is None or preview(acquire.depth_preview(frame.result, frame.fps))

            stats = acquire.run_live(devs.display, devs.camera, scanner, patterns.render_pattern(spec), sink=sink,
                                     clock=devs.clock, settle_s=settle_s, frames=frames, seconds=seconds)
        finally:
            if preview is not None:
                preview.close()
        wrote = "wrote nothing (give --record DIR to keep the frames)"
        if recorder is not None and recorder.paths:
            info = {"started": started, "camera": devs.camera.settings(), "display": devs.info,
                    "live": dataclasses.asdict(stats), "captures": recorder.log}
            write_record(record, spec, [], info, paths=recorder.paths)  # type: ignore[arg-type]
            wrote = f"wrote {recorder.paths[0]} .. {recorder.paths[-1].name} and {record / RECORD_NAME}"
    click.echo(f"live: {stats.frames} frame{'s' if stats.frames != 1 else ''} in {stats.seconds:.1f} s ({stats.fps:.2f} frames/s scanned), "
               f"{stats.completeness:.1%} of each frame with points on average; {wrote}")
