"""Feature extractors, lifting and background pruning.

Tiny randomly initialised DINOv2 backbones and sphere_mapper heads are written to disk in
the published formats (torch.hub state dict; HF folder via transformers.save_pretrained
when transformers is installed; the authors' DINOMapper checkpoint layout) and loaded
through the real loading code.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from gsa.canonical import canonical_features
from gsa.features import (
    CanonicalExtractor,
    Dinov2PCAExtractor,
    FeatureSettings,
    SphereMapExtractor,
    WeightsError,
    lift_features,
    lift_features_full,
    make_extractor,
    prepare_for_alignment,
    prune_background,
)
from gsa.features.command import add_lift_parser
from gsa.features.vit import DinoV2, VitConfig, hf_to_hub, load_backbone, load_sphere_head, sphere_mapper_head, to_input
from gsa.io.ply import read_ply, write_ply
from gsa.model import GaussianModel, ModelError, merge_models
from gsa.settings_env import feature_settings_env, sam_paths_env
from gsa.synth import make_object

TINY = VitConfig(embed_dim=64, depth=2, num_heads=1, patch_size=14, pos_grid=37)


def _randomise(module: torch.nn.Module, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.3)


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """Paths of a tiny hub-format backbone and an authors'-format head checkpoint."""
    d = tmp_path_factory.mktemp("weights")
    vit = DinoV2(TINY)
    _randomise(vit, 0)
    torch.save(vit.state_dict(), d / "dinov2_tiny_pretrain.pth")
    head = sphere_mapper_head(TINY.embed_dim)  # hidden 32 -> 1 head
    _randomise(head, 1)
    # DINOMapper.make_checkpoint layout: sphere_mapper.* next to prototypes.* and sphere.weight.
    ckpt = {f"sphere_mapper.{k}": v for k, v in head.state_dict().items()}
    ckpt["sphere.weight"] = F.normalize(torch.randn(1024, 3), dim=-1)
    ckpt["prototypes.proj.weight"] = torch.randn(64, 3)
    torch.save(ckpt, d / "sphere_mapper.ckpt")
    return {
        "backbone": str(d / "dinov2_tiny_pretrain.pth"),
        "head": str(d / "sphere_mapper.ckpt"),
        "vit": vit,
        "headmod": head,
    }


@pytest.fixture(scope="module")
def small_model():
    return make_object("car", seed=5, n_gaussians=1500)


# ------------------------------------------------------------------ loading
def test_hub_backbone_round_trip_and_head_layout(weights):
    vit = load_backbone(weights["backbone"])
    assert vit.cfg.embed_dim == 64 and vit.cfg.depth == 2 and vit.cfg.pos_grid == 37
    x = to_input(np.random.default_rng(0).random((1, 50, 60, 3)), 518)
    pre_ref, post_ref = weights["vit"](x)
    pre, post = vit(x)
    assert pre.shape == (1, 37, 37, 64)
    torch.testing.assert_close(pre, pre_ref)
    torch.testing.assert_close(post, post_ref)
    head = load_sphere_head(weights["head"], 64)
    # The authors' nn.Sequential indices: 0 Linear, 1 GELU, 2 Block (qkv without bias), 3 Linear.
    keys = set(head.state_dict())
    assert {"0.weight", "2.attn.qkv.weight", "2.mlp.fc1.weight", "3.bias"} <= keys
    assert "2.attn.qkv.bias" not in keys and head[2].attn.heads == 1


def test_hf_folder_matches_transformers(tmp_path):
    import transformers

    cfg = transformers.Dinov2Config(
        hidden_size=64, num_hidden_layers=2, num_attention_heads=2, intermediate_size=256, patch_size=14, image_size=518
    )
    ref = transformers.Dinov2Model(cfg).eval()
    _randomise(ref, 2)
    ref.save_pretrained(tmp_path)
    mine = load_backbone(tmp_path)
    assert mine.cfg.num_heads == 2
    x = to_input(np.random.default_rng(1).random((2, 40, 40, 3)), 518)
    with torch.no_grad():
        out = ref(pixel_values=x, output_hidden_states=True)
        pre, post = mine(x)
    torch.testing.assert_close(post, out.last_hidden_state[:, 1:].reshape(post.shape), atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(pre, out.hidden_states[-1][:, 1:].reshape(pre.shape), atol=1e-4, rtol=1e-4)
    # The hub path accepts the same weights renamed to hub keys (and agrees).
    torch.save(hf_to_hub(ref.state_dict()), tmp_path / "hub.pth")
    hub = load_backbone(tmp_path / "hub.pth")
    hub.blocks[0].attn.heads = 2  # hub files carry no head count: published models use 64-d heads
    hub.blocks[1].attn.heads = 2
    torch.testing.assert_close(hub(x)[1], post, atol=1e-4, rtol=1e-4)


def test_missing_weights_are_clear_errors(tmp_path, weights):
    with pytest.raises(WeightsError, match=r"features\.backbone .*not set"):
        make_extractor("spheremap", FeatureSettings())
    with pytest.raises(WeightsError, match=r"features\.backbone.*nope\.pth does not exist"):
        make_extractor("dinov2", FeatureSettings(backbone=str(tmp_path / "nope.pth")))
    with pytest.raises(WeightsError, match=r"features\.head .*not set"):
        make_extractor("spheremap", FeatureSettings(backbone=weights["backbone"]))
    with pytest.raises(WeightsError, match=r"features\.head.*missing\.ckpt does not exist"):
        make_extractor("spheremap", FeatureSettings(backbone=weights["backbone"], head=str(tmp_path / "missing.ckpt")))
    (tmp_path / "empty").mkdir()
    with pytest.raises(WeightsError, match="neither model.safetensors"):
        make_extractor("dinov2", FeatureSettings(backbone=str(tmp_path / "empty")))
    with pytest.raises(WeightsError, match="no sphere_mapper weights"):  # a backbone given as the head
        make_extractor("spheremap", FeatureSettings(backbone=weights["backbone"], head=weights["backbone"]))
    # The CLI reports the same before reading the model.
    parser = argparse.ArgumentParser()
    add_lift_parser(parser.add_subparsers())
    args = parser.parse_args(
        [
            "lift",
            str(tmp_path / "m.ply"),
            "--out",
            str(tmp_path / "o.ply"),
            "--features",
            "spheremap",
            "--backbone",
            weights["backbone"],
        ]
    )
    with pytest.raises(WeightsError, match=r"features\.head"):
        args.func(args)


# ------------------------------------------------------------------ extractors
def test_spheremap_pipeline_matches_direct_computation(weights):
    ext = make_extractor("spheremap", FeatureSettings(backbone=weights["backbone"], head=weights["head"]))
    assert isinstance(ext, SphereMapExtractor)
    rng = np.random.default_rng(3)
    image = rng.random((37, 37, 3)).astype(np.float32)  # 37 px: one output pixel per patch
    mask = np.ones((37, 37), bool)
    mask[:10, :] = False
    out = ext.extract(image, mask)
    assert out.shape == (37, 37, 3) and out.dtype == np.float32
    with torch.no_grad():
        pre, _ = weights["vit"](to_input(image[None], 518))
        ref = (F.normalize(weights["headmod"](pre.flatten(1, 2)), dim=-1) + 1) / 2
    ref = ref.reshape(37, 37, 3).numpy()
    np.testing.assert_allclose(out[10:], ref[10:], atol=1e-5)
    assert np.all(out[:10] == 0)
    # Decoded foreground features are unit vectors.
    np.testing.assert_allclose(np.linalg.norm(2 * out[10:] - 1, axis=-1), 1.0, atol=1e-4)


def test_spheremap_lifts_end_to_end_and_writes_ply(weights, small_model, tmp_path):
    ext = make_extractor("spheremap", FeatureSettings(backbone=weights["backbone"], head=weights["head"]))
    res = lift_features_full(small_model, ext, views=6, image_size=64, iterations=15, lr=0.02, batch_views=3)
    t = res.targets
    assert t.shape == (6, 64, 64, 3) and np.all(t[~res.masks] == 0) and t[res.masks].std() > 0.01
    f = res.model.features
    assert f.shape == (len(small_model), 3) and f.min() >= 0 and f.max() <= 1
    r = res.report
    assert len(r.loss_curve) == 15 and r.final_loss <= r.initial_loss + 1e-6 and r.total_seconds > 0
    write_ply(res.model, tmp_path / "lifted.ply")
    back = read_ply(tmp_path / "lifted.ply")
    np.testing.assert_allclose(back.features, f)


def test_dinov2_pca_extractor(weights, small_model):
    ext = make_extractor("dinov2", FeatureSettings(backbone=weights["backbone"]))
    assert isinstance(ext, Dinov2PCAExtractor)
    lifted, report = lift_features(small_model, ext, views=4, image_size=64, iterations=5)
    assert lifted.features.shape == (len(small_model), 3) and report.extractor == "dinov2"
    basis = ext.pca[1].clone()
    # A second model reuses the first model's basis (same feature space for a pair).
    lift_features(make_object("car", seed=6, n_gaussians=800), ext, views=2, image_size=48, iterations=0)
    torch.testing.assert_close(ext.pca[1], basis)
    img = np.full((64, 64, 3), 0.5, np.float32)
    img[16:48, 16:48] = np.random.default_rng(0).random((32, 32, 3))
    m = np.zeros((64, 64), bool)
    m[16:48, 16:48] = True
    out = Dinov2PCAExtractor(ext.backbone).extract(img, m)
    assert np.all(out[~m] == 0) and out.min() >= 0 and out.max() <= 1 and out[m].std(axis=0).min() > 0.01


# ------------------------------------------------------------------ lifting
def test_lifting_recovers_canonical_features():
    """Canonical 3-D features rendered to 2D and lifted back must match per Gaussian.

    Error per Gaussian: Euclidean norm ||f_lifted - f_canonical|| (features in [0,1]^3).
    Visible: summed blend weight over all lifting views >= 0.5 pixel (LiftResult.visibility);
    the rest get no gradient and take their nearest visible neighbour's feature."""
    model = make_object("car", seed=3, n_gaussians=1500)
    truth = canonical_features(model)
    res = lift_features_full(model, CanonicalExtractor(), views=10, image_size=64, iterations=30, lr=0.02)
    visible = res.visibility >= 0.5
    assert visible.mean() > 0.8
    err = np.linalg.norm(res.model.features - truth, axis=1)
    assert err[visible].mean() <= 0.05, err[visible].mean()
    # The bound is far from trivial: a random permutation of the true features misses it widely.
    shuffled = truth[np.random.default_rng(0).permutation(len(truth))]
    assert np.linalg.norm(shuffled - truth, axis=1)[visible].mean() > 0.3
    assert res.report.final_loss < res.report.initial_loss
    assert res.report.visible == int(visible.sum())


# ------------------------------------------------------------------ pruning
def test_prune_background_removes_near_zero_features():
    model = make_object("chair", seed=1, n_gaussians=500)
    f = np.random.default_rng(0).uniform(0.3, 1.0, (500, 3)).astype(np.float32)
    f[::10] *= 0.05  # 50 Gaussians with |f| < 0.1
    pruned, removed = prune_background(model.with_features(f), threshold=0.1)
    assert removed == 50 and len(pruned) == 450
    assert np.linalg.norm(pruned.features, axis=1).min() >= 0.1
    assert prune_background(model.with_features(f), threshold=0.0)[1] == 0
    with pytest.raises(ModelError, match="needs a model with features"):
        prune_background(model)


def test_floaters_lifted_to_zero_and_pruned(weights):
    """App. E end to end: semi-transparent Gaussians hovering outside the object mostly see
    background (feature 0) in the hard-masked feature maps, so lifting drives them to zero
    and pruning drops them while the object stays."""
    obj = make_object("car", seed=2, n_gaussians=1500)
    c = obj.means.mean(0)
    r = np.percentile(np.linalg.norm(obj.means - c, axis=1), 90)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(60, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    floaters = GaussianModel.from_colors(
        c + d * r * rng.uniform(1.05, 1.25, (60, 1)),
        rng.uniform(0, 1, (60, 3)),
        scales=np.full((60, 3), r * 0.03),
        opacities=0.3,
    )
    model = merge_models(obj, floaters)
    ext = make_extractor("spheremap", FeatureSettings(backbone=weights["backbone"], head=weights["head"]))
    lifted, _ = lift_features(model, ext, views=8, image_size=64, iterations=30)
    pruned, removed = prune_background(lifted, 0.1)
    dropped = np.linalg.norm(lifted.features, axis=1) < 0.1
    assert removed == dropped.sum() == len(model) - len(pruned)
    assert dropped[-60:].mean() > 0.8  # the floaters go
    assert dropped[:-60].mean() < 0.01  # the object stays


# ------------------------------------------------------------------ alignment wiring
def test_prepare_for_alignment_modes(small_model, weights):
    s = FeatureSettings()
    canon = prepare_for_alignment(small_model, "canonical", s)
    np.testing.assert_allclose(canon.features, canonical_features(small_model))
    assert prepare_for_alignment(small_model, "auto", s).metadata["features"] == "canonical"
    with pytest.raises(ModelError, match="no semantic"):
        prepare_for_alignment(small_model, "file", s)
    own = small_model.with_features(np.full((len(small_model), 3), 0.7, np.float32))
    assert prepare_for_alignment(own, "auto", s) is own
    s2 = FeatureSettings(
        extractor="spheremap",
        backbone=weights["backbone"],
        head=weights["head"],
        lift_views=4,
        lift_image_size=48,
        lift_iterations=3,
    )
    reports = []
    out = prepare_for_alignment(small_model, "auto", s2, reports=reports)
    assert reports and reports[0].extractor == "spheremap" and out.features.shape[1] == 3
    assert np.linalg.norm(out.features, axis=1).min() >= s2.prune_threshold
    with pytest.raises(ValueError, match="features must be one of"):
        prepare_for_alignment(small_model, "sift", s)


def test_lift_command_writes_semantic_ply(tmp_path, capsys):
    model = make_object("boat", seed=4, n_gaussians=800)
    write_ply(model, tmp_path / "m.ply")
    parser = argparse.ArgumentParser()
    add_lift_parser(parser.add_subparsers())
    args = parser.parse_args(
        [
            "lift",
            str(tmp_path / "m.ply"),
            "--out",
            str(tmp_path / "lifted.ply"),
            "--features",
            "canonical",
            "--views",
            "4",
            "--size",
            "48",
            "--iterations",
            "5",
            "--report",
            str(tmp_path / "r.json"),
            "--quiet",
        ]
    )
    assert args.func(args) == 0
    header = (tmp_path / "lifted.ply").read_bytes()[:4000]
    assert b"semantic_0" in header and b"semantic_2" in header and b"semantic_3" not in header
    lifted = read_ply(tmp_path / "lifted.ply")
    assert lifted.feature_dim == 3 and len(lifted) <= len(model)
    summary = json.loads(capsys.readouterr().out)
    assert summary["kept"] == len(lifted) and summary["kept"] + summary["pruned"] == len(model)
    assert json.loads((tmp_path / "r.json").read_text())["iterations"] == 5


def test_prepare_pair_resolves_modes_for_the_pipeline(small_model, weights):
    from gsa.features import prepare_pair

    other = make_object("car", seed=6, n_gaussians=700)
    s = FeatureSettings()
    src, dst, mode, reports = prepare_pair(small_model, other, "auto", s)
    assert mode == "canonical" and src is small_model and dst is other and reports == []
    with_f = other.with_features(np.full((len(other), 3), 0.5, np.float32))
    assert prepare_pair(small_model, with_f, "auto", s)[2] == "canonical"  # only one side has features
    assert prepare_pair(with_f, with_f, "auto", s)[2] == "file"
    with pytest.raises(ModelError, match="source has no semantic"):
        prepare_pair(small_model, with_f, "file", s)
    s2 = FeatureSettings(backbone=weights["backbone"], lift_views=3, lift_image_size=48, lift_iterations=2)
    src, dst, mode, reports = prepare_pair(small_model, other, "dinov2", s2)
    assert mode == "file" and src.feature_dim == dst.feature_dim == 3 and len(reports) == 2


def test_settings_from_environment():
    env = {
        "GSA_FEATURES_EXTRACTOR": "dinov2",
        "GSA_FEATURES_BACKBONE": "/w/dinov2",
        "GSA_LIFT_VIEWS": "7",
        "GSA_PRUNE_THRESHOLD": "0.2",
        "GSA_FEATURES_HEAD": "",
    }
    s = FeatureSettings(**feature_settings_env(env, lift_views=9, head=None))
    assert (s.extractor, s.backbone, s.head, s.lift_views, s.prune_threshold) == ("dinov2", "/w/dinov2", None, 9, 0.2)
    assert sam_paths_env("enc.onnx", None, {"GSA_SAM_DECODER": "dec.onnx"}) == ("enc.onnx", "dec.onnx")


def test_library_reads_no_environment(monkeypatch, small_model):
    """GSA_FEATURES_* reach the aligner only through settings built at the edge (gsa.cli)."""
    from gsa.align.pipeline import AlignOptions, _needs_extractor

    monkeypatch.setenv("GSA_FEATURES_EXTRACTOR", "dinov2")
    assert not _needs_extractor(AlignOptions(), small_model, small_model.with_features(None))
    assert _needs_extractor(
        AlignOptions(feature_settings=FeatureSettings(extractor="dinov2")), small_model, small_model.with_features(None)
    )
