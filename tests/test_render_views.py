"""PNG renders and the `gsa render` command."""

import argparse

import cv2
import numpy as np
import pytest

from gsa.io.ply import write_ply
from gsa.render.command import add_render_parser
from gsa.render.views import render_model_views, write_alignment_renders, write_synchronized_renders
from gsa.sim3 import Sim3
from tests.render_scenes import blob_object


def test_alignment_renders_show_the_change(tmp_path):
    src = blob_object(3000, seed=1)
    gt = Sim3(1.2, np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]), np.array([0.3, 0.0, 0.1]))
    paths = write_alignment_renders(src, src.transformed(gt), Sim3.identity(), gt, tmp_path, n_novel=2, size=64)
    assert {"before_0", "after_0", "features_0", "before_1", "after_1", "features_1"} <= set(paths)
    before, after = cv2.imread(str(paths["before_0"])), cv2.imread(str(paths["after_0"]))
    assert before.shape == after.shape and before.shape[0] == 64
    w = 64
    # after alignment the source panel equals the target panel; before it does not
    src_a, tgt_a = after[:, :w].astype(float), after[:, w + 4 : 2 * w + 4].astype(float)
    src_b = before[:, :w].astype(float)
    assert np.abs(src_a - tgt_a).mean() < 2.0
    assert np.abs(src_b - tgt_a).mean() > 5.0


def test_model_views_and_synchronized(tmp_path):
    m = blob_object(2000, seed=2)
    paths = render_model_views(m, tmp_path / "v", views=3, features=True, size=48)
    assert len([k for k in paths if k.startswith("view_")]) == 6 and paths["contact_sheet"].exists()
    img = cv2.imread(str(paths["view_0"]))
    assert img.shape == (48, 48, 3) and img.min() < 200  # something was drawn on white
    sync = write_synchronized_renders(
        [m, m], tmp_path / "s", [Sim3.identity(), Sim3.identity()], views=2, size=32, features=True
    )
    assert sync["synchronized"].exists() and sync["synchronized_features"].exists()
    with pytest.raises(ValueError):
        render_model_views(m.with_features(None), tmp_path / "x", views=1, features=True)


def test_render_command(tmp_path, capsys):
    m = blob_object(1500, seed=3)
    ply = write_ply(m, tmp_path / "m.ply")
    parser = argparse.ArgumentParser()
    add_render_parser(parser.add_subparsers())
    args = parser.parse_args(
        [
            "render",
            str(ply),
            "--out",
            str(tmp_path / "out"),
            "--views",
            "2",
            "--features",
            "--size",
            "40",
            "--backend",
            "cpu",
        ]
    )
    assert args.func(args) == 0
    assert (tmp_path / "out" / "view_1_features.png").exists()
    assert "contact_sheet.png" in capsys.readouterr().out


def test_a_large_model_is_rendered_a_few_views_a_call_into_the_same_images(monkeypatch):
    # The renderer holds every Gaussian's projection in every view of a call (1.7 GB for the
    # 3 views of a 3M-Gaussian source): calls are bounded, and the pixels do not change.
    from gsa.render import render_model
    from gsa.render import views as views_module
    from gsa.render.cameras import cameras_around

    model = blob_object(3000, seed=1)
    cams = cameras_around(model.means, 5, 48, seed=3)
    move = Sim3(1.2, np.eye(3), np.array([0.1, 0.0, 0.0]))
    whole = render_model(model, cams, features=True, background=views_module.WHITE, sim3=move)
    monkeypatch.setattr(views_module, "VIEW_GAUSSIANS_PER_CALL", 2 * len(model))  # 2 views a call
    parts = views_module.render_views(model, cams, features=True, background=views_module.WHITE, sim3=move, depth=True)
    for name in ("colors", "features", "alpha", "depth"):
        assert np.array_equal(getattr(whole, name).numpy(), getattr(parts, name).numpy()), name
    # The images people look at show no depth: unless asked, it is not composited.
    plain = views_module.render_views(model, cams, features=False, background=views_module.WHITE, sim3=move)
    assert plain.depth is None and np.array_equal(plain.colors.numpy(), whole.colors.numpy())
