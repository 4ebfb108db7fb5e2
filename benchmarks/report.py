"""Size and opening time of the HTML report of the demo scan (issue 10).

The demo's scene at the thesis's sizes (2592x1944 camera, 1024x768 projector, the sphere in
front of a wall under the demo's realistic conditions), scanned with sliscan's best pattern; the
report with the ground truth is written, then opened several times in headless Chromium
(Debian's, through Playwright: `sliscan._browser`), each time until plotly has drawn the 3D view.
Prints the size, the opening time (median and IQR) and how long building the report took.

    python benchmarks/report.py                        # 2592x1944, 5 openings
    python benchmarks/report.py --camera 640x480 --runs 3
    python benchmarks/report.py --screenshot docs/report.png   # also the README's picture

Needs the ``report`` and ``test`` extras and ``/usr/bin/chromium``.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from sliscan import __version__, _browser, patterns, report, simulate, viewer
from sliscan.pipeline import Scanner


def parse_size(text: str) -> tuple[int, int]:
    w, h = (int(v) for v in text.lower().split("x"))
    return w, h


def save_montage(page: object, path: Path, *, height: int = 1750, width: int = 1600) -> None:
    """The README's picture: the page's top (capture, spectrum) beside its 3D view section."""
    import cv2

    full = cv2.imdecode(np.frombuffer(page.screenshot(full_page=True), np.uint8), cv2.IMREAD_COLOR)
    top = page.evaluate("() => document.querySelector('#view').getBoundingClientRect().top + window.scrollY")
    view = int(top) - 20
    left, right = full[:height], full[view:view + height]
    right = np.pad(right, ((0, height - len(right)), (0, 0), (0, 0)), constant_values=255)
    both = np.hstack([left, np.full((height, 16, 3), 255, np.uint8), right])
    small = cv2.resize(both, (width, round(height * width / both.shape[1])), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(path), small, [cv2.IMWRITE_PNG_COMPRESSION, 9])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", type=parse_size, default=(2592, 1944), help="camera WxH [2592x1944]")
    parser.add_argument("--runs", type=int, default=5, help="openings of the page [5]")
    parser.add_argument("--max-points", type=int, default=viewer.MESH_BUDGET, help="3D view budget")
    parser.add_argument("--out", type=Path, help="keep the report here (default: a temporary folder)")
    parser.add_argument("--screenshot", type=Path, help="save a screenshot of the report's top and 3D view")
    args = parser.parse_args()

    rig = simulate.virtual_rig(camera_size=args.camera, projector_size=(1024, 768))
    spec = patterns.default_spec((1024, 768))
    conditions = simulate.Conditions(albedo=simulate.SmoothAlbedo(seed=0), ambient=0.1, projector_gamma=2.2,
                                     projector_blur_px=1.0, camera_blur_px=1.0, supersample=1, seed=0)
    t0 = time.perf_counter()
    capture = simulate.render(rig, simulate.sphere_scene(), patterns.render_pattern(spec), conditions)
    t1 = time.perf_counter()
    result, stages = Scanner(spec, rig.calibration).scan_stages(capture.image)
    t2 = time.perf_counter()
    page = report.scan_page(report.ScanReport(
        frames=capture.image[None], spec=spec, calibration=rig.calibration, result=result, stages=stages,
        truth=capture.truth, facts={"capture": f"benchmarks/report.py: demo sphere, {args.camera[0]}x{args.camera[1]}"},
        max_points=args.max_points))
    t3 = time.perf_counter()
    folder = args.out or Path(tempfile.mkdtemp(prefix="sliscan-report-"))
    path = report.write_page(folder / "report.html", page)
    figures_mb = sum(len(part.split('"', 1)[0]) for part in page.split('src="data:image/png;base64,')[1:]) / 1e6

    seconds = []
    with _browser.chromium() as browser:
        version = browser.version
        for run in range(args.runs):
            opened = _browser.open_page(browser, path)
            seconds.append(opened.seconds)
            if opened.errors:
                raise SystemExit(f"console errors: {opened.errors}")
            if run == 0 and args.screenshot is not None:
                save_montage(opened.page, args.screenshot)
            opened.page.close()
    q1, median, q3 = np.percentile(seconds, [25, 50, 75])
    w, h = args.camera
    print(f"sliscan {__version__}, Chromium {version}, Python {platform.python_version()}, {platform.machine()}")
    print(f"render {t1 - t0:.1f} s, scan {t2 - t1:.1f} s, report built in {t3 - t2:.1f} s; {path}")
    print(f"{'camera':>10s} {'points':>10s} {'shown':>8s} {'size MB':>8s} {'figs MB':>8s} {'open s (median)':>16s} "
          f"{'IQR s':>6s} {'runs':>5s}")
    shown = len(viewer.cloud_from_grid(result.points, result.valid, budget=args.max_points).vertices)
    print(f"{f'{w}x{h}':>10s} {int(result.valid.sum()):>10,d} {shown:>8,d} "
          f"{len(page.encode()) / 1e6:>8.1f} {figures_mb:>8.1f} {median:>16.2f} {q3 - q1:>6.2f} {args.runs:>5d}")


if __name__ == "__main__":
    main()
