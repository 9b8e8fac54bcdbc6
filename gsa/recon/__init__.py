"""Reconstruction from image sets: images -> SfM (pycolmap) -> masks -> feature-augmented 3DGS.

Entry point: `reconstruct(images_path, out_dir, preset="cpu", features="canonical")`.
"""

from gsa.recon.images import ImageSetError, load_image_set
from gsa.recon.masks import MaskError
from gsa.recon.sfm import SfMError

__all__ = ["ImageSetError", "MaskError", "SfMError", "load_image_set", "reconstruct", "ReconstructionResult"]


def __getattr__(name):  # lazy: keeps `import gsa.recon` light for the CLI
    if name in ("reconstruct", "ReconstructionResult"):
        from gsa.recon import pipeline

        return getattr(pipeline, name)
    raise AttributeError(name)
