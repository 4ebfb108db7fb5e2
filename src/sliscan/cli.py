"""The ``sliscan`` command (DESIGN.md, "The command line").

Commands: ``pattern`` (``composite``, ``carrier-only``, ``modified``, ``pmp``, ``graycode``),
``simulate``, ``scan``, ``calibrate`` (from a G file), ``calibrate-target`` and ``calibrate-board``
(from captured calibration sequences), ``report`` and ``view`` (HTML pages, issue 10), ``demo``,
and ``acquire`` and ``live`` (with a projector and a camera; in `sliscan.cli_acquire`).  Every command

* checks its output paths first: none may be one of its input files or another of its outputs,
  and none may exist unless ``--overwrite`` is given (``demo`` alone replaces its own files);
* reads and checks every input before it computes anything, and writes only at the end, each
  file atomically (temporary file + rename), so bad input leaves nothing behind;
* prints a one-line summary of what it wrote on stdout, and a progress bar on stderr (only on a
  terminal) while it works;
* on bad input prints one line ``error: <message>`` on stderr and exits with status 2.

Sizes are ``WxH`` in pixels on the command line (``1024x768``), ``(W, H)`` inside.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import glob
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

import click
import numpy as np
from numpy.typing import NDArray
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from sliscan import __version__, acquire, batch, evaluate, motion, patterns, photometry, sequences, simulate, viewer
from sliscan import report as report_module
from sliscan._validate import InputError, read_image, write_image, write_images
from sliscan.calibrate import (MIN_BOARD_VIEWS, BoardView, Residuals, board_view, calibrate_board,
                               calibrate_points, calibrate_target, target_residuals)
from sliscan.demodulate import STEP_SPREAD, camera_blur, steps_blur
from sliscan.figures import plot_residuals, require_matplotlib
from sliscan.formats import mat5, premat5
from sliscan.formats.calibration import load_calibration, write_matrix_txt
from sliscan.formats.npz import write_npz_arrays
from sliscan.pipeline import (DECISIONS, MAX_BASELINE_ANGLE_DEG, MAX_STRIPE_TILT_DEG, METHODS, MIN_CARRIER_PERIOD_PX,
                              ScanChoices, Scanner, ScanStages, baseline_angle_deg, baseline_direction,
                              carrier_period_px, stripe_tilt_deg)
from sliscan.report import require_report
from sliscan.targets import Board, CircleTarget
from sliscan.types import MULTI_FRAME_KINDS, SEQUENCE_ORIENTATIONS, Calibration, PatternSpec, ScanResult

#: Exit status for bad input (a usage error, an unreadable or inconsistent file).
BAD_INPUT = 2

#: The thesis's rig (section 4.2): a 2592x1944 camera and a 1024x768 projector.
THESIS_CAMERA = (2592, 1944)
THESIS_PROJECTOR = (1024, 768)

#: Built-in scenes of `sliscan simulate --scene`, each placed at the rig's working distance.
SCENES: dict[str, Callable[..., simulate.Surface]] = {
    "sphere": simulate.sphere_scene,
    "plane": simulate.plane_scene,
    "tilted": simulate.tilted_plane_scene,
    "steps": simulate.steps_scene,
    "cylinder": simulate.cylinder_scene,
    "objects": simulate.objects_scene,
}

#: Surface textures of `sliscan simulate --albedo`, by name; each takes the seed.
ALBEDOS: dict[str, Callable[[int], Callable[[Any], Any]]] = {
    "uniform": lambda seed: simulate.UniformAlbedo(0.8),
    "smooth": lambda seed: simulate.SmoothAlbedo(seed=seed),
    "checker": lambda seed: simulate.CheckerAlbedo(),
}

_NO_PILOT = "none"


# --------------------------------------------------------------------------------------------
# Parameter types and shared options
# --------------------------------------------------------------------------------------------


class SizeType(click.ParamType):
    """``WxH`` in pixels -> ``(W, H)`` tuple of positive ints."""

    name = "WxH"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> tuple[int, int]:
        if isinstance(value, tuple):
            return value
        try:
            w, h = (int(v) for v in str(value).lower().split("x"))
        except ValueError:
            self.fail(f"expected WxH in pixels (e.g. 1024x768), got {value!r}", param, ctx)
        if w < 1 or h < 1:
            self.fail(f"sizes must be positive, got {value!r}", param, ctx)
        return (w, h)


class FloatListType(click.ParamType):
    """Comma-separated numbers (``32,64,96,128``) -> tuple of float."""

    name = "F,F,..."

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> tuple[float, ...]:
        if isinstance(value, tuple):
            return value
        try:
            return tuple(float(v) for v in str(value).split(","))
        except ValueError:
            self.fail(f"expected comma-separated numbers (e.g. 32,64,96,128), got {value!r}", param, ctx)


class PilotType(click.ParamType):
    """A pilot carrier frequency, or ``none`` for no pilot."""

    name = "F|none"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> float | str:
        if isinstance(value, float) or value == _NO_PILOT:
            return value
        try:
            return float(value)
        except ValueError:
            self.fail(f"expected a frequency or 'none', got {value!r}", param, ctx)


SIZE = SizeType()
FLOATS = FloatListType()
INPUT_FILE = click.Path(dir_okay=False, path_type=Path)
OUTPUT_FILE = click.Path(dir_okay=False, path_type=Path)
POSITIVE = click.FloatRange(min=0, min_open=True)


def _options(*decorators: Callable[[Callable], Callable]) -> Callable[[Callable], Callable]:
    """Apply several click decorators in the order written (top first, as if stacked)."""

    def apply(func: Callable) -> Callable:
        for decorator in reversed(decorators):
            func = decorator(func)
        return func

    return apply


def _camera_option(**kwargs: Any) -> Callable[[Callable], Callable]:
    """``--camera`` (alias ``--camera-size``) WxH."""
    return click.option("--camera", "--camera-size", "camera", type=SIZE, **kwargs)


def _projector_option(**kwargs: Any) -> Callable[[Callable], Callable]:
    """``--projector`` WxH."""
    return click.option("--projector", type=SIZE, **kwargs)


_overwrite_option = click.option("--overwrite", is_flag=True,
                                 help="Replace output files that exist (else an existing output is an error).")


def _scan_choices_options(command: Callable) -> Callable:
    """``--decisions``, ``--albedo-steps/--no-albedo-steps``, ``--stripe-lines/--stripe-centres``,
    ``--trim-edges`` and ``--camera-blur``, handed to `command` as one ``choices`` `ScanChoices`
    argument."""

    @functools.wraps(command)
    def with_choices(*args: Any, decisions: str, albedo_steps: bool, stripe_lines: bool, trim_edges: int,
                     camera_blur: float | None, **kwargs: Any) -> Any:
        return command(*args, choices=ScanChoices(decisions, albedo_steps, stripe_lines, trim_edges, camera_blur),
                       **kwargs)

    return _options(
        click.option("--decisions", type=click.Choice(list(DECISIONS)), default="auto", show_default=True,
                     help="Single-shot patterns: decide the stripes down each column by the order they come in "
                          "(order; more complete, 2-3x slower to decode), each pixel from its own bits (pixel; "
                          "faster), or auto (order; the baseband method decides per pixel)."),
        click.option("--albedo-steps/--no-albedo-steps", default=True, show_default=True,
                     help="Window and baseband demodulators: divide the capture by its sharp reflectance steps "
                          "first (for textured surfaces; baseband: and by its flat field), or not (faster)."),
        click.option("--stripe-lines/--stripe-centres", default=True, show_default=True,
                     help="Window and band-pass demodulators: place each pixel's projector line between its "
                          "stripe's located borders (no staircase; with a phase channel, where the two agree), "
                          "or at its stripe's centre (the thesis's staircase; with a phase channel, the phase's "
                          "lines)."),
        click.option("--trim-edges", type=click.IntRange(min=0), default=0, show_default=True, metavar="PX",
                     help="Drop the points within PX camera pixels of a depth or shadow edge, a gap or the frame's "
                          "edge along the carriers, where the demodulation windows reach across it: fewer points, "
                          "lower RMS (e.g. 10 at 5 MP; docs/accuracy.md)."),
        click.option("--camera-blur", type=click.FloatRange(min=0, min_open=True), default=None, metavar="PX",
                     help="The camera's blur (Gaussian sigma, camera pixels) the albedo steps are found and "
                          "blurred with [default: measured on each capture's albedo edges; 1 with --method "
                          "baseband]."),
    )(with_choices)


_calibration_options = _options(
    click.option("--calibration", type=INPUT_FILE, help="Calibration JSON (DESIGN.md format)."),
    click.option("--camera-matrix", type=INPUT_FILE,
                 help="Instead of --calibration: the camera's 3x4 matrix as text (the thesis's cam.txt)."),
    click.option("--projector-matrix", type=INPUT_FILE,
                 help="With --camera-matrix: the projector's 3x4 matrix as text (proj.txt)."),
)


# --------------------------------------------------------------------------------------------
# Shared helpers
# --------------------------------------------------------------------------------------------


def _check_outputs(outputs: Sequence[Path | None], inputs: Sequence[Path | None], *, overwrite: bool) -> None:
    """Refuse an output path that is an input file, that is given twice, or (unless `overwrite`)
    that exists.

    Raises
    ------
    InputError
        Naming the output path.
    """
    given = {Path(os.path.realpath(p)): p for p in inputs if p is not None}
    seen: dict[Path, Path] = {}
    for out in outputs:
        if out is None:
            continue
        key = Path(os.path.realpath(out))
        if key in given:
            raise InputError(f"{out}: refusing to overwrite the input file {given[key]}")
        if key in seen:
            raise InputError(f"{out}: given for two outputs")
        if not overwrite and os.path.lexists(out):
            raise InputError(f"{out} exists (use --overwrite)")
        seen[key] = out


@contextlib.contextmanager
def _about(*paths: Path | str | None) -> Iterator[None]:
    """Prefix the message of an `InputError` raised inside with the files it concerns."""
    try:
        yield
    except InputError as exc:
        names = ", ".join(str(p) for p in paths if p is not None)
        raise InputError(f"{names}: {exc}") from None


@contextlib.contextmanager
def _progress(total: int) -> Iterator[Callable[[str], None]]:
    """A progress bar over `total` named stages, on stderr and only on a terminal.

    Yields ``stage(name)``: call it as each stage starts; it completes the previous one.
    """
    console = Console(stderr=True)
    progress = Progress(SpinnerColumn(), TextColumn("{task.description:<24}"), BarColumn(), MofNCompleteColumn(),
                        TimeElapsedColumn(), console=console, transient=True, disable=not console.is_terminal)
    task = progress.add_task("starting", total=total)
    started = False

    def stage(name: str) -> None:
        nonlocal started
        if started:
            progress.advance(task)
        started = True
        progress.update(task, description=name)

    with progress:
        yield stage


def _load_calibration(calibration: Path | None, camera_matrix: Path | None, projector_matrix: Path | None, *,
                      camera_size: tuple[int, int] | None, projector_size: tuple[int, int]) -> Calibration | None:
    """The calibration named by `_calibration_options`, or None when none was given.

    A text pair takes its sizes from `camera_size` (required then) and `projector_size`.
    """
    if calibration is not None:
        if camera_matrix is not None or projector_matrix is not None:
            raise click.UsageError("give --calibration or --camera-matrix with --projector-matrix, not both")
        return load_calibration(calibration)
    if camera_matrix is None and projector_matrix is None:
        return None
    if camera_matrix is None or projector_matrix is None:
        raise click.UsageError("--camera-matrix and --projector-matrix go together")
    if camera_size is None:
        raise click.UsageError("--camera WxH is needed with --camera-matrix (a text matrix has no image size)")
    return load_calibration((camera_matrix, projector_matrix), camera_size=camera_size, projector_size=projector_size)


def _calibration_source(calibration: Path | None, camera_matrix: Path | None, projector_matrix: Path | None) -> str:
    """How to name the calibration's file(s) in a message."""
    return str(calibration) if calibration is not None else f"{camera_matrix}, {projector_matrix}"


def _check_projector(spec: PatternSpec, pattern: Path, calibration: Calibration, source: str) -> None:
    """The pattern must be made for the calibrated projector."""
    if tuple(spec.projector_size) != calibration.projector.size:
        (pw, ph), (cw, ch) = spec.projector_size, calibration.projector.size
        raise InputError(f"{pattern}: the pattern is for a {pw}x{ph} projector "
                         f"but the projector of {source} is {cw}x{ch}")


def _conditions(*, albedo: str, ambient: float, gamma: float, blur: float, noise: bool, supersample: int,
                seed: int, projector_focus: float | None = None, projector_aperture: float = 8.0,
                camera_focus: float | None = None, camera_aperture: float = 3.0) -> simulate.Conditions:
    """Capture conditions: `blur` (px) applies to projector and camera in focus; `gamma` is the
    projector's; a focus (mm) gives that device a depth of field with its aperture (mm)."""
    conditions = simulate.Conditions(albedo=ALBEDOS[albedo](seed), ambient=ambient, projector_gamma=gamma,
                                     projector_blur_px=blur, camera_blur_px=blur, supersample=supersample, seed=seed,
                                     projector_focus_mm=projector_focus, projector_aperture_mm=projector_aperture,
                                     camera_focus_mm=camera_focus, camera_aperture_mm=camera_aperture)
    return conditions if noise else conditions.with_(full_well_e=None)


def _write_scan(result: ScanResult, *, mat5_prefix: Path | None, ply: Path | None, npz: Path | None) -> list[str]:
    """Write the outputs asked for; returns how to name them in the summary."""
    written = []
    if mat5_prefix is not None:
        result.save_mat5(mat5_prefix)
        written.append(f"{mat5_prefix}{{X,Y,Z}}.byt+{{C,I}}.bmp")
    if ply is not None:
        result.save_ply(ply)
        written.append(str(ply))
    if npz is not None:
        result.save_npz(npz)
        written.append(str(npz))
    return written


def _save_truth(path: Path, truth: simulate.GroundTruth) -> None:
    """Every array of the ground truth in one compressed npz, written atomically (the writer of
    ``--npz`` scans: deflate level 1, on all threads)."""
    write_npz_arrays(path, {f.name: getattr(truth, f.name) for f in dataclasses.fields(truth)})


def _mat5_files(prefix: Path | None) -> list[Path]:
    """The five files of a mat5 prefix (none for None)."""
    return [] if prefix is None else mat5.mat5_paths(prefix)


def _describe(spec: PatternSpec) -> str:
    """One-phrase description of a pattern spec."""
    carriers = ", ".join(f"{f:.5g}" for f in spec.carriers)
    pilot = "" if spec.pilot is None else f" + pilot {spec.pilot:.5g}"
    if spec.phase_carriers:
        pilot += (f" + a {len(spec.phase_carriers)}-step phase channel (period {spec.fringe_period:.4g} lines) on "
                  + ", ".join(f"{f:.5g}" for f in spec.phase_carriers))
    w, h = spec.projector_size
    return (f"{spec.kind} pattern for a {w}x{h} projector, {spec.bits} bits ({spec.stripes} stripes along "
            f"{spec.orientation}) on carriers {carriers}{pilot} cycles per {spec.orthogonal_lines} px")


# --------------------------------------------------------------------------------------------
# The command group
# --------------------------------------------------------------------------------------------


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100},
             epilog="""\b
Examples:
  sliscan demo                                    # everything, end to end, on the virtual rig
  sliscan pattern composite --projector 1024x768 -o cp.png
  sliscan simulate --pattern cp.json --scene sphere --write-rig rig.json -o capture.png
  sliscan scan capture.png --pattern cp.json --calibration rig.json --mat5 out/sphere --ply sphere.ply
  sliscan calibrate G.byt --camera-size 2592x1944 --projector 1024x768 -o rig.json
  sliscan calibrate-board pose_0/ pose_1/ pose_2/ --pattern gc.json --board 9x7 --square 75 -o rig.json""")
@click.version_option(__version__, prog_name="sliscan")
def cli() -> None:
    """Single-shot structured-light 3D scanning with the Gray code composite pattern."""


# --------------------------------------------------------------------------------------------
# sliscan pattern
# --------------------------------------------------------------------------------------------


@cli.group()
def pattern() -> None:
    """Generate a pattern image and its PatternSpec JSON (cp.png -> cp.json)."""


_pattern_options = _options(
    _projector_option(help="Projector resolution, e.g. 1024x768 [the calibration's projector with --calibration]."),
    click.option("--calibration", type=INPUT_FILE,
                 help="The rig's calibration JSON: the projector's size and the orientation its baseline needs "
                      "unless given, and warnings where its camera will not resolve the pattern or sees the "
                      "projector's lines tilted."),
    click.option("--thesis", is_flag=True,
                 help="Start from the thesis's pattern (4 bits on carriers 32, 64, 96, 128 per 1024 px, zero "
                      "code kept) instead of sliscan's best."),
    click.option("--bits", type=click.IntRange(1, 16),
                 help="Gray code bits; without --carriers they go on carriers spread evenly up to an 8-pixel "
                      "period, the most significant bit on the highest."),
    click.option("--carriers", type=FLOATS,
                 help="One carrier per bit, cycles per projector width, most significant bit first; "
                      "starts from the thesis's pattern (zero code kept)."),
    click.option("--weights", type=FLOATS, help="Amplitude weight of each bit carrier [all 1]."),
    click.option("--ap", "a_p", type=click.FloatRange(0, 1), help="Mean drive A_p of eq. 3.1 [0.5]."),
    click.option("--bp", "b_p", type=POSITIVE,
                 help="Carrier amplitude B_p of eq. 3.1 [the largest that keeps the pattern in [0, 1] with "
                      "every carrier peaking at once; --drive uses the pattern's own extremes]."),
    click.option("--drive", type=FLOATS,
                 help="LOW,HIGH: set A_p and B_p so that the pattern spans exactly this range of linear "
                      "drive, e.g. 0.2,1 (its own extremes: its carriers seldom peak together; "
                      "docs/accuracy.md, 'Sub-stripe depth from one frame'); excludes --ap and --bp."),
    click.option("--gamma", type=POSITIVE,
                 help="Gamma pre-correction of the projector [1: none]; a pre-corrected composite pattern "
                      "spans the whole light range (0-1) unless --ap, --bp or --drive say otherwise."),
    click.option("--orientation", type=click.Choice(["rows", "columns"]),
                 help="Projector coordinate the stripes code [rows; with --calibration the one its baseline "
                      "needs]."),
    click.option("--pilot", type=PilotType(), help="Pilot carrier frequency, or 'none'."),
    click.option("--phase", is_flag=True,
                 help="Add a 3-step phase channel (sub-stripe depth from the same frame): the fringe's "
                      "phase-shifted copies on the next three carriers above the bits' (160, 192, 224 per "
                      "1024 px for the default bits); the composite pattern then spans a drive of 0.2-1 "
                      "unless --ap, --bp or --drive say otherwise."),
    click.option("--phase-carriers", type=FLOATS,
                 help="The phase channel's carriers (at least 3), cycles per projector width; implies --phase."),
    click.option("--phase-period", type=POSITIVE,
                 help="Projector lines per fringe period of the phase channel [two stripes]."),
    click.option("--skip-zero-code/--keep-zero-code", default=None,
                 help="Never project the all-zero code (sliscan's best does; the thesis does not)."),
    click.option("--from-characterization", "characterization", type=INPUT_FILE,
                 help="Characterization JSON (sliscan characterize): pre-correct with its measured response "
                      "and weight the carriers against its measured roll-off."),
    click.option("-o", "--output", type=OUTPUT_FILE, required=True,
                 help="Pattern image (.png or .bmp); the JSON goes beside it."),
    _overwrite_option,
)

def _weight_sum(spec: PatternSpec) -> float:
    """Sum of the absolute carrier weights (pilot included): the swing of eq. 3.1 per unit B_p."""
    return float(np.sum(np.abs(spec.all_weights)))


def _largest_bp(spec: PatternSpec, reserved: float = 0.0) -> float:
    """Largest B_p keeping eq. 3.1 in [0, 1] when `reserved` of the swing goes elsewhere."""
    headroom = min(spec.a_p, 1.0 - spec.a_p) - reserved
    if headroom <= 0:
        raise InputError(f"no drive left for the carriers: A_p = {spec.a_p:g} with {reserved:g} taken by the sine")
    return headroom / _weight_sum(spec)


def _pattern_spec(kind: str, *, projector: tuple[int, int], thesis: bool, bits: int | None,
                  carriers: tuple[float, ...] | None, weights: tuple[float, ...] | None, a_p: float | None,
                  b_p: float | None, gamma: float | None, orientation: str, pilot: float | str | None,
                  skip_zero_code: bool | None, phase: bool = False, phase_carriers: tuple[float, ...] | None = None,
                  phase_period: float | None = None, characterization: Path | None = None,
                  modified_frequency: float | None = None, modified_amplitude: float | None = None,
                  drive: tuple[float, ...] | None = None) -> PatternSpec:
    """The PatternSpec the `sliscan pattern` options describe (see `pattern composite --help`)."""
    if drive is not None and (a_p is not None or b_p is not None):
        raise click.UsageError("--drive sets A_p and B_p; leave out --ap and --bp")
    if drive is not None and len(drive) != 2:
        raise click.UsageError(f"--drive takes LOW,HIGH, got {len(drive)} values")
    if characterization is not None and gamma is not None:
        raise click.UsageError("--gamma and --from-characterization both set the pre-correction; give one")
    if thesis and (bits is not None or carriers is not None):
        raise click.UsageError("--thesis fixes the bits and the carriers; leave out --bits and --carriers")
    if carriers is not None and bits is not None and bits != len(carriers):
        raise click.UsageError(f"--bits {bits} needs {bits} carriers, got {len(carriers)}")
    if thesis or carriers is not None:
        base = patterns.thesis_spec(projector, orientation=orientation)
    else:
        base = patterns.default_spec(projector, orientation=orientation, bits=bits or 4)
    changes: dict[str, Any] = {"kind": kind}
    if carriers is not None:
        changes.update(carriers=carriers, bits=len(carriers), weights=(1.0,) * len(carriers))
    if pilot == _NO_PILOT:
        changes["pilot"] = None
    elif pilot is not None:
        changes["pilot"] = pilot
    for name, value in (("weights", weights), ("a_p", a_p), ("gamma", gamma), ("skip_zero_code", skip_zero_code),
                        ("modified_frequency", modified_frequency), ("phase_period", phase_period)):
        if value is not None:
            changes[name] = value
    if phase or phase_carriers is not None:
        changes["phase_carriers"] = phase_carriers or patterns.carriers_above(changes.get("carriers", base.carriers))
    spec = base.with_(**changes)
    if kind == "modified_composite":
        amplitude = modified_amplitude
        if amplitude is None:  # one more carrier's worth: B_p with the sine counted as a weight-1 carrier
            amplitude = _largest_bp(spec) * _weight_sum(spec) / (_weight_sum(spec) + 1)
        spec = spec.with_(modified_amplitude=amplitude, b_p=b_p if b_p is not None else _largest_bp(spec, amplitude))
    elif b_p is not None or spec.phase_carriers or any(v is not None for v in (bits, carriers, weights, a_p, pilot)):
        spec = spec.with_(b_p=b_p if b_p is not None else _largest_bp(spec))  # the swing changed: fit B_p again
    if characterization is not None:
        measured = photometry.Characterization.load(characterization)
        with _about(characterization):  # compensated weights keep their sum, so B_p still fits
            spec = measured.apply(spec)
    if drive is None and kind == "composite" and a_p is None and b_p is None:
        if spec.phase_carriers:
            drive = patterns.PHASE_DRIVE  # as `patterns.phase_spec`
        elif spec.gamma != 1.0 or spec.response is not None:
            drive = patterns.PRECORRECTED_DRIVE
    return spec if drive is None else patterns.stretch_drive(spec, *drive)


def _write_composite(kind: str, output: Path, overwrite: bool, options: dict[str, Any]) -> None:
    """Write the single-shot pattern of `kind` that the `sliscan pattern` `options` describe,
    the projector's size and the orientation taken from ``--calibration``'s rig where not given,
    and warn (`_warn_rig`) where that rig will not scan it well."""
    calibration = options.pop("calibration")
    calib = None if calibration is None else load_calibration(calibration)
    if calib is None and options["projector"] is None:
        raise click.UsageError("give --projector WxH, or --calibration rig.json")
    if calib is not None:
        if options["projector"] is not None and tuple(options["projector"]) != calib.projector.size:
            (pw, ph), (cw, ch) = options["projector"], calib.projector.size
            raise InputError(f"{calibration}: its projector is {cw}x{ch}, not the {pw}x{ph} of --projector")
        options["projector"] = calib.projector.size
    options["orientation"] = options["orientation"] or ("rows" if calib is None else baseline_direction(calib))
    spec = _pattern_spec(kind, **options)
    _write_pattern(output, spec, overwrite=overwrite, inputs=[options["characterization"], calibration])
    if calib is not None:
        _warn_rig(spec, output.with_suffix(".json"), calib, calibration)


def _write_pattern(output: Path, spec: PatternSpec, *, overwrite: bool, inputs: Sequence[Path | None] = ()) -> None:
    """Write a pattern image and its JSON (refusing existing files unless `overwrite`); print what was written."""
    _check_outputs([output, output.with_suffix(".json")], inputs, overwrite=overwrite)
    _, json_path = patterns.save_pattern(output, spec)
    click.echo(f"wrote {output} and {json_path}: {_describe(spec)}")


_PATTERN_EPILOG = """\b
Examples:
  sliscan pattern {cmd} --projector 1024x768 -o cp.png            # sliscan's best
  sliscan pattern {cmd} --projector 1024x768 --thesis -o cp.png   # the thesis's
  sliscan pattern {cmd} --projector 1024x768 --bits 4 --carriers 32,64,96,128 -o cp.png
  sliscan pattern {cmd} --projector 1280x800 --bits 6 --orientation columns -o cp.png"""


@pattern.command("composite", epilog=_PATTERN_EPILOG.format(cmd="composite"))
@_pattern_options
def pattern_composite(output: Path, overwrite: bool, **options: Any) -> None:
    """The Gray code composite pattern (thesis eq. 3.1).

    With only --projector: the best single-shot pattern sliscan knows (the thesis's carriers
    with the most significant bit on the highest, no all-zero code).  --thesis, or --bits 4
    --carriers 32,64,96,128, gives the thesis's pattern.
    """
    _write_composite("composite", output, overwrite, options)


@pattern.command("carrier-only", epilog=_PATTERN_EPILOG.format(cmd="carrier-only"))
@_pattern_options
def pattern_carrier_only(output: Path, overwrite: bool, **options: Any) -> None:
    """Every carrier on everywhere (thesis fig. 3.9): for measuring the carriers' roll-off."""
    _write_composite("carrier_only", output, overwrite, options)


@pattern.command("modified", epilog=_PATTERN_EPILOG.format(cmd="modified") + """
  sliscan pattern modified --projector 1024x768 --thesis --modified-amplitude 0.1 -o mcp.png""")
@_pattern_options
@click.option("--modified-frequency", type=POSITIVE, default=15.0, show_default=True,
              help="Sine along the phase direction, cycles per projector height (section 6.2).")
@click.option("--modified-amplitude", type=POSITIVE,
              help="Amplitude of that sine [one carrier's; B_p shrinks to keep the pattern in [0, 1]].")
def pattern_modified(output: Path, overwrite: bool, **options: Any) -> None:
    """The modified composite pattern (thesis section 6.2): composite plus a sine along the phase direction."""
    _write_composite("modified_composite", output, overwrite, options)


def _write_sequence(output: Path, spec: PatternSpec, *, overwrite: bool) -> None:
    """Write a multi-frame pattern's images and JSON (refusing existing files unless `overwrite`);
    print what was written."""
    _check_outputs([output, *sequences.frame_paths(output, spec)], [], overwrite=overwrite)
    paths, json_path = sequences.save_sequence(output, spec)
    w, h = spec.projector_size
    click.echo(f"wrote {json_path} and {len(paths)} frames {paths[0].name} .. {paths[-1].name}: {spec.kind} pattern "
               f"for a {w}x{h} projector, {sequences.describe_frames(spec)}")


_fringe_options = _options(
    click.option("--ap", "a_p", type=click.FloatRange(0, 1), default=0.5, show_default=True,
                 help="Mean drive A_p of the fringes (eq. 2.1)."),
    click.option("--bp", "b_p", type=POSITIVE, default=0.5, show_default=True,
                 help="Fringe amplitude B_p (eq. 2.1); A_p +/- B_p must stay in [0, 1]."),
    click.option("--gamma", type=POSITIVE, default=1.0, show_default=True,
                 help="Gamma pre-correction of the projector (1: none)."),
    click.option("-o", "--output", type=OUTPUT_FILE, required=True,
                 help="PatternSpec JSON (NAME.json); the frames NAME_00.png, NAME_01.png, ... go beside it."),
    _overwrite_option,
)


@pattern.command("pmp", epilog="""\b
Examples:
  sliscan pattern pmp --projector 1024x768 -o pmp/pmp.json              # 3 frequencies x 4 steps
  sliscan pattern pmp --projector 1024x768 --steps 3 --frequencies 1,16 -o dual/pmp.json
  sliscan pattern pmp --projector 1024x768 --frequencies 15,16 -o heterodyne/pmp.json
  sliscan pattern pmp --projector 1280x800 --orientation both --gamma 2.2 -o cal/pmp.json""")
@_projector_option(required=True, help="Projector resolution, e.g. 1024x768.")
@click.option("--steps", type=click.IntRange(min=3), default=4, show_default=True,
              help="Phase steps N per frequency.")
@click.option("--frequencies", type=FLOATS, default="1,8,64", show_default=True,
              help="Fringe frequencies in cycles per projector height (rows) or width (columns), increasing: "
                   "the first 1 (hierarchical unwrapping), or a first pair differing by 1 (heterodyne).")
@click.option("--orientation", type=click.Choice(SEQUENCE_ORIENTATIONS), default="rows", show_default=True,
              help="Projector coordinate the fringes code; both: the columns' frames, then the rows'.")
@_fringe_options
def pattern_pmp(output: Path, projector: tuple[int, int], overwrite: bool, **fields: Any) -> None:
    """Phase measuring profilometry (thesis section 2.6, eq. 2.1): N phase-shifted fringe images per frequency.

    Frames in projection order: per direction (columns first for both), per frequency, the
    steps n = 0 .. N-1.  `sliscan scan` takes the captures in that order.
    """
    _write_sequence(output, PatternSpec(kind="pmp", projector_size=projector, **fields), overwrite=overwrite)


@pattern.command("graycode", epilog="""\b
Examples:
  sliscan pattern graycode --projector 1024x768 -o gc/gc.json       # OpenCV's 42 frames
  sliscan pattern graycode --projector 1024x768 --orientation rows -o gc/rows.json
  sliscan pattern graycode --projector 1024x768 --phase-steps 4 --code-width 8 -o hybrid/gc.json""")
@_projector_option(required=True, help="Projector resolution, e.g. 1024x768.")
@click.option("--orientation", type=click.Choice(SEQUENCE_ORIENTATIONS), default="both", show_default=True,
              help="Projector coordinate(s) coded; both (OpenCV's sequence): the columns' frames, then the rows'.")
@click.option("--phase-steps", "steps", type=click.IntRange(min=0), default=0, show_default=True,
              help="Phase-shifted fringes per direction refining the Gray code (0: none, else >= 3).")
@click.option("--code-width", type=click.IntRange(min=1),
              help="Projector lines per Gray code, a power of two [1; 8 with --phase-steps, whose fringe period "
                   "is two codes].")
@_fringe_options
def pattern_graycode(output: Path, projector: tuple[int, int], code_width: int | None, overwrite: bool,
                     **fields: Any) -> None:
    """Classic Gray code: a pattern and its inverse per bit, then white and black (OpenCV's order).

    With the defaults the frames are exactly OpenCV's structured_light::GrayCodePattern: the
    column bits (most significant first, each pattern then its inverse), the row bits, white,
    black.  --phase-steps appends phase-shifted fringes per direction (a Gray code + phase
    shift hybrid); --ap, --bp and --gamma apply to those only.
    """
    width = code_width if code_width is not None else (8 if fields["steps"] else 1)
    _write_sequence(output, PatternSpec(kind="graycode", projector_size=projector, code_width=width, **fields),
                    overwrite=overwrite)


@pattern.command("sine", epilog="""\b
Examples:
  sliscan pattern sine --projector 1024x768 -o sine.png        # 8 periods across the width
  sliscan pattern sine --projector 1024x768 --cycles 12 -o sine.png
  sliscan characterize gamma capture.png --pattern sine.json -o char.json""")
@_projector_option(required=True, help="Projector resolution, e.g. 1024x768.")
@click.option("--cycles", type=POSITIVE, default=8.0, show_default=True,
              help="Periods across a 1024-pixel width (scaled to the projector's); low keeps blur off its harmonics.")
@click.option("--orientation", type=click.Choice(["rows", "columns"]), default="rows", show_default=True,
              help="Projector coordinate the decoding patterns code (the sine runs across it).")
@click.option("-o", "--output", type=OUTPUT_FILE, required=True,
              help="Pattern image (.png or .bmp); the JSON goes beside it.")
@_overwrite_option
def pattern_sine(projector: tuple[int, int], cycles: float, orientation: str, output: Path, overwrite: bool) -> None:
    """A full-range sine (thesis fig. 3.6): the target of `sliscan characterize gamma`."""
    _write_pattern(output, photometry.sine_target(projector, cycles=cycles, orientation=orientation),
                   overwrite=overwrite)


# --------------------------------------------------------------------------------------------
# sliscan characterize
# --------------------------------------------------------------------------------------------


@cli.group()
def characterize() -> None:
    """Measure the projector's gamma and the optics' roll-off (thesis 3.2) into a characterization JSON."""


def _measured_capture(capture: Path, pattern_path: Path) -> tuple[NDArray[np.float32], PatternSpec]:
    """The capture and the spec of the pattern it shows."""
    return read_image(capture), PatternSpec.load(pattern_path)


def _gamma_table(fit: photometry.GammaFit) -> Table:
    """The thesis's table 3.2 with sliscan's continuous estimate."""
    table = Table(title="projector gamma (thesis table 3.2)")
    table.add_column("gamma", justify="right")
    table.add_column("RMS error", justify="right")
    for gamma, error in fit.table:
        table.add_row(f"{gamma:.2f}", f"{error:.4f}")
    table.add_row(f"[bold]{fit.gamma:.3f}[/bold]", "least", end_section=True)
    return table


@characterize.command("gamma", epilog="""\b
Examples:
  sliscan pattern sine --projector 1024x768 -o sine.png     # project it, capture it
  sliscan characterize gamma capture.png --pattern sine.json
  sliscan characterize gamma capture.png --pattern sine.json -o char.json""")
@click.argument("capture", type=INPUT_FILE)
@click.option("--pattern", "pattern_path", type=INPUT_FILE, required=True,
              help="PatternSpec JSON of the projected sine (sliscan pattern sine).")
@click.option("-o", "--output", type=OUTPUT_FILE, help="Write a characterization JSON with the measured gamma.")
@_overwrite_option
def characterize_gamma(capture: Path, pattern_path: Path, output: Path | None, overwrite: bool) -> None:
    """Projector gamma from the capture of a sine on a plain matte target (any shape).

    Prints the error of the thesis's candidate gammas and the gamma of least error; the
    response table (camera level against drive level) goes into the JSON when the sine spans
    the whole drive range.
    """
    _check_outputs([output], [capture, pattern_path], overwrite=overwrite)
    image, spec = _measured_capture(capture, pattern_path)
    with _about(capture, f"pattern {pattern_path}"):
        fit = photometry.estimate_gamma(image, spec)
    Console().print(_gamma_table(fit))
    if output is not None:
        photometry.Characterization(spec.projector_size, gamma=fit).save(output)
    table = "a response table" if fit.response is not None else "no response table (the sine is not full range)"
    wrote = f"wrote {output}" if output is not None else "wrote nothing (give -o)"
    click.echo(f"gamma {fit.gamma:.3f} (+/- {fit.spread:.3f} across the frame) from {fit.samples} pixels, "
               f"{table}; {wrote}")


@characterize.command("rolloff", epilog="""\b
Examples:
  sliscan pattern carrier-only --projector 1024x768 --from-characterization char.json -o carriers.png
  sliscan characterize rolloff capture.png --pattern carriers.json --characterization char.json -o rig-char.json
  sliscan pattern composite --projector 1024x768 --from-characterization rig-char.json -o cp.png""")
@click.argument("capture", type=INPUT_FILE)
@click.option("--pattern", "pattern_path", type=INPUT_FILE, required=True,
              help="PatternSpec JSON of the projected carrier-only pattern.")
@click.option("--characterization", type=INPUT_FILE,
              help="Characterization JSON with the measured gamma: models the projected light exactly "
                   "(needed when the carrier-only pattern was not pre-corrected) and is copied into -o.")
@click.option("-o", "--output", type=OUTPUT_FILE, help="Write a characterization JSON with the roll-off.")
@_overwrite_option
def characterize_rolloff(capture: Path, pattern_path: Path, characterization: Path | None,
                         output: Path | None, overwrite: bool) -> None:
    """Each carrier's attenuation by the optics, from the capture of a carrier-only pattern.

    Prints the relative attenuation of every carrier and the weights that compensate it; the
    JSON makes `sliscan pattern composite --from-characterization` apply them.
    """
    _check_outputs([output], [capture, pattern_path, characterization], overwrite=overwrite)
    image, spec = _measured_capture(capture, pattern_path)
    measured = (photometry.Characterization(spec.projector_size) if characterization is None
                else photometry.Characterization.load(characterization))
    gamma = measured.gamma
    response = None if gamma is None else gamma.response or photometry.gamma_response(gamma.gamma)
    with _about(capture, f"pattern {pattern_path}"):
        rolloff = photometry.measure_rolloff(image, spec, response=response)
    result = dataclasses.replace(measured, rolloff=rolloff)
    weights = photometry.compensating_weights(rolloff, spec)
    table = Table(title="carrier roll-off (thesis figs. 3.11-3.12)")
    for name in ("carrier (cycles/width)", "attenuation", "compensating weight"):
        table.add_column(name, justify="right")
    for f, a, w in zip(rolloff.carriers, rolloff.attenuation, weights):
        table.add_row(f"{f:.5g}", f"{a:.3f}", f"{w:.3f}")
    Console().print(table)
    if output is not None:
        result.save(output)
    wrote = f"wrote {output}" if output is not None else "wrote nothing (give -o)"
    click.echo(f"{len(rolloff.carriers)} carriers from {rolloff.samples} pixels, weakest at "
               f"{min(rolloff.attenuation):.0%} of the strongest; {wrote}")


# --------------------------------------------------------------------------------------------
# sliscan simulate
# --------------------------------------------------------------------------------------------


#: A mat5 point grid: points (H, W, 3) in mm, valid (H, W) and texture (H, W).
Grid = tuple[NDArray[np.floating], NDArray[np.bool_], NDArray[np.floating]]


def _load_scene(name: str, rig: simulate.Rig) -> tuple[simulate.Surface, Grid | None]:
    """A built-in scene at the rig's working distance, or a mat5 scan as a surface.

    Returns the surface and, for a mat5 scan, its ``(points, valid, texture)``.
    """
    if name in SCENES:
        return SCENES[name](distance_mm=rig.working_distance_mm), None
    indicator = mat5.mat5_paths(name)[-1]
    if not indicator.exists():
        raise InputError(f"--scene {name}: not a built-in scene ({', '.join(SCENES)}) nor a mat5 prefix "
                         f"({indicator} not found)")
    points, valid, texture = mat5.read_mat5(name)
    with _about(f"{name} (mat5)"):
        return simulate.Mat5Surface(points.astype(np.float64), valid), (points, valid, texture)


@cli.command("simulate", epilog="""\b
Examples:
  sliscan simulate --pattern cp.json --scene sphere --write-rig rig.json -o capture.png
  sliscan simulate --pattern cp.json --scene steps --calibration rig.json --albedo checker -o capture.png
  sliscan simulate --pattern cp.json --scene out/sphere --camera 640x480 --truth truth.npz -o capture.png
  sliscan simulate --pattern cp.json --scene out/sphere --calibration rig.json -o capture.png \\
      --projector-view pv.png --camera-view cv.png
  sliscan simulate --pattern pmp/pmp.json --scene sphere --camera 640x480 -o cap/pmp.png   # cap/pmp_00.png ...
  sliscan simulate --pattern cp.json --scene sphere --motion 20 --velocity 3,0,-2 --spin 4 \\
      --albedo checker --truth take/truth.npz -o take/frame.png          # take/frame_00.png ... + truths""")
@click.option("--pattern", "pattern_path", type=INPUT_FILE, required=True, help="PatternSpec JSON of the pattern.")
@click.option("--scene", default="sphere", show_default=True,
              help=f"{', '.join(SCENES)}, or the PREFIX of a mat5 scan (PREFIXX.byt ...).")
@_calibration_options
@_camera_option(help=f"Camera size of the virtual rig (or of --camera-matrix) [{THESIS_CAMERA[0]}x{THESIS_CAMERA[1]}].")
@click.option("--projector-roll", type=click.FloatRange(min=-44, max=44), default=0.0, show_default=True,
              help="The virtual rig's projector turned about its own axis, degrees (clockwise as the camera sees "
                   "it), as a real mounting leaves it.")
@click.option("--projector-offset", type=float, default=0.0, show_default=True,
              help="The virtual rig's projector moved sideways (to the camera's right), mm, still aimed at the "
                   "working point: a diagonal baseline.")
@click.option("--write-rig", type=OUTPUT_FILE, help="Save the calibration used (JSON).")
@click.option("-o", "--output", type=OUTPUT_FILE, required=True,
              help="Capture image (8-bit PNG); for a multi-frame pattern OUT.png means OUT_00.png, OUT_01.png, "
                   "... one per frame.")
@click.option("--albedo", type=click.Choice(list(ALBEDOS)), default="uniform", show_default=True,
              help="Surface texture: 0.8 everywhere, smooth random 0.15-1, or a 40 mm checker.")
@click.option("--ambient", type=click.FloatRange(min=0), default=0.1, show_default=True,
              help="Ambient light, fraction of the projector's full white.")
@click.option("--gamma", type=POSITIVE, default=2.2, show_default=True, help="Projector gamma.")
@click.option("--blur", type=click.FloatRange(min=0), default=1.0, show_default=True,
              help="Projector and camera blur in focus (Gaussian sigma, px).")
@click.option("--projector-focus", type=POSITIVE, metavar="MM",
              help="A depth of field: the distance along the projector's axis it is focused at (default: in "
                   "focus at every depth); nearer and farther points are blurred by a thin lens of "
                   "--projector-aperture.")
@click.option("--projector-aperture", type=POSITIVE, default=8.0, show_default=True, metavar="MM",
              help="With --projector-focus: the projector lens's aperture diameter.")
@click.option("--camera-focus", type=POSITIVE, metavar="MM",
              help="A depth of field: the distance along the camera's axis it is focused at (default: in focus "
                   "at every depth), with --camera-aperture.")
@click.option("--camera-aperture", type=POSITIVE, default=3.0, show_default=True, metavar="MM",
              help="With --camera-focus: the camera lens's aperture diameter.")
@click.option("--noise/--no-noise", default=True, show_default=True, help="Shot and read noise.")
@click.option("--supersample", type=click.IntRange(min=1), default=3, show_default=True,
              help="Sub-pixels per camera pixel per axis.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the noise and of the smooth albedo.")
@click.option("--truth", type=OUTPUT_FILE, help="Save the ground truth (points, proj, lit, surface, ...) as npz.")
@click.option("--projector-view", type=OUTPUT_FILE,
              help="Save the thesis's projector view (chapter 5) of the scene's points.")
@click.option("--camera-view", type=OUTPUT_FILE, help="Save the thesis's camera view (chapter 5).")
@click.option("--motion", "motion_frames", type=click.IntRange(min=1),
              help="A moving object: N frames of the scene's object (all but its planes) moving by --velocity "
                   "and --spin each frame, centred on the nominal pose; OUT_00.png ... and, with --truth, "
                   "TRUTH_00.npz ... one per frame.")
@click.option("--velocity", type=FLOATS, default="3,0,0", show_default=True,
              help="With --motion: translation per frame, mm (X right, Y down, Z away).")
@click.option("--spin", type=float, default=4.0, show_default=True,
              help="With --motion: rotation per frame about the vertical axis through the working point, degrees.")
@_overwrite_option
def simulate_cmd(pattern_path: Path, scene: str, calibration: Path | None, camera_matrix: Path | None,
                 projector_matrix: Path | None, camera: tuple[int, int] | None, projector_roll: float,
                 projector_offset: float, write_rig: Path | None, output: Path, truth: Path | None, projector_view: Path | None,
                 camera_view: Path | None,
                 motion_frames: int | None, velocity: tuple[float, ...], spin: float, overwrite: bool,
                 **physics: Any) -> None:
    """Render a camera capture of a pattern on a scene with the virtual rig.

    The rig is --calibration (or --camera-matrix/--projector-matrix) if given, else the
    built-in one: the thesis's set-up with the projector 200 mm above the camera, both aimed at
    a point 800 mm away.  Scenes are placed at the rig's working distance.

    A multi-frame pattern (pmp, graycode) gives one capture per frame, OUT_00.png,
    OUT_01.png, ... in the pattern's order, each with its own noise, of one scene under one
    set of conditions (one ground truth).
    """
    if calibration is not None and camera is not None:
        raise click.UsageError("--camera sets the virtual rig's size; a calibration JSON has its own")
    if (projector_roll or projector_offset) and (calibration is not None or camera_matrix is not None
                                                 or projector_matrix is not None):
        raise click.UsageError("--projector-roll and --projector-offset move the virtual rig's projector; a "
                               "calibration has its own")
    mat5_prefix = None if scene in SCENES else Path(scene)
    spec = PatternSpec.load(pattern_path)
    multi = spec.kind in MULTI_FRAME_KINDS
    if multi and (projector_view is not None or camera_view is not None):
        raise click.UsageError("--projector-view and --camera-view need a single-image pattern, not a sequence")
    if motion_frames is not None:
        if multi or projector_view is not None or camera_view is not None:
            raise click.UsageError("--motion renders a single-shot pattern, one capture per frame, without views")
        if len(velocity) != 3:
            raise click.UsageError(f"--velocity takes 3 numbers (mm per frame along X, Y, Z), got {len(velocity)}")
        moving = motion.Motion(motion_frames, (velocity[0], velocity[1], velocity[2]), spin)
        outputs = sequences.indexed_paths(output, motion_frames)
        truths = [] if truth is None else sequences.indexed_paths(truth, motion_frames)
    else:
        outputs = sequences.indexed_paths(output, spec.frame_count) if multi else [output]
        truths = [truth]
    _check_outputs([*outputs, write_rig, *truths, projector_view, camera_view],
                   [pattern_path, calibration, camera_matrix, projector_matrix, *_mat5_files(mat5_prefix)],
                   overwrite=overwrite)
    calib = _load_calibration(calibration, camera_matrix, projector_matrix, camera_size=camera,
                              projector_size=spec.projector_size)
    if calib is None:
        rig = simulate.virtual_rig(camera_size=camera or THESIS_CAMERA, projector_size=spec.projector_size,
                                   projector_roll_deg=projector_roll, projector_offset_mm=projector_offset)
    else:
        source = _calibration_source(calibration, camera_matrix, projector_matrix)
        _check_projector(spec, pattern_path, calib, source)
        with _about(source):
            rig = simulate.Rig(calib)
    surface, grid = _load_scene(scene, rig)
    conditions = _conditions(**physics)
    projected = None if multi else patterns.render_pattern(spec)
    if motion_frames is not None:
        return _simulate_motion(rig, surface, projected, moving, conditions, outputs=outputs, truths=truths,
                                write_rig=write_rig, scene=scene)
    with _progress(2) as stage:
        stage("render")
        if projected is None:
            capture = simulate.render_sequence(rig, surface, sequences.render_frames(spec), conditions)
            images = capture.images
        else:
            capture = simulate.render(rig, surface, projected, conditions)
            images = capture.image[None]
        stage("write")
        write_images(outputs, images)
        written = [str(output) if len(outputs) == 1 else f"{outputs[0]} .. {outputs[-1]}"]
        if write_rig is not None:
            rig.calibration.save(write_rig)
            written.append(str(write_rig))
        if truth is not None:
            _save_truth(truth, capture.truth)
            written.append(str(truth))
        if grid is None:  # the views of an analytic scene splat its ground-truth points
            t = capture.truth
            grid = (t.points, t.surface, np.nan_to_num(t.albedo))
        views: list[tuple[Path | None, Callable[..., NDArray[np.float32]]]] = [
            (projector_view, simulate.projector_view), (camera_view, simulate.camera_view)]
        for path, view in views:
            if path is not None:
                write_image(path, view(rig, *grid, projected))
                written.append(str(path))
    w, h = rig.camera.size
    lit = float(np.mean(capture.truth.lit))
    what = f"{len(outputs)} {w}x{h} captures" if multi else f"{w}x{h} capture"
    click.echo(f"wrote {', '.join(written)}: {what} of the {scene} scene ({lit:.0%} of pixels lit)")


def _simulate_motion(rig: simulate.Rig, surface: simulate.Surface, projected: NDArray[np.float32],
                     moving: motion.Motion, conditions: simulate.Conditions, *, outputs: Sequence[Path],
                     truths: Sequence[Path], write_rig: Path | None, scene: str) -> None:
    """`sliscan simulate --motion`: render and write the frames (and truths) one at a time."""
    if write_rig is not None:
        rig.calibration.save(write_rig)
    lit = []
    with _progress(moving.frames) as stage:
        frames = motion.render_motion(rig, surface, projected, moving, conditions)
        for k, capture in enumerate(frames):
            stage(f"frame {k + 1}/{moving.frames}")
            write_image(outputs[k], capture.image)
            if truths:
                _save_truth(truths[k], capture.truth)
            lit.append(float(np.mean(capture.truth.lit)))
    written = [f"{outputs[0]} .. {outputs[-1]}", *([f"{truths[0]} .. {truths[-1]}"] if truths else []),
               *([str(write_rig)] if write_rig is not None else [])]
    w, h = rig.camera.size
    click.echo(f"wrote {', '.join(written)}: {moving.frames} {w}x{h} captures of the moving {scene} scene "
               f"({min(lit):.0%}-{max(lit):.0%} of pixels lit)")


# --------------------------------------------------------------------------------------------
# sliscan scan
# --------------------------------------------------------------------------------------------

#: Below this fraction of the frame decoded, `sliscan scan` warns (it still writes the points).
LOW_YIELD = 0.01

#: File name endings `sliscan scan` takes from a folder.
IMAGE_SUFFIXES = (".png", ".bmp", ".tif", ".tiff", ".jpg", ".jpeg", ".pgm", ".ppm")


def _capture_files(args: Sequence[Path]) -> list[Path]:
    """The capture files named on the command line, in order: a file as given, a folder's image
    files (`IMAGE_SUFFIXES`) and a glob's matches each sorted by name."""
    files: list[Path] = []
    for arg in args:
        if arg.is_dir():
            found = sorted(p for p in arg.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
            if not found:
                raise InputError(f"{arg}: the folder holds no image files ({', '.join(IMAGE_SUFFIXES)})")
        elif any(c in str(arg) for c in "*?["):
            found = sorted(Path(p) for p in glob.glob(str(arg)))
            if not found:
                raise InputError(f"{arg}: matches no files")
        else:
            found = [arg]
        files += found
    return files


def _read_frames(files: Sequence[Path]) -> list[NDArray[np.float32]]:
    """Read capture files; all must have the size of the first."""
    frames = [read_image(files[0])]
    for path in files[1:]:
        frames.append(read_image(path))
        if frames[-1].shape != frames[0].shape:
            (h0, w0), (h, w) = frames[0].shape, frames[-1].shape
            raise InputError(f"{path}: the frame is {w}x{h} but {files[0]} is {w0}x{h0}")
    return frames


@dataclasses.dataclass(frozen=True, eq=False)
class _ScanInputs:
    """A scan's checked inputs: the capture files, frames and pattern, the calibration and a scanner."""

    files: list[Path]
    frames: list[NDArray[np.float32]]
    capture: str
    pattern_path: Path
    spec: PatternSpec
    calib: Calibration
    source: str
    scanner: Scanner


def _scan_inputs(files: list[Path], pattern_path: Path, calibration: Path | None, camera_matrix: Path | None,
                 projector_matrix: Path | None, *, method: str, choices: ScanChoices = ScanChoices(),
                 spec: PatternSpec | None = None) -> _ScanInputs:
    """Read and check what `sliscan scan` and `sliscan report` scan: the pattern (`spec` if
    already read), the frames (one for a composite pattern), the calibration (its camera of the
    frames' size, its projector the pattern's), and build the scanner."""
    spec = PatternSpec.load(pattern_path) if spec is None else spec
    if spec.kind not in MULTI_FRAME_KINDS and len(files) != 1:
        raise InputError(f"{pattern_path}: a {spec.kind} pattern takes one capture, got {len(files)}")
    with _about(pattern_path):
        options = choices.scanner_options(spec)
    frames = _read_frames(files)
    capture = str(files[0]) if len(files) == 1 else f"{files[0]} .. {files[-1]}"
    h, w = frames[0].shape
    calib, source = _scan_calibration(spec, pattern_path, (calibration, camera_matrix, projector_matrix), (w, h),
                                      capture)
    with _about(source):
        scanner = Scanner(spec, calib, method=method, **options)
    return _ScanInputs(files, frames, capture, pattern_path, spec, calib, source, scanner)


def _write_scan_report(path: Path, inputs: _ScanInputs, result: ScanResult, stages: ScanStages,
                       timings: dict[str, float], *, truth: simulate.GroundTruth | None = None,
                       max_points: int = viewer.MESH_BUDGET) -> None:
    """Write the HTML report of a scan (`sliscan.report.scan_page`)."""
    spec = inputs.spec
    pattern = (f"{spec.kind}, {sequences.describe_frames(spec)}" if spec.kind in MULTI_FRAME_KINDS
               else _describe(spec))
    facts = {"capture": inputs.capture, "pattern": f"{inputs.pattern_path}: {pattern}", "calibration": inputs.source}
    if spec.kind not in MULTI_FRAME_KINDS:
        facts["demodulator"] = inputs.scanner.method
        facts["stripe tilt"] = (f"the projector's {spec.orientation} cross the camera's at up to "
                                f"{stripe_tilt_deg(inputs.calib, spec.orientation):.1f} degrees "
                                f"(keep under {MAX_STRIPE_TILT_DEG:g})")
        facts["camera blur"] = _describe_camera_blur(inputs, stages)
    frames = np.stack(inputs.frames)
    page = report_module.scan_page(report_module.ScanReport(
        frames=frames, spec=spec, calibration=inputs.calib, result=result, stages=stages,
        method=inputs.scanner.method, truth=truth, timings=timings, facts=facts, max_points=max_points))
    report_module.write_page(path, page)


def _describe_camera_blur(inputs: _ScanInputs, stages: ScanStages) -> str:
    """The report's line on the camera's blur: what the capture's albedo edges measure
    (`sliscan.demodulate.camera_blur`) and what the scan's albedo steps assumed."""
    measured = camera_blur(inputs.frames[0], inputs.spec, stages.carriers)
    if inputs.scanner.camera_blur is not None:
        used = f"the albedo steps found for {inputs.scanner.camera_blur:g} px (--camera-blur)"
    elif inputs.scanner.method == "baseband":
        used = f"the albedo steps found for {STEP_SPREAD:g} px (baseband)"
    elif steps_blur(measured) != STEP_SPREAD:
        used = "the albedo steps found for it"
    else:
        used = f"the albedo steps found for {STEP_SPREAD:g} px"
    seen = "not told (too few tall albedo edges)" if measured is None else f"{measured:.2f} px on the albedo edges"
    return f"{seen}; {used}"


#: The calibration options of `sliscan scan`: --calibration, --camera-matrix, --projector-matrix.
CalibrationArgs = tuple[Path | None, Path | None, Path | None]


def _scan_calibration(spec: PatternSpec, pattern_path: Path, args: CalibrationArgs, size: tuple[int, int] | None,
                      capture: object) -> tuple[Calibration, str]:
    """The calibration of a scan and how to name it, checked against the capture's ``(W, H)``
    `size` (None: unknown) and the pattern's projector."""
    calib = _load_calibration(*args, camera_size=size, projector_size=spec.projector_size)
    if calib is None:
        raise click.UsageError("give --calibration rig.json, or --camera-matrix and --projector-matrix")
    source = _calibration_source(*args)
    if size is not None and calib.camera.size != size:
        (w, h), (cw, ch) = size, calib.camera.size
        raise InputError(f"{capture}: the capture is {w}x{h} but the camera of {source} is {cw}x{ch}")
    _check_projector(spec, pattern_path, calib, source)
    _warn_rig(spec, pattern_path, calib, source)
    return calib, source


#: Where the camera sits from the projector when the projector lines that move with depth are
#: its rows, or its columns (`baseline_direction`).
_STRAIGHT_FROM = {"rows": "above or below", "columns": "beside"}


def _warn_rig(spec: PatternSpec, pattern_path: Path, calib: Calibration, source: object) -> None:
    """Warnings on stderr where the rig will not scan a single-shot pattern well: its camera
    does not resolve the finest carrier (`carrier_period_px`), the pattern codes the projector
    lines that run along the baseline (they do not move with depth), or `_warn_geometry`."""
    if spec.kind in MULTI_FRAME_KINDS:
        return
    period = carrier_period_px(spec, calib)
    if period < MIN_CARRIER_PERIOD_PX:
        click.echo(f"warning: {pattern_path}: its finest carrier ({max(spec.all_carriers):g} cycles per "
                   f"{spec.orthogonal_lines} projector px) spans {period:.1f} camera px per period with {source}; "
                   f"under {MIN_CARRIER_PERIOD_PX:g} the camera does not resolve it: use coarser carriers (fewer "
                   "bits, no --phase) or more camera pixels across the projected area", err=True)
    across = baseline_direction(calib)
    if spec.orientation != across:
        click.echo(f"warning: {pattern_path}: the pattern codes the projector's {spec.orientation}, but with the "
                   f"camera {_STRAIGHT_FROM[across]} the projector ({source}) it is the projector's {across} that change with "
                   f"depth along a camera ray: make the pattern with --orientation {across}", err=True)
        return
    _warn_geometry(calib, spec.orientation, source)


def _warn_geometry(calib: Calibration, orientation: str, source: object) -> None:
    """Warnings on stderr where the rig's baseline runs off the coded direction by more than
    `MAX_BASELINE_ANGLE_DEG` (`baseline_angle_deg`: depth moves the carriers) or its coded
    lines cross the camera's by more than `MAX_STRIPE_TILT_DEG` (`stripe_tilt_deg`): single-shot
    patterns lose points or accuracy there."""
    angle = baseline_angle_deg(calib, orientation)
    if angle > MAX_BASELINE_ANGLE_DEG:
        straight = _STRAIGHT_FROM[orientation]
        click.echo(f"warning: {source}: the projector sits {angle:.0f} degrees off straight {straight} the camera, "
                   f"so depth moves the carriers: scans of surfaces whose depth varies lose points beyond "
                   f"{MAX_BASELINE_ANGLE_DEG:g} degrees (the virtual rig's sphere 3 points less complete at 18 with the "
                   f"stripe pattern, 6 with the phase pattern): move the projector straight {straight} the camera",
                   err=True)
    tilt = stripe_tilt_deg(calib, orientation)
    if tilt > MAX_STRIPE_TILT_DEG:
        click.echo(f"warning: {source}: the projector's {orientation} cross the camera's {orientation} at up to "
                   f"{tilt:.1f} degrees; single-shot scans lose accuracy beyond {MAX_STRIPE_TILT_DEG:g} (median error "
                   "about 1.7x at 5 degrees, 3x at 10 on the virtual rig): turn the projector or the camera about its "
                   "axis", err=True)


@contextlib.contextmanager
def _frames_progress(total: int) -> Iterator[Callable[[dict[str, Any]], None]]:
    """A progress bar over the frames of a batch (frames done, frames per second, failures),
    on stderr and only on a terminal.  Yields ``done(row)``: call it with each summary row."""
    console = Console(stderr=True)
    progress = Progress(SpinnerColumn(), TextColumn("frames"), BarColumn(), MofNCompleteColumn(),
                        TextColumn("{task.fields[fps]:5.1f} frames/s  {task.fields[failed]} failed"),
                        TimeElapsedColumn(), console=console, transient=True, disable=not console.is_terminal)
    task = progress.add_task("frames", total=total or None, fps=0.0, failed=0)
    t0 = time.perf_counter()
    failed = 0

    def done(row: dict[str, Any]) -> None:
        nonlocal failed
        failed += row["status"] == "failed"
        progress.advance(task)
        elapsed = time.perf_counter() - t0
        completed = progress.tasks[0].completed
        progress.update(task, fps=completed / elapsed if elapsed > 0 else 0.0, failed=failed)

    with progress:
        yield done


def _scan_batch(files: Sequence[Path], spec: PatternSpec, pattern_path: Path, calibration: CalibrationArgs, *,
                method: str, choices: ScanChoices, out: Path | None, formats: Sequence[str],
                workers: int | None,
                scheduler: str | None, resume: bool, report: Path | None, overwrite: bool) -> int:
    """`sliscan scan` of a batch of single-shot frames (`sliscan.batch`), with its HTML `report`
    if asked; returns the exit status."""
    if out is None:
        raise click.UsageError("several single-shot frames (or a video) are a batch: give --out DIR")
    if resume and overwrite:
        raise click.UsageError("--resume keeps the outputs in --out, --overwrite replaces them: give one")
    if workers is not None and scheduler is not None:
        raise click.UsageError("--workers sizes a local cluster; a --scheduler cluster has its own workers")
    inputs = {Path(os.path.realpath(p)) for p in [*files, pattern_path, *calibration] if p is not None}
    if Path(os.path.realpath(out)) in inputs:
        raise InputError(f"--out {out}: is an input")
    earlier = out.is_dir() and any(out.glob("frame_*")) or (out / batch.SUMMARY_JSON).exists()
    if earlier and not (resume or overwrite):
        raise InputError(f"--out {out}: holds the outputs of an earlier batch (use --resume or --overwrite)")
    if report is not None:
        _check_outputs([report], [*files, pattern_path, *calibration], overwrite=overwrite)
        require_report()
    calib, source = _scan_calibration(spec, pattern_path, calibration, batch.first_frame_size(files)
                                      if calibration[0] is None else None, files[0])
    with _about(source):
        job = batch.Job.create(spec, calib, method=method, formats=formats, choices=choices)
    total = batch.count_frames(files)
    skip = (lambda index: batch.outputs_exist(out, index, job.formats)) if resume else (lambda index: False)
    with _frames_progress(total) as done, batch.dask_client(workers=workers, scheduler=scheduler) as client:
        totals = batch.run_batch(client, job, batch.iter_frames(files, skip), out, resume=resume, on_frame=done)
    ok, failed, skipped = (totals.count(s) for s in ("ok", "failed", "skipped"))
    written = [f"{out}/frame_*", str(out / batch.SUMMARY_CSV)]
    if report is not None:
        summary = out / batch.SUMMARY_JSON
        rows = report_module.read_batch_summary(summary)
        report_module.write_page(report, report_module.batch_page(rows, facts={"summary": str(summary)}))
        written.append(str(report))
    counts = ", ".join([f"{ok} frames scanned", *([f"{failed} failed"] if failed else []),
                        *([f"{skipped} already done"] if skipped else [])])
    click.echo(f"{counts} in {totals.seconds:.1f} s ({totals.frames_per_second:.2f} frames/s); "
               f"wrote {', '.join(written)}")
    if failed:
        first = next(r for r in totals.rows if r["status"] == "failed")
        click.echo(f"error: {failed} of {len(totals.rows)} frames failed (see {out / batch.SUMMARY_CSV}); "
                   f"the first: {first['error']}", err=True)
        return 1
    return 0


def _scan_sources(captures: Sequence[Path], pattern_path: Path | None) -> tuple[list[Path], PatternSpec, Path]:
    """The capture files and pattern of `sliscan scan`, and the file the pattern came from:
    `--pattern`, or an acquisition record given alone as CAPTURES."""
    if len(captures) == 1 and acquire.is_record(captures[0]):
        if pattern_path is not None:
            raise click.UsageError(f"{captures[0]} holds its pattern: leave out --pattern")
        record = acquire.read_record(captures[0])
        return record.files, record.spec, captures[0]
    if pattern_path is None:
        raise click.UsageError("give --pattern PATTERN.json (or an acquisition record, which holds its pattern)")
    return _capture_files(captures), PatternSpec.load(pattern_path), pattern_path


@cli.command(epilog="""\b
Examples:
  sliscan scan capture.png --pattern cp.json --calibration rig.json --mat5 out/sphere --ply sphere.ply
  sliscan scan capture.png --pattern cp.json --camera-matrix cam.txt --projector-matrix proj.txt --npz scan.npz
  sliscan scan capture.png --pattern cp.json --calibration rig.json --method bandpass --ply sphere.ply
  sliscan scan capture.png --pattern cp.json --calibration rig.json --timings             # ms per stage
  sliscan scan capture.png --pattern cp.json --calibration rig.json --ply s.ply --report scan.html
  sliscan scan cap/ --pattern pmp/pmp.json --calibration rig.json --ply sphere.ply        # a folder
  sliscan scan 'cap/pmp_*.png' --pattern pmp/pmp.json --calibration rig.json --npz s.npz  # a glob
  sliscan scan gc_00.png gc_01.png ... gc_41.png --pattern gc.json --calibration rig.json --ply s.ply
  sliscan scan acq/acquisition.json --calibration rig.json --ply s.ply   # what sliscan acquire took
\b
Batches of single-shot frames (one output per frame, named by frame index, and a summary):
  sliscan scan video/ --pattern cp.json --calibration rig.json --out scans --format ply --format npz
  sliscan scan take.avi --pattern cp.json --calibration rig.json --out scans --workers 2
  sliscan scan take.avi --pattern cp.json --calibration rig.json --out scans --resume
  sliscan scan 'cap/*.png' --pattern cp.json --calibration rig.json --out scans --scheduler tcp://head:8786""")
@click.argument("captures", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--pattern", "pattern_path", type=INPUT_FILE,
              help="PatternSpec JSON of the projected pattern (not with an acquisition record, which holds it).")
@_calibration_options
@click.option("--mat5", "mat5_prefix", type=click.Path(path_type=Path),
              help="Write PREFIX{X,Y,Z}.byt, PREFIXC.bmp, PREFIXI.bmp.")
@click.option("--ply", type=OUTPUT_FILE, help="Write the valid points as a binary PLY point cloud.")
@click.option("--npz", type=OUTPUT_FILE, help="Write every array of the scan to one npz file.")
@click.option("--method", type=click.Choice(list(METHODS)), default="window", show_default=True,
              help="Demodulator: sliscan's sliding window, the thesis's Butterworth band-pass (3.4), or baseband: "
                   "the real-time path (decimated envelopes, per-pixel decisions; stripe patterns only).")
@_scan_choices_options
@click.option("--timings", is_flag=True, help="Also print the milliseconds of every stage, one per line.")
@click.option("--report", type=OUTPUT_FILE,
              help="Also write an HTML report of every stage with a 3D view (needs sliscan[report]; see sliscan report); "
                   "of a batch: the per-frame table and plots.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Batch: scan every single-shot frame (image files, videos) into this folder: "
                   "frame_000000.npz ..., summary.csv and summary.json.")
@click.option("--format", "formats", type=click.Choice(batch.FORMATS), multiple=True,
              help="Batch: output format(s) of each frame (repeat the option for several)  [default: npz]")
@click.option("--workers", type=click.IntRange(min=1),
              help="Batch: local Dask worker processes [default: this machine's CPUs].")
@click.option("--scheduler", metavar="tcp://HOST:PORT",
              help="Batch: run on this Dask distributed cluster instead of a local one.")
@click.option("--resume", is_flag=True, help="Batch: skip the frames whose outputs are all in --out.")
@_overwrite_option
def scan(captures: tuple[Path, ...], pattern_path: Path | None, calibration: Path | None, camera_matrix: Path | None,
         projector_matrix: Path | None, mat5_prefix: Path | None, ply: Path | None, npz: Path | None,
         method: str, choices: ScanChoices, timings: bool, report: Path | None,
         out_dir: Path | None, formats: tuple[str, ...], workers: int | None, scheduler: str | None, resume: bool,
         overwrite: bool) -> int:
    """Reconstruct 3D points from a camera capture: one image of a composite pattern, or the
    frames of a multi-frame pattern (pmp, graycode) in the order its JSON lists them, or a
    batch of single-shot frames.

    CAPTURES are image files, folders (their image files, sorted by name) or quoted globs
    (sorted by name), taken in the order given: name frames with zero-padded numbers; or the
    acquisition.json record of `sliscan acquire` or `sliscan live --record` (its frames, with
    the pattern it holds: no --pattern).  Every
    capture must have the calibrated camera's size.  A --camera-matrix/--projector-matrix
    pair takes its sizes from the capture and the pattern.  Writes exactly the outputs asked
    for (creating their folders) and prints the number of points, the completeness of the frame
    and the seconds per stage.

    \b
    A single-shot pattern with several frames, a video file or --out is a batch: every frame
    (of every video, read frame by frame) becomes frame_NNNNNN.{npz,ply} or frame_NNNNNN_{X,Y,Z}
    .byt... in --out, scanned on a Dask cluster (local worker processes, or --scheduler).  A
    frame that fails is recorded in summary.csv/summary.json and the others go on.  Exit
    status 0 when every frame succeeded, 1 when some failed.
    """
    files, spec, pattern_path = _scan_sources(captures, pattern_path)
    batch_options = out_dir is not None or formats or workers is not None or scheduler is not None or resume
    if spec.kind not in MULTI_FRAME_KINDS and (len(files) > 1 or batch_options or batch.is_video(files[0])):
        if mat5_prefix is not None or ply is not None or npz is not None or timings:
            raise click.UsageError("a batch writes into --out DIR in the --format(s) asked for; "
                                   "--mat5, --ply, --npz and --timings are for one capture")
        return _scan_batch(files, spec, pattern_path, (calibration, camera_matrix, projector_matrix),
                           method=method, choices=choices, out=out_dir,
                           formats=formats or ("npz",),
                           workers=workers, scheduler=scheduler, resume=resume, report=report, overwrite=overwrite)
    if batch_options:
        raise click.UsageError("--out, --format, --workers, --scheduler and --resume are for batches of "
                               "single-shot frames")
    _check_outputs([*_mat5_files(mat5_prefix), ply, npz, report], [*files, pattern_path, calibration, camera_matrix,
                                                                     projector_matrix], overwrite=overwrite)
    if report is not None:
        require_report()
    with _progress(3 + (report is not None)) as stage:
        stage("read")
        t0 = time.perf_counter()
        inputs = _scan_inputs(files, pattern_path, calibration, camera_matrix, projector_matrix, method=method,
                              choices=choices, spec=spec)
        frames, capture, scanner = inputs.frames, inputs.capture, inputs.scanner
        h, w = frames[0].shape
        stage("scan")
        t1 = time.perf_counter()
        with _about(capture, f"pattern {pattern_path}"):
            result, stages = scanner.scan_stages(frames if spec.kind in MULTI_FRAME_KINDS else frames[0])
        stage("write")
        t2 = time.perf_counter()
        written = _write_scan(result, mat5_prefix=mat5_prefix, ply=ply, npz=npz)
        t3 = time.perf_counter()
        if report is not None:
            stage("report")
            _write_scan_report(report, inputs, result, stages, {"read": t1 - t0, **result.timings})
            written.append(str(report))
    n = int(result.valid.sum())
    if n < LOW_YIELD * result.valid.size:
        click.echo(f"warning: {capture}: only {n / result.valid.size:.2%} of the frame decoded: check the focus, the "
                   f"exposure and that the object is in the projector's light", err=True)
    stages = {"read": t1 - t0, **{k: v for k, v in result.timings.items() if k != "total"}, "write": t3 - t2}
    times = ", ".join(f"{k} {v:.2f}" for k, v in stages.items())
    wrote = f"wrote {', '.join(written)}" if written else "wrote nothing (give --mat5, --ply, --npz or --report)"
    click.echo(f"{n} points ({n / result.valid.size:.1%} of the {w}x{h} frame) in {t3 - t0:.2f} s "
               f"({times}); {wrote}")
    if timings:
        for name, seconds in {**stages, "total": t3 - t0}.items():
            click.echo(f"  {name:12s} {1e3 * seconds:10.1f} ms")


# --------------------------------------------------------------------------------------------
# sliscan calibrate
# --------------------------------------------------------------------------------------------


@cli.command(epilog="""\b
Examples:
  sliscan calibrate G.byt --camera-size 2592x1944 --projector 1024x768 -o rig.json
  sliscan calibrate G.txt --camera-size 2592x1944 --projector 1024x768 --method lstsq -o rig.json \\
      --cam-txt cam.txt --proj-txt proj.txt
  sliscan calibrate grid.csv --camera-size 640x480 --projector 1024x768 --pixels -o rig.json
\b
From captured images instead of measured points, use the command of your target (each has
the options it needs, and writes the same calibration JSON):
  sliscan calibrate-target cap/ --pattern pmp.json --target target.json -o rig.json   # 3-D circle target
  sliscan calibrate-board pose_*/ --pattern gc.json --board 9x7 --square 25 -o rig.json  # planar board""")
@click.argument("g_file", nargs=-1, required=True, metavar="G_FILE", type=click.Path(path_type=Path))
@_camera_option(help="Camera image size, e.g. 2592x1944 (required).")
@_projector_option(help="Projector size, e.g. 1024x768 (required).")
@click.option("--method", type=click.Choice(["svd", "lstsq"]), default="svd", show_default=True,
              help="DLT by SVD (thesis 4.3) or by least squares with m34 = 1 (4.4).")
@click.option("--pixels", is_flag=True, help="The G file's projector columns are pixels, not phases in radians.")
@click.option("-o", "--output", type=OUTPUT_FILE, help="Calibration JSON to write (required).")
@click.option("--cam-txt", type=OUTPUT_FILE, help="Also write the camera matrix as text (the thesis's cam.txt).")
@click.option("--proj-txt", type=OUTPUT_FILE, help="Also write the projector matrix as text (proj.txt).")
@_overwrite_option
def calibrate(g_file: Any, camera: tuple[int, int] | None, projector: tuple[int, int] | None, method: str,
              pixels: bool, output: Path | None, cam_txt: Path | None, proj_txt: Path | None, overwrite: bool) -> None:
    """Calibrate camera and projector from a calibration grid (a G file, thesis 4.3-4.4).

    G_FILE holds one point per row: Xw Yw Zw (mm), xc yc (camera pixels), xp yp (projector
    phases in radians, x = phase * size / 2pi, or pixels with --pixels); binary .byt (float32)
    or text.  Prints the reprojection residuals.  Captured calibration images go to
    calibrate-target or calibrate-board (see below).
    """
    images = [p for p in g_file if p.is_dir() or p.suffix.lower() in IMAGE_SUFFIXES or any(c in str(p) for c in "*?[")]
    if images or len(g_file) > 1:
        raise InputError(f"{(images or g_file)[0]}: captured images, not a G file; calibrate from images with sliscan "
                         "calibrate-board (a planar board in several poses) or sliscan calibrate-target (a 3-D circle "
                         "target)")
    g_file = g_file[0]
    # Checked here, after the images, so that images get the message above whatever else is missing.
    for value, option in ((camera, "--camera-size"), (projector, "--projector"), (output, "--output")):
        if value is None:
            raise click.UsageError(f"Missing option '{option}'.")
    _check_outputs([output, cam_txt, proj_txt], [g_file], overwrite=overwrite)
    rows = premat5.read_g(g_file)
    with _about(g_file):
        calib = calibrate_points(rows, camera, projector, method=method, phases=not pixels)
    calib.save(output)
    written = [str(output)]
    for path, device in ((cam_txt, calib.camera), (proj_txt, calib.projector)):
        if path is not None:
            write_matrix_txt(path, device.matrix)
            written.append(str(path))
    click.echo(f"wrote {', '.join(written)}: {method} DLT from {len(rows)} points; reprojection "
               f"{_residual_summary(calib)}")
    _warn_geometry(calib, baseline_direction(calib), output)


# --------------------------------------------------------------------------------------------
# sliscan calibrate-target, calibrate-board: calibration from captured images (issue 5)
# --------------------------------------------------------------------------------------------


def _sequence_spec(pattern_path: Path) -> PatternSpec:
    """A multi-frame PatternSpec coding both projector directions (calibration needs xp and yp)."""
    spec = PatternSpec.load(pattern_path)
    if spec.kind not in MULTI_FRAME_KINDS or spec.orientation != "both":
        raise InputError(f"{pattern_path}: calibration needs a pmp or graycode sequence with orientation 'both' "
                         f"(columns and rows), got {spec.kind} {spec.orientation}")
    return spec


def _subpixel(spec: PatternSpec) -> bool:
    """Whether the decoded maps are sub-pixel (PMP, Gray code + phase): interpolate them directly."""
    return spec.kind == "pmp" or spec.steps > 0


def _residual_summary(calib: Calibration) -> str:
    res = calib.extra["residuals"]
    return "; ".join(f"{name} RMS {r['rms_px']:.3g} px, max {r['max_px']:.3g} px" for name, r in res.items())


@cli.command("calibrate-target", epilog="""\b
Examples:
  sliscan calibrate-target cap/ --pattern pmp/pmp.json --target target.json -o rig.json
  sliscan calibrate-target 'cap/gc_*.png' --pattern gc/gc.json --target target.json -o rig.json \\
      --g-file G.byt --method lstsq --cam-txt cam.txt --proj-txt proj.txt
\b
target.json: {"circles": [[Xw, Yw, Zw], ...], "normals": [[nx, ny, nz], ...], "radius_mm": 10}
(centres in mm, at least 6, not all in one plane; normals and radius optional, for the
perspective correction of the circle centres).""")
@click.argument("captures", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--pattern", "pattern_path", type=INPUT_FILE, required=True,
              help="PatternSpec JSON of the sequence (pmp or graycode, orientation both).")
@click.option("--target", "target_path", type=INPUT_FILE, required=True,
              help="The target's circle centres (JSON, see below).")
@click.option("--method", type=click.Choice(["svd", "lstsq"]), default="svd", show_default=True,
              help="DLT by SVD (thesis 4.3) or by least squares with m34 = 1 (4.4).")
@click.option("-o", "--output", type=OUTPUT_FILE, required=True, help="Calibration JSON to write.")
@click.option("--g-file", type=OUTPUT_FILE, help="Also write the calibration grid (G file: .byt binary, else text).")
@click.option("--cam-txt", type=OUTPUT_FILE, help="Also write the camera matrix as text (the thesis's cam.txt).")
@click.option("--proj-txt", type=OUTPUT_FILE, help="Also write the projector matrix as text (proj.txt).")
@click.option("--plot", type=OUTPUT_FILE,
              help="Also write a PNG of the camera and projector residuals per circle (needs sliscan[plot]).")
@click.option("--residuals", "residuals_path", type=OUTPUT_FILE,
              help="Also write every circle's residual vectors as JSON (for sliscan report --residuals).")
@_overwrite_option
def calibrate_target_cmd(captures: tuple[Path, ...], pattern_path: Path, target_path: Path, method: str,
                         output: Path, g_file: Path | None, cam_txt: Path | None, proj_txt: Path | None,
                         plot: Path | None, residuals_path: Path | None, overwrite: bool) -> None:
    """Calibrate camera and projector from one capture of a 3-D circle target (thesis 4.0-4.4).

    CAPTURES are the frames of the sequence (files, folders or quoted globs, in the order of
    the pattern's JSON).  The circles are found in the white (or mean) image and matched to the
    target's circles, the projector coordinates are read at their centres, and both devices are
    calibrated by the DLT.  Prints the reprojection residuals.
    """
    files = _capture_files(captures)
    _check_outputs([output, g_file, cam_txt, proj_txt, plot, residuals_path], [*files, pattern_path, target_path],
                   overwrite=overwrite)
    if plot is not None:
        require_matplotlib()
    spec = _sequence_spec(pattern_path)
    target = CircleTarget.load(target_path)
    _run_calibrate_target(files, spec, pattern_path, target, target_path, method=method, output=output, g_file=g_file,
                          cam_txt=cam_txt, proj_txt=proj_txt, plot=plot, residuals_path=residuals_path)


def _save_residuals(residuals: Residuals, plot: Path | None, path: Path | None, *, title: str) -> list[str]:
    """Write a calibration's residual plot (`plot`, PNG) and residuals (`path`, JSON) where asked;
    returns the files written."""
    written = []
    if plot is not None:
        plot_residuals(plot, residuals, title=title)
        written.append(str(plot))
    if path is not None:
        residuals.save(path)
        written.append(str(path))
    return written


def _run_calibrate_target(files: Sequence[Path], spec: PatternSpec, pattern_path: Path, target: CircleTarget,
                          target_path: Path, *, method: str, output: Path, g_file: Path | None = None,
                          cam_txt: Path | None = None, proj_txt: Path | None = None, plot: Path | None = None,
                          residuals_path: Path | None = None) -> None:
    """`calibrate-target` once its inputs are checked (also the end of `sliscan acquire
    --calibration-target`): decode, calibrate, write, print."""
    capture = files[0] if len(files) == 1 else f"{files[0]} .. {files[-1]}"
    with _progress(3) as stage:
        stage("read")
        frames = _read_frames(files)
        stage("decode")
        with _about(capture, f"pattern {pattern_path}"):
            maps = sequences.decode_frames(frames, spec)
        stage("calibrate")
        with _about(capture, f"target {target_path}"):
            calib, rows = calibrate_target(maps, target, spec.projector_size, method=method,
                                           interpolate=_subpixel(spec))
        calib.save(output)
    written = [str(output)]
    if g_file is not None:
        premat5.write_g(g_file, rows)
        written.append(str(g_file))
    for path, device in ((cam_txt, calib.camera), (proj_txt, calib.projector)):
        if path is not None:
            write_matrix_txt(path, device.matrix)
            written.append(str(path))
    residuals = target_residuals(calib, rows, label=target_path.name)
    written += _save_residuals(residuals, plot, residuals_path,
                               title=f"calibrate-target: {method} DLT, {len(rows)} circles")
    click.echo(f"wrote {', '.join(written)}: {method} DLT from {len(rows)} circles (perspective bias "
               f"{calib.extra['perspective_bias_px']:.2g} px corrected); reprojection {_residual_summary(calib)}")
    _warn_geometry(calib, baseline_direction(calib), output)


def _board_table(calib: Calibration, poses: Sequence[Path]) -> Table:
    """Per-view reprojection RMS and the geometry of the triangulated board points."""
    table = Table(title="board views")
    for name in ("pose", "camera RMS px", "projector RMS px", "points", "flatness RMS", "spacing error"):
        table.add_column(name, justify="left" if name == "pose" else "right")
    for k, (pose, view) in enumerate(zip(poses, calib.extra["views"])):
        flag = " (outlier)" if k in calib.extra["outlier_views"] else ""
        table.add_row(f"{pose.name}{flag}", f"{view['camera_rms_px']:.3f}", f"{view['projector_rms_px']:.3f}",
                      f"{view['projector_corners']}/{view['corners']}", f"{view['planarity_rms']:.3g}",
                      f"{view['spacing_error']:+.2%}")
    return table


#: The options that describe a planar board beside its size (calibrate-board, acquire).
_board_options = _options(
    click.option("--square", type=POSITIVE, help="Chessboard: the square size (mm, or any unit: the unit of the "
                                                 "world coordinates)."),
    click.option("--circles", type=click.Choice(["symmetric", "asymmetric"]),
                 help="The board is an OpenCV circle grid (dark circles on white), symmetric or asymmetric, instead "
                      "of a chessboard."),
    click.option("--spacing", type=POSITIVE,
                 help="Circle grid: distance between neighbouring circles of a row (symmetric) or between rows "
                      "(asymmetric: OpenCV's spacing, circles of a row 2 x SPACING apart), in mm."),
    click.option("--radius", type=POSITIVE,
                 help="Circle grid: the circles' radius in mm, to correct the perspective bias of their centres."),
)


def _board(size: tuple[int, int], square: float | None, circles: str | None, spacing: float | None,
           radius: float | None, *, size_option: str = "--board") -> Board:
    """The `Board` of the board options, checked: a chessboard takes --square, a circle grid
    (--circles) --spacing and optionally --radius."""
    if circles is None:
        if square is None or spacing is not None or radius is not None:
            raise click.UsageError(f"a chessboard ({size_option} with no --circles) takes --square (the square size), "
                                   "not --spacing or --radius")
        return Board("chessboard", size, square)
    if spacing is None or square is not None:
        raise click.UsageError(f"a circle grid (--circles {circles}) takes --spacing (the circle spacing), "
                               "not --square")
    return Board(circles, size, spacing, radius)


#: OpenCV's standard deviation of the camera's principal point (px) above which calibrate-board
#: advises more, view-filling poses.
_PRINCIPAL_POINT_ADVICE_PX = 0.5


@cli.command("calibrate-board", epilog="""\b
Examples:
  sliscan calibrate-board pose_0/ pose_1/ pose_2/ --pattern gc/gc.json --board 9x7 --square 75 -o rig.json
  sliscan calibrate-board capture_* --pattern gc.json --board 9x7 --square 25 --no-projector-distortion -o rig.json
  sliscan calibrate-board pose_*/ --pattern pmp.json --board 4x11 --circles asymmetric --spacing 20 --radius 5 \\
      -o rig.json
\b
Each POSE is a folder holding the frames of one board pose, sorted by name in the pattern's
order (OpenCV's Gray code order for kind graycode: column bits, row bits, each pattern then its
inverse, then white and black).  Boards are OpenCV's: a chessboard (--board: inner corners per
row and per column, --square) or a circle grid (--circles symmetric|asymmetric, --board: circles
per row and rows, e.g. 4x11 asymmetric, --spacing).""")
@click.argument("poses", nargs=-1, required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--pattern", "pattern_path", type=INPUT_FILE, required=True,
              help="PatternSpec JSON of the sequence (pmp or graycode, orientation both).")
@click.option("--board", type=SIZE, required=True,
              help="OpenCV's pattern size COLUMNSxROWS: a chessboard's inner corners (e.g. 9x7), a circle grid's "
                   "circles per row and rows (e.g. 4x11).")
@_board_options
@click.option("--projector-distortion/--no-projector-distortion", default=True, show_default=True,
              help="Estimate the projector's lens distortion, or fix it at 0.")
@click.option("-o", "--output", type=OUTPUT_FILE, required=True, help="Calibration JSON to write.")
@click.option("--plot", type=OUTPUT_FILE,
              help="Also write a PNG of the camera and projector residuals of each pose (needs sliscan[plot]).")
@click.option("--residuals", "residuals_path", type=OUTPUT_FILE,
              help="Also write every point's residual vectors per pose as JSON (for sliscan report --residuals).")
@_overwrite_option
def calibrate_board_cmd(poses: tuple[Path, ...], pattern_path: Path, board: tuple[int, int], square: float | None,
                        circles: str | None, spacing: float | None, radius: float | None, projector_distortion: bool,
                        output: Path, plot: Path | None, residuals_path: Path | None, overwrite: bool) -> None:
    """Calibrate camera and projector (intrinsics, lens distortion, pose) from board poses.

    Per POSE: the board's points (chessboard inner corners or circle centres) are found in the
    white frame and each point's projector coordinates are fitted to the decoded pixels around
    it; then OpenCV calibrates the camera, the projector as an inverse camera, and their
    relative pose.  The calibration JSON has the world in the camera frame: matrix = K [R | t]
    with intrinsics and distortion (sliscan scan and sliscan simulate use both lenses).  A pose
    whose board is not found (or does not decode, or lacks frames) is skipped with a warning
    while at least 3 good poses remain.  Prints per-pose reprojection RMS, outlier poses, and
    the flatness and point spacing of the board triangulated with the result.
    """
    layout = _board(board, square, circles, spacing, radius)
    spec = _sequence_spec(pattern_path)
    pose_files = {pose: _capture_files([pose]) for pose in poses}
    _check_outputs([output, plot, residuals_path], [pattern_path, *(f for files in pose_files.values() for f in files)],
                   overwrite=overwrite)
    if plot is not None:
        require_matplotlib()
    _run_calibrate_board(pose_files, spec, layout, projector_distortion=projector_distortion, output=output,
                         plot=plot, residuals_path=residuals_path)


def _run_calibrate_board(pose_files: dict[Path, list[Path]], spec: PatternSpec, board: Board,
                         *, projector_distortion: bool, output: Path, plot: Path | None = None,
                         residuals_path: Path | None = None) -> None:
    """`calibrate-board` once its inputs are checked (also the end of `sliscan acquire
    --calibration-board`): per pose read and decode the frames and find the board, calibrate,
    write, print."""
    poses = list(pose_files)
    views: list[BoardView] = []
    used: list[Path] = []
    shape = None
    with _progress(len(poses) + 1) as stage:
        for pose, files in pose_files.items():
            stage(f"pose {pose.name}")
            frames = _read_frames(files)
            if shape is not None and frames[0].shape != shape:
                raise InputError(f"{files[0]}: the frame is {frames[0].shape[1]}x{frames[0].shape[0]} but the first "
                                 f"pose's are {shape[1]}x{shape[0]}")
            shape = frames[0].shape
            try:
                with _about(pose):
                    views.append(board_view(sequences.decode_frames(frames, spec), board,
                                            interpolate=_subpixel(spec)))
                used.append(pose)
            except InputError as exc:
                click.echo(f"warning: {exc}; skipping this pose", err=True)
        if len(views) < MIN_BOARD_VIEWS:
            raise InputError(f"only {len(views)} of {len(poses)} poses are usable; calibration needs at least "
                             f"{MIN_BOARD_VIEWS}")
        stage("calibrate")
        calib, residuals = calibrate_board(views, board, (shape[1], shape[0]), spec.projector_size,
                                           projector_distortion=projector_distortion, with_residuals=True)
        calib.save(output)
    written = [str(output)]
    residuals = Residuals(tuple(p.name for p in used), residuals.camera, residuals.projector, residuals.points)
    written += _save_residuals(residuals, plot, residuals_path,
                               title=f"calibrate-board: {len(views)} poses, {board.describe()}")
    Console().print(_board_table(calib, used))
    outliers = calib.extra["outlier_views"]
    flagged = f"; outlier poses: {', '.join(str(used[k]) for k in outliers)}" if outliers else ""
    bias = calib.extra["perspective_bias_px"]
    corrected = f" (perspective bias {bias:.2g} px corrected)" if board.radius is not None else ""
    std = calib.extra["intrinsics_std_px"]["camera"]
    click.echo(f"wrote {', '.join(written)}: {len(views)} of {len(poses)} poses, {board.describe()}{corrected}; "
               f"reprojection {_residual_summary(calib)}; stereo RMS {calib.extra['stereo_rms_px']:.3g} px; "
               f"camera principal point +-{std['cx']:.2g}, {std['cy']:.2g} px{flagged}")
    if max(std["cx"], std["cy"]) > _PRINCIPAL_POINT_ADVICE_PX:
        click.echo(f"note: the camera's principal point is uncertain by more than {_PRINCIPAL_POINT_ADVICE_PX:g} px, "
                   "which turns the whole calibration's frame by that over the focal length: take more poses "
                   "with the board filling most of the view (out to the image corners)", err=True)
    _warn_geometry(calib, baseline_direction(calib), output)


# --------------------------------------------------------------------------------------------
# sliscan demo
# --------------------------------------------------------------------------------------------


#: Fewest camera pixels per period of a pattern's finest carrier that the demo scans.
_DEMO_MIN_PERIOD_PX = 4.0


def _finest_period_px(spec: PatternSpec, rig: simulate.Rig) -> float:
    """Camera pixels per period of `spec`'s finest carrier, at the rig's working distance."""
    points = np.array([[0.0, 0.0, rig.working_distance_mm], [1.0, 0.0, rig.working_distance_mm]])
    cam, proj = rig.calibration.camera.project(points), rig.calibration.projector.project(points)
    magnification = np.linalg.norm(cam[1] - cam[0]) / np.linalg.norm(proj[1] - proj[0])
    return float(spec.orthogonal_lines / max(spec.all_carriers) * magnification)


def _demo_specs(which: str, rig: simulate.Rig) -> dict[str, PatternSpec]:
    """The demo's patterns; with "all", the phase pattern only where the camera resolves it."""
    projector = rig.calibration.projector.size
    specs = {"thesis": patterns.thesis_spec(projector), "best": patterns.default_spec(projector),
             "phase": patterns.phase_spec(projector)}
    if which == "both":
        return {k: specs[k] for k in ("thesis", "best")}
    if which != "all":
        return {which: specs[which]}
    period = _finest_period_px(specs["phase"], rig)
    if period < _DEMO_MIN_PERIOD_PX:
        click.echo(f"phase: left out, this camera sees its finest carrier at {period:.1f} px a period "
                   f"(under {_DEMO_MIN_PERIOD_PX:g}); give a larger --camera", err=True)
        del specs["phase"]
    return specs


def _accuracy_table(results: dict[str, tuple[evaluate.Accuracy, float]]) -> Table:
    """Accuracy figures, one column per pattern."""
    table = Table(title="sphere scan vs the virtual rig's ground truth")
    table.add_column("")
    for name in results:
        table.add_column(name, justify="right")
    rows: list[tuple[str, Callable[[evaluate.Accuracy, float], str]]] = [
        ("stripe accuracy (% of lit px)", lambda a, s: f"{a.stripe_accuracy:.1%}"),
        ("off > 1 stripe (% of lit px)", lambda a, s: f"{a.far_stripe:.2%}"),
        ("completeness (% of lit px)", lambda a, s: f"{a.completeness:.1%}"),
        ("outliers (% of points)", lambda a, s: f"{a.outliers:.2%}"),
        ("gross outliers (% of points)", lambda a, s: f"{a.gross_outliers:.2%}"),
        ("RMS error (mm)", lambda a, s: f"{a.rms_mm:.2f}"),
        ("median error (mm)", lambda a, s: f"{a.median_mm:.2f}"),
        ("oracle RMS error (mm)", lambda a, s: f"{a.oracle_rms_mm:.2f}"),
        ("oracle median error (mm)", lambda a, s: f"{a.oracle_median_mm:.2f}"),
        ("scan time (s)", lambda a, s: f"{s:.2f}"),
    ]
    for label, cell in rows:
        table.add_row(label, *(cell(*r) for r in results.values()))
    return table


@cli.command(epilog="""\b
Examples:
  sliscan demo                                  # thesis sizes, both patterns, into demo-out/
  sliscan demo --camera 640x480 --out /tmp/demo # small and quick
  sliscan demo --pattern best --supersample 3 --seed 1""")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=Path("demo-out"),
              show_default=True, help="Folder for everything the demo writes (an earlier demo's files there are "
                                      "replaced: no --overwrite needed).")
@_camera_option(default=f"{THESIS_CAMERA[0]}x{THESIS_CAMERA[1]}", show_default=True, help="Camera size.")
@_projector_option(default=f"{THESIS_PROJECTOR[0]}x{THESIS_PROJECTOR[1]}", show_default=True,
                   help="Projector size.")
@click.option("--pattern", "which", type=click.Choice(["all", "best", "thesis", "phase", "both"]), default="all",
              show_default=True,
              help="sliscan's best stripe pattern, the thesis's, the stripes plus a phase channel (sub-stripe "
                   "depth, issue 8), the first two ('both'), or all three side by side (the phase pattern "
                   "where the camera resolves its finest carrier).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the noise and of the albedo.")
@click.option("--supersample", type=click.IntRange(min=1), default=1, show_default=True,
              help="Sub-pixels per camera pixel per axis (render time grows with its square).")
def demo(out: Path, camera: tuple[int, int], projector: tuple[int, int], which: str, seed: int,
         supersample: int) -> None:
    """Everything end to end on the built-in virtual rig.

    Builds the thesis's rig, generates the pattern(s), renders the thesis's sphere (245 mm,
    800 mm away, in front of a wall) under realistic conditions (smooth albedo 0.15-1, ambient
    10 %, uncorrected projector gamma 2.2, 1 px blur, shot and read noise, 8 bits), scans each
    capture, writes OUT/rig.json and per pattern OUT/NAME/{pattern.png, pattern.json,
    capture.png, sphere mat5 files, sphere.ply}, with sliscan's best stripe pattern's capture
    also through the real-time path (``--method baseband`` with its 3D filters: OUT/baseband/,
    timed as the next frame of a stream), and prints the accuracy against the ground truth.
    Unlike the other commands it replaces its own files from an earlier run, so it can be run
    again into the same folder.
    """
    t0 = time.perf_counter()
    rig = simulate.virtual_rig(camera_size=camera, projector_size=projector)
    specs = _demo_specs(which, rig)
    scene = simulate.sphere_scene()
    conditions = _conditions(albedo="smooth", ambient=0.1, gamma=2.2, blur=1.0, noise=True,
                             supersample=supersample, seed=seed)
    results: dict[str, tuple[evaluate.Accuracy, float]] = {}
    baseband: dict[str, tuple[evaluate.Accuracy, float]] = {}  # its column last
    folders = list(specs)
    with _progress(4 * len(specs) + 2 * ("best" in specs)) as stage:
        for name, spec in specs.items():
            stage(f"{name}: render")
            capture = simulate.render(rig, scene, patterns.render_pattern(spec), conditions)
            stage(f"{name}: scan")
            t_scan = time.perf_counter()
            result = Scanner(spec, rig.calibration).scan(capture.image)
            t_scan = time.perf_counter() - t_scan
            stage(f"{name}: evaluate")
            results[name] = (evaluate.accuracy(result, capture.truth, spec, rig.calibration), t_scan)
            stage(f"{name}: write")
            folder = out / name
            patterns.save_pattern(folder / "pattern.png", spec)
            write_image(folder / "capture.png", capture.image)
            _write_scan(result, mat5_prefix=folder / "sphere", ply=folder / "sphere.ply", npz=None)
            if name == "best":  # the same frame through the real-time path, timed as a stream's next frame
                stage("best: baseband scan")
                scanner = Scanner(spec, rig.calibration, method="baseband")
                scanner.scan(capture.image)  # the first frame finds the carriers and the rig's stripe table
                t_scan = time.perf_counter()
                result = scanner.scan(capture.image)
                t_scan = time.perf_counter() - t_scan
                baseband["best, baseband"] = (evaluate.accuracy(result, capture.truth, spec, rig.calibration), t_scan)
                stage("best: write baseband")
                _write_scan(result, mat5_prefix=out / "baseband" / "sphere", ply=out / "baseband" / "sphere.ply",
                            npz=None)
                folders.append("baseband")
        rig.calibration.save(out / "rig.json")
    Console().print(_accuracy_table({**results, **baseband}))
    w, h = camera
    click.echo(f"wrote {out}/rig.json and {', '.join(f'{out}/{n}/' for n in folders)}: {w}x{h} sphere demo "
               f"in {time.perf_counter() - t0:.1f} s")


# `sliscan acquire` and `sliscan live` (scanning with a projector and a camera) live in their own
# module, which registers them on `cli`.
from sliscan import cli_acquire  # noqa: E402,F401


# --------------------------------------------------------------------------------------------
# sliscan report, sliscan view (issue 10)
# --------------------------------------------------------------------------------------------


def _calibration_residuals(calib: Calibration, calibration: Path, residuals: Path | None, g_file: Path | None,
                           pixels: bool) -> Residuals:
    """The residual vectors of a calibration: saved by calibrate-board/-target ``--residuals``,
    or recomputed from the calibration grid (G file) a DLT was calibrated from."""
    if residuals is not None:
        return Residuals.load(residuals)
    rows = premat5.read_g(g_file)
    if pixels:  # the residuals take phases: x = phase * size / 2 pi
        (w, h), rows = calib.projector.size, rows.copy()
        rows[:, 5], rows[:, 6] = premat5.pixel_to_phase(rows[:, 5], w), premat5.pixel_to_phase(rows[:, 6], h)
    with _about(g_file, calibration):
        return target_residuals(calib, rows, label=g_file.name)


@cli.command(epilog="""\b
Examples:
  sliscan report capture.png --pattern cp.json --calibration rig.json -o report.html
  sliscan report capture.png --pattern cp.json --calibration rig.json --truth truth.npz -o report.html
  sliscan report cap/ --pattern pmp/pmp.json --calibration rig.json -o pmp-report.html
  sliscan report --calibration rig.json --residuals residuals.json -o calibration.html
  sliscan report --calibration rig-g.json --g-file G.byt -o calibration.html
  sliscan report --batch out/summary.json -o batch.html
\b
The page is one HTML file with every figure and plotly.js inside: it opens offline, in any
browser (needs sliscan[report]).""")
@click.argument("captures", nargs=-1, type=click.Path(path_type=Path))
@click.option("--pattern", "pattern_path", type=INPUT_FILE, help="PatternSpec JSON of the projected pattern.")
@_calibration_options
@click.option("--method", type=click.Choice(list(METHODS)), default="window", show_default=True,
              help="Demodulator: sliscan's sliding window, the thesis's Butterworth band-pass (3.4), or baseband: "
                   "the real-time path (decimated envelopes, per-pixel decisions; stripe patterns only).")
@_scan_choices_options
@click.option("--truth", type=INPUT_FILE,
              help="Ground truth of a simulated capture (sliscan simulate --truth): adds the error against it.")
@click.option("--residuals", type=INPUT_FILE,
              help="With --calibration and no capture: a calibration report of these residuals "
                   "(calibrate-board or calibrate-target --residuals).")
@click.option("--g-file", type=INPUT_FILE,
              help="With --calibration and no capture: a calibration report of the DLT's residuals on this grid.")
@click.option("--pixels", is_flag=True, help="The G file's projector columns are pixels, not phases in radians.")
@click.option("--batch", "batch_summary", type=INPUT_FILE,
              help="A batch report instead: the per-frame summary (summary.json or .csv of a batch scan).")
@click.option("--max-points", type=click.IntRange(min=1), default=viewer.MESH_BUDGET, show_default=True,
              help="Most points of the 3D view (the scan is decimated by a grid stride to fit).")
@click.option("-o", "--output", type=OUTPUT_FILE, required=True, help="HTML file to write.")
@_overwrite_option
def report(captures: tuple[Path, ...], pattern_path: Path | None, calibration: Path | None,
           camera_matrix: Path | None, projector_matrix: Path | None, method: str, choices: ScanChoices,
           truth: Path | None,
           residuals: Path | None, g_file: Path | None, pixels: bool, batch_summary: Path | None, max_points: int,
           output: Path, overwrite: bool) -> None:
    """Write one self-contained HTML report of a scan, a calibration or a batch.

    A scan (CAPTURES with --pattern and a calibration, as for sliscan scan): the capture, its
    spectrum with the carriers and pass bands, the envelopes and bit planes (or a sequence's
    phase and bits), the decoded stripes and projector coordinate, the confidence and validity
    masks, the depth map, an interactive 3D view, the time of each stage and, with --truth, the
    error against the ground truth.  A calibration (--calibration with --residuals or --g-file):
    the matrices and the residual plots per view.  A batch (--batch): the per-frame table and
    the points and seconds per frame.
    """
    modes = [bool(captures), residuals is not None or g_file is not None, batch_summary is not None]
    if sum(modes) != 1:
        raise click.UsageError("give CAPTURES (a scan), --residuals or --g-file (a calibration), or --batch: one of them")
    if residuals is not None and g_file is not None:
        raise click.UsageError("give --residuals or --g-file, not both")
    files = _capture_files(captures) if captures else []
    _check_outputs([output], [*files, pattern_path, calibration, camera_matrix, projector_matrix, truth, residuals,
                              g_file, batch_summary], overwrite=overwrite)
    require_report()
    t0 = time.perf_counter()
    if batch_summary is not None:
        rows = report_module.read_batch_summary(batch_summary)
        report_module.write_page(output, report_module.batch_page(rows, facts={"summary": str(batch_summary)}))
        click.echo(f"wrote {output}: batch report of {len(rows)} frames in {time.perf_counter() - t0:.1f} s")
        return
    if not captures:
        if calibration is None:
            raise click.UsageError("a calibration report needs --calibration rig.json")
        calib = load_calibration(calibration)
        res = _calibration_residuals(calib, calibration, residuals, g_file, pixels)
        source = str(residuals if residuals is not None else g_file)
        page = report_module.calibration_page(calib, res, facts={"calibration": str(calibration), "residuals": source})
        report_module.write_page(output, page)
        views = f"{len(res.labels)} view{'s' if len(res.labels) != 1 else ''}"
        click.echo(f"wrote {output}: calibration report of {views} in {time.perf_counter() - t0:.1f} s")
        return
    if pattern_path is None:
        raise click.UsageError("a scan report needs --pattern P.json")
    with _progress(3) as stage:
        stage("read")
        inputs = _scan_inputs(files, pattern_path, calibration, camera_matrix, projector_matrix, method=method,
                              choices=choices)
        ground = None if truth is None else evaluate.read_truth(truth, shape=inputs.frames[0].shape)
        t1 = time.perf_counter()
        stage("scan")
        frames = inputs.frames if inputs.spec.kind in MULTI_FRAME_KINDS else inputs.frames[0]
        with _about(inputs.capture, f"pattern {pattern_path}"):
            result, stages = inputs.scanner.scan_stages(frames)
        stage("report")
        t2 = time.perf_counter()
        _write_scan_report(output, inputs, result, stages, {"read": t1 - t0, **result.timings}, truth=ground,
                           max_points=max_points)
    n = int(result.valid.sum())
    click.echo(f"wrote {output}: scan report of {inputs.capture}, {n} points ({n / result.valid.size:.1%} of the "
               f"frame){', with the error against ' + str(truth) if truth is not None else ''}; scan "
               f"{t2 - t1:.1f} s, report {time.perf_counter() - t2:.1f} s")


@cli.command(epilog="""\b
Examples:
  sliscan view sphere.ply                     # writes a temporary page and opens it
  sliscan view scan.npz -o scan.html --no-open
  sliscan view out/sphere -o sphere.html      # a mat5 prefix (out/sphereX.byt ...)""")
@click.argument("scan_path", metavar="SCAN", type=click.Path(path_type=Path))
@click.option("-o", "--output", type=OUTPUT_FILE, help="HTML file to write [a new temporary folder's SCAN.html].")
@click.option("--max-points", type=click.IntRange(min=1),
              help=f"Most points shown [{viewer.MESH_BUDGET} for a mesh of an npz or mat5 scan, {viewer.POINT_BUDGET} "
                   f"for a PLY point cloud].")
@click.option("--open/--no-open", "open_page", default=True, show_default=True,
              help="Open the page in the default web browser.")
@_overwrite_option
def view(scan_path: Path, output: Path | None, max_points: int | None, open_page: bool, overwrite: bool) -> None:
    """Write (and open) an interactive 3D view of a scan: a PLY point cloud, a sliscan npz scan
    or a mat5 prefix.

    An npz or mat5 scan keeps its pixel grid and is shown as a mesh, coloured by Zw or by its
    texture; a PLY file as points.  Large scans are decimated (every k-th row and column, or
    point) to --max-points.  The page is one HTML file with plotly.js inside (needs
    sliscan[report]).
    """
    inputs = [scan_path] if scan_path.suffix.lower() in (".ply", ".npz") else _mat5_files(scan_path)
    _check_outputs([output], inputs, overwrite=overwrite)
    require_report()
    budgets = {} if max_points is None else {"mesh_budget": max_points, "point_budget": max_points}
    cloud = viewer.load_cloud(scan_path, **budgets)
    if output is None:
        import tempfile

        output = Path(tempfile.mkdtemp(prefix="sliscan-view-")) / f"{Path(scan_path).stem or 'scan'}.html"
    report_module.write_page(output, report_module.view_page(cloud, str(scan_path)))
    click.echo(f"wrote {output}: {cloud.describe()}")
    if open_page:
        import webbrowser

        webbrowser.open(output.resolve().as_uri())


# --------------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------------


def _fail(message: str) -> NoReturn:
    click.echo(f"error: {' '.join(message.split())}", err=True)
    sys.exit(BAD_INPUT)


def main(args: Sequence[str] | None = None) -> None:
    """Run the ``sliscan`` command; bad input ends in one line ``error: ...`` and exit status 2.

    Parameters
    ----------
    args : sequence of str, optional
        Command-line arguments; default ``sys.argv[1:]``.
    """
    try:
        status = cli.main(args=args, prog_name="sliscan", standalone_mode=False)
    except click.Abort:
        click.echo("error: interrupted", err=True)
        sys.exit(130)
    except click.UsageError as exc:
        where = f"{exc.ctx.command_path}: " if exc.ctx is not None else ""
        hint = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
        _fail(f"{where}{exc.format_message()}{hint}")
    except click.ClickException as exc:
        _fail(exc.format_message())
    except InputError as exc:
        _fail(str(exc))
    except OSError as exc:
        _fail(f"{exc.filename}: {exc.strerror}" if exc.filename else str(exc))
    sys.exit(status if isinstance(status, int) else 0)
