"""`reconstruct()`: image set -> SfM -> masks -> feature-augmented 3DGS, one call.

Outputs in out_dir: model.ply (INRIA layout + semantic_* features), cameras.json
(COLMAP-compatible PINHOLE + qvec/tvec), sparse/model (COLMAP text model), anchors.npz (the SfM
points' descriptors, gsa.recon.anchors), masks/*.png, training_curve.json, report.json.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from gsa.io.ply import write_ply
from gsa.model import GaussianModel
from gsa.recon.anchors import ANCHORS_FILE
from gsa.recon.images import load_image_set
from gsa.recon.masks import SamOnnxMasker, compute_masks
from gsa.recon.sfm import SfMResult, run_sfm
from gsa.recon.train import PRESETS, TrainConfig, TrainResult, train_gaussians
from gsa.render.cameras import write_cameras_json

Progress = Callable[[str, float], None]


@dataclass
class ReconstructionResult:
    model: GaussianModel
    model_path: Path
    cameras_path: Path
    out_dir: Path
    sfm: SfMResult
    train: TrainResult
    mask_methods: list[str]
    timings: dict = field(default_factory=dict)
    image_notes: dict = field(default_factory=dict)  # what loading changed (gsa.recon.photos)

    @property
    def n_images(self) -> int:
        return self.sfm.n_images

    @property
    def n_registered(self) -> int:
        return self.sfm.n_registered

    def summary(self) -> dict:
        return {
            "images": self.sfm.n_images,
            "image_set": self.image_notes,
            "registered": self.sfm.n_registered,
            "unregistered": self.sfm.unregistered,
            "mapping_attempts": self.sfm.mapping_attempts,
            "sfm_points": int(len(self.sfm.points)),
            "gaussians": len(self.model),
            "feature_dim": self.model.feature_dim,
            "psnr_heldout_db": self.train.psnr_heldout,
            "psnr_heldout_masked_db": self.train.psnr_heldout_masked,
            "heldout_views": self.train.heldout,
            "masks": sorted(set(self.mask_methods)),
            # an object capture's region and the distant background dropped beyond it ({}: none)
            "far_background": self.train.region,
            "model": str(self.model_path),
            "cameras": str(self.cameras_path),
            "timings_s": self.timings,
        }


def reconstruct(
    images_path: str | Path,
    out_dir: str | Path,
    preset: str | TrainConfig = "cpu",
    features: str | np.ndarray = "canonical",
    progress: Progress | None = None,
    *,
    masks: str = "auto",
    matching: str = "exhaustive",
    iterations: int | None = None,
    sam_encoder: str | None = None,
    sam_decoder: str | None = None,
) -> ReconstructionResult:
    """Reconstruct a feature-augmented 3DGS model from a directory or zip of images.

    preset: "cpu" | "gpu" or a TrainConfig; features: "canonical" (weight-free, lifted after
    a colour-only phase), "none", or (C, h, w, D) extractor maps in image order;
    masks: "auto" | "key" | "grabcut" | "sam" | "none". Raises ImageSetError / SfMError / MaskError
    with a user-readable message on bad input.
    """
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"preset must be one of {', '.join(PRESETS)}, got {preset!r}")
        cfg = PRESETS[preset]
    else:
        cfg = preset
    if iterations is not None:
        cfg = replace(cfg, iterations=iterations, densify_until=min(cfg.densify_until, int(0.7 * iterations)))
    report = progress or (lambda stage, frac: None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings = {}
    t0 = time.perf_counter()

    t = time.perf_counter()
    imset = load_image_set(images_path)  # before any progress line: its warnings are lines of their own
    report("images", 1.0)
    timings["load"] = time.perf_counter() - t

    t = time.perf_counter()
    sfm = run_sfm(imset, out / "sfm", matching=matching, progress=lambda s, f: report(s, f), seed=cfg.seed)
    timings["sfm"] = time.perf_counter() - t
    order = [imset.names.index(n) for n in sfm.names]
    imgs = np.stack([imset.read(i) for i in order])

    t = time.perf_counter()
    report("masks", 0.0)
    sam = None
    if masks == "sam":
        sam = SamOnnxMasker(sam_encoder, sam_decoder)
    mk, used = compute_masks(imgs, masks, sfm.cameras, sfm.points, sam=sam)
    (out / "masks").mkdir(exist_ok=True)
    for n, m in zip(sfm.names, mk):
        cv2.imwrite(str(out / "masks" / (Path(n).stem + ".png")), m.astype(np.uint8) * 255)
    timings["masks"] = time.perf_counter() - t

    if isinstance(features, np.ndarray):
        features = features[order]
    t = time.perf_counter()
    tr = train_gaussians(
        imgs,
        mk,
        sfm.cameras,
        sfm.points,
        sfm.colors,
        cfg,
        names=sfm.names,
        features=features,
        progress=lambda s, f: report(s, f),
    )
    timings["train"] = time.perf_counter() - t

    model_path = write_ply(tr.model, out / "model.ply")
    tr.model.metadata["training_cameras"] = sfm.cameras  # align()'s fine stage renders from these
    if sfm.anchors is not None:  # align() registers two reconstructions by their photos (gsa.align.photo)
        sfm.anchors.save(out / ANCHORS_FILE)
        tr.model.metadata["photo_anchors"] = sfm.anchors
    cameras_path = write_cameras_json(out / "cameras.json", sfm.cameras, sfm.names)
    (out / "training_curve.json").write_text(json.dumps(tr.curve))
    timings["total"] = time.perf_counter() - t0
    res = ReconstructionResult(tr.model, Path(model_path), cameras_path, out, sfm, tr, used, timings, imset.notes)
    (out / "report.json").write_text(json.dumps(res.summary(), indent=1))
    report("done", 1.0)
    return res
