"""The results page's guide on `gsa view` (the guided path): alternatives stated in file coordinates by
the result writer, the page's guide config, and, in headless Chromium against a real `gsa view`,
each control (alternatives, point picking by mouse and keyboard, up and front axes) showing the
`gsa align` command that a person then runs: the commands are run here too and their results
checked.

The source is an SPZ file (a 180° turn from the internal frame the previews are drawn in), so a
point, pose or axis sent without its conversion into file coordinates fails these tests."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gsa.align.outputs import result_dict, write_outputs
from gsa.align.pipeline import AlignOptions, align
from gsa.geometry import axis_rotation
from gsa.io.formats import read_model, write_model
from gsa.io.ply import write_ply
from gsa.metrics import rre_deg
from gsa.sim3 import Sim3
from gsa.synth import make_object
from gsa.viewer.local import collect
from gsa.viewer.page import ResultView, guide_config, render_page
from gsa.viewer.preview import read_splat
from tests.browser import (
    browser_page,
    click_pairs,
    errors,
    project,
    spread_points,
    visible_in_both,
    wait_drawn,
    wait_ready,
)

FLIP = np.diag([1.0, -1.0, -1.0])  # internal (RDF) <-> SPZ (RUB)
# The truth turns the chair's up (-y internally, +y in the SPZ file) onto the target's +z.
TRUTH = Sim3(
    1.7, axis_rotation([0, 0, 1.0], np.radians(130)) @ axis_rotation([1.0, 0, 0], np.radians(-90)), [0.3, -0.2, 0.5]
)


@pytest.fixture(scope="module")
def spz_pair(tmp_path_factory):
    """A chair as source.spz and its copy moved by TRUTH as target.ply, aligned (coarse stage),
    with gsa align's outputs (result.json naming the inputs, previews) in out/."""
    d = tmp_path_factory.mktemp("guide")
    write_model(make_object("chair", seed=5, n_gaussians=3000), d / "source.spz", "spz")
    source = read_model(d / "source.spz")
    write_ply(source.transformed(TRUTH), d / "target.ply")
    target = read_model(d / "target.ply")  # as gsa align reads it: a PLY (metadata "format")
    options = AlignOptions(stages=("coarse",), coarse_iterations=30, seed=0, alternatives="always")
    result = align(source, target, options)
    paths = write_outputs(result, source, target, d / "out", outputs={"result", "preview"})
    data = json.loads(paths["result.json"].read_text())
    data["inputs"] = {"source": str(d / "source.spz"), "target": str(d / "target.ply")}
    paths["result.json"].write_text(json.dumps(data))
    assert data["metrics"]["alternatives"], data["metrics"]  # the page steps through them
    return {"dir": d, "source": source, "target": target, "result": result, "json": data}


def test_alternatives_are_also_stated_in_file_coordinates(spz_pair):
    source, target, result = spz_pair["source"], spz_pair["target"], spz_pair["result"]
    before = json.dumps(result.verdict.entries()["alternatives"])
    data = result_dict(result, source, target)
    x_internal = source.means[:50].astype(np.float64)
    x_file = x_internal @ FLIP  # the points as the SPZ file stores them
    for alt, kept in zip(data["metrics"]["alternatives"], result.verdict.alternatives):
        assert alt["transform"] == kept.details["transform"]  # still internal: --alternative N and refine read it
        internal = Sim3.from_matrix(np.asarray(alt["transform"]))
        file = Sim3.from_matrix(np.asarray(alt["file_transform"]))
        # The file-frame pose takes the source file's points where the internal pose puts them
        # in the target's file (PLY: the internal frame).
        np.testing.assert_allclose(file.apply(x_file), internal.apply(x_internal), atol=1e-9)
        assert rre_deg(file.rotation, internal.rotation) > 90  # SPZ: a real difference, not a copy
    assert json.dumps(result.verdict.entries()["alternatives"]) == before  # the result itself is not changed


def test_guide_config_for_an_spz_source(spz_pair):
    data = spz_pair["json"]
    cfg = guide_config(data)
    np.testing.assert_allclose(cfg["to_file"]["source"], FLIP)
    np.testing.assert_allclose(cfg["to_file"]["target"], np.eye(3))
    assert cfg["up"] == {"source": "+y", "target": "-y"}  # each file's own up (SPZ RUB, PLY RDF)
    np.testing.assert_allclose(cfg["pose"], data["transform_internal"])  # the previews' frame
    alts = data["metrics"]["alternatives"]
    assert [a["index"] for a in cfg["alternatives"]] == list(range(len(alts)))
    for a, alt in zip(cfg["alternatives"], alts):
        np.testing.assert_allclose(a["transform"], alt["transform"])
        np.testing.assert_allclose(a["file_transform"], alt["file_transform"])
    # A result written before file_transform existed gets it computed; a broken entry keeps the
    # others' indices (they are what --alternative N and "alternative": N mean).
    old = json.loads(json.dumps(data))
    for alt in old["metrics"]["alternatives"]:
        del alt["file_transform"]
    old["metrics"]["alternatives"].insert(0, {"transform": [[float("nan")] * 4] * 4})
    cfg_old = guide_config(old)
    assert [a["index"] for a in cfg_old["alternatives"]] == list(range(1, len(alts) + 1))
    for a, alt in zip(cfg_old["alternatives"], alts):
        np.testing.assert_allclose(a["file_transform"], alt["file_transform"], atol=1e-12)


def test_guide_only_for_one_source_with_previews(spz_pair):
    view = ResultView("s", spz_pair["json"], preview={k: f"{k}.splat" for k in ("source", "target", "aligned")})
    guide = {"mode": "cli", "source": "a", "target": "b", "result": "r"}

    def config(page):
        return json.loads(page.split("id=gsa-config>", 1)[1].split("</script>", 1)[0])

    one = render_page("t", [view], "static/", guide=guide)
    assert "id=guide " in one and config(one)["guide"]["mode"] == "cli"
    for views in ([view, view], [ResultView("s", spz_pair["json"])]):  # two sources; no previews
        page = render_page("t", views, "static/", guide=guide)
        assert "id=guide " not in page and "guide" not in config(page)
    assert "id=guide " not in render_page("t", [view], "static/")


def test_gsa_view_makes_previews_in_the_internal_frame(spz_pair, tmp_path):
    """result.json without previews: gsa view makes them from the inputs it names, which are read
    into the internal frame, so the pose applied is transform_internal (not the file-frame one)."""
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "result.json").write_text(json.dumps(spz_pair["json"]))
    _, views, files, _ = collect(bare, tmp_path / "work")
    aligned = read_splat(files["s0/aligned.splat"])["position"].astype(np.float64)
    source = read_splat(files["s0/source.splat"])["position"].astype(np.float64)
    np.testing.assert_allclose(aligned, TRUTH.apply(source), atol=0.02 * TRUTH.scale)


def serve(path: Path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "gsa.cli", "view", str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    url = proc.stdout.readline().strip()
    assert url.startswith("http://127.0.0.1:"), (url, proc.stderr.read() if not url else "")
    return proc, url


def run_shown_command(command: str, cwd: Path) -> dict:
    """Runs what the page shows (its heredoc writes pairs.json; the `gsa view` after && is left
    out: it would serve until killed) and returns the refined result.json."""
    cwd.mkdir(parents=True, exist_ok=True)
    lines = command.splitlines()
    if lines[0].startswith("cat > pairs.json"):
        (cwd / "pairs.json").write_text(lines[1])
        lines = lines[3:]
    argv = shlex.split(lines[0].split(" && ", 1)[0])
    assert argv[:2] == ["gsa", "align"], argv
    done = subprocess.run([sys.executable, "-m", "gsa.cli", *argv[1:]], cwd=cwd, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert (cwd / "refined" / "preview" / "aligned.splat").is_file()  # --preview: gsa view shows it
    return json.loads((cwd / "refined" / "result.json").read_text())


def file_truth_rotation() -> np.ndarray:
    """TRUTH from the SPZ file's coordinates to the target PLY's (internal) ones."""
    return TRUTH.rotation @ FLIP


@pytest.mark.slow
def test_guide_controls_on_gsa_view(spz_pair, tmp_path):
    data = spz_pair["json"]
    alts = data["metrics"]["alternatives"]
    proc, url = serve(spz_pair["dir"] / "out" / "result.json")
    try:
        with browser_page() as (page, messages):
            page.goto(url)
            assert wait_ready(page)["error"] is None
            shown = "() => Object.entries(gsaViewer.panes.overlay.meshes).filter(([k, m]) => m.visible).map(([k]) => k)"
            assert sorted(page.evaluate(shown)) == ["source0", "target"]

            # Alternatives: "next" draws the source preview at alternative 0's internal pose in
            # place of the aligned preview; "previous" comes back to the chosen pose.
            page.click("#alt-next")
            assert sorted(page.evaluate(shown)) == ["alternative", "target"]
            # The pose the page set on the mesh (position, quaternion, scale), column-major.
            matrix = page.evaluate(
                "() => { const m = gsaViewer.panes.overlay.meshes.alternative; m.updateMatrix(); return m.matrix.elements; }"
            )
            np.testing.assert_allclose(np.reshape(matrix, (4, 4)).T, alts[0]["transform"], atol=1e-5)
            assert "alternative 0 (1 of" in page.locator("#alt-label").inner_text()
            wait_drawn(page, "#view-overlay")
            page.locator("#alt-use").click()
            command = page.locator("#guide-command").inner_text()
            assert f"--init {spz_pair['dir'] / 'out' / 'result.json'} --alternative 0" in command
            refined = run_shown_command(command, tmp_path / "alt")
            assert refined["metrics"]["guidance"]["start"]["from"] == "init_transform"
            # A local refinement of that alternative: near it, not back at the chosen pose.
            sr = np.asarray(alts[0]["file_transform"])[:3, :3]
            near = rre_deg(np.asarray(refined["rotation"]), sr / np.cbrt(np.linalg.det(sr)))
            assert near < 10, near
            page.click("#alt-prev")
            assert sorted(page.evaluate(shown)) == ["source0", "target"] and page.locator("#alt-use").is_disabled()

            # Up axes: each select turns its model's views upright (the source's SPZ +y is internal -y),
            # and the command carries both vectors in file coordinates.
            page.select_option("#up-source", "+y")
            page.select_option("#up-target", "+z")
            up = "() => [gsaViewer.panes.source.camera.up.toArray(), gsaViewer.panes.target.camera.up.toArray()]"
            page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
            np.testing.assert_allclose(page.evaluate(up), [[0, -1, 0], [0, 0, 1]], atol=1e-9)
            page.click("#up-submit")
            command = page.locator("#guide-command").inner_text()
            assert " --up 0,1,0:0,0,1 " in command
            refined = run_shown_command(command, tmp_path / "up")
            np.testing.assert_allclose(refined["metrics"]["guidance"]["up_axes"][1], [0, 0, 1], atol=1e-9)
            assert rre_deg(np.asarray(refined["rotation"]), file_truth_rotation()) < 5.0
            # Keyboard: a focused view orbits with the arrow keys; with picking on, Enter picks
            # the point at its centre (a half pair), and the undo button drops it.
            camera = "() => gsaViewer.panes.source.camera.position.toArray()"
            start = page.evaluate(camera)
            page.locator("#view-source").focus()
            page.keyboard.press("ArrowLeft")
            page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
            assert page.evaluate(camera) != start
            page.locator("#pick-toggle").focus()
            page.keyboard.press("Enter")
            assert page.locator("#pick-toggle").get_attribute("aria-pressed") == "true"
            # Picking unlinks the views: the target turns on its own until it shows the side the
            # source view shows (TRUTH turns the upright chair by 130° about its up: 23 presses).
            assert page.evaluate("() => gsaViewer.linked") is False and not page.is_checked("#link-views")
            source_camera = page.evaluate(camera)
            page.locator("#view-target").focus()
            for _ in range(23):
                page.keyboard.press("ArrowLeft")
            assert page.evaluate(camera) == source_camera
            page.locator("#view-source").focus()
            page.keyboard.press("Enter")
            assert page.evaluate("() => gsaViewer.guide.pending.source") is not None
            page.click("#pairs-undo")
            assert page.evaluate("() => gsaViewer.guide.pending") == {}

            # Point pairs by mouse: four clicked pairs, listed, then the command with their file
            # coordinates (the SPZ source's turned back from the previews' internal frame).
            assert page.locator("#pairs-submit").is_disabled()
            radius = float(np.sqrt(((spz_pair["target"].means - spz_pair["target"].means.mean(0)) ** 2).sum(1).mean()))
            preview = read_splat(spz_pair["dir"] / "out" / "preview" / "source.splat")
            pickable = preview["position"][preview["rgba"][:, 3] >= 40]
            candidates = spread_points(visible_in_both(page, pickable, TRUTH.apply), 12)
            pairs = click_pairs(page, candidates, TRUTH.apply, 4, 0.02 * radius)
            assert page.locator("#pair-list li").count() == len(pairs) == 4
            page.click("#pairs-submit")
            command = page.locator("#guide-command").inner_text()
            sent = json.loads(command.splitlines()[1])
            np.testing.assert_allclose(
                sent["source"], [np.asarray(p["source"]) @ FLIP for p in pairs], rtol=1e-5, atol=1e-6
            )
            np.testing.assert_allclose(sent["target"], [p["target"] for p in pairs], rtol=1e-5, atol=1e-6)
            refined = run_shown_command(command, tmp_path / "pairs")
            assert refined["metrics"]["guidance"]["point_pairs"] == 4
            assert rre_deg(np.asarray(refined["rotation"]), file_truth_rotation()) < 2.0

            assert page.evaluate("() => gsaViewer.guide.requests.length") == 3
            assert project(page, "target", [0, 0, 0]) is not None
            assert errors(messages) == [], messages
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.mark.slow
def test_front_axes_on_gsa_view(spz_pair, tmp_path):
    """The fronts beside the up axes: both or neither, each across its own up (a message beside
    them, and nothing shown, otherwise); given, the command carries --front in file coordinates
    after --up, and its run reports them (internal frame: the SPZ source's turned back)."""
    proc, url = serve(spz_pair["dir"] / "out" / "result.json")
    try:
        with browser_page() as (page, messages):
            page.goto(url)
            assert wait_ready(page)["error"] is None
            page.select_option("#up-source", "+y")
            page.select_option("#up-target", "+z")
            assert not page.locator("#front-error").is_visible()
            for source, target, words in (("+x", "", "both fronts"), ("-y", "+y", "source front is along its up")):
                page.select_option("#front-source", source)
                page.select_option("#front-target", target)
                page.click("#up-submit")
                assert words in page.locator("#front-error").inner_text()
                assert page.locator("#guide-command").count() == 0
            assert page.evaluate("() => gsaViewer.guide.requests.length") == 0
            # TRUTH turns the source's x (SPZ +x, internal +x) 130° about the target's +z: +y is
            # the target's axis nearest it (40° off, within the fronts' 45°).
            page.select_option("#front-source", "+x")
            page.select_option("#front-target", "+y")
            assert not page.locator("#front-error").is_visible()  # a change clears the message
            page.click("#up-submit")
            command = page.locator("#guide-command").inner_text()
            assert " --up 0,1,0:0,0,1 --front 1,0,0:0,1,0 " in command
            assert page.evaluate("() => gsaViewer.guide.requests.at(-1)") == {
                "up_axes": [[0, 1, 0], [0, 0, 1]],
                "front_axes": [[1, 0, 0], [0, 1, 0]],
            }
            refined = run_shown_command(command, tmp_path / "front")
            np.testing.assert_allclose(refined["metrics"]["guidance"]["front_axes"], [[1, 0, 0], [0, 1, 0]], atol=1e-9)
            assert rre_deg(np.asarray(refined["rotation"]), file_truth_rotation()) < 5.0
            # "not given" on both: the up axes alone, as before
            page.select_option("#front-source", "")
            page.select_option("#front-target", "")
            page.click("#up-submit")
            assert "--front" not in page.locator("#guide-command").inner_text()
            assert errors(messages) == [], messages
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.mark.slow
def test_known_scale_on_gsa_view(spz_pair, tmp_path):
    """The scale input: a bad value stops the control with a message beside it; a good one puts
    --scale S in the command of "use this one" and of the up axes (the first run: its scale is S)."""
    proc, url = serve(spz_pair["dir"] / "out" / "result.json")
    try:
        with browser_page() as (page, messages):
            page.goto(url)
            assert wait_ready(page)["error"] is None
            page.click("#alt-next")
            for bad in ("0", "-1", "two"):
                page.fill("#scale-input", bad)
                page.click("#alt-use")
                assert page.locator("#scale-error").is_visible()
                assert "positive number" in page.locator("#scale-error").inner_text()
                assert page.locator("#guide-command").count() == 0
            assert page.evaluate("() => gsaViewer.guide.requests.length") == 0
            page.fill("#scale-input", "1.7")
            assert not page.locator("#scale-error").is_visible()
            page.click("#alt-use")
            command = page.locator("#guide-command").inner_text()
            assert " --alternative 0 --scale 1.7 " in command
            refined = run_shown_command(command, tmp_path / "alt")
            assert refined["scale"] == pytest.approx(1.7, abs=1e-6)
            page.click("#up-submit")
            assert " --scale 1.7 " in page.locator("#guide-command").inner_text()
            assert page.evaluate("() => gsaViewer.guide.requests.map((r) => r.fixed_scale)") == [1.7, 1.7]
            assert errors(messages) == [], messages
    finally:
        proc.terminate()
        proc.wait(10)
