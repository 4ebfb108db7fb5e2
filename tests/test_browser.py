"""The HTML pages in a real browser: Debian's headless Chromium driven by Playwright (issue 10).

Each page must load without a console error or an uncaught exception, show every figure (each
``<img>`` decoded), and draw its 3D view (a WebGL canvas that is not blank).  Screenshots go to
``test-artifacts/`` at the repository's root.

Chromium is launched as installed (never ``playwright install``) with flags that keep it off the
network (`sliscan._browser`); WebGL then runs on SwiftShader, Chromium's software renderer.
Without ``/usr/bin/chromium`` the tests skip, unless ``SLISCAN_REQUIRE_BROWSER`` is set (CI sets
it: ``.ci/run`` installs the browser).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from sliscan import _browser
from test_cli import ok
from test_report import COMPOSITE_FIGURES, write_summary

ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts"
#: The issue's size limit for the demo scan's report, checked here on a 640x480 scan; its 5 s
#: opening time is measured by benchmarks/report.py (a timing on a busy 2-core test run is
#: noise: it failed at 5.04 s once), so the test only guards against a page that hangs.
MAX_MB, HANG_S = 30, 60.0


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    """A headless Chromium (Playwright's Browser)."""
    if not _browser.CHROMIUM.exists():
        message = f"{_browser.CHROMIUM} not found: install Debian's chromium (apt-get install chromium)"
        if os.environ.get("SLISCAN_REQUIRE_BROWSER"):
            pytest.fail(message + " (SLISCAN_REQUIRE_BROWSER is set)")
        pytest.skip(message)
    pytest.importorskip("playwright.sync_api")
    with _browser.chromium() as chromium:
        yield chromium


@pytest.fixture(scope="module")
def pages(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 640x480 sphere on the virtual rig: its scan report with the ground truth, the PLY's view
    and a batch report."""
    folder = tmp_path_factory.mktemp("pages")
    ok("pattern", "composite", "--projector", "1024x768", "-o", "cp.png", cwd=folder)
    ok("simulate", "--pattern", "cp.json", "--scene", "sphere", "--camera", "640x480", "--albedo", "smooth",
       "--write-rig", "rig.json", "--truth", "truth.npz", "-o", "capture.png", cwd=folder)
    ok("report", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json", "--truth", "truth.npz",
       "-o", "report.html", cwd=folder)
    ok("scan", "capture.png", "--pattern", "cp.json", "--calibration", "rig.json", "--ply", "s.ply", cwd=folder)
    ok("view", "s.ply", "-o", "view.html", "--no-open", cwd=folder)
    write_summary(folder, "list")
    ok("report", "--batch", "summary.json", "-o", "batch.html", cwd=folder)
    return folder


def view_pixels(opened: _browser.Opened, name: str) -> np.ndarray:
    """A screenshot of the 3D view, saved as a test artifact, as a BGR image."""
    png = opened.view_png()
    ARTIFACTS.mkdir(exist_ok=True)
    (ARTIFACTS / name).write_bytes(png)
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def assert_drawn(pixels: np.ndarray) -> None:
    """A rendered plot, not a blank canvas: many coloured (non-grey) pixels and contrast."""
    b, g, r = (pixels[..., k].astype(np.int16) for k in range(3))
    coloured = (np.maximum(np.maximum(abs(r - g), abs(g - b)), abs(r - b)) > 40).mean()
    assert coloured > 0.02 and pixels.std() > 20, (coloured, pixels.std())


def test_scan_report_in_the_browser(browser, pages: Path) -> None:
    opened = _browser.open_page(browser, pages / "report.html")
    assert opened.errors == []
    shown = opened.figures()
    assert set(shown) == COMPOSITE_FIGURES and all(width > 0 for width in shown.values()), shown
    assert opened.page.locator("#view3d canvas").count() >= 1  # plotly's WebGL canvas
    assert opened.page.evaluate("() => !!document.createElement('canvas').getContext('webgl')")
    assert_drawn(view_pixels(opened, "report-3d.png"))
    assert opened.page.locator("#timings td").first.inner_text() == "read"
    assert "stripe accuracy" in opened.page.locator("#accuracy").inner_text()
    # colour by texture: the switch decodes the grey levels and restyles without an error
    opened.page.select_option("#view select", "texture")
    opened.page.wait_for_timeout(500)
    assert opened.errors == []
    assert view_pixels(opened, "report-3d-texture.png").std() > 20  # grey: contrast, no colour to count
    opened.page.screenshot(path=str(ARTIFACTS / "report.png"), full_page=True)
    opened.page.close()


def test_scan_report_is_small_and_opens(browser, pages: Path) -> None:
    size_mb = (pages / "report.html").stat().st_size / 1e6
    assert size_mb < MAX_MB
    opened = _browser.open_page(browser, pages / "report.html")
    opened.page.close()
    assert opened.seconds < HANG_S and opened.errors == []


def test_view_of_a_ply_in_the_browser(browser, pages: Path) -> None:
    opened = _browser.open_page(browser, pages / "view.html")
    assert opened.errors == [] and opened.figures() == {}
    assert_drawn(view_pixels(opened, "view-3d.png"))
    opened.page.close()


def test_batch_report_in_the_browser(browser, pages: Path) -> None:
    opened = _browser.open_page(browser, pages / "batch.html")
    assert opened.errors == []
    shown = opened.figures()
    assert set(shown) == {"batch"} and shown["batch"] > 0
    assert opened.page.locator("#frames tbody tr").count() == 3
    opened.page.screenshot(path=str(ARTIFACTS / "batch.png"), full_page=True)
    opened.page.close()


def test_artifacts_folder_is_ignored_by_git() -> None:
    root = ARTIFACTS.parent
    if shutil.which("git") is None or not (root / ".git").exists():
        pytest.skip("not a git checkout")
    import subprocess

    result = subprocess.run(["git", "check-ignore", "-q", str(ARTIFACTS / "report.png")], cwd=root)
    assert result.returncode == 0
