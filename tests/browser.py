"""Headless Chromium for the results-page tests: Debian's `chromium` (software WebGL
through SwiftShader) driven by playwright, and the pixel checks on the three views."""

from __future__ import annotations

import shutil
import time
from contextlib import contextmanager

import cv2
import numpy as np

BACKGROUND = np.array([27, 29, 34])  # the views' clear colour (web/src/main.js BACKGROUND)
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def chromium_path() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        raise RuntimeError(
            "the browser tests need Debian's chromium (./dev.sh test installs it: apt-get install chromium)"
        )
    return path


@contextmanager
def browser_page(width: int = 1280, height: int = 900):
    """(page, messages): a page in a fresh headless Chromium; messages collects console
    messages and page errors as (type, text)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            messages: list[tuple[str, str]] = []
            page.on("console", lambda m: messages.append((m.type, m.text)))
            page.on("pageerror", lambda e: messages.append(("pageerror", str(e))))
            yield page, messages
        finally:
            browser.close()


def wait_ready(page, timeout: float = 60.0) -> dict:
    """window.gsaViewer once it is ready or failed. Polled from here: the page's CSP
    forbids eval, which playwright's wait_for_function needs."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        state = page.evaluate(
            "() => window.gsaViewer ? {ready: gsaViewer.ready, error: gsaViewer.error, "
            "firstFrameMs: gsaViewer.firstFrameMs, loadedMs: gsaViewer.loadedMs ?? null} : null"
        )
        if state and (state["ready"] or state["error"]):
            return state
        time.sleep(0.1)
    raise AssertionError(f"the viewer was not ready within {timeout} s")


def canvas_pixels(page, selector: str) -> np.ndarray:
    """The element's screenshot as an (H, W, 3) RGB array."""
    png = page.locator(selector).screenshot()
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return bgr[:, :, ::-1].astype(np.int32)


def drawn_fraction(rgb: np.ndarray) -> float:
    """Share of pixels that differ from the clear colour."""
    return float((np.abs(rgb - BACKGROUND).max(axis=2) > 12).mean())


def wait_drawn(page, selector: str, minimum: float = 0.02, timeout: float = 30.0) -> float:
    """The share of the view's pixels that are drawn, once it reaches `minimum`."""
    deadline = time.monotonic() + timeout
    while True:
        found = drawn_fraction(canvas_pixels(page, selector))
        if found >= minimum:
            return found
        if time.monotonic() > deadline:
            raise AssertionError(f"{selector}: only {found:.4f} of the pixels drawn")
        time.sleep(0.25)


def colour_fractions(rgb: np.ndarray) -> dict[str, float]:
    """Shares of pixels of each overlay tint (web/src/main.js: target blue [.15, .45, 1],
    sources orange [1, .5, .1] then magenta [.95, .2, .75]) and of plain green, which no
    tint makes (the generated car's roof, seen with the tint off)."""
    r, g, b = rgb[:, :, 0], rgb[:, :, 1], rgb[:, :, 2]
    return {
        "orange": float(((r > 110) & (r - b > 70) & (r - g > 30)).mean()),
        "blue": float(((b > 110) & (b - r > 70)).mean()),
        "magenta": float(((r > 110) & (b > 90) & (np.minimum(r, b) - g > 60)).mean()),
        "green": float(((g - r > 30) & (g - b > 30)).mean()),
    }


def wait_colours(page, selector: str, predicate, timeout: float = 30.0) -> dict[str, float]:
    """The view's colour fractions once `predicate` holds for them (a toggle redraws
    on a later frame); the last ones in the assertion message otherwise."""
    deadline = time.monotonic() + timeout
    while True:
        found = colour_fractions(canvas_pixels(page, selector))
        if predicate(found):
            return found
        if time.monotonic() > deadline:
            raise AssertionError(f"{selector}: colours never matched: {found}")
        time.sleep(0.25)


def errors(messages) -> list[tuple[str, str]]:
    return [(t, m) for t, m in messages if t in ("error", "pageerror")]
