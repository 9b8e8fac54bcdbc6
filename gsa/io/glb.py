"""Binary glTF (GLB) with the ratified KHR_gaussian_splatting extension.

Our own code on `struct` + `json`: pygltflib (the tests' reference reader) parses the
whole document into dataclasses and leaves the buffer checks to the caller. Written:
one node, one mesh, one POINTS primitive with float accessors POSITION,
KHR_gaussian_splatting:ROTATION (x, y, z, w — glTF's order), :SCALE (linear),
:OPACITY (linear in [0, 1]) and :SH_DEGREE_l_COEF_n (the 3DGS basis, m from −l to l).
Read: the first primitive carrying the extension; float or normalized-integer
accessors as the spec allows; the node's matrix or TRS is applied. Every offset and
length is checked against the file before a byte is read.
"""

from __future__ import annotations

import json
import struct

import numpy as np

from gsa.errors import GSAError
from gsa.io.ply import ALPHA_EPS
from gsa.model import GaussianModel, sh_coeff_count
from gsa.sim3 import Sim3

EXT = "KHR_gaussian_splatting"
GLB_MAGIC = b"glTF"
_JSON, _BIN = 0x4E4F534A, 0x004E4942
_COMPONENTS = {
    5120: ("i1", 127.0),
    5121: ("u1", 255.0),
    5122: ("<i2", 32767.0),
    5123: ("<u2", 65535.0),
    5126: ("<f4", None),
}
_WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}


class GlbError(GSAError, ValueError):
    """A GLB that is not a readable KHR_gaussian_splatting asset."""


def sh_attribute_names(degree: int) -> list[str]:
    """Attribute semantics of SH coefficients 0..K-1 in the 3DGS order."""
    names = []
    for level in range(degree + 1):
        names += [f"{EXT}:SH_DEGREE_{level}_COEF_{n}" for n in range(2 * level + 1)]
    return names


def encode_glb(model: GaussianModel) -> list:
    """The GLB as a list of byte strings and arrays to write in order (no joined copy)."""
    n = len(model)
    columns: list[tuple[str, np.ndarray, str]] = [
        ("POSITION", model.means, "VEC3"),
        (
            f"{EXT}:ROTATION",
            (model.quats / np.linalg.norm(model.quats, axis=1, keepdims=True))[:, [1, 2, 3, 0]],
            "VEC4",
        ),
        (f"{EXT}:SCALE", np.exp(model.log_scales.astype(np.float64)), "VEC3"),
        (f"{EXT}:OPACITY", model.opacities, "SCALAR"),
    ]
    columns += [(name, model.sh[:, k, :], "VEC3") for k, name in enumerate(sh_attribute_names(model.sh_degree))]
    views, accessors, attributes, blobs, offset = [], [], {}, [], 0
    for i, (name, values, kind) in enumerate(columns):
        data = np.ascontiguousarray(values, dtype="<f4").reshape(n, -1)
        blob = memoryview(data).cast("B")
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        accessor = {"bufferView": i, "componentType": 5126, "count": n, "type": kind}
        if name == "POSITION":  # required by the glTF spec
            accessor["min"], accessor["max"] = data.min(0).tolist(), data.max(0).tolist()
        accessors.append(accessor)
        attributes[name] = i
        blobs.append(blob)
        offset += len(blob)  # float data keeps every offset a multiple of 4
    doc = {
        "asset": {"version": "2.0", "generator": "gsa"},
        "extensionsUsed": [EXT],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [
            {
                "primitives": [
                    {
                        "mode": 0,
                        "attributes": attributes,
                        "extensions": {EXT: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}},
                    }
                ]
            }
        ],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": accessors,
    }
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + offset
    return [
        struct.pack("<4sII", GLB_MAGIC, 2, total),
        struct.pack("<II", len(js), _JSON),
        js,
        struct.pack("<II", offset, _BIN),
        *blobs,
    ]


def _chunks(data: bytes) -> tuple[dict, memoryview]:
    if len(data) < 20:
        raise GlbError("truncated: shorter than a GLB header")
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    if magic != GLB_MAGIC or version != 2:
        raise GlbError(f"not a glTF 2.0 binary (magic {magic!r}, version {version})")
    if length > len(data):
        raise GlbError(f"truncated: the header declares {length} bytes but the file has {len(data)}")
    js_len, js_type = struct.unpack_from("<II", data, 12)
    if js_type != _JSON or 20 + js_len > length:
        raise GlbError("the first chunk is not a complete JSON chunk")
    try:
        doc = json.loads(bytes(data[20 : 20 + js_len]))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GlbError(f"the JSON chunk does not parse: {exc}") from None
    if not isinstance(doc, dict):
        raise GlbError("the JSON chunk is not an object")
    pos = 20 + js_len + (-js_len % 4)
    binary = memoryview(b"")
    if pos + 8 <= length:
        bin_len, bin_type = struct.unpack_from("<II", data, pos)
        if bin_type == _BIN:
            if pos + 8 + bin_len > length:
                raise GlbError(f"truncated: the BIN chunk declares {bin_len} bytes but fewer follow")
            binary = memoryview(data)[pos + 8 : pos + 8 + bin_len]
    return doc, binary


def _accessor(doc: dict, binary: memoryview, index, kind: str, count: int | None) -> np.ndarray:
    try:
        acc = doc["accessors"][index]
        view = doc["bufferViews"][acc["bufferView"]]
        ctype, n, acc_type = acc["componentType"], int(acc["count"]), acc["type"]
        if view.get("buffer", 0) != 0:
            raise GlbError("an accessor points outside the GLB's own buffer")
        start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
        view_end = int(view.get("byteOffset", 0)) + int(view["byteLength"])
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        raise GlbError(f"accessor {index!r} is malformed ({exc!r})") from None
    if acc_type != kind or ctype not in _COMPONENTS:
        raise GlbError(f"accessor {index} is {acc_type}/{ctype}, expected {kind} float or normalized integers")
    if count is not None and n != count:
        raise GlbError(f"accessor {index} holds {n} values, the positions {count}")
    dtype, norm = _COMPONENTS[ctype]
    width = _WIDTH[kind]
    item = np.dtype(dtype).itemsize * width
    stride = int(view.get("byteStride", item))
    if n <= 0 or stride < item or start < 0 or start + (n - 1) * stride + item > min(view_end, len(binary)):
        raise GlbError(f"truncated: accessor {index} runs past its buffer view or the BIN chunk")
    raw = np.ndarray((n, width), dtype, buffer=binary, offset=start, strides=(stride, np.dtype(dtype).itemsize))
    values = raw.astype(np.float32)
    if norm is not None:
        if not acc.get("normalized", False) and ctype != 5121 and ctype != 5123:
            raise GlbError(f"accessor {index}: integer data must be normalized")
        if acc.get("normalized", False):
            values = np.maximum(values / norm, -1.0)
    return values


def _node_transform(doc: dict, mesh_index: int) -> Sim3 | None:
    for node in doc.get("nodes", []):
        if isinstance(node, dict) and node.get("mesh") == mesh_index:
            if "matrix" in node:
                m = np.asarray(node["matrix"], np.float64).reshape(4, 4).T  # column-major in glTF
            else:
                from gsa.geometry import quat_to_rotation

                x, y, z, w = node.get("rotation", [0, 0, 0, 1])
                s = np.asarray(node.get("scale", [1, 1, 1]), np.float64)
                if not np.allclose(s, s[0]):
                    raise GlbError("the splat node has a non-uniform scale (undefined by KHR_gaussian_splatting)")
                m = np.eye(4)
                m[:3, :3] = s[0] * quat_to_rotation(np.array([w, x, y, z], np.float64))
                m[:3, 3] = node.get("translation", [0, 0, 0])
            return None if np.allclose(m, np.eye(4)) else Sim3.from_matrix(m)
    return None


def decode_glb(data: bytes) -> GaussianModel:
    doc, binary = _chunks(data)
    for mesh_index, mesh in enumerate(doc.get("meshes", [])):
        for prim in mesh.get("primitives", []) if isinstance(mesh, dict) else []:
            if isinstance(prim, dict) and EXT in (prim.get("extensions") or {}):
                return _decode_primitive(doc, binary, prim, mesh_index)
    raise GlbError(f"no mesh primitive carries the {EXT} extension")


def _decode_primitive(doc: dict, binary: memoryview, prim: dict, mesh_index: int) -> GaussianModel:
    attrs = prim.get("attributes") or {}
    required = ["POSITION", f"{EXT}:ROTATION", f"{EXT}:SCALE", f"{EXT}:OPACITY", f"{EXT}:SH_DEGREE_0_COEF_0"]
    missing = [a for a in required if a not in attrs]
    if missing:
        raise GlbError(f"the splat primitive lacks {', '.join(missing)}")
    means = _accessor(doc, binary, attrs["POSITION"], "VEC3", None)
    n = len(means)
    quats = _accessor(doc, binary, attrs[f"{EXT}:ROTATION"], "VEC4", n)[:, [3, 0, 1, 2]]
    scales = _accessor(doc, binary, attrs[f"{EXT}:SCALE"], "VEC3", n)
    stored = _accessor(doc, binary, attrs[f"{EXT}:OPACITY"], "SCALAR", n)[:, 0].astype(np.float64)
    # alpha 0 and 1 (an infinite logit) are read as ALPHA_EPS and 1 − ALPHA_EPS, and counted
    opacity = np.clip(stored, ALPHA_EPS, 1.0 - ALPHA_EPS)
    clamped = int(np.count_nonzero((stored <= 0.0) | (stored >= 1.0)))
    degree = 0
    while degree < 3 and all(a in attrs for a in sh_attribute_names(degree + 1)):
        degree += 1
    sh = np.empty((n, sh_coeff_count(degree), 3), np.float32)
    for k, name in enumerate(sh_attribute_names(degree)):
        sh[:, k, :] = _accessor(doc, binary, attrs[name], "VEC3", n)
    if (scales < 0).any():
        raise GlbError("negative scales (the spec forbids them)")
    with np.errstate(divide="ignore"):
        log_scales = np.log(scales)
    model = GaussianModel(
        means=means, quats=quats, log_scales=log_scales, opacity_logits=np.log(opacity / (1 - opacity)), sh=sh
    )
    model.metadata["clamped_opacity"] = clamped
    node = _node_transform(doc, mesh_index)
    return model if node is None else model.transformed(node)
