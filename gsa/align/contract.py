"""The transform contract of result.json (docs/formats.md): what the numbers map, between
which frames, in the forms integrators use (4×4 row-major, wxyz and xyzw quaternions, a
glTF node matrix, the inverse).

`align()` works in the internal convention (gsa.io.frames); the contract states the
transform in each input file's own coordinates, so it is exact for the files as given.
"""

from __future__ import annotations

import numpy as np

from gsa.io import frames
from gsa.sim3 import Sim3

MAPS = "source file coordinates -> target file coordinates: x_target = scale * rotation @ x_source + translation"


def frame_description(fmt: str) -> dict:
    return {"format": fmt, **frames.FRAME_OF_FORMAT[fmt].to_dict()}


def gltf_node_matrix(transform: Sim3) -> list[float]:
    """A 4×4 as glTF's node `matrix`: 16 numbers, column-major."""
    return [float(v) for v in transform.matrix().T.reshape(-1)]


def transform_contract(internal: Sim3, source_format: str = "ply", target_format: str = "ply") -> dict:
    """result.json's transform fields for an internal source -> target Sim(3)."""
    t = frames.file_transform(internal, source_format, target_format)
    q = t.quaternion()
    as_gltf = frames.file_transform(internal, "glb", "glb")
    out = {
        **t.to_dict(),
        "quaternion_xyzw": [float(q[1]), float(q[2]), float(q[3]), float(q[0])],
        "inverse_transform": t.inverse().matrix().tolist(),
        "gltf_node_matrix": gltf_node_matrix(as_gltf),
        "frames": {
            "source": frame_description(source_format),
            "target": frame_description(target_format),
            "internal": {"format": None, **frames.INTERNAL.to_dict()},
            "transform_maps": MAPS,
            "gltf_node_matrix_maps": "the source as a glTF asset (+Y up) into the target's glTF asset frame",
        },
    }
    if not np.allclose(t.matrix(), internal.matrix()):
        out["transform_internal"] = internal.matrix().tolist()
    return out
