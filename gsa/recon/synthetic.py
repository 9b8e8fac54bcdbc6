"""Synthetic image sets for testing reconstruction: a generated object (gsa.synth)
rendered from known cameras on a plain background with the project rasterizer.

The procedural objects are nearly flat-coloured, which gives SIFT little to hold
on to, so `textured_object` adds a high-contrast 3D noise texture to the colours
(as printed patterns on real objects do). The true cameras are written beside the
PNGs so SfM poses can be checked after a Sim(3) fit.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsa.model import GaussianModel
from gsa.recon.images import write_rgb
from gsa.render import Cameras, render_model
from gsa.render.cameras import look_at
from gsa.sh import rgb_to_sh_dc
from gsa.sim3 import Sim3
from gsa.synth import make_object


@dataclass
class SyntheticSet:
    directory: Path
    names: list[str]
    cameras: Cameras  # true world-to-camera poses and intrinsics
    model: GaussianModel  # the rendered object, in the same world frame
    radius: float  # orbit radius (world units)


def _value_noise(points: np.ndarray, freq: float, seed: int) -> np.ndarray:
    """(N,) smooth random field in [-1, 1] at (N, 3) points: trilinear lattice noise."""
    rng = np.random.default_rng(seed)
    lattice = rng.uniform(-1, 1, (64, 64, 64))
    p = points * freq
    i0 = np.floor(p).astype(np.int64)
    f = p - i0
    f = f * f * (3 - 2 * f)
    out = np.zeros(len(points))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (
                    (f[:, 0] if dx else 1 - f[:, 0])
                    * (f[:, 1] if dy else 1 - f[:, 1])
                    * (f[:, 2] if dz else 1 - f[:, 2])
                )
                out += w * lattice[(i0[:, 0] + dx) % 64, (i0[:, 1] + dy) % 64, (i0[:, 2] + dz) % 64]
    return out


def textured_object(
    category: str = "car", seed: int = 0, n_gaussians: int = 60_000, contrast: float = 0.7, n_spots: int = 3000
) -> GaussianModel:
    """A gsa.synth object whose colours carry a 3D noise texture plus random coloured
    spots of varied size (blob-like marks give SIFT distinctive keypoints)."""
    from scipy.spatial import cKDTree

    model = make_object(category, seed=seed, n_gaussians=n_gaussians)
    size = float(np.linalg.norm(model.means.max(0) - model.means.min(0)))
    x = model.means.astype(np.float64) / size
    tex = _value_noise(x, 12.0, seed + 1)
    rgb = model.base_colors * (1.0 + 0.5 * contrast * tex[:, None])
    rng = np.random.default_rng(seed + 3)
    centres = x[rng.choice(len(x), n_spots, replace=False)]
    radii = rng.uniform(0.007, 0.016, n_spots)
    spot_rgb = rng.uniform(0.0, 1.0, (n_spots, 3))
    d, k = cKDTree(centres).query(x, k=1)
    inside = d < radii[k]
    rgb[inside] = (1 - contrast) * rgb[inside] + contrast * spot_rgb[k[inside]]
    rgb = np.clip(rgb, 0.02, 0.98)
    sh = model.sh.copy()
    sh[:, 0, :] = rgb_to_sh_dc(rgb)
    sh[:, 1:, :] = 0.0
    return GaussianModel(model.means, model.quats, model.log_scales, model.opacity_logits, sh, None)


def render_image_set(
    out_dir: str | Path,
    *,
    category: str = "car",
    seed: int = 0,
    n_views: int = 30,
    size: int = 256,
    fov: float = 45.0,
    rig: Sim3 | None = None,
    orbit_seed: int = 0,
    background=(1.0, 1.0, 1.0),
    n_gaussians: int = 60_000,
    elevation_range=(5.0, 65.0),
    model: GaussianModel | None = None,
) -> SyntheticSet:
    """Render `n_views` PNGs of a textured object into out_dir/images and write out_dir/cameras_true.json.

    Cameras orbit the object (directions spread by a golden-angle spiral between the
    elevation limits, azimuth phase from orbit_seed) at a radius that frames it.
    `rig` (a Sim3) moves the whole world (object and cameras) into another frame: the
    images are unchanged but the true poses/model are expressed in the moved frame.
    """
    out_dir = Path(out_dir)
    img_dir = out_dir / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    model = model if model is not None else textured_object(category, seed, n_gaussians)
    center = 0.5 * (model.means.min(0) + model.means.max(0)).astype(np.float64)
    extent = float(np.percentile(np.linalg.norm(model.means - center, axis=1), 99))
    radius = 1.05 * extent / np.sin(np.radians(fov) / 2)
    # Object captures are not full spheres: cameras above and around, not below.
    rng = np.random.default_rng(orbit_seed)
    i = np.arange(n_views)
    az = rng.uniform(0, 2 * np.pi) + i * np.pi * (3 - np.sqrt(5))
    lo, hi = np.radians(elevation_range)
    el = np.arcsin(np.sin(lo) + (np.sin(hi) - np.sin(lo)) * (i + 0.5) / n_views)
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    views = np.stack([look_at(center + radius * d, center) for d in dirs])
    f = 0.5 * size / np.tan(np.radians(fov) / 2)
    cams = Cameras(views, f, f, size / 2, size / 2, size, size)
    names = []
    for k in range(0, n_views, 8):  # chunks bound memory at larger sizes
        out = render_model(model, cams[k : k + 8], features=False, background=background, depth=False, backend="cpu")
        for j, img in enumerate(out.colors.numpy()):
            name = f"view_{k + j:03d}.png"
            write_rgb(img_dir / name, img)
            names.append(name)
    if rig is not None:
        model = model.transformed(rig)
        cams = cams.for_transformed_model(rig.inverse())
        radius *= rig.scale
    _write_true_cameras(out_dir / "cameras_true.json", names, cams)
    return SyntheticSet(img_dir, names, cams, model, radius)


def _write_true_cameras(path: Path, names: list[str], cams: Cameras) -> None:
    data = {
        "width": cams.width,
        "height": cams.height,
        "images": [
            {
                "name": n,
                "viewmat": cams.viewmats[i].tolist(),
                "fx": float(cams.fx[i]),
                "fy": float(cams.fy[i]),
                "cx": float(cams.cx[i]),
                "cy": float(cams.cy[i]),
            }
            for i, n in enumerate(names)
        ],
    }
    path.write_text(json.dumps(data))
