"""Reconstruction from image sets: images -> SfM (pycolmap) -> masks -> feature-augmented 3DGS.

Entry point: `reconstruct(images_path, out_dir, preset="cpu", features="canonical")`.
"""

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


def __getattr__(name):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'gsa.recon' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
