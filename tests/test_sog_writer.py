"""Our SOG writer (gsa/io/sog.py): the layout gaussforge's reader expects, and a round trip
through gaussforge within the format's bounds, with the SH palette clustered."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
import pytest

from benchmarks.formats_io import attribute_errors
from gsa.io import packed, sog
from gsa.io.formats import ROUNDTRIP_BOUNDS
from gsa.synth import make_object


@pytest.fixture(scope="module")
def model():
    return make_object("car", seed=5, n_gaussians=2000, sh_degree=3)


def test_layout_matches_the_sog_v2_specification(model):
    data = sog.encode_sog(model)
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        meta = json.loads(zf.read("meta.json"))
        names = set(zf.namelist())
    assert meta["version"] == 2 and meta["count"] == len(model)
    assert len(meta["scales"]["codebook"]) == len(meta["sh0"]["codebook"]) == len(meta["shN"]["codebook"]) == 256
    assert meta["shN"]["bands"] == 3 and meta["shN"]["count"] % 64 == 0
    assert names == {"meta.json", "means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp"} | {
        "shN_centroids.webp",
        "shN_labels.webp",
    }


def test_clustered_palette_reads_back_within_bounds_in_gaussforge(model, monkeypatch):
    import gaussforge

    monkeypatch.setattr(sog, "PALETTE_SIZE", 256)  # fewer entries than Gaussians: k-means runs
    monkeypatch.setattr(sog, "PALETTE_SAMPLE", 1000)
    data = sog.encode_sog(model)
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        assert json.loads(zf.read("meta.json"))["shN"]["count"] == 256
    assert gaussforge.GaussForge().read(data, "sog")["data"]["numPoints"] == len(model)
    back = packed.decode("sog", data)  # gaussforge's decoder, in its child process
    errors = attribute_errors(model, back, "sog")
    for name, bound in ROUNDTRIP_BOUNDS["sog"].items():
        if name != "sh_rest":
            assert errors[name]["max"] <= bound, (name, errors[name])
    # a 256-entry palette for 2000 Gaussians of independent random SH: better than nothing
    rest = model.sh[:, 1:].astype(np.float64)
    assert errors["sh_rest"]["rms"] < np.sqrt(np.mean(rest**2))
    assert errors["sh_rest"]["max"] <= np.abs(rest).max() + 0.05


def test_transparent_gaussians_keep_their_colour(model):
    # Lossless WebP drops the colour of texels with alpha 0: the writer keeps alpha ≥ 1.
    clear = model.subset(np.arange(len(model)))
    clear.opacity_logits = np.full_like(clear.opacity_logits, -20.0)
    back = packed.decode("sog", sog.encode_sog(clear))
    errors = attribute_errors(clear, back, "sog")
    assert errors["colour"]["max"] <= ROUNDTRIP_BOUNDS["sog"]["colour"]
    assert errors["opacity"]["max"] <= 1 / 255 + 1e-6
