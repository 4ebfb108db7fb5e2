"""Batch scanning of a moving object (issue 9): frames per second on 1 and 2 local Dask workers
against a plain in-process loop, memory as the number of frames grows, and the accuracy of
every frame against the virtual rig's ground truth.

The take: the thesis's sphere (smooth random albedo that moves with it, the accuracy
benchmark's realistic conditions, sliscan's default 4-bit pattern) translating by (3, -1, 2) mm
and turning by 3 degrees per frame, rendered once per frame at 1280x1024 (cached in --cache).

* Throughput: a folder of N PNG frames (the rendered frames cycled) scanned to npz by
  `sliscan.batch.run_batch` on a `LocalCluster` of 1 worker process scanning with 1 thread,
  of 1 with 2 threads (the default on 2 CPUs), and of 2 with 1 thread each (the default with
  --workers 2), and by the loop a user would
  write without sliscan.batch (read, `Scanner.scan`, `save_npz`, one frame after the other, in
  this process with all its threads): median of --runs runs, the cluster started once per
  size and its start-up time reported apart.  Peak memory: the summed resident set of this
  process and its children (the workers), sampled every 50 ms.
* Flat memory: a lossless FFV1 video of --long frames at 640x480 (the rendered frames
  resized and cycled) scanned on 2 workers, against a tenth as many frames: the peak resident
  set must not grow with the number of frames.
* Accuracy: each distinct frame's scan (from the batch's npz) against its ground truth
  (`sliscan.evaluate.accuracy`).

    python benchmarks/batch.py --json benchmarks/batch.json
    python benchmarks/batch.py --quick          # fewer frames and runs
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import psutil

from sliscan import batch, evaluate, motion, patterns, simulate
from sliscan._validate import read_image, write_image
from sliscan.formats import npz
from sliscan.pipeline import Scanner

sys.path.insert(0, str(Path(__file__).parent))
from accuracy import conditions  # noqa: E402

PROJECTOR = (1024, 768)
MOTION = dict(velocity_mm=(3.0, -1.0, 2.0), spin_deg=3.0)


def render_take(camera: tuple[int, int], frames: int, cache: Path) -> tuple[list[Path], simulate.Rig]:
    """The take's PNG frames (rendered once into `cache`, with each frame's truth beside it)."""
    rig = simulate.virtual_rig(camera_size=camera, projector_size=PROJECTOR)
    folder = cache / f"take_{camera[0]}x{camera[1]}_{frames}"
    paths = [folder / f"frame_{k:03d}.png" for k in range(frames)]
    if not all(p.exists() for p in paths):
        spec = patterns.default_spec(PROJECTOR)
        take = motion.render_motion(rig, simulate.sphere_scene(), patterns.render_pattern(spec),
                                    motion.Motion(frames, **MOTION), conditions("smooth", 0))
        for path, capture in zip(paths, take):
            print(f"rendering {path.name}", file=sys.stderr)
            write_image(path, capture.image)
            np.savez_compressed(path.with_suffix(".truth.npz"), **vars(capture.truth))
    return paths, rig


class PeakMemory:
    """Peak summed RSS (MiB) of this process and its children while in the `with` block."""

    def __enter__(self) -> PeakMemory:
        self.peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        me = psutil.Process()
        while not self._stop.is_set():
            total = 0
            for proc in [me, *me.children(recursive=True)]:
                try:
                    total += proc.memory_info().rss
                except psutil.Error:
                    pass
            self.peak = max(self.peak, total / 2**20)
            self._stop.wait(0.05)

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def cycled(paths: list[Path], n: int, folder: Path) -> list[Path]:
    """`n` frame files in `folder`: the take's frames over and over (hard links)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for k in range(n):
        target = folder / f"f{k:05d}.png"
        if not target.exists():
            target.hardlink_to(paths[k % len(paths)])
        out.append(target)
    return out


def loop_peer(job: batch.Job, files: list[Path], out: Path) -> float:
    """Seconds of the plain loop: read, scan, save npz, frame after frame in this process."""
    scanner = job.scanner()
    t0 = time.perf_counter()
    for k, path in enumerate(files):
        scanner.scan(read_image(path)).save_npz(out / f"frame_{k:06d}.npz")
    return time.perf_counter() - t0


def throughput(job: batch.Job, files: list[Path], runs: int, scratch: Path) -> list[dict]:
    """Frames per second and peak memory of the loop and of 1 and 2 workers."""
    rows = []
    seconds, peaks = [], []
    warm = job.scanner()
    warm.scan(read_image(files[0]))  # compile and cache the kernels before timing
    for r in range(runs):
        out = scratch / f"loop{r}"
        out.mkdir()
        with PeakMemory() as mem:
            seconds.append(loop_peer(job, files, out))
        peaks.append(mem.peak)
        shutil.rmtree(out)
    loop_fps = len(files) / statistics.median(seconds)
    rows.append({"runner": "plain loop (1 process)", "frames": len(files), "fps": loop_fps,
                 "fps_min": len(files) / max(seconds), "fps_max": len(files) / min(seconds),
                 "startup_s": 0.0, "peak_mib": max(peaks)})
    for workers, threads in ((1, 1), (1, 2), (2, 1)):
        t0 = time.perf_counter()
        with batch.dask_client(workers=workers, threads=threads) as client:
            startup = time.perf_counter() - t0
            batch.run_batch(client, job, batch.iter_frames(files[:2 * workers]), scratch / "warm")  # load kernels
            shutil.rmtree(scratch / "warm")
            seconds, peaks = [], []
            for r in range(runs):
                out = scratch / f"w{workers}_{r}"
                with PeakMemory() as mem:
                    report = batch.run_batch(client, job, batch.iter_frames(files), out)
                assert report.count("ok") == len(files), report.rows
                seconds.append(report.seconds)
                peaks.append(mem.peak)
                shutil.rmtree(out)
        fps = len(files) / statistics.median(seconds)
        name = f"sliscan.batch, {workers} worker{'s' if workers > 1 else ''} x {threads} thread{'s' if threads > 1 else ''}"
        rows.append({"runner": name, "frames": len(files),
                     "fps": fps, "fps_min": len(files) / max(seconds), "fps_max": len(files) / min(seconds),
                     "startup_s": startup, "peak_mib": max(peaks)})
    for row in rows:
        row["vs_loop"] = row["fps"] / loop_fps
    return rows


def write_video(paths: list[Path], n: int, size: tuple[int, int], path: Path) -> Path:
    """A lossless FFV1 video of `n` frames: the take's frames resized to `size`, cycled."""
    frames = [cv2.resize(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), size, interpolation=cv2.INTER_AREA)
              for p in paths]
    video = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 25, size, isColor=False)
    for k in range(n):
        video.write(frames[k % len(frames)])
    video.release()
    return path


def flat_memory(paths: list[Path], counts: list[int], scratch: Path) -> list[dict]:
    """Peak memory of 2 workers scanning videos of `counts` frames at 640x480."""
    size = (640, 480)
    rig = simulate.virtual_rig(camera_size=size, projector_size=PROJECTOR)
    job = batch.Job.create(patterns.default_spec(PROJECTOR), rig.calibration)
    rows = []
    with batch.dask_client(workers=2) as client:
        for n in counts:
            video = write_video(paths, n, size, scratch / f"take{n}.avi")
            with PeakMemory() as mem:
                report = batch.run_batch(client, job, batch.iter_frames([video]), scratch / f"long{n}")
            rows.append({"frames": n, "ok": report.count("ok"), "fps": report.frames_per_second,
                         "peak_mib": mem.peak})
            shutil.rmtree(scratch / f"long{n}")
            video.unlink()
    return rows


def per_frame_accuracy(paths: list[Path], rig: simulate.Rig, job: batch.Job, scratch: Path) -> list[dict]:
    """Each distinct frame of the take, scanned by a batch, against its ground truth."""
    spec = patterns.default_spec(PROJECTOR)
    with batch.dask_client(workers=2) as client:
        batch.run_batch(client, job, batch.iter_frames(paths), scratch / "acc")
    rows = []
    for k, path in enumerate(paths):
        truth = simulate.GroundTruth(**np.load(path.with_suffix(".truth.npz")))
        result = npz.read_scan_npz(scratch / "acc" / f"frame_{k:06d}.npz")
        acc = evaluate.accuracy(result, truth, spec, rig.calibration)
        rows.append({"frame": k, **{key: getattr(acc, key) for key in
                                    ("completeness", "stripe_accuracy", "outliers", "rms_mm", "median_mm")}})
    return rows


def table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """A markdown table of `rows`: (key, header, format) per column."""
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    rule = "|" + "|".join("---:" if f else "---" for _, _, f in columns) + "|"
    body = ["| " + " | ".join(format(r[k], f) if f else str(r[k]) for k, _, f in columns) + " |" for r in rows]
    return "\n".join([head, rule, *body])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", default="1280x1024")
    parser.add_argument("--distinct", type=int, default=8, help="frames rendered (the take cycles through them)")
    parser.add_argument("--frames", type=int, default=32, help="frames per throughput run")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--long", type=int, default=1000, help="frames of the flat-memory run (and a tenth)")
    parser.add_argument("--quick", action="store_true", help="16 frames, 2 runs, 200-frame memory run")
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "sliscan-bench")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.quick:
        args.frames, args.runs, args.long = 16, 2, 200
    camera = tuple(int(v) for v in args.camera.split("x"))
    paths, rig = render_take(camera, args.distinct, args.cache)
    job = batch.Job.create(patterns.default_spec(PROJECTOR), rig.calibration)
    with tempfile.TemporaryDirectory(prefix="sliscan-batch-") as tmp:
        scratch = Path(tmp)
        files = cycled(paths, args.frames, scratch / "frames")
        speed = throughput(job, files, args.runs, scratch)
        memory = flat_memory(paths, [args.long // 10, args.long], scratch)
        accuracy = per_frame_accuracy(paths, rig, job, scratch)
    w, h = camera
    print(f"\nThroughput, {w}x{h} frames to npz ({args.frames} frames, median of {args.runs} runs; "
          f"{psutil.cpu_count()} CPUs)\n")
    print(table(speed, [("runner", "runner", ""), ("fps", "frames/s", ".2f"), ("fps_min", "min", ".2f"),
                        ("fps_max", "max", ".2f"), ("vs_loop", "x loop", ".2f"), ("startup_s", "start-up s", ".1f"),
                        ("peak_mib", "peak MiB", ".0f")]))
    one, threaded, two = (row["fps"] for row in speed[1:])
    print(f"\n2 workers / 1 single-threaded worker: {two / one:.2f}x; "
          f"2 workers / 1 worker with 2 threads: {two / threaded:.2f}x")
    print("\nMemory against the number of frames (640x480 FFV1 video, 2 workers)\n")
    print(table(memory, [("frames", "frames", "d"), ("ok", "scanned", "d"), ("fps", "frames/s", ".2f"),
                         ("peak_mib", "peak MiB", ".0f")]))
    print(f"\nAccuracy of each frame of the moving sphere ({w}x{h}, against the ground truth)\n")
    print(table(accuracy, [("frame", "frame", "d"), ("completeness", "completeness", ".3f"),
                           ("stripe_accuracy", "right stripe", ".3f"), ("outliers", "outliers", ".4f"),
                           ("rms_mm", "RMS mm", ".1f"), ("median_mm", "median mm", ".1f")]))
    if args.json:
        args.json.write_text(json.dumps({"camera": args.camera, "throughput": speed, "workers_ratio": two / one,
                                         "workers_ratio_threaded": two / threaded,
                                         "memory": memory, "accuracy": accuracy}, indent=1))


if __name__ == "__main__":
    main()
