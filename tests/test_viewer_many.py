"""The many-job results page (N-way registration): the graph of a hand-made many.json marks pruned and
corrected edges, names the reference, and escapes the names; `gsa view many.json` (a real local
server, then headless Chromium) shows every model with a toggle and the marked graph."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from gsa.viewer.page import EDGE_STYLES, is_many_result, many_graph_svg, render_many_page
from tests.browser import browser_page, errors, wait_drawn, wait_ready

EYE = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]


def many_json(statuses=("kept", "pruned", "corrected")) -> dict:
    names = ["a", "b", "<c>"]
    pairs = [(0, 1), (1, 2), (0, 2)]
    return {
        "reference": "b",
        "models": [
            {"name": n, "index": k, "transform": EYE, "confidence": 0.9 - 0.3 * k, "doubtful": k == 2}
            for k, n in enumerate(names)
        ],
        "edges": [
            {
                "source": names[i],
                "target": names[j],
                "source_index": i,
                "target_index": j,
                "status": s,
                "confidence": 0.8,
                "residual": {"rotation_deg": 1.0, "log_scale": 0.01, "translation": 0.02, "units": u},
            }
            for (i, j), s, u in zip(pairs, statuses, (0.2, 7.5, 1.5))
        ],
        "pruned": [f"{names[i]} -> {names[j]}" for (i, j), s in zip(pairs, statuses) if s == "pruned"],
        "corrected": [f"{names[i]} -> {names[j]}" for (i, j), s in zip(pairs, statuses) if s == "corrected"],
    }


def edge_groups(svg: str) -> dict[str, str]:
    """status -> the <g> of that edge."""
    return {m.group(1): m.group(0) for m in re.finditer(r'<g class="edge ([a-z-]+)".*?</g>', svg)}


def test_graph_marks_pruned_and_corrected_edges():
    data = many_json()
    assert is_many_result(data)
    svg = many_graph_svg(data)
    assert svg.count('<g class="node') == 3 and svg.count('<g class="edge') == 3
    edges = edge_groups(svg)
    assert set(edges) == {"kept", "pruned", "corrected"}
    red, dashed = EDGE_STYLES["pruned"]
    assert f'stroke="{red}"' in edges["pruned"] and f'stroke-dasharray="{dashed}"' in edges["pruned"]
    purple, dotted = EDGE_STYLES["corrected"]
    assert f'stroke="{purple}"' in edges["corrected"] and f'stroke-dasharray="{dotted}"' in edges["corrected"]
    assert dashed != dotted and red != purple
    assert "stroke-dasharray" not in edges["kept"]
    assert ">7.5<" in edges["pruned"]  # its residual in tolerance units
    # The reference is ringed and named; a hostile name is escaped.
    ref = re.search(r'<g class="node reference" data-model="(\d)">.*?</g>', svg)
    assert ref and ref.group(1) == "1" and "b (reference)" in ref.group(0)
    assert "<c>" not in svg and "&lt;c&gt;" in svg


def test_many_page_has_a_toggle_per_model_and_the_config():
    data = many_json()
    page = render_many_page("Job x", data, ["/p0.splat", "/p1.splat", None], "/static/")
    assert page.count("data-many-model=") == 3 and "id=view-many" in page
    config = json.loads(page.split("id=gsa-config>", 1)[1].split("</script>", 1)[0])
    models = config["many"]["models"]
    assert [m["reference"] for m in models] == [False, True, False]
    assert [m["preview"] for m in models] == ["/p0.splat", "/p1.splat", None]
    assert models[0]["transform"] == EYE and models[2]["label"] == "<c>"
    assert "Pruned (inconsistent with the cycles): b -&gt; &lt;c&gt;" in page
    assert "class=edge-pruned" in page or 'class="edge-pruned"' in page
    assert "1 of 3 model(s) doubtful" in page


def test_graph_skips_malformed_edges():
    data = many_json()
    data["edges"].append({"source_index": 7, "target_index": 0, "status": "kept"})
    data["edges"].append("junk")
    assert many_graph_svg(data).count('<g class="edge') == 3
    assert many_graph_svg({"models": [], "edges": []}) == ""


def serve(path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "gsa.cli", "view", str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    url = proc.stdout.readline().strip()
    assert url.startswith("http://127.0.0.1:") and url.endswith("/"), (url, proc.stderr.read() if not url else "")
    return proc, url


@pytest.mark.slow
def test_gsa_view_of_a_many_json_in_the_browser(tmp_path):
    """`gsa view many.json` of gsa align-many (hand-made: the true transforms, one edge pruned):
    previews made from the files it names, a toggle per model, the pruned edge marked."""
    from gsa.io.ply import write_ply
    from gsa.synth import make_object, random_sim3

    rng = np.random.default_rng(3)
    data = many_json()
    files = []
    for k, m in enumerate(data["models"]):
        t = random_sim3(rng) if k != 1 else None  # model 1 is the reference: the identity
        car = make_object("car", seed=1, n_gaussians=1200, sample_seed=k)
        write_ply(car.transformed(t) if t else car, tmp_path / f"m{k}.ply")
        files.append(str(tmp_path / f"m{k}.ply"))
        m["transform"] = t.inverse().matrix().tolist() if t else EYE  # file k -> the reference frame
    data["files"] = files
    (tmp_path / "many.json").write_text(json.dumps(data))
    proc, url = serve(tmp_path / "many.json")
    try:
        with browser_page() as (page, messages):
            page.goto(url)
            state = wait_ready(page)
            assert state["ready"] and state["error"] is None, state
            wait_drawn(page, "#view-many")
            assert page.locator("input[data-many-model]").count() == 3
            page.locator('input[data-many-model="0"]').set_checked(False)
            assert page.evaluate("() => gsaViewer.visible") == {
                "model0": False,
                "model1": True,
                "model2": True,
                "tint": True,
            }
            visible = "() => Object.entries(gsaViewer.panes.many.meshes).filter(([k, m]) => m.visible).map(([k]) => k)"
            assert page.evaluate(visible) == ["model1", "model2"]
            assert page.locator("#many-graph g.node").count() == 3
            pruned = page.locator('#many-graph g.edge[data-status="pruned"] line')
            assert pruned.count() == 1 and pruned.get_attribute("stroke-dasharray") == EDGE_STYLES["pruned"][1]
            assert page.locator('#many-graph g.edge[data-status="corrected"]').count() == 1
            assert errors(messages) == [], messages
    finally:
        proc.terminate()
        proc.wait(10)
