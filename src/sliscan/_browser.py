"""Opening sliscan's HTML pages in a headless Chromium, for the tests and the benchmark (issue 10).

Playwright drives the Chromium the system installed (Debian's ``chromium``; never a browser
downloaded by ``playwright install``), with flags that keep it off the network (on a closed
network Chromium otherwise waits on its background connections).  WebGL then runs on
SwiftShader, Chromium's software renderer: ``--disable-gpu`` needs no further flag for it.
Playwright is part of the ``test`` extra, imported only here.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: The browser's executable (``SLISCAN_CHROMIUM`` overrides it).
CHROMIUM = Path(os.environ.get("SLISCAN_CHROMIUM", "/usr/bin/chromium"))
#: Headless, and nothing that reaches for the network.
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync")
#: The viewport pages are opened in (CSS px).
VIEWPORT = {"width": 1280, "height": 900}


@contextlib.contextmanager
def chromium() -> Iterator[Any]:
    """A headless Chromium (Playwright's ``Browser``), closed on exit."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=list(FLAGS), headless=True)
        try:
            yield browser
        finally:
            browser.close()


@dataclass
class Opened:
    """A page opened by `open_page`.

    Attributes
    ----------
    page : playwright Page
    seconds : float
        From the navigation's start until the page's load event and, when it has a 3D view,
        until plotly drew it (``#view3d[data-rendered="1"]``).
    errors : list of str
        Console errors and uncaught exceptions, as they come.
    """

    page: Any
    seconds: float
    errors: list[str] = field(default_factory=list)

    def figures(self) -> dict[str, int]:
        """The natural width (px) of every stage figure, by id (0: not decoded)."""
        return self.page.evaluate("() => Object.fromEntries(Array.from(document.querySelectorAll('img[data-figure]'))"
                                  ".map(i => [i.dataset.figure, i.complete ? i.naturalWidth : 0]))")

    def view_png(self) -> bytes:
        """A PNG screenshot of the 3D view."""
        return self.page.locator("#view3d").screenshot()


def open_page(browser: Any, path: str | os.PathLike, *, timeout_s: float = 60.0) -> Opened:
    """Open an HTML file and wait until it has loaded and its 3D view (if any) is drawn."""
    page = browser.new_page(viewport=VIEWPORT)
    opened = Opened(page, 0.0)
    page.on("console", lambda m: opened.errors.append(f"console: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: opened.errors.append(f"pageerror: {e}"))
    start = time.perf_counter()
    page.goto(Path(path).resolve().as_uri(), wait_until="load", timeout=timeout_s * 1e3)
    if page.query_selector("#view3d") is not None:
        page.wait_for_selector("#view3d[data-rendered='1']", state="attached", timeout=timeout_s * 1e3)
    opened.seconds = time.perf_counter() - start
    return opened
