"""Reconstruction from image sets: images -> SfM (pycolmap) -> masks -> feature-augmented 3DGS.

Entry point: `reconstruct(images_path, out_dir, preset="cpu", features="canonical")`.
"""

from gsa.lazy import lazy_exports

__all__ = ["ImageSetError", "MaskError", "SfMError", "load_image_set", "reconstruct", "ReconstructionResult"]

# Every name is resolved on first use: `import gsa.recon` (and gsa.recon.command, which
# the CLI imports to register `gsa reconstruct`) must not load OpenCV or the pipeline.
_LAZY = {
    "ImageSetError": "gsa.recon.images",
    "load_image_set": "gsa.recon.images",
    "MaskError": "gsa.recon.masks",
    "SfMError": "gsa.recon.sfm",
    "reconstruct": "gsa.recon.pipeline",
    "ReconstructionResult": "gsa.recon.pipeline",
}
__getattr__, __dir__ = lazy_exports(__name__, _LAZY)
