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


def wait_colours(page, selector: str, predicate, timeout: float = 60.0) -> dict[str, float]:
    """The view's colour fractions once `predicate` holds for them (a toggle redraws
    on a later frame); the last ones in the assertion message otherwise. 60 s: software WebGL
    on a shared 2-core machine has missed 30 s (a clean-clone run beside a benchmark)."""
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


def project(page, pane: str, point) -> list[float] | None:
    """Where internal point `point` shows in the view (client px), by the page's own camera."""
    return page.evaluate("([n, p]) => gsaViewer.project(n, p)", [pane, [float(v) for v in point]])


def click_pairs(page, candidates, truth, want: int, tolerance: float) -> list[dict]:
    """Point picking as a person does it, with the picking mode on: click a candidate's spot on
    the source view, then the spot where `truth` (internal source -> internal target, a callable)
    puts the point the page picked there on the target view. A pair whose target click landed
    on another surface (hidden from this side) is removed with the page's undo and the next
    candidate tried. Returns the page's pairs (internal coordinates)."""
    for p in candidates:
        made = len(page.evaluate("() => gsaViewer.guide.pairs"))
        if made >= want:
            break
        page.evaluate("() => window.scrollTo(0, 0)")  # the views in sight (a button click scrolls)
        xy = project(page, "source", p)
        if xy is None:
            continue
        page.mouse.click(*xy)
        picked = page.evaluate("() => gsaViewer.guide.pending.source || null")
        if picked is None:
            continue
        q = truth(np.asarray(picked, np.float64))
        xy = project(page, "target", q)
        if xy is not None:
            page.mouse.click(*xy)
        pairs = page.evaluate("() => gsaViewer.guide.pairs")
        if len(pairs) > made and np.linalg.norm(np.asarray(pairs[-1]["target"]) - q) <= tolerance:
            continue
        page.click("#pairs-undo")  # the half pair, or the pair whose target point was another one
    pairs = page.evaluate("() => gsaViewer.guide.pairs")
    assert len(pairs) >= want, f"only {len(pairs)} of {want} pairs could be clicked"
    return pairs


def screen_positions(page, pane: str, points) -> np.ndarray:
    """(N, 3): each internal point's client x, y and depth in the view, by the page's camera
    (the same projection its picking uses); depth <= 0 behind the camera."""
    project(page, pane, [0, 0, 0])  # places the camera for the current orbit
    cam = page.evaluate(
        "(n) => { const p = gsaViewer.panes[n]; const r = p.canvas.getBoundingClientRect(); "
        "return {proj: p.camera.projectionMatrix.elements, view: p.camera.matrixWorldInverse.elements, "
        "rect: [r.left, r.top, r.width, r.height]}; }",
        pane,
    )
    m = np.reshape(cam["proj"], (4, 4)).T @ np.reshape(cam["view"], (4, 4)).T  # three.js: column-major
    pts = np.asarray(points, np.float64)
    clip = np.c_[pts, np.ones(len(pts))] @ m.T
    w = clip[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = cam["rect"][0] + (0.5 + 0.5 * clip[:, 0] / w) * cam["rect"][2]
        y = cam["rect"][1] + (0.5 - 0.5 * clip[:, 1] / w) * cam["rect"][3]
    return np.c_[x, y, w]


def front_most(
    screen: np.ndarray, inside: tuple[float, float, float, float], slack: float, radius: float = 8.0
) -> np.ndarray:
    """Which points lie on the surface facing the view: no point within `radius` px of theirs is
    nearer the camera by more than `slack`, so a click on their spot picks them or a neighbour
    on that surface (web/src/guide.js nearestSplat: the nearest within 8 px); and inside the
    view's rectangle (left, top, w, h)."""
    from scipy.spatial import cKDTree

    ok = (screen[:, 2] > 0) & np.isfinite(screen).all(1)
    left, top, w, h = inside
    ok &= (screen[:, 0] > left + 10) & (screen[:, 0] < left + w - 10) & (screen[:, 1] > top + 10)
    ok &= screen[:, 1] < top + h - 10
    idx = np.flatnonzero(ok)
    tree = cKDTree(screen[idx, :2])
    keep = np.zeros(len(screen), bool)
    for j, near in zip(idx, tree.query_ball_point(screen[idx, :2], radius - 0.5)):
        keep[j] = screen[j, 2] <= screen[idx[near], 2].min() + slack
    return keep


def visible_in_both(page, source_points, truth) -> np.ndarray:
    """Source preview points (internal, opaque enough to be picked) on the surface the source view
    shows whose images under `truth` are on the surface the target view shows (the target's
    preview holds those images: a moved copy): the pairs a person could click from this side."""
    pts = np.asarray(source_points, np.float64)
    page.evaluate("() => window.scrollTo(0, 0)")
    rect = "(n) => { const r = gsaViewer.panes[n].canvas.getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; }"
    moved = truth(pts)
    slack = [0.02 * np.sqrt(((p - p.mean(0)) ** 2).sum(1).mean()) for p in (pts, moved)]  # 2 % of the size
    in_source = front_most(screen_positions(page, "source", pts), tuple(page.evaluate(rect, "source")), slack[0])
    in_target = front_most(screen_positions(page, "target", moved), tuple(page.evaluate(rect, "target")), slack[1])
    return pts[in_source & in_target]


def spread_points(points: np.ndarray, count: int) -> np.ndarray:
    """`count` of the points far apart (farthest-point order from the one nearest the centre)."""
    pts = np.asarray(points, np.float64)
    chosen = [int(np.argmin(np.linalg.norm(pts - pts.mean(0), axis=1)))]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    for _ in range(count - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(pts - pts[chosen[-1]], axis=1))
    return pts[chosen[1:] + chosen[:1]]
