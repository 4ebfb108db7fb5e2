"""Batch scanning (issue 9): a 20-frame moving-sphere take, as image files and as a video, on a
real Dask `LocalCluster` of 2 worker processes, with one corrupted frame in the middle.

The take is rendered once per module on the small virtual rig (640x480 camera, no supersampling)
so each batch takes a few seconds; the frame rate is the benchmark's business
(`benchmarks/batch.py`), not a test's.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from sliscan import batch, motion, patterns, simulate
from sliscan._validate import write_image
from sliscan.formats import npz
from sliscan.pipeline import ScanChoices, Scanner
from sliscan.types import Calibration, PatternSpec
from test_cli import CAMERA, PROJECTOR, listing, ok, sliscan

FRAMES = 20
BAD = 10  # the corrupted frame

# One xdist worker runs the module, so the take is rendered and each batch run once.
pytestmark = pytest.mark.xdist_group("batch")


@pytest.fixture(scope="module")
def take(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """cp.json, rig.json, 20 frames as PNG files (frame 10 corrupt: not an image) and as a
    lossless FFV1 video (frame 10 black: a dropped frame), and each frame's ground truth."""
    folder = tmp_path_factory.mktemp("take")
    spec = patterns.default_spec(PROJECTOR).with_(image="cp.png")
    spec.save(folder / "cp.json")
    rig = simulate.virtual_rig(camera_size=CAMERA, projector_size=PROJECTOR)
    rig.calibration.save(folder / "rig.json")
    conditions = simulate.Conditions(supersample=1, seed=7)
    moving = motion.Motion(FRAMES, velocity_mm=(4.0, -1.0, 3.0), spin_deg=3.0)
    video = cv2.VideoWriter(str(folder / "take.avi"), cv2.VideoWriter_fourcc(*"FFV1"), 25, CAMERA, isColor=False)
    assert video.isOpened()
    for k, capture in enumerate(motion.render_motion(rig, simulate.sphere_scene(), patterns.render_pattern(spec),
                                                     moving, conditions)):
        write_image(folder / f"frames/f{k:02d}.png", capture.image)
        np.save(folder / f"truth{k:02d}.npy", capture.truth.points)
        video.write(np.zeros(capture.image.shape, np.uint8) if k == BAD else cv2.imread(
            str(folder / f"frames/f{k:02d}.png"), cv2.IMREAD_GRAYSCALE))
    video.release()
    (folder / f"frames/f{BAD:02d}.png").write_bytes(b"\x89PNG\r\n\x1a\n but then the card was pulled out")
    return folder


def summary(out: Path) -> list[dict]:
    rows = json.loads((out / batch.SUMMARY_JSON).read_text())["frames"]
    with open(out / batch.SUMMARY_CSV, newline="") as f:
        assert [int(r["frame"]) for r in csv.DictReader(f)] == [r["frame"] for r in rows]
    return rows


def run_batch(take: Path, source: str, out: str, *extra: str):
    return sliscan("scan", source, "--pattern", "cp.json", "--calibration", "rig.json", "--out", out,
                   "--workers", "2", *extra, cwd=take)


def check_first_run(take: Path, out: Path, result, formats: tuple[str, ...]) -> list[dict]:
    """19 frames written, one failure recorded, exit status 1 with a one-line error."""
    assert result.returncode == 1, result.stderr
    assert result.stderr.splitlines()[-1].startswith(f"error: 1 of {FRAMES} frames failed")
    rows = summary(out)
    assert [r["frame"] for r in rows] == list(range(FRAMES))
    assert [r["status"] for r in rows] == ["ok"] * BAD + ["failed"] + ["ok"] * (FRAMES - BAD - 1)
    assert rows[BAD]["error"] and rows[BAD]["points"] is None
    for r in rows:
        names = batch.output_names(r["frame"], formats)
        assert all((out / n).is_file() for n in names) == (r["status"] == "ok")
    scans = sorted(p.name for p in out.glob("frame_*"))
    assert len(scans) == (FRAMES - 1) * len(batch.output_names(0, formats))
    return rows


@pytest.fixture(scope="module")
def folder_run(take: Path) -> tuple[Path, list[dict]]:
    """The take's image files scanned to npz and PLY in scans/: the folder and the summary rows."""
    out = take / "scans"
    rows = check_first_run(take, out, run_batch(take, "frames", "scans", "--format", "npz", "--format", "ply"),
                           ("npz", "ply"))
    return out, rows


@pytest.fixture(scope="module")
def video_run(take: Path) -> tuple[Path, list[dict]]:
    """The take's video scanned to npz in vscans/: the folder and the summary rows."""
    out = take / "vscans"
    return out, check_first_run(take, out, run_batch(take, "take.avi", "vscans"), ("npz",))


def test_folder_batch_records_the_failure_and_resumes(take: Path, folder_run: tuple[Path, list[dict]]) -> None:
    out, rows = folder_run
    result = npz.read_scan_npz(out / "frame_000003.npz")
    assert rows[3]["points"] == int(result.valid.sum()) > 0.3 * result.valid.size
    assert rows[3]["completeness"] == pytest.approx(rows[3]["points"] / result.valid.size, abs=1e-6)
    assert rows[BAD]["source"].endswith(f"f{BAD:02d}.png") and "not an image" in rows[BAD]["error"]

    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("frame_*")}
    again = run_batch(take, "frames", "scans", "--format", "npz", "--format", "ply", "--resume")
    assert again.returncode == 1, again.stderr  # the corrupt frame fails again
    assert again.stdout.startswith(f"0 frames scanned, 1 failed, {FRAMES - 1} already done in "), again.stdout
    resumed = summary(out)
    assert [r["status"] for r in resumed].count("skipped") == FRAMES - 1
    assert resumed[3]["points"] == rows[3]["points"]  # counts carried over from the first run
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("frame_*")} == stamps  # no work redone


def test_video_batch_of_a_dropped_frame(video_run: tuple[Path, list[dict]]) -> None:
    _, rows = video_run
    assert rows[BAD]["source"] == f"take.avi#{BAD}" and "dark" in rows[BAD]["error"]
    assert rows[0]["source"] == "take.avi#0"


def test_batch_outputs_equal_scanning_each_frame_alone(take: Path, folder_run: tuple[Path, list[dict]]) -> None:
    out, _ = folder_run
    ok("scan", "frames/f05.png", "--pattern", "cp.json", "--calibration", "rig.json", "--ply", "alone/f05.ply",
       "--npz", "alone/f05.npz", cwd=take)
    assert (out / "frame_000005.ply").read_bytes() == (take / "alone/f05.ply").read_bytes()
    batch_npz, alone_npz = np.load(out / "frame_000005.npz"), np.load(take / "alone/f05.npz")
    assert sorted(batch_npz.files) == sorted(alone_npz.files)
    for name in set(batch_npz.files) - {"timings"}:  # the seconds of each stage differ, the arrays not
        np.testing.assert_array_equal(batch_npz[name], alone_npz[name], err_msg=name)


def test_video_frames_scan_like_the_decoded_frame(take: Path, video_run: tuple[Path, list[dict]]) -> None:
    """A video frame travels as a PNG of its grey image: the scan equals `Scanner.scan` of the
    frame that OpenCV decodes."""
    out, _ = video_run
    capture = cv2.VideoCapture(str(take / "take.avi"))
    for _ in range(5):
        ok_, frame = capture.read()
    capture.release()
    alone = Scanner(PatternSpec.load(take / "cp.json"), Calibration.load(take / "rig.json")).scan(
        cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    batched = npz.read_scan_npz(out / "frame_000004.npz")
    np.testing.assert_array_equal(batched.valid, alone.valid)
    np.testing.assert_array_equal(batched.points, alone.points)


def test_batch_points_follow_the_moving_sphere(take: Path, folder_run: tuple[Path, list[dict]]) -> None:
    """Per-frame accuracy against the ground truth: the median depth error of the decoded points
    stays within half a stripe's depth (4-bit code: a stripe is 60-120 mm here) on every frame,
    and the object moves as the motion says (the scans' centroids follow 4, -1, 3 mm per frame)."""
    out, _ = folder_run
    centroids = []
    for k in [0, 5, 15, 19]:
        result = npz.read_scan_npz(out / f"frame_{k:06d}.npz")
        truth = np.load(take / f"truth{k:02d}.npy")
        sphere = result.valid & (np.abs(truth[..., 2] - 1000) > 1)  # not the wall at 1000 mm
        dz = result.points[sphere][:, 2] - truth[sphere][:, 2]
        assert np.median(np.abs(dz)) < 30, k
        centroids.append(truth[sphere].mean(axis=0))
    step = (centroids[-1] - centroids[0]) / 19
    assert step[0] == pytest.approx(4.0, abs=1.5) and step[2] == pytest.approx(3.0, abs=1.5)


def test_batch_on_an_existing_scheduler(take: Path) -> None:
    """--scheduler sends the same work to a running cluster (here one started by the test)."""
    from distributed import LocalCluster

    (take / "three").mkdir(exist_ok=True)
    for k in (1, 2, 3):
        (take / f"three/f{k}.png").write_bytes((take / f"frames/f{k:02d}.png").read_bytes())
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        result = sliscan("scan", "three", "--pattern", "cp.json", "--calibration", "rig.json", "--out", "remote",
                         "--scheduler", cluster.scheduler_address, cwd=take)
    assert result.returncode == 0, result.stderr
    assert [r["status"] for r in summary(take / "remote")] == ["ok"] * 3
    alone = Scanner(PatternSpec.load(take / "cp.json"), Calibration.load(take / "rig.json")).scan(
        cv2.imread(str(take / "three/f1.png"), cv2.IMREAD_UNCHANGED))
    np.testing.assert_array_equal(npz.read_scan_npz(take / "remote/frame_000000.npz").points, alone.points)


BAD_BATCH: dict[str, tuple[tuple[str, ...], str]] = {
    "no --out": (("frames",), "give --out DIR"),
    "--ply in a batch": (("frames", "--out", "o", "--ply", "x.ply"), "a batch writes into --out DIR"),
    "--resume and --overwrite": (("frames", "--out", "o", "--resume", "--overwrite"), "give one"),
    "--out is a file": (("frames", "--out", "cp.json"), "'cp.json' is a file"),
    "a video that is not one": (("cp.avi",), "not a video OpenCV can read"),
    "--workers and --scheduler": (("frames", "--out", "o", "--workers", "2", "--scheduler", "tcp://x:1"),
                                  "has its own workers"),
}


@pytest.mark.parametrize("case", BAD_BATCH)
def test_bad_batch_arguments_are_one_line_and_write_nothing(take: Path, tmp_path: Path, case: str) -> None:
    for name in ("cp.json", "rig.json"):
        (tmp_path / name).write_bytes((take / name).read_bytes())
    (tmp_path / "frames").mkdir()
    for k in (0, 1):
        (tmp_path / f"frames/f{k}.png").write_bytes((take / f"frames/f0{k}.png").read_bytes())
    (tmp_path / "cp.avi").write_bytes(b"RIFF....AVI not really")
    args, message = BAD_BATCH[case]
    if case == "a video that is not one":
        args = (*args, "--out", "o")
    before = listing(tmp_path)
    result = sliscan("scan", *args, "--pattern", "cp.json", "--calibration", "rig.json", cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], result.stderr
    assert listing(tmp_path) == before


def test_an_earlier_batch_needs_resume_or_overwrite(take: Path, tmp_path: Path) -> None:
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "frame_000000.npz").write_bytes(b"earlier")
    for name in ("cp.json", "rig.json"):
        (tmp_path / name).write_bytes((take / name).read_bytes())
    result = sliscan("scan", str(take / "frames"), "--pattern", "cp.json", "--calibration", "rig.json", "--out", "o",
                     cwd=tmp_path)
    assert result.returncode == 2 and "use --resume or --overwrite" in result.stderr
    assert (tmp_path / "o" / "frame_000000.npz").read_bytes() == b"earlier"


# --------------------------------------------------------------------------------------------
# The library: frames, names, the worker function
# --------------------------------------------------------------------------------------------


def test_iter_frames_reads_lazily_and_skips(take: Path) -> None:
    files = [take / "take.avi", take / "frames/f00.png"]
    frames = batch.iter_frames(files, skip=lambda i: i % 2 == 1)
    first = next(frames)
    assert first.index == 0 and first.source.endswith("take.avi#0") and first.data[:4] == b"\x89PNG"
    rest = list(frames)
    assert [f.index for f in rest] == list(range(1, FRAMES + 1))
    assert all((f.data is None) == (f.index % 2 == 1) for f in rest)
    assert rest[-1].source.endswith("f00.png") and rest[-1].data is not None  # index 20, after the video
    assert batch.count_frames(files) == FRAMES + 1


def test_output_names_sort_by_frame() -> None:
    assert batch.output_names(12, ("npz", "ply")) == ["frame_000012.npz", "frame_000012.ply"]
    assert batch.output_names(3, ("mat5",))[0] == "frame_000003_X.byt"
    with pytest.raises(Exception, match="formats must be"):
        batch.Job({}, {}, formats=("obj",))


def test_scan_frame_never_raises_and_reuses_its_scanner(take: Path) -> None:
    job = batch.Job.create(PatternSpec.load(take / "cp.json"), Calibration.load(take / "rig.json"))
    good = batch.scan_frame(job, batch.Frame(0, "f00", (take / "frames/f00.png").read_bytes()))
    assert good.status == "ok" and good.points > 0 and list(good.files) == ["frame_000000.npz"]
    scanner = batch._SCANNERS[job.token]
    again = batch.scan_frame(job, batch.Frame(1, "f01", (take / "frames/f01.png").read_bytes()))
    assert batch._SCANNERS[job.token] is scanner and again.status == "ok"
    bad = batch.scan_frame(job, batch.Frame(2, "junk", b"junk"))
    assert bad.status == "failed" and bad.error == "junk: not an image (cannot decode)" and not bad.files
    small = cv2.imencode(".png", np.full((48, 64), 128, np.uint8))[1].tobytes()
    wrong = batch.scan_frame(job, batch.Frame(3, "small", small))
    assert wrong.status == "failed" and "640" in wrong.error


def test_job_choices_shape_its_scanner(take: Path) -> None:
    """A job's decisions, albedo steps and stripe lines reach the worker's scanner (and its token), so a batch
    decodes as `sliscan scan` does."""
    spec, calibration = PatternSpec.load(take / "cp.json"), Calibration.load(take / "rig.json")
    jobs = {d: batch.Job.create(spec, calibration, choices=ScanChoices(decisions=d))
            for d in ("auto", "order", "pixel")}
    assert len({job.token for job in jobs.values()}) == 3
    assert [jobs[d].scanner().decode_options for d in ("auto", "order", "pixel")] == [{}, {"order": True},
                                                                                      {"order": False}]
    with pytest.raises(Exception, match="decisions must be one of"):
        batch.Job.create(spec, calibration, choices=ScanChoices(decisions="majority"))
    plain = batch.Job.create(spec, calibration, choices=ScanChoices(albedo_steps=False))
    centres = batch.Job.create(spec, calibration, choices=ScanChoices(stripe_lines=False))
    assert len({plain.token, centres.token, jobs["auto"].token}) == 3
    assert (plain.scanner().albedo, jobs["auto"].scanner().albedo) == (None, "steps")
    assert (centres.scanner().interpolate_stripes, jobs["auto"].scanner().interpolate_stripes) == (False, True)


def test_batch_report_lists_every_frame(take: Path) -> None:
    """scan --out ... --report writes the batch's HTML page: every frame, failures with their error."""
    pytest.importorskip("plotly")
    (take / "pair").mkdir(exist_ok=True)
    for k in (0, BAD):
        (take / f"pair/f{k:02d}.png").write_bytes((take / f"frames/f{k:02d}.png").read_bytes())
    result = sliscan("scan", "pair", "--pattern", "cp.json", "--calibration", "rig.json", "--out", "pair-out",
                     "--workers", "1", "--report", "pair.html", cwd=take)
    assert result.returncode == 1 and "pair.html" in result.stdout, result.stderr
    page = (take / "pair.html").read_text()
    assert "pair/f00.png" in page and "pair/f10.png: not an image (cannot decode)" in page
