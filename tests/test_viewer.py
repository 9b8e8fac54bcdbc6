"""The results page's parts in the library: .splat previews, the escaped HTML page, and
`gsa view` (a real local server, then headless Chromium on its page)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from gsa.align.outputs import write_outputs
from gsa.align.pipeline import AlignOptions, align
from gsa.io.ply import write_ply
from gsa.synth import make_object, random_sim3
from gsa.viewer.local import collect
from gsa.viewer.page import ResultView, loss_curve_svg, render_page, script_json
from gsa.viewer.preview import PREVIEW_NAMES, downsample, read_splat, write_previews, write_splat
from tests.browser import browser_page, errors, wait_colours, wait_drawn, wait_ready

ROOT = Path(__file__).resolve().parents[1]
EVIL = "</script><script>alert(1)</script>&<b>"


@pytest.fixture(scope="module")
def aligned_pair(tmp_path_factory):
    """Two independent samplings of one car, the source moved by a random Sim(3), aligned;
    gsa align's outputs (result.json with previews) in a folder."""
    d = tmp_path_factory.mktemp("viewer")
    target = make_object("car", seed=2, n_gaussians=6000, sample_seed=2)
    truth = random_sim3(np.random.default_rng(5))
    source = make_object("car", seed=2, n_gaussians=5000, sample_seed=1002).transformed(truth.inverse())
    write_ply(source, d / "source.ply")
    write_ply(target, d / "target.ply")
    result = align(source, target, AlignOptions())
    paths = write_outputs(result, source, target, d / "out", outputs={"result", "preview"})
    data = json.loads(paths["result.json"].read_text())
    data["inputs"] = {"source": str(d / "source.ply"), "target": str(d / "target.ply")}
    paths["result.json"].write_text(json.dumps(data))
    return {"dir": d, "source": source, "target": target, "result": result, "out": d / "out"}


def test_splat_records_round_trip(aligned_pair):
    m = aligned_pair["source"]
    rec = read_splat(write_splat(m, aligned_pair["dir"] / "m.splat"))
    assert len(rec) == len(m)
    np.testing.assert_allclose(rec["position"], m.means, rtol=0, atol=1e-6)
    np.testing.assert_allclose(rec["scale"], np.exp(m.log_scales), rtol=1e-6)
    np.testing.assert_allclose(rec["rgba"][:, :3] / 255.0, m.base_colors, atol=0.5 / 255 + 1e-9)
    np.testing.assert_allclose(rec["rgba"][:, 3] / 255.0, m.opacities, atol=0.5 / 255 + 1e-9)
    q = (rec["rotation"].astype(np.float64) - 128.0) / 128.0
    q_true = m.quats / np.linalg.norm(m.quats, axis=1, keepdims=True)
    assert np.abs(q - q_true).max() <= 0.5 / 128 + 1e-9
    with pytest.raises(ValueError, match="32-byte"):
        (aligned_pair["dir"] / "bad.splat").write_bytes(b"x" * 33)
        read_splat(aligned_pair["dir"] / "bad.splat")


def test_downsample_caps_seeded_and_keeps_coverage(aligned_pair):
    m = aligned_pair["target"]
    small = downsample(m, 1500)
    assert len(small) == 1500
    np.testing.assert_array_equal(small.means, downsample(m, 1500).means)  # seeded
    # Each kept Gaussian grows by (N / cap)^(1/3) so the surface stays covered.
    idx = [int(np.flatnonzero((m.means == p).all(axis=1))[0]) for p in small.means[:20]]
    np.testing.assert_allclose(small.log_scales[:20] - m.log_scales[idx], np.log((len(m) / 1500) ** (1 / 3)), atol=1e-5)
    assert downsample(m, 10**6) is m
    faint = m.subset(np.arange(len(m)))
    faint.opacity_logits = faint.opacity_logits.copy()
    faint.opacity_logits[:100] = -20.0
    assert len(downsample(faint, 10**6)) == len(m) - 100
    with pytest.raises(ValueError):
        downsample(m, 0)


def test_previews_are_the_same_sample_in_both_frames(aligned_pair):
    r = aligned_pair["result"]
    paths = write_previews(aligned_pair["source"], aligned_pair["target"], r.transform, aligned_pair["dir"] / "p", 2000)
    assert sorted(paths) == sorted(PREVIEW_NAMES.values())
    src, aligned = read_splat(paths["preview/source.splat"]), read_splat(paths["preview/aligned.splat"])
    assert len(src) == len(aligned) == 2000 and len(read_splat(paths["preview/target.splat"])) == 2000
    np.testing.assert_allclose(aligned["position"], r.transform.apply(src["position"].astype(np.float64)), atol=1e-4)
    np.testing.assert_allclose(aligned["scale"], src["scale"] * r.transform.scale, rtol=1e-5)


def test_page_escapes_every_user_string():
    result = {
        "metrics": {"confidence": 0.2, "doubtful": True, "ambiguous": True, "note": EVIL},
        "scale": 2.0,
        "hypotheses": [{"origin": EVIL, "score": 0.5, "chosen": True}],
        "stages": {"fine": {"loss_history": [0.5, 0.25, 0.2]}},
    }
    view = ResultView(label=EVIL, result=result, preview={"source": "a.splat"}, renders=[(EVIL, f"r/{EVIL}.png")])
    page = render_page(EVIL, [view], "static/", subtitle=EVIL, notes=[EVIL], extra_renders=[(EVIL, EVIL)])
    assert "<script>alert" not in page and "<b>" not in page and "</script><script>" not in page
    assert page.count("&lt;/script&gt;&lt;script&gt;alert(1)&lt;/script&gt;&amp;&lt;b&gt;") >= 6
    config = page.split("id=gsa-config>", 1)[1].split("</script>", 1)[0]
    assert json.loads(config)["results"][0]["label"] == EVIL and "<" not in config
    assert "doubtful" in page and "<svg class=loss" in page and "3 iterations" in page
    assert "</" not in script_json({"x": "</script>"})


def test_page_says_whether_the_photos_gave_the_pose():
    def page_of(photo_match):
        result = {"metrics": {"confidence": 1.0, "doubtful": False, "photo_match": photo_match}, "scale": 1.0}
        return render_page("t", [ResultView(label="r", result=result)], "static/")

    used = page_of({"accepted": True, "reason": "511 of 548 matched point pairs agree"})
    assert "Registered by the photos: 511 of 548 matched point pairs agree" in used
    refused = page_of({"accepted": False, "reason": f"13 point pairs matched {EVIL}"})
    assert "Photos not used: 13 point pairs matched" in refused and "<script>alert" not in refused
    plain = page_of(None)
    assert "Registered by the photos" not in plain and "Photos not used" not in plain


def test_loss_curve_only_with_values():
    assert loss_curve_svg(None) == "" and loss_curve_svg([1.0]) == "" and loss_curve_svg([1.0, float("nan")]) == ""
    svg = loss_curve_svg([3.0, 2.0, 1.0], width=100, height=50)
    points = svg.split('points="', 1)[1].split('"', 1)[0].split()
    assert points == ["8.0,8.0", "50.0,25.0", "92.0,42.0"]  # highest loss at the top, lowest at the bottom


def test_gsa_view_refuses_what_is_not_a_result(tmp_path, capsys):
    from gsa.cli import main

    (tmp_path / "x.json").write_text('{"hello": 1}')
    for path in (tmp_path / "missing", tmp_path / "x.json", tmp_path):
        assert main(["view", str(path)]) == 1
        err = capsys.readouterr().err
        assert err.startswith("gsa: error: ") and err.count("\n") == 1 and str(path) in err, err


def serve(path: Path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "gsa.cli", "view", str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    url = proc.stdout.readline().strip()
    assert url.startswith("http://127.0.0.1:") and url.endswith("/"), (url, proc.stderr.read() if not url else "")
    return proc, url


def test_gsa_view_serves_only_its_files(aligned_pair):
    proc, url = serve(aligned_pair["out"] / "result.json")
    try:
        with urllib.request.urlopen(url) as r:
            assert r.headers["Content-Security-Policy"].startswith("default-src 'none'")
            assert b"files/s0/aligned.splat" in r.read()
        with urllib.request.urlopen(url + "files/s0/target.splat") as r:
            assert len(r.read()) == 32 * 6000
        base = url.rsplit("/", 2)[0]
        for bad in (url + "files/../result.json", url + "files/s0/result.json", base + "/static/viewer.js", base + "/"):
            with pytest.raises(urllib.error.HTTPError) as e:
                urllib.request.urlopen(bad)
            assert e.value.code == 404, bad
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.mark.slow
def test_gsa_view_in_the_browser(aligned_pair, tmp_path):
    # Previews written beside result.json are used; without them gsa view makes them
    # from the input files result.json names.
    out = aligned_pair["out"]
    bare = tmp_path / "bare"
    bare.mkdir()
    (bare / "result.json").write_text((out / "result.json").read_text())
    with browser_page() as (page, messages):
        for path in (out / "result.json", bare):
            proc, url = serve(path)
            try:
                page.goto(url)
                state = wait_ready(page)
                assert state["ready"] and state["error"] is None, state
                for pane in ("source", "target", "overlay"):
                    wait_drawn(page, f"#view-{pane}")
                wait_colours(page, "#view-overlay", lambda c: c["orange"] > 0.003 and c["blue"] > 0.003)
                page.locator('input[data-model="target"]').set_checked(False)
                wait_colours(page, "#view-overlay", lambda c: c["orange"] > 0.003 and c["blue"] < 0.0005)
            finally:
                proc.terminate()
                proc.wait(10)
        assert errors(messages) == [], messages


def test_gsa_view_reads_a_fetched_multi_model_job(aligned_pair, tmp_path):
    """`gsa fetch JOB --out DIR` of a two-model job: s0/, s1/ (result.json, preview/) and synchronized/."""

    for i in range(2):
        shutil.copytree(aligned_pair["out"], tmp_path / f"s{i}")
        data = json.loads((tmp_path / f"s{i}" / "result.json").read_text())
        del data["inputs"]  # a service result names no local files
        (tmp_path / f"s{i}" / "result.json").write_text(json.dumps(data))
    (tmp_path / "synchronized").mkdir()
    (tmp_path / "synchronized" / "synchronized.png").write_bytes(b"\x89PNG")
    _, views, files, extra = collect(tmp_path, tmp_path / "work")
    assert [v.label for v in views] == ["source 1", "source 2"]
    assert views[1].preview == {k: f"files/s1/{k}.splat" for k in ("source", "target", "aligned")}
    assert files["s1/aligned.splat"] == tmp_path / "s1" / "preview" / "aligned.splat"
    assert extra == [("synchronized.png", "files/sync/synchronized.png")]
