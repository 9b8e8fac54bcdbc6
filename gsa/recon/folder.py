"""A folder `reconstruct()` wrote, read back as reconstruct() returned its model.

Light on purpose (no OpenCV, pycolmap or torch): `gsa align` asks whether each input folder is
a reconstruction or an image set to reconstruct.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

from gsa.io.ply import ReaderWarning
from gsa.model import GaussianModel
from gsa.recon.anchors import ANCHORS_FILE


def is_reconstruction(path: str | Path) -> bool:
    """Whether `path` is a folder `reconstruct()` wrote (its model and report are there)."""
    p = Path(path)
    return p.is_dir() and (p / "model.ply").is_file() and (p / "report.json").is_file()


def read_reconstruction(path: str | Path) -> GaussianModel:
    """The model of a folder `reconstruct()` wrote, as reconstruct() returned it: its training
    cameras, photo anchors and EXIF camera in `metadata` (align() uses the first two; another
    set of the same camera is reconstructed with its intrinsics, gsa.recon.calibration)."""
    from gsa.io.ply import read_ply
    from gsa.recon.anchors import PhotoAnchors
    from gsa.render.cameras import read_cameras_json

    out = Path(path)
    model = read_ply(out / "model.ply")
    if (out / "cameras.json").is_file():
        model.metadata["training_cameras"] = read_cameras_json(out / "cameras.json")[0]
    try:
        camera = json.loads((out / "report.json").read_text()).get("exif_camera")
    except (OSError, ValueError, AttributeError):
        camera = None  # an older or hand-edited report: the intrinsics are simply not shared
    model.metadata["exif_camera"] = camera if isinstance(camera, list) else None
    if (out / ANCHORS_FILE).is_file():
        try:
            model.metadata["photo_anchors"] = PhotoAnchors.load(out / ANCHORS_FILE)
        except (OSError, ValueError, KeyError, EOFError) as exc:  # the model still aligns by its Gaussians
            warnings.warn(
                f"{out / ANCHORS_FILE}: not read ({exc}); aligning without its photos", ReaderWarning, stacklevel=2
            )
    return model
