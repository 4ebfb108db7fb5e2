"""One self-contained HTML page per scan, calibration or batch (issue 10).

The page shows a scan's work at every stage, as the thesis's figures do: the capture (fig.
3.26), its line spectrum with the detected carriers and the pass bands (figs. 3.18-3.22), the
envelopes (3.23) and bit planes (3.24), the decoded stripes and projector coordinate (3.25,
3.27), the confidence and validity masks, the depth map, an interactive 3D view (6.1-6.4), the
time of each stage and, for a capture of the virtual rig, the error against its ground truth.
A multi-frame capture (PMP, Gray code) shows what applies to it instead of the carriers.

Static figures are PNG files drawn by matplotlib (`sliscan.figures`) and embedded as base64;
the 3D view is plotly's (`sliscan.viewer`) with plotly.js inline: the page needs no network.
Both are the optional ``report`` extra (``pip install 'sliscan[report]'``).
"""

from __future__ import annotations

import base64
import csv
import dataclasses
import datetime
import html
import io
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sliscan import __version__, evaluate, figures, graycode, patterns, pmp, viewer
from sliscan._validate import InputError, atomic_write_text, check_image
from sliscan.calibrate import Residuals
from sliscan.demodulate import along_carriers, bandpass_filters, line_spectrum
from sliscan.figures import Panel
from sliscan.pipeline import ScanStages
from sliscan.simulate import GroundTruth
from sliscan.types import Calibration, PatternSpec, ScanResult

#: Side (camera px) of the full-resolution crop of the capture's centre.
CROP_PX = 192
#: Longest side (px) of the downsampled capture.
CAPTURE_SIDE = 1200


def require_report() -> None:
    """Raise a one-line `InputError` naming the extra when plotly or matplotlib is missing."""
    viewer.require_plotly()
    figures.require_matplotlib()


# --------------------------------------------------------------------------------------------
# HTML pieces
# --------------------------------------------------------------------------------------------

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 0 auto; max-width: 1200px;
       padding: 0 1.5em 3em; color: #222; }
h1 { margin-top: 1em; } h2 { border-bottom: 1px solid #ddd; padding-bottom: 0.2em; margin-top: 1.6em; }
figure { margin: 1em 0; } figure img { max-width: 100%; height: auto; display: block; }
figcaption, .note { color: #555; font-size: 0.92em; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.92em; }
th, td { border: 1px solid #ddd; padding: 0.25em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
.bar { background: #4c78a8; height: 0.8em; display: inline-block; }
.view-controls { margin: 0.5em 0; font-size: 0.92em; }
.failed { color: #b00; }
"""


def escape(text: object) -> str:
    """HTML-escaped text."""
    return html.escape(str(text))


def figure_html(fig_id: str, title: str, fig: Any, caption: str = "") -> str:
    """An embedded PNG of a matplotlib figure: ``<figure id="fig-ID"><img data-figure="ID">``."""
    data = base64.b64encode(figures.png_bytes(fig)).decode("ascii")
    note = f"<figcaption>{caption}</figcaption>" if caption else ""
    return (f'<figure id="fig-{fig_id}"><img data-figure="{fig_id}" alt="{escape(title)}" '
            f'src="data:image/png;base64,{data}">{note}</figure>')


def table_html(header: Sequence[str], rows: Sequence[Sequence[object]], *, table_id: str = "") -> str:
    """A table; cells are escaped unless they are `Markup`."""
    def cell(value: object, tag: str) -> str:
        return f"<{tag}>{value if isinstance(value, Markup) else escape(value)}</{tag}>"

    ident = f' id="{table_id}"' if table_id else ""
    head = "".join(cell(h, "th") for h in header)
    body = "".join("<tr>" + "".join(cell(v, "td") for v in row) + "</tr>" for row in rows)
    return f"<table{ident}><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


class Markup(str):
    """HTML that `table_html` puts in a cell unescaped."""


def section(title: str, *parts: str, section_id: str = "") -> str:
    """An ``<h2>`` section."""
    ident = f' id="{section_id}"' if section_id else ""
    return f"<section{ident}><h2>{escape(title)}</h2>{''.join(parts)}</section>"


def note(text: str) -> str:
    """A paragraph of explanation."""
    return f'<p class="note">{text}</p>'


def html_page(title: str, sections: Sequence[str], *, facts: Mapping[str, str] = {}, with_plotly: bool = False) -> str:
    """A whole self-contained page: its title, a table of `facts`, the sections, and plotly.js
    inline when a section holds a 3D view."""
    made = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    rows = [(k, v) for k, v in facts.items()] + [("made by", f"sliscan {__version__}, {made}")]
    head = viewer.plotly_script() if with_plotly else ""
    return (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{escape(title)}</title>'
            f'<meta name="viewport" content="width=device-width, initial-scale=1"><style>{_CSS}</style>{head}'
            f"</head><body><h1>{escape(title)}</h1>{table_html(('', ''), rows, table_id='facts')}"
            f"{''.join(sections)}</body></html>")


def write_page(path: str | os.PathLike, page: str) -> Path:
    """Write a page atomically (UTF-8)."""
    return atomic_write_text(path, page)


def view_page(cloud: viewer.Cloud, source: str) -> str:
    """The page of ``sliscan view``: the 3D view of one scan file."""
    body = section("3D view", note(f"Showing {cloud.describe()}."), viewer.view_div(cloud, height_px=760),
                   section_id="view")
    return html_page(f"sliscan view: {Path(source).name}", [body], facts={"scan": source}, with_plotly=True)


# --------------------------------------------------------------------------------------------
# Scan report
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ScanReport:
    """Everything a scan report shows.

    Attributes
    ----------
    frames : (K, H, W) array
        The capture: one frame for a composite pattern, the sequence for ``pmp``/``graycode``;
        uint8, uint16 or float in [0, 1].
    spec : PatternSpec
    calibration : Calibration
    result : ScanResult
    stages : ScanStages
        From `sliscan.pipeline.Scanner.scan_stages`.
    method : str
        The demodulator (``"window"`` or ``"bandpass"``).
    truth : GroundTruth, optional
        The virtual rig's ground truth of the capture.
    timings : dict of str -> float
        Seconds per stage (read, demodulate, ...); default the scan's own.
    facts : dict of str -> str
        Lines for the page's header (capture files, pattern, calibration).
    max_points : int
        Most vertices of the 3D view (`sliscan.viewer.cloud_from_grid`).
    """

    frames: NDArray
    spec: PatternSpec
    calibration: Calibration
    result: ScanResult
    stages: ScanStages
    method: str = "window"
    truth: GroundTruth | None = None
    timings: dict[str, float] = field(default_factory=dict)
    facts: dict[str, str] = field(default_factory=dict)
    max_points: int = viewer.MESH_BUDGET


def _capture_section(frames: NDArray[np.float32], spec: PatternSpec) -> str:
    """The capture (downsampled by area) and a full-resolution crop of its centre (fig. 3.26)."""
    import cv2

    image = frames[0]
    h, w = image.shape
    scale = min(1.0, CAPTURE_SIDE / max(h, w))
    small = cv2.resize(image, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    y0, x0 = max(0, h // 2 - CROP_PX // 2), max(0, w // 2 - CROP_PX // 2)
    crop = image[y0:y0 + CROP_PX, x0:x0 + CROP_PX]
    what = "the capture" if len(frames) == 1 else f"frame 0 of {len(frames)}"
    fig = figures.maps_figure([Panel(f"{what}, {w}x{h}", small, vmin=0, vmax=1, extent=(w, h)),
                               Panel(f"centre, pixel for pixel (x {x0}, y {y0})", crop, vmin=0, vmax=1)],
                              columns=2)
    return section("Capture", figure_html("capture", "capture", fig,
                                          "Thesis fig. 3.26. Left: the whole frame (area-averaged); right: its "
                                          "centre at full resolution."), section_id="capture")


def passbands(frequency: NDArray[np.float64], carriers: Any, method: str, width: int) -> tuple[NDArray[np.float64], str]:
    """Each carrier's pass band over `frequency` (cycles per camera pixel), ``(C, F)`` in [0, 1].

    ``bandpass``: the thesis's one-sided Butterworth band-passes (figs. 3.21-3.22, the analytic
    signal's factor 2 left out).  ``window``: the magnitude response of sliscan's sliding-window
    fit of each carrier, ``|sin(pi d L) / (L sin(pi d))|`` at ``d = f - f_n`` for the window of
    ``L`` pixels (a Dirichlet kernel: zero on every other carrier).
    """
    if method == "bandpass":
        full = bandpass_filters(width, carriers) / 2
        grid = np.fft.fftfreq(width)
        order = np.argsort(grid)
        return np.stack([np.interp(frequency, grid[order], band[order]) for band in full]), \
            "one-sided Butterworth band-pass (figs. 3.21-3.22)"
    length = carriers.window
    d = frequency[None, :] - carriers.frequencies[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        response = np.abs(np.sin(np.pi * d * length) / (length * np.sin(np.pi * d)))
    return np.where(np.abs(d) < 1e-12, 1.0, response), f"window fit response ({length} px window)"


def carrier_labels(spec: PatternSpec) -> list[str]:
    """Names of ``spec.all_carriers``: bit 0 (most significant) ..., phase 0 ..., and the pilot."""
    return ([f"bit {n}" for n in range(spec.bits)] + [f"phase {n}" for n in range(len(spec.phase_carriers))]
            + (["pilot"] if spec.pilot is not None else []))


def _spectrum_section(report: ScanReport) -> str:
    """The mean line spectrum with the detected carriers and their pass bands (figs. 3.18-3.22)."""
    carriers = report.stages.carriers
    view = along_carriers(report.frames[0], report.spec)
    frequency, power = line_spectrum(view)
    bands, band_label = passbands(frequency, carriers, report.method, view.shape[1])
    labels = carrier_labels(report.spec)
    fig = figures.spectrum_figure(frequency, power, carriers.frequencies, labels, bands, band_label)
    along = "rows (camera x)" if report.spec.orientation == "rows" else "columns (camera y)"
    found = ", ".join(f"{label} {f:.4f}" for label, f in zip(labels, carriers.frequencies))
    return section("Spectrum and carriers", figure_html(
        "spectrum", "line spectrum", fig,
        f"Mean power spectrum of the capture's {along}, the carriers detected in it (dashed: {found} cycles per "
        f"camera pixel, {carriers.scale:.3f} projector px per camera px) and each carrier's pass band "
        f"({band_label})."), section_id="spectrum")


def _composite_sections(report: ScanReport) -> list[str]:
    """Spectrum, envelopes and bit planes of a composite-pattern scan (figs. 3.18-3.24)."""
    demod, decoded, spec = report.stages.demodulated, report.stages.decoded, report.spec
    labels = carrier_labels(spec)
    f_proj = spec.all_carriers
    envelopes = [Panel(f"{label} envelope ({f:g} cycles/width)", demod.amplitude[n], cmap="magma", vmin=0,
                       label="amplitude") for n, (label, f) in enumerate(zip(labels, f_proj))]
    envelopes.append(Panel("local mean (DC)", demod.dc, vmin=0, label="intensity"))
    planes = [Panel(f"bit {n} (carrier {f_proj[n]:g})", np.where(decoded.lit, decoded.levels[n] >= 0.5, np.nan),
                    vmin=0, vmax=1) for n in range(spec.bits)]
    return [
        _spectrum_section(report),
        section("Envelopes", figure_html("envelopes", "envelopes", figures.maps_figure(envelopes, columns=3),
                                         "Thesis fig. 3.23: the demodulated amplitude of each carrier, and the "
                                         "local mean it is compared with."), section_id="envelopes"),
        section("Bit planes", figure_html("bit-planes", "bit planes", figures.maps_figure(planes, columns=min(4, spec.bits)),
                                          "Thesis fig. 3.24: each envelope binarised at its own threshold "
                                          "(white = 1; pale blue = not lit)."), section_id="bit-planes"),
    ]


def _pmp_sections(report: ScanReport) -> list[str]:
    """Wrapped phase and modulation of each PMP frequency (the coordinate triangulated)."""
    spec, direction = report.spec, report.stages.direction
    fits = pmp.fringe_fits(report.frames, spec, direction)
    phase = [Panel(f"wrapped phase, {f:g} cycles", 2 * np.pi * fit.cycles, cmap="twilight", vmin=0, vmax=2 * np.pi,
                   label="rad") for fit, f in zip(fits, spec.frequencies)]
    modulation = [Panel(f"modulation B, {f:g} cycles", fit.modulation, cmap="magma", vmin=0, label="intensity")
                  for fit, f in zip(fits, spec.frequencies)]
    return [
        section("Phase", figure_html("phase", "wrapped phase", figures.maps_figure(phase, columns=3),
                                     f"Eq. 2.3: the wrapped phase of each frequency along the projector's {direction}, "
                                     f"unwrapped hierarchically into the projector coordinate below."),
                section_id="phase"),
        section("Modulation", figure_html("modulation", "modulation", figures.maps_figure(modulation, columns=3),
                                          "The fringe amplitude of each frequency; a pixel needs all of them above the "
                                          "noise."), section_id="modulation"),
    ]


def _graycode_sections(report: ScanReport) -> list[str]:
    """The Gray code bit planes (pattern brighter than its inverse) of the coordinate triangulated."""
    spec, direction = report.spec, report.stages.direction
    pairs = graycode.bit_pairs(report.frames, spec, direction)
    white, black = graycode.white_black_frames(spec)
    lit = report.frames[white] - report.frames[black] > graycode.BLACK_THRESHOLD
    planes = [Panel(f"bit {n}", np.where(lit, pairs[n, 0] > pairs[n, 1], np.nan), vmin=0, vmax=1)
              for n in range(len(pairs))]
    parts = [section("Bit planes", figure_html("bit-planes", "bit planes", figures.maps_figure(planes, columns=5),
                                               f"Each Gray code bit of the projector's {direction}: 1 (white) where the "
                                               f"pattern is brighter than its inverse; pale blue = not lit."),
                     section_id="bit-planes")]
    if spec.steps:
        fit = graycode.phase_fit(report.frames, spec, direction)
        panel = Panel("wrapped phase", 2 * np.pi * fit.cycles, cmap="twilight", vmin=0, vmax=2 * np.pi, label="rad")
        parts.append(section("Phase", figure_html("phase", "wrapped phase", figures.maps_figure([panel], columns=1),
                                                  "The phase-shifted fringes' wrapped phase, unwrapped by the Gray "
                                                  "code."), section_id="phase"))
    return parts


def _decoded_section(report: ScanReport) -> str:
    """The decoded stripe (or fringe order / code) and projector coordinate maps (figs. 3.25, 3.27)."""
    result, direction = report.result, report.stages.direction
    coordinate = "yp" if direction == "rows" else "xp"
    index = {"pmp": "fringe order", "graycode": "Gray code index"}.get(report.spec.kind, "stripe")
    panels = [Panel(f"decoded {index}", np.where(result.stripe >= 0, result.stripe, np.nan), cmap="turbo",
                    label=index),
              Panel(f"projector {coordinate}", result.proj_map, cmap="viridis", label="projector px")]
    return section("Decoded", figure_html("decoded", "decoded", figures.maps_figure(panels),
                                          f"Thesis figs. 3.25 and 3.27: what each camera pixel decoded to, and the "
                                          f"projector {'row' if direction == 'rows' else 'column'} it is triangulated "
                                          f"with (pale blue: no point)."), section_id="decoded")


def _masks_section(report: ScanReport) -> str:
    """Confidence, the decoder's validity and the final validity after the 3D filters."""
    result, stages = report.result, report.stages
    decoded_valid = stages.decoded.valid if stages.decoded is not None else stages.maps[stages.direction].valid
    panels = [Panel("confidence", result.confidence, cmap="viridis", vmin=0, vmax=1, label="0..1"),
              Panel(f"decoded ({decoded_valid.mean():.1%})", decoded_valid, vmin=0, vmax=1),
              Panel(f"valid points ({result.valid.mean():.1%})", result.valid, vmin=0, vmax=1)]
    if stages.decoded is not None:
        panels.insert(1, Panel(f"lit ({stages.decoded.lit.mean():.1%})", stages.decoded.lit, vmin=0, vmax=1))
    return section("Confidence and validity", figure_html(
        "masks", "masks", figures.maps_figure(panels, columns=len(panels)),
        "Confidence: the weakest bit's margin (composite), fringe visibility (PMP) or bit contrast (Gray code). "
        "Decoded: pixels with a code; valid: those left after the projector-frustum, triangulation-angle and "
        "speckle filters."), section_id="masks")


def _depth_section(report: ScanReport) -> str:
    """The depth map along the camera's axis, and the texture."""
    depth = np.where(report.result.valid, viewer.camera_depth(report.result.points, report.calibration), np.nan)
    panels = [Panel("depth along the camera axis", depth, cmap="viridis", label="mm"),
              Panel("texture", report.result.texture, vmin=0, vmax=1)]
    return section("Depth", figure_html("depth", "depth map", figures.maps_figure(panels),
                                        "Distance of each valid point from the camera along its optical axis."),
                   section_id="depth")


def _view_section(report: ScanReport) -> str:
    """The interactive 3D view of the scan."""
    cloud = viewer.cloud_from_grid(report.result.points, report.result.valid, texture=report.result.texture,
                                   calibration=report.calibration, budget=report.max_points)
    return section("3D view", note(
        f"Showing {cloud.describe()}: a grid stride keeps the scan's structure and bounds the page's size; the "
        f"full cloud is in the scan's PLY, npz or mat5 files (<code>sliscan view --max-points</code> shows more). "
        f"Triangles across depth jumps of more than {viewer.MAX_EDGE_FACTOR:g} times the median edge are left out."),
        viewer.view_div(cloud), section_id="view")


def _timings_section(timings: Mapping[str, float]) -> str:
    """Seconds per stage, as a table with bars."""
    total = sum(v for k, v in timings.items() if k != "total")
    longest = max([v for k, v in timings.items() if k != "total"], default=1.0)
    rows = [(name, f"{1e3 * s:.1f}", Markup(f'<span class="bar" style="width:{200 * s / max(longest, 1e-9):.0f}px">'
                                            f'</span>'))
            for name, s in timings.items() if name != "total"]
    rows.append(("total", f"{1e3 * total:.1f}", ""))
    return section("Timings", table_html(("stage", "ms", ""), rows, table_id="timings"), section_id="timings")


def _truth_section(report: ScanReport) -> str:
    """Error against the virtual rig's ground truth: map, histogram, accuracy table."""
    truth, result, spec = report.truth, report.result, report.spec
    errors = evaluate.error_map(result, truth)
    finite = errors[np.isfinite(errors)]
    top = float(np.percentile(finite, 99)) if finite.size else 1.0
    map_fig = figures.maps_figure([Panel("3D error of each valid point", errors, cmap="inferno", vmin=0, vmax=top,
                                         label="mm"),
                                   Panel("lit by the projector (truth)", truth.lit, vmin=0, vmax=1)])
    hist_fig, counts = figures.histogram_figure(errors, label="3D error (mm)",
                                                title=f"{finite.size:,} valid points on the surface")
    if spec.kind in ("pmp", "graycode"):
        yardstick = patterns.thesis_spec(spec.projector_size, orientation=report.stages.direction)
        quantum = evaluate.stripe_depth(truth, yardstick, report.calibration)
        figures_of = evaluate.surface_accuracy(result, truth, quantum).as_dict()
    else:
        figures_of = evaluate.accuracy(result, truth, spec, report.calibration).as_dict()
    rows = [(name.replace("_", " "), _format_figure(name, value)) for name, value in figures_of.items()]
    return section("Error against the ground truth",
                   figure_html("error", "error map", map_fig, "Distance (mm) from each valid point to the true "
                                                             "surface point of its pixel."),
                   figure_html("error-histogram", "error histogram", hist_fig,
                               f"{int(counts.sum()):,} comparisons: every valid point whose pixel sees a true "
                               f"surface (the last bin holds everything above the 99.5th percentile)."),
                   table_html(("figure", "value"), rows, table_id="accuracy"),
                   note("See <code>sliscan.evaluate</code> for the definitions (stripe accuracy, completeness, "
                        "outliers, oracle)."), section_id="truth")


def _format_figure(name: str, value: float) -> str:
    """An accuracy figure for the table: pixels as integers, fractions as %, mm to 3 decimals."""
    if name.endswith("pixels"):
        return f"{int(value):,}"
    if name.endswith("_mm"):
        return f"{value:.3f} mm"
    return f"{value:.2%}"


def scan_page(report: ScanReport) -> str:
    """The whole HTML page of a scan report."""
    report = dataclasses.replace(report, frames=np.stack([check_image(f"frame {k}", frame)
                                                          for k, frame in enumerate(report.frames)]))
    spec, result = report.spec, report.result
    h, w = result.shape
    n = int(result.valid.sum())
    sections = [_capture_section(report.frames, spec)]
    if spec.kind in ("pmp", "graycode"):
        sections.append(section("Spectrum and carriers", note(
            f"A {spec.kind} capture is a sequence of {len(report.frames)} frames without carriers: there is no "
            f"carrier spectrum to show."), section_id="spectrum"))
        sections += _pmp_sections(report) if spec.kind == "pmp" else _graycode_sections(report)
    else:
        sections += _composite_sections(report)
    sections += [_decoded_section(report), _masks_section(report), _depth_section(report), _view_section(report),
                 _timings_section(report.timings or result.timings)]
    if report.truth is not None:
        sections.append(_truth_section(report))
    facts = {**report.facts, "points": f"{n:,} ({n / result.valid.size:.1%} of the {w}x{h} frame)"}
    return html_page("sliscan scan report", sections, facts=facts, with_plotly=True)


# --------------------------------------------------------------------------------------------
# Calibration report
# --------------------------------------------------------------------------------------------


def calibration_page(calibration: Calibration, residuals: Residuals, *, facts: Mapping[str, str] = {}) -> str:
    """A calibration's matrices, residual summary and per-view residual plots (camera, projector)."""
    fig, panels = figures.residual_figure(residuals)
    rows = [(p["view"], p["device"], f"{p['rms_px']:.3f}", p["points"]) for p in panels]
    devices = [(name, "x".join(map(str, device.size)),
                Markup("<br>".join(" ".join(f"{v:.6g}" for v in row) for row in np.asarray(device.matrix))))
               for name, device in (("camera", calibration.camera), ("projector", calibration.projector))]
    summary = calibration.extra.get("residuals", {})
    sections = [
        section("Rig", table_html(("device", "size (WxH)", "3x4 matrix"), devices, table_id="devices"),
                note("; ".join(f"{name}: RMS {r['rms_px']:.3g} px, max {r['max_px']:.3g} px"
                               for name, r in summary.items()) or "no residual summary in the calibration"),
                section_id="rig"),
        section("Residuals per view", figure_html("residuals", "residuals", fig,
                                                  "Reprojection residual vectors (projected - observed, px) of every "
                                                  "point, camera left and projector right; dashed: their RMS."),
                table_html(("view", "device", "RMS px", "points"), rows, table_id="views"), section_id="residuals"),
    ]
    return html_page("sliscan calibration report", sections, facts=facts)


# --------------------------------------------------------------------------------------------
# Batch report
# --------------------------------------------------------------------------------------------

#: Columns of a batch summary row (``summary.json`` or ``.csv`` of a batch scan).
BATCH_COLUMNS = ("frame", "source", "points", "completeness", "seconds", "status", "error")


def _number(value: object, name: str, path: Path, row: int) -> float:
    """A finite number of a summary row (empty: NaN, e.g. a failed frame's points)."""
    if value is None or value == "":
        return float("nan")
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{path}: row {row}: {name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not np.isfinite(number) and not np.isnan(number):
        raise InputError(f"{path}: row {row}: {name} must be a finite number, got {value!r}")
    return number


def read_batch_summary(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The rows of a batch summary: a JSON list of objects (or an object holding one under
    ``"frames"`` or ``"rows"``), or a CSV file with a header, each row with `BATCH_COLUMNS`.

    Returns
    -------
    rows : list of dict
        ``points``, ``completeness`` and ``seconds`` as float (NaN where empty), the others as str.

    Raises
    ------
    InputError
        If the file cannot be read or parsed, or a row lacks a column or has a bad number.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise InputError(f"{p}: not a batch summary (not UTF-8 text)") from None
    if p.suffix.lower() == ".csv":
        try:
            raw: Any = list(csv.DictReader(io.StringIO(text)))
        except csv.Error as exc:
            raise InputError(f"{p}: not valid CSV ({exc})") from None
    else:
        try:
            raw = json.loads(text)
        except ValueError as exc:
            raise InputError(f"{p}: not valid JSON ({exc})") from None
        if isinstance(raw, dict):
            raw = raw.get("frames", raw.get("rows"))
    if not isinstance(raw, list) or not all(isinstance(r, dict) for r in raw):
        raise InputError(f"{p}: a batch summary is a list of rows (objects with {', '.join(BATCH_COLUMNS)})")
    if not raw:
        raise InputError(f"{p}: the batch summary has no rows")
    rows = []
    for k, r in enumerate(raw):
        missing = [c for c in BATCH_COLUMNS if c not in r]
        if missing:
            raise InputError(f"{p}: row {k}: missing {', '.join(missing)}")
        row = {c: "" if r[c] is None else str(r[c]) for c in ("frame", "source", "status", "error")}
        row.update({c: _number(r[c], c, p, k) for c in ("points", "completeness", "seconds")})
        rows.append(row)
    return rows


def batch_page(rows: Sequence[Mapping[str, Any]], *, facts: Mapping[str, str] = {}) -> str:
    """A batch's per-frame table and a plot of points and seconds per frame."""
    frames = [str(r["frame"]) for r in rows]
    points = np.array([r["points"] for r in rows], dtype=np.float64)
    seconds = np.array([r["seconds"] for r in rows], dtype=np.float64)
    fig = figures.batch_figure(frames, np.nan_to_num(points), np.nan_to_num(seconds))
    ok = [r for r in rows if r["status"] == "ok"]
    failed = len(rows) - len(ok)

    def number(value: float, spec: str) -> str:
        return "" if np.isnan(value) else format(value, spec)

    table = [(r["frame"], r["source"], number(r["points"], ",.0f"), number(r["completeness"], ".1%"),
              number(r["seconds"], ".2f"), Markup(f'<span class="{"" if r["status"] == "ok" else "failed"}">'
                                                  f'{escape(r["status"])}</span>'), r["error"]) for r in rows]
    summary = (f"{len(rows)} frames, {len(ok)} ok, {failed} failed; {np.nansum(points):,.0f} points in "
               f"{np.nansum(seconds):.1f} s (median {np.nanmedian(seconds):.2f} s per frame)")
    sections = [section("Points and time per frame", note(summary),
                        figure_html("batch", "points and time per frame", fig, "Points (top) and seconds (bottom) "
                                    "of each frame, in order."), section_id="batch"),
                section("Frames", table_html(("frame", "source", "points", "completeness", "seconds", "status",
                                              "error"), table, table_id="frames"), section_id="frames")]
    return html_page("sliscan batch report", sections, facts=facts)
