"""HTML reports (issue 10): what each page shows, batch summaries, calibration residuals, and the
``report``, ``view`` and ``scan --report`` commands (the browser checks: test_browser.py)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from sliscan import InputError, evaluate, figures, patterns, report, sequences, simulate
from sliscan.calibrate import Residuals, calibrate_points, target_residuals
from sliscan.formats import premat5
from sliscan.pipeline import Scanner
from sliscan.types import Calibration, PatternSpec
from test_cli import fails_cleanly, ok, sliscan

pytest.importorskip("plotly")
pytest.importorskip("matplotlib")

PROJECTOR = (1024, 768)
#: The stage figures of a composite scan report with a ground truth, by id.
COMPOSITE_FIGURES = {"capture", "spectrum", "envelopes", "bit-planes", "decoded", "masks", "depth", "error",
                     "error-histogram"}


def figure_ids(page: str) -> set[str]:
    """The ids of the embedded PNG figures of a page."""
    return set(re.findall(r'<img data-figure="([^"]+)" alt="[^"]*" src="data:image/png;base64,', page))


@pytest.fixture(scope="module")
def rig() -> simulate.Rig:
    return simulate.virtual_rig(camera_size=(320, 240), projector_size=PROJECTOR)


def scan_report(rig: simulate.Rig, spec: PatternSpec, **options) -> tuple[str, report.ScanReport]:
    """Render the sphere, scan it and build the report page (with the ground truth)."""
    multi = spec.kind in ("pmp", "graycode")
    conditions = simulate.Conditions(albedo=simulate.SmoothAlbedo(), seed=2)
    if multi:
        capture = simulate.render_sequence(rig, simulate.sphere_scene(), sequences.render_frames(spec), conditions)
        frames = capture.images
    else:
        capture = simulate.render(rig, simulate.sphere_scene(), patterns.render_pattern(spec), conditions)
        frames = capture.image[None]
    method = options.pop("method", "window")
    result, stages = Scanner(spec, rig.calibration, method=method).scan_stages(frames if multi else frames[0])
    inputs = report.ScanReport(frames=frames, spec=spec, calibration=rig.calibration, result=result, stages=stages,
                               method=method, truth=capture.truth, **options)
    return report.scan_page(inputs), inputs


@pytest.fixture(scope="module")
def composite(small_rig: simulate.Rig) -> tuple[str, report.ScanReport]:
    """A 640x480 composite scan's report (at 320x240 the finest carrier is too fine to decode)."""
    return scan_report(small_rig, patterns.default_spec(PROJECTOR), facts={"capture": "sphere <&> test"})


def test_composite_report_shows_every_stage(composite) -> None:
    page, inputs = composite
    assert figure_ids(page) == COMPOSITE_FIGURES
    for section in ("capture", "spectrum", "envelopes", "bit-planes", "decoded", "masks", "depth", "view", "timings",
                    "truth"):
        assert f'<section id="{section}">' in page
    assert 'id="view3d"' in page and "Plotly.newPlot" in page
    assert "sphere &lt;&amp;&gt; test" in page  # facts are escaped
    assert "https://" not in page.split("<body>")[1]  # the body loads nothing from the network
    for stage in inputs.result.timings:
        if stage != "total":
            assert f"<td>{stage}</td>" in page


def test_error_histogram_counts_every_comparison(composite) -> None:
    page, inputs = composite
    errors = evaluate.error_map(inputs.result, inputs.truth)
    compared = int((inputs.result.valid & inputs.truth.surface).sum())
    assert np.count_nonzero(np.isfinite(errors)) == compared > 1000
    _, counts = figures.histogram_figure(errors)
    assert int(counts.sum()) == compared
    assert f"{compared:,} comparisons" in page
    # the map's RMS is the accuracy table's
    accuracy = evaluate.accuracy(inputs.result, inputs.truth, inputs.spec, inputs.calibration)
    rms = float(np.sqrt(np.nanmean(errors.astype(np.float64) ** 2)))
    assert abs(rms - accuracy.rms_mm) < 1e-3 and f"{accuracy.rms_mm:.3f} mm" in page


def test_bandpass_report_draws_the_butterworth_pass_bands(small_rig: simulate.Rig) -> None:
    page, inputs = scan_report(small_rig, patterns.thesis_spec(PROJECTOR), method="bandpass")
    assert "one-sided Butterworth band-pass" in page and figure_ids(page) == COMPOSITE_FIGURES
    carriers = inputs.stages.carriers
    bands, _ = report.passbands(carriers.frequencies, carriers, "bandpass", 640)
    # each passes its own carrier and notches the others (fig. 3.22)
    assert np.all(np.diag(bands) > 0.9) and np.all(bands[~np.eye(len(bands), dtype=bool)] < 0.05)
    assert np.all(report.passbands(np.linspace(0, 0.5, 501), carriers, "bandpass", 640)[0] <= 1.0 + 1e-9)


def test_window_pass_bands_are_one_on_their_carrier_and_zero_on_the_others(composite) -> None:
    _, inputs = composite
    carriers = inputs.stages.carriers
    bands, label = report.passbands(carriers.frequencies, carriers, "window", 640)
    assert f"{carriers.window} px window" in label
    # whole periods of every carrier in the window: a Dirichlet kernel, 1 on its own, ~0 elsewhere
    np.testing.assert_allclose(np.diag(bands), 1.0, rtol=0, atol=1e-9)
    assert np.all(bands[~np.eye(len(bands), dtype=bool)] < 0.15)


@pytest.mark.parametrize("spec, shown", [
    (PatternSpec(kind="pmp", projector_size=PROJECTOR, steps=4, frequencies=(1, 8, 64), a_p=0.5, b_p=0.5),
     {"capture", "phase", "modulation", "decoded", "masks", "depth", "error", "error-histogram"}),
    (PatternSpec(kind="graycode", projector_size=PROJECTOR, orientation="rows"),
     {"capture", "bit-planes", "decoded", "masks", "depth", "error", "error-histogram"}),
    (PatternSpec(kind="graycode", projector_size=PROJECTOR, orientation="both", steps=4, code_width=8),
     {"capture", "bit-planes", "phase", "decoded", "masks", "depth", "error", "error-histogram"}),
])
def test_multi_frame_reports_show_what_applies(rig: simulate.Rig, spec: PatternSpec, shown: set[str]) -> None:
    page, _ = scan_report(rig, spec)
    assert figure_ids(page) == shown
    assert "without carriers: there is no carrier spectrum to show" in page
    assert 'id="view3d"' in page


# --------------------------------------------------------------------------------------------
# Batch summaries and calibration residuals
# --------------------------------------------------------------------------------------------

ROWS = [
    {"frame": 0, "source": "cap/f000.png", "points": 120000, "completeness": 0.61, "seconds": 1.2, "status": "ok",
     "error": None},
    {"frame": 1, "source": "cap/f001.png", "points": None, "completeness": None, "seconds": 0.1, "status": "failed",
     "error": "cap/f001.png: the capture is dark"},
    {"frame": 2, "source": "cap/f002.png", "points": 118500, "completeness": 0.60, "seconds": 1.1, "status": "ok",
     "error": ""},
]


def write_summary(folder: Path, kind: str, rows: list[dict] = ROWS) -> Path:
    """A batch summary as the batch feature writes it: JSON rows (a list or under "frames") or CSV."""
    if kind == "csv":
        lines = [",".join(report.BATCH_COLUMNS)]
        lines += [",".join("" if r[c] is None else str(r[c]) for c in report.BATCH_COLUMNS) for r in rows]
        path = folder / "summary.csv"
        path.write_text("\n".join(lines) + "\n")
        return path
    path = folder / "summary.json"
    path.write_text(json.dumps(rows if kind == "list" else {"frames": rows}))
    return path


@pytest.mark.parametrize("kind", ["list", "object", "csv"])
def test_batch_summary_is_read_and_shown(tmp_path: Path, kind: str) -> None:
    rows = report.read_batch_summary(write_summary(tmp_path, kind))
    assert [r["frame"] for r in rows] == ["0", "1", "2"]
    assert rows[0]["points"] == 120000 and np.isnan(rows[1]["points"]) and rows[1]["status"] == "failed"
    page = report.batch_page(rows)
    assert figure_ids(page) == {"batch"} and "3 frames, 2 ok, 1 failed; 238,500 points" in page
    assert "cap/f001.png: the capture is dark" in page and 'class="failed"' in page
    assert "Plotly" not in page  # no 3D view: no plotly.js either


@pytest.mark.parametrize("content, match", [
    ("[]", "no rows"),
    ('{"frames": 3}', "list of rows"),
    ("[1, 2]", "list of rows"),
    ('[{"frame": 0}]', "row 0: missing source"),
    (json.dumps([{**ROWS[0], "seconds": "fast"}]), "row 0: seconds must be a number"),
    (json.dumps([{**ROWS[0], "points": True}]), "row 0: points must be a finite number"),
    ("{not json", "not valid JSON"),
])
def test_bad_batch_summary(tmp_path: Path, content: str, match: str) -> None:
    (tmp_path / "s.json").write_text(content)
    with pytest.raises(InputError, match=match):
        report.read_batch_summary(tmp_path / "s.json")


def grid_rows(rig: simulate.Rig, rng: np.random.Generator) -> np.ndarray:
    """G rows (Xw Yw Zw xc yc xp_phase yp_phase) of 40 random points seen by the rig, 0.2 px noise."""
    world = rng.uniform([-150, -100, 700], [150, 100, 900], (40, 3))
    camera = rig.calibration.camera.project(world) + rng.normal(0, 0.2, (40, 2))
    projector = rig.calibration.projector.project(world) + rng.normal(0, 0.2, (40, 2))
    w, h = rig.calibration.projector.size
    return np.c_[world, camera, premat5.pixel_to_phase(projector[:, 0], w), premat5.pixel_to_phase(projector[:, 1], h)]


def test_calibration_page_shows_the_residuals(rig: simulate.Rig, rng: np.random.Generator, tmp_path: Path) -> None:
    rows = grid_rows(rig, rng)
    calib = calibrate_points(rows, rig.calibration.camera.size, PROJECTOR)
    residuals = target_residuals(calib, rows, label="G")
    residuals.save(tmp_path / "r.json")
    loaded = Residuals.load(tmp_path / "r.json")
    assert loaded.labels == ("G",) and loaded.points == "circle"
    np.testing.assert_array_equal(loaded.camera[0], residuals.camera[0])
    np.testing.assert_allclose(loaded.rms("projector"), calib.extra["residuals"]["projector"]["rms_px"], rtol=1e-9)
    page = report.calibration_page(calib, loaded)
    assert figure_ids(page) == {"residuals"} and f"{loaded.rms('camera')[0]:.3f}" in page


@pytest.mark.parametrize("content, match", [
    ('{"labels": []}', "non-empty list"),
    ('{"labels": ["a"], "camera": [[[1, 2]]]}', "'projector' must list one view"),
    ('{"labels": ["a"], "camera": [[[1, "x"]]], "projector": [[[1, 2]]]}', "lists of \\[dx, dy\\] numbers"),
    ('{"labels": ["a"], "camera": [[]], "projector": [[[1, 2]]]}', "non-empty and finite"),
])
def test_bad_residuals(tmp_path: Path, content: str, match: str) -> None:
    (tmp_path / "r.json").write_text(content)
    with pytest.raises(InputError, match=match):
        Residuals.load(tmp_path / "r.json")


def test_truth_must_match_the_camera(tmp_path: Path, rig: simulate.Rig) -> None:
    np.savez(tmp_path / "t.npz", points=np.zeros((4, 5, 3)))
    with pytest.raises(InputError, match="not a ground truth"):
        evaluate.read_truth(tmp_path / "t.npz")
    truth = {name: np.zeros((4, 5, 3) if name == "points" else (4, 5, 2) if name == "proj" else (4, 5))
             for name in evaluate.TRUTH_DTYPES}
    np.savez(tmp_path / "t.npz", **truth)
    assert evaluate.read_truth(tmp_path / "t.npz").lit.shape == (4, 5)
    with pytest.raises(InputError, match=r"points has shape \(4, 5, 3\), expected \(240, 320, 3\)"):
        evaluate.read_truth(tmp_path / "t.npz", shape=(240, 320))


# --------------------------------------------------------------------------------------------
# The commands
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """pattern -> simulate (rig, truth) -> scan with --report, PLY and npz, at 640x480."""
    folder = tmp_path_factory.mktemp("report")
    ok("pattern", "composite", "--projector", "1024x768", "-o", "cp.png", cwd=folder)
    ok("simulate", "--pattern", "cp.json", "--scene", "sphere", "--camera", "640x480", "--supersample", "1",
       "--write-rig", "rig.json", "--truth", "truth.npz", "-o", "capture.png", cwd=folder)
    ok("scan", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json", "--ply", "s.ply", "--npz", "s.npz",
       "--mat5", "m/s", "--report", "scan.html", cwd=folder)
    write_summary(folder, "list")
    return folder


def test_scan_report_option_writes_the_page(run: Path) -> None:
    page = (run / "scan.html").read_text()
    assert figure_ids(page) == COMPOSITE_FIGURES - {"error", "error-histogram"}  # no truth given to scan
    assert "capture.png" in page and "window" in page
    # the virtual rig is level: its rows run along the camera's (`pipeline.stripe_tilt_deg`)
    assert "the projector&#x27;s rows cross the camera&#x27;s at up to 0.0 degrees" in page
    # a uniform albedo has no edges to measure the camera's blur on (`demodulate.camera_blur`)
    assert "not told (too few tall albedo edges); the albedo steps found for 1 px" in page


def test_report_command_with_truth(run: Path, tmp_path: Path) -> None:
    result = ok("report", run / "capture.png", "--pattern", run / "cp.json", "--calibration", run / "rig.json",
                "--truth", run / "truth.npz", "--max-points", "5000", "-o", "r.html", cwd=tmp_path)
    assert len(result.stdout.splitlines()) == 1 and "wrote r.html: scan report" in result.stdout
    page = (tmp_path / "r.html").read_text()
    assert figure_ids(page) == COMPOSITE_FIGURES
    points = int(re.search(r"on ([\d,]+) of the scan's", page).group(1).replace(",", ""))
    assert 2000 < points <= 5000


def test_report_command_batch_and_calibration(run: Path, tmp_path: Path, rng: np.random.Generator) -> None:
    result = ok("report", "--batch", run / "summary.json", "-o", "b.html", cwd=tmp_path)
    assert "batch report of 3 frames" in result.stdout and figure_ids((tmp_path / "b.html").read_text()) == {"batch"}
    rows = grid_rows(simulate.Rig(Calibration.load(run / "rig.json")), rng)
    premat5.write_g(tmp_path / "G.byt", rows)
    ok("calibrate", "G.byt", "--camera-size", "640x480", "--projector", "1024x768", "-o", "rig-g.json", cwd=tmp_path)
    result = ok("report", "--calibration", "rig-g.json", "--g-file", "G.byt", "-o", "c.html", cwd=tmp_path)
    assert "calibration report of 1 view in" in result.stdout
    assert figure_ids((tmp_path / "c.html").read_text()) == {"residuals"}


@pytest.mark.parametrize("scan_file", ["s.ply", "s.npz", "m/s"])
def test_view_command(run: Path, tmp_path: Path, scan_file: str) -> None:
    result = ok("view", run / scan_file, "-o", "v.html", "--no-open", cwd=tmp_path)
    assert result.stdout.startswith("wrote v.html: ") and len(result.stdout.splitlines()) == 1
    page = (tmp_path / "v.html").read_text()
    trace = re.search(r'Plotly\.newPlot\(\s*"view3d",\s*\[\{.*?"type":"(\w+)"\}\],', page, re.S).group(1)
    assert trace == ("scatter3d" if scan_file == "s.ply" else "mesh3d")


BAD_CASES = {
    "unreadable PLY": (("view", "bad.ply", "-o", "o.html", "--no-open"), "bad.ply"),
    "missing scan": (("view", "missing.npz", "-o", "o.html", "--no-open"), "missing.npz"),
    "not a scan npz": (("view", "truth.npz", "-o", "o.html", "--no-open"), "truth.npz"),
    "view onto an existing file": (("view", "s.ply", "-o", "capture.png", "--no-open"), "capture.png"),
    "report truth of another size": (("report", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json",
                                      "--truth", "small-truth.npz", "-o", "o.html"), "small-truth.npz"),
    "report of a flat capture": (("report", "flat.png", "--pattern", "cp.json", "--calibration", "rig.json",
                                  "-o", "o.html"), "flat.png"),
    "report without a mode": (("report", "-o", "o.html"), "report"),
    "report of two modes": (("report", "capture.png", "--batch", "summary.json", "-o", "o.html"), "report"),
    "bad batch summary": (("report", "--batch", "cp.json", "-o", "o.html"), "cp.json"),
    "bad residuals": (("report", "--calibration", "rig.json", "--residuals", "cp.json", "-o", "o.html"), "cp.json"),
    "scan report onto the capture": (("scan", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json",
                                      "--report", "capture.png"), "capture.png"),
}


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_input_is_one_line_and_writes_nothing(run: Path, tmp_path: Path, case: str) -> None:
    folder = tmp_path / "run"
    shutil.copytree(run, folder)
    (folder / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nend_header\n\x00")
    np.savez(folder / "small-truth.npz", **{name: np.zeros((4, 5, 3) if name == "points" else
                                                           (4, 5, 2) if name == "proj" else (4, 5))
                                            for name in evaluate.TRUTH_DTYPES})
    flat = np.full((480, 640), 128, np.uint8)
    import cv2

    cv2.imwrite(str(folder / "flat.png"), flat)
    fails_cleanly(*BAD_CASES[case], folder)


@pytest.mark.parametrize("command", [["report"], ["view"]])
def test_help_has_examples(tmp_path: Path, command: list[str]) -> None:
    result = sliscan(*command, "--help", cwd=tmp_path)
    assert result.returncode == 0 and "Examples:" in result.stdout
