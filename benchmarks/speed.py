"""Speed of single-shot scanning, stage by stage, against the open tools a user would pick.

On the same rendered frames (the virtual rig's sphere under the accuracy benchmark's smooth
albedo conditions, sliscan's default pattern), for a 1280x1024 and a 2592x1944 camera and
each Scanner configuration of `CONFIGS` (the two demodulators, the baseband path with the 3D
filters, the real-time configuration without them, into reused or new output arrays): each stage of `Scanner.scan` (demodulate, decode, triangulate with its
filters), the whole in-memory scan, and the export to npz and PLY; median and spread (min to
max) over 7 runs after one warm-up run, 3 runs for anything over 1 s; the peak memory of one
scan (ru_maxrss of a fresh subprocess).  In the same run, when installed (the `bench`
extra): OpenCV's structured_light (`SinusoidalPattern` PSP phase + unwrap of three frames:
its single-frame FTP crashes with a segmentation fault in `computePhaseMap` in
opencv-contrib 4.14 and 5.0 for every frame size tried, so the three-step method stands in
for it and flatters OpenCV by the two frames it does not need; `GrayCodePattern` decode of a stereo sequence of the projector's Gray code) and the
`fringes` package against `sliscan.pmp.decode_pmp` on 3 frequencies x 4 steps, each as the
ratio peer / sliscan.  Rendering a 5 MP frame takes minutes, so frames are cached (``--cache``).

    pip install -e '.[bench]'
    python benchmarks/speed.py --json benchmarks/speed.json --markdown speed.md
    python benchmarks/speed.py --quick               # 1280x1024 only, fewer runs
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from sliscan import patterns, simulate
from sliscan.decode import decode
from sliscan.pipeline import Scanner
from sliscan.types import PatternSpec

sys.path.insert(0, str(Path(__file__).parent))
from accuracy import conditions  # noqa: E402

PROJECTOR = (1024, 768)


#: `--pattern` choices: sliscan's stripe pattern and the one with a phase channel (issue 8).
PATTERNS = {"default": patterns.default_spec, "phase": patterns.phase_spec}

#: `--methods` choices: the `Scanner` options of each.  ``realtime``: the baseband path as a
#: stream of frames from one rig uses it, carriers found in the first frame and kept, without
#: the 3D filters (issue 6's configuration: demodulate + decode + triangulate) and without
#: dividing the capture by its albedo (``Scanner(albedo=None)``), each frame scanned into the
#: previous frame's result (`REUSE_OUTPUTS`); ``realtime-fresh``: the same with new output
#: arrays for every frame; ``realtime-textured``: ``realtime`` divided by its albedo steps and
#: flat field (the baseband path's default, for textured surfaces).
_REALTIME = dict(method="baseband", reuse_carriers=True, remove_speckles=False, remove_narrow_runs=False, albedo=None)
CONFIGS: dict[str, dict] = {"window": dict(method="window"), "bandpass": dict(method="bandpass"),
                            "baseband": dict(method="baseband"), "realtime": _REALTIME, "realtime-fresh": _REALTIME,
                            "realtime-textured": dict(_REALTIME, albedo="steps")}

#: The configurations whose scans overwrite the previous scan's arrays (`Scanner.scan`'s `out`).
REUSE_OUTPUTS = {"realtime", "realtime-textured"}


def frame(camera: tuple[int, int], cache: Path, pattern: str = "default") -> tuple[np.ndarray, simulate.Rig, PatternSpec]:
    """The sphere capture for `camera` (rendered once, then read from `cache`), its rig and spec."""
    rig = simulate.virtual_rig(camera_size=camera, projector_size=PROJECTOR)
    spec = PATTERNS[pattern](PROJECTOR)
    path = cache / f"sphere_{camera[0]}x{camera[1]}{'' if pattern == 'default' else '_' + pattern}.npy"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        capture = simulate.render(rig, simulate.sphere_scene(), patterns.render_pattern(spec), conditions("smooth", 0))
        np.save(path, capture.image)
    return np.load(path), rig, spec


def timed(fn: Callable[[], object], runs: int) -> dict:
    """Median, min and max seconds of `fn` over `runs` runs after one warm-up (3 if it takes > 1 s)."""
    t0 = time.perf_counter()
    fn()
    if time.perf_counter() - t0 > 1.0:
        runs = min(runs, 3)
    seconds = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        seconds.append(time.perf_counter() - t0)
    return {"median": statistics.median(seconds), "min": min(seconds), "max": max(seconds), "runs": runs}


def stage_times(image: np.ndarray, rig: simulate.Rig, spec: PatternSpec, config: str, runs: int) -> dict[str, dict]:
    """Per-stage and whole-scan times of one frame (stages from `ScanResult.timings`) with the
    Scanner options of `CONFIGS[config]`."""
    scanner = Scanner(spec, rig.calibration, **CONFIGS[config])
    scanner.scan(image)  # the rig's one-time setup (kernels from their cache, the baseband path's geometry)
    timings, last = [], []  # each run's stage times, the last result (not every one: memory)

    def scan() -> None:
        last[:] = [scanner.scan(image, out=last[0] if last and config in REUSE_OUTPUTS else None)]
        timings.append(last[0].timings)

    total = timed(scan, runs)
    out = {}
    for stage in ("demodulate", "decode", "triangulate"):
        seconds = [t[stage] for t in timings[1:]]
        out[stage] = {"median": statistics.median(seconds), "min": min(seconds), "max": max(seconds),
                      "runs": len(seconds)}
    out["scan"] = total
    if scanner.method != "baseband":  # its decoding is part of one pass with the triangulation
        demod, _ = scanner.demodulate(image)
        out["decode only"] = timed(lambda: decode(demod, spec), runs)
        out["decode only, per-pixel decisions"] = timed(lambda: decode(demod, spec, order=False), runs)
    result = last[0]
    with tempfile.TemporaryDirectory() as tmp:
        out["export npz"] = timed(lambda: result.save_npz(Path(tmp) / "scan.npz"), runs)
        out["export PLY"] = timed(lambda: result.save_ply(Path(tmp) / "scan.ply"), runs)
    return out


def peak_memory_mib(camera: tuple[int, int], config: str, cache: Path, pattern: str = "default") -> float:
    """Peak resident memory (MiB) of a fresh process that loads the frame, builds a Scanner and
    scans once, with the compiled kernels already cached.

    Read from ``VmHWM`` in ``/proc/self/status``, which a new program image starts afresh:
    ``ru_maxrss`` survives ``exec``, so a child started from this process (holding the scans
    of the timing runs) would report this process's size instead of its own."""
    code = ("import sys; sys.path.insert(0, {bench!r}); from speed import CONFIGS, frame; "
            "from sliscan.pipeline import Scanner; from pathlib import Path; "
            "image, rig, spec = frame({camera!r}, Path({cache!r}), {pattern!r}); "
            "Scanner(spec, rig.calibration, **CONFIGS[{config!r}]).scan(image); "
            "print(next(line.split()[1] for line in open('/proc/self/status') if line.startswith('VmHWM')))")
    command = [sys.executable, "-c", code.format(bench=str(Path(__file__).parent), camera=camera, cache=str(cache),
                                                 config=config, pattern=pattern)]
    # twice: a first process may compile the numba kernels (LLVM's memory, not the scan's) and caches them
    outs = [subprocess.run(command, check=True, capture_output=True, text=True).stdout for _ in range(2)]
    return int(outs[-1].split()[-1]) / 1024


def opencv_psp(image: np.ndarray, runs: int) -> dict | None:
    """OpenCV structured_light PSP: wrapped phase + unwrapping of three 8-bit frames (the
    frame and two copies: the cost does not depend on content)."""
    try:
        import cv2
        sl = cv2.structured_light
    except (ImportError, AttributeError):
        return None
    h, w = image.shape
    params = sl.SinusoidalPattern.Params()
    params.width, params.height, params.nbrOfPeriods = w, h, 64
    params.methodId, params.horizontal, params.setMarkers = sl.PSP, False, False
    pattern = sl.SinusoidalPattern_create(params)
    frame8 = [np.clip(image * 255, 0, 255).astype(np.uint8)] * 3

    def run() -> None:
        wrapped, mask = pattern.computePhaseMap(frame8)[:2]
        pattern.unwrapPhaseMap(wrapped, (w, h), shadowMask=mask)

    return timed(run, runs)


def opencv_graycode(camera: tuple[int, int], runs: int) -> dict | None:
    """OpenCV structured_light GrayCodePattern decode of a stereo sequence (the projector's
    Gray code frames resized to the camera: the decode's cost does not depend on content)."""
    try:
        import cv2
        sl = cv2.structured_light
    except (ImportError, AttributeError):
        return None
    pattern = sl.GrayCodePattern_create(*PROJECTOR)
    _, frames = pattern.generate()
    views = [cv2.resize(f, camera, interpolation=cv2.INTER_NEAREST) for f in frames]
    white, black = np.full(views[0].shape, 255, np.uint8), np.zeros(views[0].shape, np.uint8)
    return timed(lambda: pattern.decode([views, views], blackImages=[black, black], whiteImages=[white, white],
                                        flags=sl.DECODE_3D_UNDERWORLD), runs)


def pmp_times(camera: tuple[int, int], runs: int) -> tuple[dict | None, dict | None]:
    """`sliscan.pmp.decode_pmp` and `fringes` decoding 3 frequencies x 4 steps at `camera`
    (each on its own encoding of the same size: cost does not depend on content)."""
    try:
        from sliscan import pmp
    except ImportError:
        return None, None
    freqs = (1, 8, 64)
    spec = PatternSpec(kind="pmp", projector_size=camera, steps=4, frequencies=freqs, orientation="rows")
    frames = pmp.pattern_frames(spec).astype(np.float32)
    ours = timed(lambda: pmp.decode_pmp(frames, spec, "rows"), runs)
    try:
        import fringes
    except ImportError:
        return ours, None
    peer = fringes.Fringes(X=camera[0], Y=camera[1], K=3, N=4, v=freqs, axes=(1,))
    encoded = peer.encode()
    return ours, timed(lambda: peer.decode(encoded), runs)


def markdown(report: dict) -> str:
    """The report as Markdown tables (milliseconds)."""
    lines = ["| camera | method | stage | median (ms) | min-max (ms) | runs |", "|---|---|---|---|---|---|"]
    for row in report["stages"]:
        lines.append(f"| {row['camera']} | {row['method']} | {row['stage']} | {1e3 * row['median']:.1f} "
                     f"| {1e3 * row['min']:.1f}-{1e3 * row['max']:.1f} | {row['runs']} |")
    lines += ["", "| camera | peer | peer median (ms) | sliscan (ms) | peer / sliscan |", "|---|---|---|---|---|"]
    for row in report["peers"]:
        if row["peer"] is None or row["sliscan"] is None:
            lines.append(f"| {row['camera']} | {row['name']} | not available | | |")
        else:
            lines.append(f"| {row['camera']} | {row['name']} | {1e3 * row['peer']:.1f} | {1e3 * row['sliscan']:.1f} "
                         f"| {row['peer'] / row['sliscan']:.2f} |")
    lines += ["", "| camera | method | peak memory (MiB) |", "|---|---|---|"]
    lines += [f"| {r['camera']} | {r['method']} | {r['mib']:.0f} |" for r in report["memory"]]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="1280x1024 only, 3 runs")
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--methods", default=",".join(CONFIGS),
                        help=f"comma-separated, of {', '.join(CONFIGS)} (see CONFIGS)")
    parser.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "sliscan-speed-frames"))
    parser.add_argument("--pattern", choices=sorted(PATTERNS), default="default",
                        help="the scanned pattern: sliscan's stripes, or with a phase channel (issue 8)")
    parser.add_argument("--no-peers", action="store_true", help="time sliscan only")
    parser.add_argument("--json", help="write the report as JSON to this file")
    parser.add_argument("--markdown", help="also write the tables as Markdown to this file")
    args = parser.parse_args()
    cameras = [(1280, 1024)] if args.quick else [(1280, 1024), (2592, 1944)]
    runs = 3 if args.quick else args.runs
    cache = Path(args.cache)
    report: dict = {"pattern": args.pattern, "stages": [], "peers": [], "memory": []}
    for camera in cameras:
        name = f"{camera[0]}x{camera[1]}"
        image, rig, spec = frame(camera, cache, args.pattern)
        scans = {}
        for method in args.methods.split(","):
            for stage, t in stage_times(image, rig, spec, method, runs).items():
                report["stages"].append({"camera": name, "method": method, "stage": stage, **t})
                if stage == "scan":
                    scans[method] = t["median"]
                print(f"{name} {method:8s} {stage:12s} {1e3 * t['median']:9.1f} ms "
                      f"({1e3 * t['min']:.1f}-{1e3 * t['max']:.1f}, {t['runs']} runs)", flush=True)
            report["memory"].append({"camera": name, "method": method,
                                     "mib": peak_memory_mib(camera, method, cache, args.pattern)})
        if args.no_peers:
            continue
        ours = {method: scans[method] for method in ("window", "realtime") if method in scans} or dict(
            [next(iter(scans.items()))])
        for peer, t in (("OpenCV PSP phase + unwrap (3 frames; its FTP crashes)", opencv_psp(image, runs)),
                        ("OpenCV Gray code decode (stereo, 2 x 22 frames)", opencv_graycode(camera, runs))):
            for method, seconds in ours.items():
                report["peers"].append({"camera": name, "name": f"{peer} / sliscan {method}", "peer": t and t["median"],
                                        "sliscan": seconds})
        if camera == (1280, 1024):
            sliscan_pmp, fringes_pmp = pmp_times(camera, runs)
            report["peers"].append({"camera": name, "name": "fringes PMP decode, 3 freq x 4 steps",
                                    "peer": fringes_pmp and fringes_pmp["median"],
                                    "sliscan": sliscan_pmp and sliscan_pmp["median"]})
    report["ru_maxrss_mib_this_process"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    table = markdown(report)
    print(table)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    if args.markdown:
        Path(args.markdown).write_text(table)


if __name__ == "__main__":
    main()
