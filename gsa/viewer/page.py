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

from gsa.errors import GSAError

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


class ViewerNotBuilt(GSAError, ValueError):
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
    photo = m.get("photo_match") if isinstance(m.get("photo_match"), dict) else None
    if photo is not None:  # two reconstructions: did their photos give the pose (gsa.align.photo)?
        said = "Registered by the photos" if photo.get("accepted") is True else "Photos not used"
        verdict += f'<p class="verdict photos">{said}: {esc(str(photo.get("reason", "")))}</p>'
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


# Up- and front-axis choices of the guide (gsa align --up/--front, REST/gRPC up_axes/front_axes):
# unit vectors in a file's own coordinates; the viewer turns them into the internal frame the
# previews are drawn in.
AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


def _finite_matrix(m, n: int) -> list[list[float]] | None:
    """m as an n×n list of finite floats, else None (a result from elsewhere may hold anything)."""
    try:
        rows = [[float(v) for v in row] for row in m]
    except (TypeError, ValueError):
        return None
    if len(rows) != n or any(len(r) != n or not all(math.isfinite(v) for v in r) for r in rows):
        return None
    return rows


def _number(v) -> float | None:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) else None


def guide_config(result: dict) -> dict:
    """What the viewer needs to guide a one-source result: the chosen pose and each alternative
    in align()'s internal frame (the frame the .splat previews are in, so the overlay can show
    them), each alternative also in the files' own coordinates, the rotations taking internal
    coordinates to each file's (picked points and up axes are sent in file coordinates, as
    init_transform, point_pairs and up_axes are given), and each file's up axis."""
    from gsa.io import frames  # numpy only
    from gsa.sim3 import Sim3

    fr = result.get("frames") if isinstance(result.get("frames"), dict) else {}
    formats, to_file, up = {}, {}, {}
    for role in ("source", "target"):
        desc = fr.get(role) if isinstance(fr.get(role), dict) else {}
        fmt = desc.get("format") if desc.get("format") in frames.FRAME_OF_FORMAT else "ply"
        formats[role] = fmt
        to_file[role] = frames.internal_to_file(fmt).rotation.tolist()
        up[role] = frames.FRAME_OF_FORMAT[fmt].up_axis
    pose = _finite_matrix(result.get("transform_internal") or result.get("transform"), 4)
    m = result.get("metrics") if isinstance(result.get("metrics"), dict) else {}
    alternatives = []
    for i, alt in enumerate(m.get("alternatives") or []):
        internal = _finite_matrix(alt.get("transform"), 4) if isinstance(alt, dict) else None
        if internal is None:
            continue  # kept out, but the others keep their index (--alternative N, "alternative": N)
        file = _finite_matrix(alt.get("file_transform"), 4) or (
            frames.file_transform(Sim3.from_matrix(internal), formats["source"], formats["target"]).matrix().tolist()
        )
        alternatives.append(
            {
                "index": i,
                "transform": internal,
                "file_transform": file,
                **{k: _number(alt.get(k)) for k in ("score", "rotation_offset_deg", "scale_ratio")},
            }
        )
    return {"pose": pose, "alternatives": alternatives, "to_file": to_file, "up": up}


def _guide(view: ResultView, mode: str) -> str:
    """The guide's controls (web/src/main.js drives them): alternatives, point pairs, up axes
    (with the fronts, when given) and a known scale (sent with each of the others)."""
    m = view.result.get("metrics") if isinstance(view.result.get("metrics"), dict) else {}
    n_alt = len(m.get("alternatives") or [])
    axes = "".join(f'<option value="{a}">{a}</option>' for a in AXES)
    fronts = '<option value="">not given</option>' + axes  # front_axes is optional
    act = (
        "starts a follow-up job; its page opens here and shows the result when it is done"
        if mode == "service"
        else "shows the gsa align command that does it"
    )
    return (
        "<section class=guide id=guide aria-labelledby=guide-title><h3 id=guide-title>Not right? Guide the alignment</h3>"
        f"<p class=hint>Each control below {act}.</p>"
        "<fieldset><legend>Alternatives</legend>"
        '<button type=button id=alt-prev aria-label="previous pose">◀ previous</button> '
        f"<output id=alt-label aria-live=polite>the chosen pose ({n_alt} alternative{'' if n_alt == 1 else 's'})</output> "
        '<button type=button id=alt-next aria-label="next pose">next ▶</button> '
        "<button type=button id=alt-use disabled>Use this one</button></fieldset>"
        "<fieldset><legend>Point pairs</legend>"
        "<button type=button id=pick-toggle aria-pressed=false>Pick point pairs</button> "
        "<button type=button id=pairs-undo disabled>Remove the last</button> "
        "<button type=button id=pairs-submit disabled>Align from these pairs</button>"
        "<p class=hint id=pick-hint>Click a point on the source view, then the same point on the target view; "
        "three pairs or more. While picking, each view orbits on its own: turn both to show the same side "
        "(the up axes below stand both models upright). Keyboard: focus a view (Tab), arrow keys orbit, "
        "+/− zoom, Enter picks the point under the centre cross.</p>"
        "<p id=pick-state class=status aria-live=polite>no pairs yet</p><ol id=pair-list class=pairs></ol></fieldset>"
        "<fieldset><legend>Up axes (in each file's own coordinates)</legend>"
        f"<label>source up <select id=up-source>{axes}</select></label> "
        f"<label>target up <select id=up-target>{axes}</select></label> "
        f"<label>source front <select id=front-source aria-describedby=front-error>{fronts}</select></label> "
        f"<label>target front <select id=front-target aria-describedby=front-error>{fronts}</select></label> "
        "<button type=button id=up-submit>Align with these up axes</button>"
        "<p class=hint>Optional: the way each model faces (its nose, its front door), across its up: "
        "the answer then turns about up only where the two fronts agree.</p>"
        "<p id=front-error class=error role=alert hidden></p></fieldset>"
        "<fieldset><legend>Scale</legend>"
        "<label>known scale (target units per source unit) "
        '<input id=scale-input type=text inputmode=decimal size=10 placeholder="not fixed" '
        "aria-describedby=scale-error autocomplete=off></label>"
        "<p class=hint>Optional: when given, each control above keeps the answer at this scale.</p>"
        "<p id=scale-error class=error role=alert hidden></p></fieldset>"
        "<div id=guide-out aria-live=polite></div></section>"
    )


def _canvas(name: str) -> str:
    # Focusable, so the views orbit from the keyboard too (web/src/main.js); the wrapper holds the
    # centre cross that Enter picks at (viewer.css).
    return (
        f'<div class=canvas-wrap><canvas id=view-{name} tabindex=0 role=img aria-label="{name} view: drag or '
        f'arrow keys to orbit, scroll or +/− to zoom"></canvas></div>'
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
        f"<figure class=pane><figcaption>Source (its own frame) {pick}</figcaption>{_canvas('source')}</figure>"
        f"<figure class=pane><figcaption>Target</figcaption>{_canvas('target')}</figure>"
        f"<figure class=pane><figcaption>Aligned overlay</figcaption>{_canvas('overlay')}</figure>"
        f"</div><div class=toggles>{boxes}<label><input type=checkbox id=toggle-tint checked> tint</label>"
        "<label><input type=checkbox id=link-views checked> orbit the views together</label>"
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
    guide: dict | None = None,
    poll: str | None = None,
) -> str:
    """The whole results page. `guide`: how its guide submits ({"mode": "service", "refine": URL}
    or {"mode": "cli", "source", "target", "result": shell-quoted paths}); shown for a one-source
    result with previews (refining takes one source). `poll`: a URL of the job's state, polled
    until it has finished, then the page reloads."""
    config = {
        "up": up if up in ("+z", "+y", "-y") else "+z",
        "results": [{"label": v.label, "preview": dict(v.preview)} for v in results],
    }
    guided = guide is not None and len(results) == 1 and bool(results[0].preview.get("target"))
    if guided:
        config["guide"] = {**guide, **guide_config(results[0].result)}
    if poll:
        config["poll"] = poll
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
        f"{_guide(results[0], guide['mode']) if guided else ''}"
        + "".join(result_section(i, v) for i, v in enumerate(results))
        + extra
        + note_list
        + f'<script type="application/json" id=gsa-config>{script_json(config)}</script>'
    )
    return layout(title, body, static_url, script=True)


# ---------------------------------------------------------------- many jobs (N-way registration)

# How the graph draws an edge of each verdict (gsa.align.many Edge.status): pruned edges red and
# dashed (inconsistent with the cycles, not used), corrected ones purple and dotted (re-estimated).
EDGE_STYLES = {
    "kept": ("#2e9e48", ""),
    "down-weighted": ("#e67e00", ""),
    "pruned": ("#d62828", "6 4"),
    "corrected": ("#7b3fbf", "2 3"),
}
MANY_TINTS = ("#2673ff", "#ff801a", "#f233bf", "#4de64d", "#ffe633")  # web/src/main.js MANY_TINTS


def is_many_result(result) -> bool:
    """many.json's content (gsa align-many, a many job's result): models and edges."""
    return isinstance(result, dict) and isinstance(result.get("models"), list) and isinstance(result.get("edges"), list)


def many_labels(result: dict) -> list[str]:
    """Each model's display name: its uploaded file name, else its name in many.json."""
    out = []
    for k, m in enumerate(result.get("models") or []):
        m = m if isinstance(m, dict) else {}
        out.append(str(m.get("filename") or m.get("name") or f"model {k + 1}"))
    return out


def _reference_index(result: dict) -> int | None:
    for k, m in enumerate(result.get("models") or []):
        if isinstance(m, dict) and m.get("name") == result.get("reference"):
            return k
    return None


def _edge_parts(e: dict, n: int) -> tuple[int, int, str, float | None] | None:
    i, j = e.get("source_index"), e.get("target_index")
    if not (isinstance(i, int) and isinstance(j, int) and 0 <= i < n and 0 <= j < n):
        return None
    status = e.get("status") if e.get("status") in EDGE_STYLES else "kept"
    res = e.get("residual") if isinstance(e.get("residual"), dict) else {}
    return i, j, status, _number(res.get("units"))


def many_graph_svg(result: dict, size: int = 360) -> str:
    """The models as nodes on a circle (the reference on top, ringed) and the pairwise edges
    as lines styled by verdict (EDGE_STYLES), each labelled with its residual in tolerance
    units; a <title> on each for the full numbers. '' without models."""
    labels = many_labels(result)
    n = len(labels)
    if not n:
        return ""
    ref = _reference_index(result)
    c, r = size / 2, size / 2 - 56
    start = ref or 0
    pos = [
        (c + r * math.sin(2 * math.pi * (k - start) / n), c - r * math.cos(2 * math.pi * (k - start) / n))
        for k in range(n)
    ]
    edges = []
    for e in result.get("edges") or []:
        parts = _edge_parts(e, n) if isinstance(e, dict) else None
        if parts is None:
            continue
        i, j, status, units = parts
        colour, dash = EDGE_STYLES[status]
        (x1, y1), (x2, y2) = pos[i], pos[j]
        dash_attr = f' stroke-dasharray="{dash}"' if dash else ""
        label = f"{units:.2g}" if units is not None else ""
        title = f"{labels[i]} → {labels[j]}: {status}, residual {fmt(units, 3)} tolerance units"
        edges.append(
            f'<g class="edge {status}" data-status="{status}" data-source="{i}" data-target="{j}">'
            f"<title>{esc(title)}</title>"
            f'<line x1="{x1:.1f}" y1="{y1:.1f}" x2="{x2:.1f}" y2="{y2:.1f}" stroke="{colour}" stroke-width="3"{dash_attr} />'
            f'<text x="{(x1 + x2) / 2:.1f}" y="{(y1 + y2) / 2 - 4:.1f}" fill="{colour}">{esc(label)}</text></g>'
        )
    nodes = []
    for k, (x, y) in enumerate(pos):
        m = result["models"][k] if isinstance(result["models"][k], dict) else {}
        is_ref = k == ref
        name = labels[k] if len(labels[k]) <= 22 else labels[k][:21] + "…"
        ring = (
            f'<circle cx="{x:.1f}" cy="{y:.1f}" r="17" fill="none" stroke="#1d2127" stroke-width="2" />'
            if is_ref
            else ""
        )
        nodes.append(
            f'<g class="node{" reference" if is_ref else ""}" data-model="{k}">'
            f"<title>{esc(labels[k])}{' (reference)' if is_ref else ''}: confidence {fmt(m.get('confidence'), 3)}</title>"
            f'{ring}<circle cx="{x:.1f}" cy="{y:.1f}" r="12" fill="{MANY_TINTS[k % len(MANY_TINTS)]}" />'
            f'<text x="{x:.1f}" y="{y + (30 if y >= c else -20):.1f}" text-anchor="middle">'
            f"{esc(name)}{' (reference)' if is_ref else ''}</text></g>"
        )
    return (
        f'<svg class="graph" id="many-graph" viewBox="0 0 {size} {size}" width="{size}" height="{size}" role="img" '
        f'aria-label="the pairwise alignments: models as nodes, edges by verdict">'
        + "".join(edges)
        + "".join(nodes)
        + "</svg>"
    )


def _many_edges_table(result: dict, labels: list[str]) -> str:
    rows = []
    for e in result.get("edges") or []:
        parts = _edge_parts(e, len(labels)) if isinstance(e, dict) else None
        if parts is None:
            continue
        i, j, status, units = parts
        res = e.get("residual") if isinstance(e.get("residual"), dict) else {}
        rows.append(
            f'<tr class="edge-{status}"><td>{esc(labels[i])} → {esc(labels[j])}</td><td>{esc(status)}</td>'
            f"<td>{fmt(e.get('confidence'), 3)}</td><td>{fmt(units, 3)}</td><td>{fmt(res.get('rotation_deg'), 3)}</td>"
            f"<td>{fmt(res.get('log_scale'), 3)}</td><td>{fmt(res.get('translation'), 3)}</td></tr>"
        )
    head = "".join(
        f"<th>{h}</th>"
        for h in ("edge", "verdict", "confidence", "residual (tol. units)", "rotation °", "|log scale|", "translation")
    )
    return f"<table class=edges><tr>{head}</tr>{''.join(rows)}</table>"


def _many_section(result: dict) -> str:
    labels = many_labels(result)
    ref = _reference_index(result)
    doubtful = [labels[k] for k, m in enumerate(result["models"]) if isinstance(m, dict) and m.get("doubtful")]
    pruned, corrected = result.get("pruned") or [], result.get("corrected") or []
    verdict = (
        f'<p class="verdict doubtful">{len(doubtful)} of {len(labels)} model(s) doubtful: {esc(", ".join(doubtful))}</p>'
        if doubtful
        else f'<p class="verdict ok">All {len(labels)} models placed confidently.</p>'
    )
    legend = "".join(
        f'<li><svg width="36" height="10"><line x1="0" y1="5" x2="36" y2="5" stroke="{c}" stroke-width="3"'
        + (f' stroke-dasharray="{d}"' if d else "")
        + f" /></svg> {esc(s)}</li>"
        for s, (c, d) in EDGE_STYLES.items()
    )
    return (
        "<section class=result id=many-result>"
        f"<h3>Reference: {esc(labels[ref]) if ref is not None else '—'}</h3>{verdict}"
        f"<p>Pruned (inconsistent with the cycles): {esc(', '.join(pruned)) or 'none'}. "
        f"Corrected: {esc(', '.join(corrected)) or 'none'}.</p>"
        f"<div class=tables><div><h4>Graph</h4>{many_graph_svg(result)}<ul class=legend>{legend}</ul></div>"
        f"<div><h4>Edges</h4>{_many_edges_table(result, labels)}</div></div></section>"
    )


def _many_viewer(result: dict) -> str:
    labels = many_labels(result)
    ref = _reference_index(result)
    boxes = "".join(
        f'<label class="tint-many{k % len(MANY_TINTS)}"><input type=checkbox data-many-model="{k}" checked> '
        f"{esc(name)}{' (reference)' if k == ref else ''} "
        f"<span class=conf>{fmt((result['models'][k] or {}).get('confidence'), 3)}</span></label>"
        for k, name in enumerate(labels)
    )
    up = "".join(f'<option value="{u}">{u} up</option>' for u in ("+z", "+y", "-y"))
    return (
        "<section class=viewer><div class=panes>"
        f"<figure class='pane many'><figcaption>All models in the reference frame</figcaption>{_canvas('many')}</figure>"
        f"</div><div class=toggles id=many-toggles>{boxes}<label><input type=checkbox id=toggle-tint checked> tint</label>"
        f"<select id=pick-up aria-label=up>{up}</select></div>"
        "<p id=viewer-status class=status>loading the models…</p>"
        "<p class=hint>Drag to orbit, scroll to zoom; the boxes show or hide each model (its confidence beside it).</p>"
        "</section>"
    )


def render_many_page(
    title: str,
    result: dict,
    previews: list[str | None],
    static_url: str,
    *,
    subtitle: str = "",
    notes: list[str] | None = None,
    links: list[tuple[str, str]] | None = None,
    up: str = "+z",
) -> str:
    """The results page of N models aligned into one frame (many.json): every model's preview
    (previews[k]: a URL of model k's .splat in its own frame, or None) placed by its transform
    into the reference frame, one toggle per model, and the graph of pairwise edges."""
    models = []
    for k, m in enumerate(result["models"]):
        m = m if isinstance(m, dict) else {}
        models.append(
            {
                "label": many_labels(result)[k],
                "transform": _finite_matrix(m.get("transform"), 4),
                "preview": previews[k] if k < len(previews) else None,
                "reference": k == _reference_index(result),
            }
        )
    config = {"up": up if up in ("+z", "+y", "-y") else "+z", "results": [], "many": {"models": models}}
    nav = " · ".join(f'<a href="{esc(u)}">{esc(t)}</a>' for t, u in links or [])
    note_list = "".join(f"<li>{esc(n)}</li>" for n in notes or [])
    note_list = f"<section><h3>Notes</h3><ul>{note_list}</ul></section>" if note_list else ""
    body = (
        f"<header><h1>{esc(title)}</h1><p class=sub>{esc(subtitle)}</p><nav>{nav}</nav></header>"
        f"{_many_viewer(result)}{_many_section(result)}{note_list}"
        f'<script type="application/json" id=gsa-config>{script_json(config)}</script>'
    )
    return layout(title, body, static_url, script=True)
