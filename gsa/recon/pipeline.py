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
from gsa.recon.calibration import Calibration, same_camera
from gsa.recon.images import load_image_set
from gsa.recon.masks import SamOnnxMasker, compute_masks
from gsa.recon.sfm import SfMError, SfMResult, run_sfm
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
    intrinsics: dict = field(default_factory=dict)  # estimated, or fixed from another reconstruction

    @property
    def calibration(self) -> Calibration | None:
        """This reconstruction's intrinsics, to reconstruct another set of the same camera with."""
        return Calibration.of_model(self.model)

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
            "exif_camera": self.model.metadata.get("exif_camera"),
            "intrinsics": self.intrinsics,
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
    calibration: Calibration | None = None,
    calibration_check: str = "same-camera",
) -> ReconstructionResult:
    """Reconstruct a feature-augmented 3DGS model from a directory or zip of images.

    preset: "cpu" | "gpu" or a TrainConfig; features: "canonical" (weight-free, lifted after
    a colour-only phase), "none", or (C, h, w, D) extractor maps in image order;
    masks: "auto" | "key" | "grabcut" | "sam" | "none". calibration: another reconstruction's
    intrinsics (gsa.recon.calibration), held fixed through SfM when this set was taken with the
    same camera by EXIF (calibration_check "same-camera") or in any case ("none"), so that two
    models of one camera share their lens; otherwise this set's own are estimated, as without it
    (report.json's "intrinsics" says which and why). Raises ImageSetError / SfMError / MaskError
    with a user-readable message on bad input.
    """
    if calibration_check not in ("same-camera", "none"):
        raise ValueError(f"calibration_check must be same-camera or none, got {calibration_check!r}")
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

    fixed, intrinsics = _fixed_intrinsics(imset, calibration, calibration_check)
    t = time.perf_counter()

    def sfm_with(params):
        return run_sfm(
            imset,
            out / "sfm",
            matching=matching,
            progress=lambda s, f: report(s, f),
            seed=cfg.seed,
            fixed_intrinsics=params,
        )

    try:
        sfm = sfm_with(fixed)
    except SfMError as exc:
        if fixed is None:
            raise
        # EXIF can name one camera for two crops (an unrecorded digital zoom): intrinsics that
        # do not fit this set's photos must not cost the reconstruction, so it estimates its own.
        sfm = sfm_with(None)
        intrinsics = {"fixed": False, "reason": f"estimated from this set: with the other set's camera, {exc}"}
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
    tr.model.metadata["exif_camera"] = list(imset.camera) if imset.camera else None
    if sfm.anchors is not None:  # align() registers two reconstructions by their photos (gsa.align.photo)
        sfm.anchors.save(out / ANCHORS_FILE)
        tr.model.metadata["photo_anchors"] = sfm.anchors
    cameras_path = write_cameras_json(out / "cameras.json", sfm.cameras, sfm.names)
    (out / "training_curve.json").write_text(json.dumps(tr.curve))
    timings["total"] = time.perf_counter() - t0
    res = ReconstructionResult(
        tr.model, Path(model_path), cameras_path, out, sfm, tr, used, timings, imset.notes, intrinsics
    )
    (out / "report.json").write_text(json.dumps(res.summary(), indent=1))
    report("done", 1.0)
    return res


def _fixed_intrinsics(imset, calibration: Calibration | None, check: str) -> tuple[tuple | None, dict]:
    """(fx, fy, cx, cy) to hold fixed through SfM, or None, and report.json's account of it."""
    if calibration is None:
        return None, {"fixed": False, "reason": "estimated from this set"}
    if check == "same-camera" and not same_camera(calibration.camera, imset.camera):
        why = "no EXIF camera on one of the sets" if not (calibration.camera and imset.camera) else "another camera"
        return None, {"fixed": False, "reason": f"estimated from this set: {why}"}
    if imset.camera_groups is not None:
        return None, {"fixed": False, "reason": "estimated from this set: it holds photos of several cameras"}
    params = calibration.for_size(imset.width, imset.height)
    if params is None:
        return None, {
            "fixed": False,
            "reason": f"estimated from this set: the given intrinsics are for {calibration.width}x{calibration.height} "
            f"images, not the aspect of {imset.width}x{imset.height}",
        }
    return params, {"fixed": True, "reason": "the other set's camera", "fx": params[0], "fy": params[1]}
