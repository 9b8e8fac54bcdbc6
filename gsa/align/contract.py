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


def hints_from_files(options, source_format: str = "ply", target_format: str = "ply"):
    """AlignOptions whose guidance (gsa.align.guided) was given in each input FILE's own
    coordinates, as result.json states transforms, re-expressed in the internal convention
    align() works in: a previous result.json's `transform` (or an alternative's) is then a
    valid init_transform for the same files."""
    from dataclasses import replace

    to_src, to_dst = frames.internal_to_file(source_format), frames.internal_to_file(target_format)
    if np.allclose(to_src.rotation, np.eye(3)) and np.allclose(to_dst.rotation, np.eye(3)):
        return options
    changes = {}
    if options.init_transform is not None:
        t = Sim3.from_matrix(np.asarray(options.init_transform))
        changes["init_transform"] = to_dst.inverse().compose(t).compose(to_src).matrix()
    if options.point_pairs is not None:
        src, dst = (np.asarray(p, np.float64) for p in options.point_pairs)
        changes["point_pairs"] = (to_src.inverse().apply(src), to_dst.inverse().apply(dst))
    if options.up_axes is not None:
        src_up, dst_up = (np.asarray(v, np.float64) for v in options.up_axes)
        changes["up_axes"] = (to_src.rotation.T @ src_up, to_dst.rotation.T @ dst_up)
    if options.front_axes is not None:
        src_front, dst_front = (np.asarray(v, np.float64) for v in options.front_axes)
        changes["front_axes"] = (to_src.rotation.T @ src_front, to_dst.rotation.T @ dst_front)
    return replace(options, **changes) if changes else options
