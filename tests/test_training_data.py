"""The training-data manifest and converter (training/): no held-out shape, proper frames, OBJ parsing."""

import json
from pathlib import Path

import numpy as np
import pytest

from training.fetch_meshes import normalise, parse_obj
from training.heldout import HELDOUT, refuse_heldout

MANIFEST = json.loads((Path(__file__).parents[1] / "training" / "manifest.json").read_text())


def test_manifest_lists_no_heldout_instance():
    refuse_heldout(MANIFEST["entries"])
    assert not {e["instance"] for e in MANIFEST["entries"]} & HELDOUT


def test_refuse_heldout_names_the_instance():
    entry = {
        "source": "trneedham/QuantizedGromovWasserstein",
        "path": "data/CAPOD/class15/m170.obj",
        "instance": "m170",
    }
    with pytest.raises(ValueError, match="m170"):
        refuse_heldout([entry])
    # a wrong instance id does not hide a held-out path
    entry = {"path": "scale/chair/341a2d3df9800314fa260f4362cac599/models/model_normalized.obj", "instance": "x"}
    with pytest.raises(ValueError, match="341a2d3df9800314fa260f4362cac599"):
        refuse_heldout([entry])


def _rotations():
    for frames in MANIFEST["frames"].values():
        for frame in frames.values():
            yield frame["to_canonical"]
    for e in MANIFEST["entries"]:
        if "to_canonical" in e:
            yield e["to_canonical"]


def test_every_frame_is_a_proper_signed_permutation():
    for R in _rotations():
        R = np.asarray(R)
        assert R.dtype.kind == "i" and R.shape == (3, 3)
        assert (np.abs(R).sum(0) == 1).all() and (np.abs(R).sum(1) == 1).all()
        assert round(np.linalg.det(R)) == 1


def test_every_entry_has_a_frame():
    for e in MANIFEST["entries"]:
        assert "to_canonical" in e or e["source_class"] in MANIFEST["frames"][e["source"]]


OBJ = """\
mtllib m.mtl
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0 0
vn 0 0 1
usemtl red
f 1/1/1 2/1/1 3/1/1 4/1/1
usemtl none
f -4//1 -2//1 -1//1
v 0 0 2
f 1 2/1 -1
"""


def test_parse_obj_quad_negative_indices_and_slash_forms():
    V, F, C = parse_obj(OBJ, lambda name: "newmtl red\nKd 1 0 0\n" if name == "m.mtl" else None)
    assert V.dtype == np.float32 and F.dtype == np.int32 and C.dtype == np.float16
    assert V.shape == (5, 3)
    # the quad becomes a fan of two triangles; -4//1 etc. count back from the 4 vertices read so far
    assert F.tolist() == [[0, 1, 2], [0, 2, 3], [0, 2, 3], [0, 1, 4]]
    assert C[:2].tolist() == [[1, 0, 0], [1, 0, 0]]
    assert np.isnan(C[2:].astype(np.float32)).all()  # unknown material -> NaN


def test_normalise_rotates_centres_and_scales():
    V = np.array([[0, 0, 0], [2, 0, 0], [0, 4, 4]], np.float32)
    N = normalise(V, [[1, 0, 0], [0, 0, 1], [0, -1, 0]])  # source +Z up -> canonical +Y
    assert np.allclose(N.min(0), -N.max(0))
    assert np.isclose(np.linalg.norm(N.max(0) - N.min(0)), 1)
    assert N[:, 1].argmax() == 2  # the +Z-most source vertex is now the highest
