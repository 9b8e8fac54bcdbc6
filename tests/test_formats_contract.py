"""The transform contract of result.json: docs/formats.md's worked example runs, and the
numbers are exact in each file's own coordinates (checked on the raw file contents)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gsa.align.contract import transform_contract
from gsa.io.formats import read_model, write_model
from gsa.io.frames import RDF_TO_RUB
from gsa.merge import merge_dedup
from gsa.sim3 import Sim3
from gsa.synth import make_object, random_sim3

DOC = Path(__file__).resolve().parents[1] / "docs" / "formats.md"


def doc_python_blocks() -> list[str]:
    text = DOC.read_text()
    section = text[text.index("### Worked example") :]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_the_documented_example_runs_on_a_real_contract(tmp_path, monkeypatch):
    truth = random_sim3(np.random.default_rng(11))
    (tmp_path / "result.json").write_text(json.dumps(transform_contract(truth, "spz", "ply")))
    monkeypatch.chdir(tmp_path)
    blocks = doc_python_blocks()
    assert len(blocks) == 2
    scope: dict = {}
    for block in blocks:
        exec(compile(block, str(DOC), "exec"), scope)  # noqa: S102 - the documentation's own code
    # the example's point really went through the internal truth
    x_internal = RDF_TO_RUB @ scope["x_source"]  # the .spz point in RDF
    assert np.allclose(scope["x_target"], truth.apply(x_internal))


def test_contract_is_exact_on_the_raw_files(tmp_path):
    """x_target_file = transform · x_source_file on the numbers stored in the files, for every
    pair of axis conventions; the glTF node matrix on the numbers stored in two GLBs."""
    truth = random_sim3(np.random.default_rng(5))
    source = make_object("chair", seed=2, n_gaussians=500, sh_degree=1)
    target = source.transformed(truth)
    pygltflib = pytest.importorskip("pygltflib")

    def raw_positions(path, fmt):
        if fmt == "ply":
            return read_model(path).means.astype(np.float64)  # PLY's frame is the internal one
        gltf = pygltflib.GLTF2().load(str(path))
        acc = gltf.accessors[gltf.meshes[0].primitives[0].attributes.POSITION]
        return np.frombuffer(gltf.binary_blob(), "<f4", acc.count * 3, gltf.bufferViews[acc.bufferView].byteOffset)

    for sf, tf in [("ply", "ply"), ("glb", "ply"), ("ply", "glb"), ("glb", "glb")]:
        sp = write_model(source, tmp_path / f"s.{sf}", sf)
        tp = write_model(target, tmp_path / f"t.{tf}", tf)
        c = transform_contract(truth, sf, tf)
        xs = raw_positions(sp, sf).reshape(-1, 3)
        xt = raw_positions(tp, tf).reshape(-1, 3)
        mapped = Sim3.from_matrix(np.array(c["transform"])).apply(xs)
        assert np.abs(mapped - xt).max() < 1e-4, (sf, tf)
        back = Sim3.from_matrix(np.array(c["inverse_transform"])).apply(xt)
        assert np.abs(back - xs).max() < 1e-4
        q = np.array(c["quaternion"])
        assert np.allclose(c["quaternion_xyzw"], [q[1], q[2], q[3], q[0]])
        assert c["frames"]["source"]["format"] == sf and c["frames"]["target"]["format"] == tf
        if (sf, tf) == ("glb", "glb"):
            node = np.array(c["gltf_node_matrix"]).reshape(4, 4).T
            assert np.abs(xs @ node[:3, :3].T + node[:3, 3] - xt).max() < 1e-4
        if sf == tf == "ply":
            assert "transform_internal" not in c and np.allclose(c["transform"], truth.matrix())


def test_align_cli_spz_onto_glb_writes_the_sources_format_and_dedups(tmp_path):
    truth = random_sim3(np.random.default_rng(3))
    src = make_object("car", seed=4, n_gaussians=4000, sample_seed=1, sh_degree=1)
    tgt = make_object("car", seed=4, n_gaussians=4000, sample_seed=2, sh_degree=1).transformed(truth)
    write_model(src, tmp_path / "s.spz", "spz")
    write_model(tgt, tmp_path / "t.glb", "glb")
    r = subprocess.run(
        [sys.executable, "-m", "gsa.cli", "align", tmp_path / "s.spz", tmp_path / "t.glb", "--quiet"]
        + ["--out", tmp_path / "r.json", "--aligned-out", tmp_path / "aligned", "--merged-out", tmp_path / "merged"]
        + ["--merge", "dedup"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    result = json.loads((tmp_path / "r.json").read_text())
    assert result["frames"]["source"]["convention"] == "RUB" and result["frames"]["target"]["format"] == "glb"
    # both RUB: the file transform is the internal truth seen through F = diag(1, -1, -1)
    expected = Sim3(truth.scale, RDF_TO_RUB @ truth.rotation @ RDF_TO_RUB, RDF_TO_RUB @ truth.translation)
    got = Sim3.from_matrix(np.array(result["transform"]))
    angle = np.degrees(np.arccos(np.clip((np.trace(got.rotation.T @ expected.rotation) - 1) / 2, -1, 1)))
    assert angle < 1.0 and abs(got.scale / expected.scale - 1) < 0.01
    aligned = read_model(tmp_path / "aligned")
    assert aligned.metadata["format"] == "spz"  # the source's format by default
    merged = read_model(tmp_path / "merged")
    assert result["merge"]["mode"] == "dedup" and result["merge"]["removed"] > 0
    assert len(merged) == result["merge"]["gaussians"] == 8000 - result["merge"]["removed"]


def test_dedup_removes_duplicates_keeps_the_more_opaque_and_spares_other_colours():
    a = make_object("car", seed=1, n_gaussians=2000, sh_degree=0)
    b = a.subset(np.arange(len(a)))
    b.opacity_logits = a.opacity_logits + 1.0  # b is the more opaque copy
    merged, removed = merge_dedup(a, b)
    assert removed == len(a) and len(merged) == len(a)
    assert np.allclose(np.sort(merged.opacity_logits), np.sort(b.opacity_logits))
    recoloured = b.subset(np.arange(len(b)))
    recoloured.sh = recoloured.sh.copy()
    shift = np.where(a.base_colors > 0.5, -0.5, 0.5)  # every channel 0.5 away: not the same surface
    recoloured.sh[:, 0, :] += shift / 0.28209479177387814
    merged, removed = merge_dedup(a, recoloured)
    assert removed == 0 and len(merged) == 2 * len(a)
    far = b.transformed(Sim3(1.0, np.eye(3), np.array([10.0, 0, 0])))
    assert merge_dedup(a, far)[1] == 0
