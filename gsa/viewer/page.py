"""The results page: one HTML document for an alignment result, served by the service
(`GET /v1/jobs/{id}/view`) and by `gsa view`.

Everything shown is escaped here (file names and notes are user input); the 3D views
are drawn by static/viewer.js (built from web/), which reads the JSON config in
#gsa-config (escaped for a <script> element) and the preview files it names.
"""

from __future__ import annotations

import html
import json
import math
from dataclasses import dataclass, field
from importlib import resources

# The page loads only same-origin code; Spark runs its sorter in a blob: worker and
# compiles its inlined WebAssembly ('wasm-unsafe-eval').
CONTENT_SECURITY_POLICY = (
    "default-src 'none'; script-src 'self' 'wasm-unsafe-eval'; worker-src 'self' blob:; "
    "connect-src 'self' blob: data:; img-src 'self' data: blob:; style-src 'self'; "
    "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)
PAGE_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-store",
}
STATIC_FILES = {"viewer.js": "text/javascript; charset=utf-8", "viewer.css": "text/css; charset=utf-8"}


class ViewerNotBuilt(ValueError):
    """static/viewer.js is missing: the front end was not built (./dev.sh builds it from web/)."""


def static_file(name: str) -> bytes:
    """A file of the viewer's static assets (viewer.js, viewer.css)."""
    if name not in STATIC_FILES:
        raise FileNotFoundError(name)
    path = resources.files("gsa.viewer") / "static" / name
    try:
        return path.read_bytes()
    except FileNotFoundError:
        if name == "viewer.js":
            raise ViewerNotBuilt(
                "the viewer's bundle gsa/viewer/static/viewer.js is not built: run ./dev.sh build-web "
                "(npm ci + esbuild in web/)"
            ) from None
        raise


@dataclass
class ResultView:
    """One aligned source: its label (user text), its result dict and the URLs of its files."""

    label: str
    result: dict
    preview: dict[str, str | None] = field(default_factory=dict)  # source / target / aligned -> URL
    renders: list[tuple[str, str]] = field(default_factory=list)  # (name, URL)


def esc(value) -> str:
    return html.escape(str(value), quote=True)


def fmt(value, digits: int = 4) -> str:
    """A number or flag for display, escaped."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return esc(value)
    if isinstance(value, float):
        return esc(f"{value:.{digits}g}") if math.isfinite(value) else esc(value)
    if value is None:
        return "—"
    return esc(value)


def script_json(data) -> str:
    """JSON safe inside <script type="application/json">: no '<', '>' or '&' survive."""
    text = json.dumps(data, allow_nan=False, default=str)
    return text.replace("&", "\\u0026").replace("<", "\\u003c").replace(">", "\\u003e")


def layout(title: str, body: str, static_url: str, *, script: bool = False) -> str:
    js = f'<script type="module" src="{esc(static_url)}viewer.js"></script>' if script else ""
    return (
        "<!doctype html>\n<html lang=en><head><meta charset=utf-8>"
        '<meta name=viewport content="width=device-width, initial-scale=1">'
        f'<title>{esc(title)}</title><link rel=icon href="data:,"><link rel=stylesheet href="{esc(static_url)}viewer.css">{js}'
        f"</head><body>{body}</body></html>\n"
    )


def _rows(pairs) -> str:
    return "".join(f"<tr><th>{esc(k)}</th><td>{v}</td></tr>" for k, v in pairs)


def _vector(values, digits: int = 5) -> str:
    try:
        return "(" + ", ".join(fmt(float(v), digits) for v in values) + ")"
    except (TypeError, ValueError):
        return esc(values)


def _matrix(m) -> str:
    try:
        rows = "".join("<tr>" + "".join(f"<td>{fmt(float(v), 5)}</td>" for v in row) + "</tr>" for row in m)
    except (TypeError, ValueError):
        return esc(m)
    return f"<table class=matrix>{rows}</table>"


def loss_curve_svg(losses, width: int = 360, height: int = 140) -> str:
    """The fine stage's loss per iteration as an inline SVG polyline ('' without values)."""
    ys = [float(v) for v in losses or [] if isinstance(v, int | float) and math.isfinite(v)]
    if len(ys) < 2:
        return ""
    lo, hi = min(ys), max(ys)
    span = (hi - lo) or 1.0
    pad = 8
    pts = " ".join(
        f"{pad + i * (width - 2 * pad) / (len(ys) - 1):.1f},{pad + (hi - y) * (height - 2 * pad) / span:.1f}"
        for i, y in enumerate(ys)
    )
    return (
        f'<svg class=loss viewBox="0 0 {width} {height}" width={width} height={height} role=img '
        f'aria-label="fine-stage loss per iteration"><polyline fill=none stroke="#ff9f43" stroke-width=2 '
        f'points="{pts}"/><text x={pad} y={height - 2}>{len(ys)} iterations; loss {fmt(ys[0])} → '
        f"{fmt(ys[-1])} (min {fmt(lo)})</text></svg>"
    )


def _hypotheses(hyps) -> str:
    if not isinstance(hyps, list) or not hyps:
        return ""
    cols = ("origin", "score", "geometry", "colour", "overlap", "rotation_offset_deg", "scale_ratio")
    head = "".join(f"<th>{esc(c)}</th>" for c in cols)
    body = "".join(
        f"<tr{' class=chosen' if h.get('chosen') else ''}>"
        + "".join(f"<td>{fmt(h.get(c))}</td>" for c in cols)
        + "</tr>"
        for h in hyps[:24]
        if isinstance(h, dict)
    )
    more = f"<p>{len(hyps) - 24} more in result.json</p>" if len(hyps) > 24 else ""
    return (
        f"<h4>Hypotheses ({len(hyps)}; the chosen one marked)</h4><table class=hyps><tr>{head}</tr>{body}</table>{more}"
    )


def result_section(index: int, view: ResultView) -> str:
    r = view.result if isinstance(view.result, dict) else {}
    m = r.get("metrics") if isinstance(r.get("metrics"), dict) else {}
    doubtful = bool(m.get("doubtful"))
    verdict = (
        '<p class="verdict doubtful">Doubtful: '
        + ("ambiguous — other poses score as well; " if m.get("ambiguous") else "")
        + f"confidence {fmt(m.get('confidence'), 3)}. Check the overlay before trusting it.</p>"
        if doubtful
        else f'<p class="verdict ok">Confident: {fmt(m.get("confidence"), 3)}</p>'
    )
    sim3 = _rows(
        [
            ("scale", fmt(r.get("scale"), 6)),
            ("quaternion (w, x, y, z)", _vector(r.get("quaternion") or [])),
            ("translation", _vector(r.get("translation") or [])),
            ("4×4 (source → target)", _matrix(r.get("transform") or [])),
        ]
    )
    quality = _rows(
        (k, fmt(m.get(k)))
        for k in (
            "confidence",
            "ambiguous",
            "doubtful",
            "inlier_fraction",
            "rms_residual",
            "overlap_score",
            "margin",
            "colour_weight",
            "feature_agreement",
        )
        if k in m
    )
    stages = r.get("stages") if isinstance(r.get("stages"), dict) else {}
    fine = stages.get("fine") if isinstance(stages.get("fine"), dict) else {}
    curve = loss_curve_svg(fine.get("loss_history"))
    curve = f"<h4>Fine stage loss</h4>{curve}" if curve else ""
    renders = "".join(
        f'<figure><img src="{esc(url)}" alt="{esc(name)}" loading=lazy><figcaption>{esc(name)}</figcaption></figure>'
        for name, url in view.renders
    )
    renders = f"<h4>Before / after renders</h4><div class=renders>{renders}</div>" if renders else ""
    return (
        f'<section class=result id="result-{index}"><h3>{esc(view.label)}</h3>{verdict}'
        f"<div class=tables><div><h4>Sim(3)</h4><table>{sim3}</table></div>"
        f"<div><h4>Quality</h4><table>{quality}</table></div></div>"
        f"{_hypotheses(r.get('hypotheses'))}{curve}{renders}</section>"
    )


def _viewer(results: list[ResultView]) -> str:
    picks = "".join(f'<option value="{i}">{esc(v.label)}</option>' for i, v in enumerate(results))
    pick = f'<select id=pick-source aria-label="source shown">{picks}</select>' if len(results) > 1 else ""
    boxes = "<label class=tint-target><input type=checkbox data-model=target checked> target</label>" + "".join(
        f'<label class="tint-source{i % 4}"><input type=checkbox data-model="source{i}" checked> {esc(v.label)}</label>'
        for i, v in enumerate(results)
    )
    up = "".join(f'<option value="{u}">{u} up</option>' for u in ("+z", "+y", "-y"))
    return (
        "<section class=viewer><div class=panes>"
        f"<figure class=pane><figcaption>Source (its own frame) {pick}</figcaption><canvas id=view-source></canvas></figure>"
        "<figure class=pane><figcaption>Target</figcaption><canvas id=view-target></canvas></figure>"
        "<figure class=pane><figcaption>Aligned overlay</figcaption><canvas id=view-overlay></canvas></figure>"
        f"</div><div class=toggles>{boxes}<label><input type=checkbox id=toggle-tint checked> tint</label>"
        f"<select id=pick-up aria-label=up>{up}</select></div>"
        "<p id=viewer-status class=status>loading the models…</p>"
        "<p class=hint>Drag any view to orbit all three, scroll to zoom.</p></section>"
    )


def render_page(
    title: str,
    results: list[ResultView],
    static_url: str,
    *,
    subtitle: str = "",
    notes: list[str] | None = None,
    extra_renders: list[tuple[str, str]] | None = None,
    links: list[tuple[str, str]] | None = None,
    up: str = "+z",
) -> str:
    """The whole results page."""
    config = {
        "up": up if up in ("+z", "+y", "-y") else "+z",
        "results": [{"label": v.label, "preview": dict(v.preview)} for v in results],
    }
    doubtful = [v.label for v in results if (v.result.get("metrics") or {}).get("doubtful")]
    banner = (
        f'<p class="banner doubtful">{len(doubtful)} of {len(results)} result(s) doubtful: '
        + esc(", ".join(doubtful))
        + "</p>"
        if doubtful
        else ""
    )
    nav = " · ".join(f'<a href="{esc(u)}">{esc(t)}</a>' for t, u in links or [])
    extra = "".join(
        f'<figure><img src="{esc(u)}" alt="{esc(n)}" loading=lazy><figcaption>{esc(n)}</figcaption></figure>'
        for n, u in extra_renders or []
    )
    extra = (
        f"<section><h3>All models from shared cameras</h3><div class=renders>{extra}</div></section>" if extra else ""
    )
    note_list = "".join(f"<li>{esc(n)}</li>" for n in notes or [])
    note_list = f"<section><h3>Notes</h3><ul>{note_list}</ul></section>" if note_list else ""
    body = (
        f"<header><h1>{esc(title)}</h1><p class=sub>{esc(subtitle)}</p><nav>{nav}</nav></header>{banner}"
        f"{_viewer(results) if results else '<p>No results.</p>'}"
        + "".join(result_section(i, v) for i, v in enumerate(results))
        + extra
        + note_list
        + f'<script type="application/json" id=gsa-config>{script_json(config)}</script>'
    )
    return layout(title, body, static_url, script=True)
