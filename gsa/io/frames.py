"""Axis conventions of the 3DGS file formats, and the one internal convention.

Internally every model is in the INRIA/COLMAP PLY convention, **RDF**: x right, y down,
z forward (the camera looks along +z), right-handed, units those of the file (scenes from
SfM have no metric scale). PLY, compressed PLY, .splat, .ksplat and SOG store that
convention as is. SPZ (Niantic's spec) and glTF (the base spec: +Y up, +Z toward the
viewer) are **RUB**: x right, y up, z back. RDF -> RUB is a rotation by 180° about x,
F = diag(1, -1, -1): proper (det +1), so a file's transform stays a Sim(3) and
quaternions, scales and SH bands map exactly (GaussianModel.transformed).

Each reader maps the file's convention into RDF, each writer maps back, so reading and
writing never moves a Gaussian in its file's own coordinates.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from gsa.model import GaussianModel
from gsa.sim3 import Sim3


@dataclass(frozen=True)
class Frame:
    """How a file's coordinates are meant: axis letters (Right/Left, Up/Down, Forward/Back
    for +x, +y, +z), handedness, the up axis, and units when the format says."""

    convention: str
    handedness: str
    up_axis: str
    units: str | None = None

    def to_dict(self) -> dict:
        return asdict(self)


RDF = Frame("RDF", "right", "-y")
RUB = Frame("RUB", "right", "+y")
GLTF = Frame("RUB", "right", "+y", units="metre (glTF spec; the scene's scale is the capture's)")
INTERNAL = RDF

# Rotation taking internal (RDF) coordinates to RUB coordinates; its own inverse.
RDF_TO_RUB = np.diag([1.0, -1.0, -1.0])

FRAME_OF_FORMAT: dict[str, Frame] = {
    "ply": RDF,
    "compressed-ply": RDF,
    "splat": RDF,
    "ksplat": RDF,
    "sog": RDF,
    "spz": RUB,
    "glb": GLTF,
}


def _frame_rotation(frame: Frame) -> np.ndarray:
    """Rotation taking internal coordinates into `frame`'s."""
    return np.eye(3) if frame.convention == INTERNAL.convention else RDF_TO_RUB


def internal_to_file(fmt: str) -> Sim3:
    """The rotation taking internal (RDF) coordinates to format `fmt`'s own."""
    return Sim3(1.0, _frame_rotation(FRAME_OF_FORMAT[fmt]), np.zeros(3))


# Signs of the 16 real SH basis functions (3DGS order) under (x, y, z) -> (x, -y, -z):
# band 1 (y, z, x); band 2 (xy, yz, 3z²-r², xz, x²-y²); band 3 (y(3x²-y²), xyz, y(4z²-x²-y²),
# z(2z²-3x²-3y²), x(4z²-x²-y²), z(x²-y²), x(x²-3y²)). tests/test_formats.py checks them
# against the general SH rotation (gsa.sh.rotate_sh).
_FLIP_YZ_SH_SIGNS = np.array([1, -1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float32)


def flip_yz(model: GaussianModel) -> GaussianModel:
    """`model` turned 180° about x (RDF <-> RUB, its own inverse): exactly what
    model.transformed(Sim3(1, diag(1, -1, -1), 0)) computes, by sign flips (no rounding,
    ~20× faster than the general SH rotation)."""
    w, x, y, z = model.quats.T
    k = model.sh.shape[1]
    return GaussianModel(
        means=model.means * np.array([1, -1, -1], np.float32),
        quats=np.stack([-x, w, -z, y], axis=1),  # (0, 1, 0, 0) ⊗ q
        log_scales=model.log_scales,
        opacity_logits=model.opacity_logits,
        sh=model.sh * _FLIP_YZ_SH_SIGNS[:k, None],
        features=model.features,
        metadata=dict(model.metadata),
    )


def to_internal(model: GaussianModel, fmt: str) -> GaussianModel:
    """A model read in `fmt`'s own axes, expressed in the internal convention."""
    return model if FRAME_OF_FORMAT[fmt].convention == INTERNAL.convention else flip_yz(model)


def from_internal(model: GaussianModel, fmt: str) -> GaussianModel:
    """An internal model expressed in `fmt`'s own axes, ready to write."""
    return model if FRAME_OF_FORMAT[fmt].convention == INTERNAL.convention else flip_yz(model)


def file_transform(internal: Sim3, source_format: str, target_format: str) -> Sim3:
    """An internal source -> target Sim(3) expressed from the source file's own
    coordinates to the target file's own: F_t ∘ T ∘ F_s⁻¹."""
    return internal_to_file(target_format).compose(internal).compose(internal_to_file(source_format).inverse())
