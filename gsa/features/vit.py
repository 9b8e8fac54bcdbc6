"""DINOv2 ViT backbone and the spherical-map head, in plain torch, loaded from local files.

Why our own ~150-line ViT instead of `transformers` or `torch.hub`: torch.hub needs the
network and torchvision; `transformers` is a 15 s import and a large dependency tree for
what is one standard ViT. Both published weight formats load into this one module:

* torch.hub format (`dinov2_vitb14_pretrain.pth`): a state dict with keys
  `cls_token, pos_embed, mask_token, patch_embed.proj.{weight,bias},
  blocks.{i}.{norm1,attn.qkv,attn.proj,ls1.gamma,norm2,mlp.fc1,mlp.fc2,ls2.gamma}.*, norm.*`.
  Sizes (depth, width, heads, patch) are read from the tensors themselves.
* Hugging Face folder (`facebook/dinov2-base` as saved by `save_pretrained`):
  `config.json` + `model.safetensors` (or `pytorch_model.bin`); keys
  `embeddings.*, encoder.layer.{i}.attention.attention.{query,key,value}.*, ...,
  layernorm.*` (or transformers-5 in-memory names `attention.{q,k,v,o}_proj`), mapped onto
  the hub names below (q, k, v are concatenated into qkv).

The sphere-mapper head follows the authors' `DINOMapper.sphere_mapper` (Mariotti et al.,
CVPR 2024, github.com/VICO-UoE/SphericalMaps) exactly, as an `nn.Sequential` so that their
state dict loads unchanged:
  0: Linear(768, 384)              keys 0.weight (384,768), 0.bias
  1: GELU
  2: Block(dim 384, 6 heads, MLP x4, qkv without bias, LayerNorm eps 1e-5, no layer scale)
     keys 2.norm1.*, 2.attn.qkv.weight (1152,384), 2.attn.proj.*, 2.norm2.*, 2.mlp.fc1.*, 2.mlp.fc2.*
  3: Linear(384, 3)                keys 3.weight, 3.bias
Their checkpoints (`make_checkpoint`) hold these under the prefix `sphere_mapper.` next to
`prototypes.*` and `sphere.weight`, which we ignore. Their head reads DINOv2's *pre-norm*
patch tokens (`forward_features(x)["x_prenorm"][:, 1:]`), so `DinoV2.forward` returns both.
"""

from __future__ import annotations

import json
import math
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gsa.errors import GSAError


class WeightsError(GSAError, ValueError):
    """A weight file or folder named by a setting is missing or unreadable."""


# ------------------------------------------------------------------ backbone
@dataclass(frozen=True)
class VitConfig:
    embed_dim: int = 768
    depth: int = 12
    num_heads: int = 12
    patch_size: int = 14
    mlp_ratio: float = 4.0
    num_register_tokens: int = 0
    pos_grid: int = 37  # the published checkpoints carry 37x37 position embeddings (518 px)
    layer_norm_eps: float = 1e-6
    layerscale: bool = True


class _Attention(nn.Module):
    def __init__(self, dim: int, heads: int, qkv_bias: bool):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, key_mask: torch.Tensor | None = None) -> torch.Tensor:
        b, n, c = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        x = F.scaled_dot_product_attention(q, k, v, attn_mask=key_mask)
        return self.proj(x.transpose(1, 2).reshape(b, n, c))


class _Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class _LayerScale(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Block(nn.Module):
    """Pre-norm transformer block; `layerscale` False gives the timm/DINO-v1 block of the head."""

    def __init__(
        self,
        dim: int,
        heads: int,
        mlp_ratio: float = 4.0,
        qkv_bias: bool = True,
        eps: float = 1e-6,
        layerscale: bool = True,
    ):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=eps)
        self.attn = _Attention(dim, heads, qkv_bias)
        self.norm2 = nn.LayerNorm(dim, eps=eps)
        self.mlp = _Mlp(dim, int(dim * mlp_ratio))
        self.ls1 = _LayerScale(dim) if layerscale else nn.Identity()
        self.ls2 = _LayerScale(dim) if layerscale else nn.Identity()

    def forward(self, x: torch.Tensor, key_mask: torch.Tensor | None = None) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), key_mask))
        return x + self.ls2(self.mlp(self.norm2(x)))


class _PatchEmbed(nn.Module):
    def __init__(self, patch: int, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, patch, patch)


class DinoV2(nn.Module):
    """DINOv2 ViT with torch.hub parameter names. forward(images (B,3,H,W), ImageNet-normalised,
    H and W multiples of the patch size) -> (prenorm (B,h,w,D), normed (B,h,w,D)) patch tokens."""

    def __init__(self, cfg: VitConfig = VitConfig()):
        super().__init__()
        self.cfg = cfg
        d = cfg.embed_dim
        self.patch_embed = _PatchEmbed(cfg.patch_size, d)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + cfg.pos_grid**2, d))
        self.mask_token = nn.Parameter(torch.zeros(1, d))  # unused at inference; kept so hub dicts load strictly
        self.register_tokens = (
            nn.Parameter(torch.zeros(1, cfg.num_register_tokens, d)) if cfg.num_register_tokens else None
        )
        self.blocks = nn.ModuleList(
            Block(d, cfg.num_heads, cfg.mlp_ratio, True, cfg.layer_norm_eps, cfg.layerscale) for _ in range(cfg.depth)
        )
        self.norm = nn.LayerNorm(d, eps=cfg.layer_norm_eps)

    @property
    def patch_size(self) -> int:
        return self.cfg.patch_size

    def _pos(self, h: int, w: int) -> torch.Tensor:
        pos = self.pos_embed
        g = self.cfg.pos_grid
        if h == g and w == g:
            return pos  # the 518x518 case GSA uses: exact, no interpolation
        # Other sizes: bicubic resize of the patch grid (as both reference implementations do,
        # up to their small offset conventions).
        grid = pos[:, 1:].reshape(1, g, g, -1).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, size=(h, w), mode="bicubic", align_corners=False)
        return torch.cat([pos[:, :1], grid.permute(0, 2, 3, 1).reshape(1, h * w, -1)], 1)

    def forward(
        self, images: torch.Tensor, keep: torch.Tensor | None = None, layers: tuple[int, ...] = ()
    ) -> tuple[torch.Tensor, ...]:
        """keep: optional (B, h, w) bool, the patches to compute; the others are left out of
        the transformer altogether (they come back as zero tokens). Patches of empty background
        around a rendered object cost as much as the object's: leaving them out of a grey
        render on white changed the object's tokens by a cosine of ~0.994 (docs/benchmarks.md,
        "The backbone on the object's patches alone").
        layers: indices of blocks whose (un-normed) output patch tokens are returned after the
        two, each (B,h,w,D)."""
        b, _, hh, ww = images.shape
        p = self.cfg.patch_size
        if hh % p or ww % p:
            raise ValueError(f"image size {hh}x{ww} is not a multiple of the patch size {p}")
        h, w = hh // p, ww // p
        pos = self._pos(h, w)
        x = self.patch_embed.proj(images).flatten(2).transpose(1, 2) + pos[:, 1:]
        cls = self.cls_token + pos[:, :1]
        key_mask = order = None
        if keep is not None:
            keep = keep.reshape(b, h * w).bool()
            count = int(keep.sum(1).max())
            # kept patches first (stable: in image order), padded to the batch's largest count
            order = torch.argsort((~keep).to(torch.int8), dim=1, stable=True)[:, :count]
            x = torch.gather(x, 1, order[..., None].expand(-1, -1, x.shape[-1]))
            valid = torch.gather(keep, 1, order)
            key_mask = torch.cat([torch.ones(b, 1 + self.cfg.num_register_tokens, dtype=torch.bool), valid], 1)
            key_mask = key_mask[:, None, None, :]
        x = torch.cat([cls.expand(b, -1, -1), x], 1)
        if self.register_tokens is not None:
            x = torch.cat([x[:, :1], self.register_tokens.expand(b, -1, -1), x[:, 1:]], 1)
        skip = 1 + self.cfg.num_register_tokens
        taken = []
        for i, blk in enumerate(self.blocks):
            x = blk(x, key_mask)
            if i in layers:
                taken.append(x[:, skip:])
        out = [x[:, skip:], self.norm(x)[:, skip:], *taken]
        if order is not None:
            out = [_scattered(t, order, valid, h * w) for t in out]
        return tuple(t.reshape(b, h, w, -1) for t in out)


def _scattered(tokens: torch.Tensor, order: torch.Tensor, valid: torch.Tensor, n: int) -> torch.Tensor:
    """(B, K, D) tokens of the patches `order` names (`valid` of them real) -> (B, n, D), zeros elsewhere."""
    out = torch.zeros(tokens.shape[0], n, tokens.shape[-1], dtype=tokens.dtype)
    return out.scatter(1, order[..., None].expand(-1, -1, tokens.shape[-1]), tokens * valid[..., None])


def sphere_mapper_head(embed_dim: int = 768, hidden: int | None = None, heads: int | None = None) -> nn.Sequential:
    """The authors' head (see module docstring); hidden = embed_dim // 2, heads = hidden // 64 by default."""
    hidden = hidden or embed_dim // 2
    heads = heads or max(1, hidden // 64)
    return nn.Sequential(
        nn.Linear(embed_dim, hidden),
        nn.GELU(),
        Block(hidden, heads, 4.0, qkv_bias=False, eps=1e-5, layerscale=False),
        nn.Linear(hidden, 3),
    )


# ----------------------------------------------------------------- file reading
_ST_DTYPES = {
    "F32": torch.float32,
    "F16": torch.float16,
    "BF16": torch.bfloat16,
    "F64": torch.float64,
    "I64": torch.int64,
    "I32": torch.int32,
}


def read_safetensors(path: str | Path) -> dict[str, torch.Tensor]:
    """Minimal reader for the .safetensors layout (u64 header length, JSON header, raw
    little-endian data), so loading a HF folder needs no extra package."""
    path = Path(path)
    raw = path.read_bytes()
    (n,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8 : 8 + n])
    base = 8 + n
    out = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        dtype = _ST_DTYPES.get(info["dtype"])
        if dtype is None:
            raise WeightsError(f"{path}: tensor {name} has unsupported dtype {info['dtype']}")
        start, end = info["data_offsets"]
        buf = bytearray(raw[base + start : base + end])
        t = torch.frombuffer(buf, dtype=dtype) if buf else torch.empty(0, dtype=dtype)
        out[name] = t.reshape(info["shape"]).clone()
    return out


def _torch_load(path: Path, setting: str) -> dict:
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt file, pickle with code objects, ...
        raise WeightsError(f"{setting}: cannot read {path}: {exc}") from exc
    for key in ("state_dict", "model", "teacher"):
        if isinstance(obj, dict) and key in obj and isinstance(obj[key], dict):
            obj = obj[key]
    if not isinstance(obj, dict):
        raise WeightsError(f"{setting}: {path} does not hold a state dict")
    return obj


def _require(path, setting: str) -> Path:
    if path is None or str(path) == "":
        raise WeightsError(f"{setting} is not set: give the local path of the weights (nothing is downloaded)")
    p = Path(path).expanduser()
    if not p.exists():
        raise WeightsError(
            f"{setting}: {p} does not exist (weights are never downloaded; put the file there or point {setting} at it)"
        )
    return p


# ----------------------------------------------------------------- backbone loading
def _config_from_hub(sd: dict) -> VitConfig:
    d = sd["cls_token"].shape[-1]
    depth = 1 + max(int(k.split(".")[1]) for k in sd if k.startswith("blocks."))
    patch = sd["patch_embed.proj.weight"].shape[-1]
    grid = round(math.sqrt(sd["pos_embed"].shape[1] - 1))
    regs = sd["register_tokens"].shape[1] if "register_tokens" in sd else 0
    hidden = sd["blocks.0.mlp.fc1.weight"].shape[0]
    # All published DINOv2 models use 64-d heads.
    return VitConfig(
        embed_dim=d,
        depth=depth,
        num_heads=max(1, d // 64),
        patch_size=patch,
        mlp_ratio=hidden / d,
        num_register_tokens=regs,
        pos_grid=grid,
        layerscale="blocks.0.ls1.gamma" in sd,
    )


def hf_to_hub(sd: dict) -> dict:
    """Rename a HF `Dinov2Model` state dict to torch.hub names (q,k,v -> qkv)."""
    sd = {k.removeprefix("dinov2."): v for k, v in sd.items()}
    out = {
        "cls_token": sd["embeddings.cls_token"],
        "pos_embed": sd["embeddings.position_embeddings"],
        "patch_embed.proj.weight": sd["embeddings.patch_embeddings.projection.weight"],
        "patch_embed.proj.bias": sd["embeddings.patch_embeddings.projection.bias"],
        "norm.weight": sd["layernorm.weight"],
        "norm.bias": sd["layernorm.bias"],
    }
    if "embeddings.mask_token" in sd:
        out["mask_token"] = sd["embeddings.mask_token"].reshape(1, -1)
    if "embeddings.register_tokens" in sd:
        out["register_tokens"] = sd["embeddings.register_tokens"]
    layers = sorted({int(k.split(".")[2]) for k in sd if k.startswith("encoder.layer.")})
    for i in layers:
        s, t = f"encoder.layer.{i}.", f"blocks.{i}."
        if s + "mlp.fc1.weight" not in sd:
            raise WeightsError("SwiGLU DINOv2 variants (giant) are not supported")
        # Published checkpoints name q,k,v `attention.attention.{query,key,value}` and the output
        # `attention.output.dense`; transformers >= 5 modules name them `attention.{q,k,v,o}_proj`.
        legacy = s + "attention.attention.query.weight" in sd
        qkv = [
            s + (f"attention.attention.{n}" if legacy else f"attention.{n[0]}_proj") for n in ("query", "key", "value")
        ]
        o = s + ("attention.output.dense" if legacy else "attention.o_proj")
        for part in ("weight", "bias"):
            out[t + f"attn.qkv.{part}"] = torch.cat([sd[f"{n}.{part}"] for n in qkv])
            out[t + f"attn.proj.{part}"] = sd[f"{o}.{part}"]
            for a, b in (("norm1", "norm1"), ("norm2", "norm2"), ("mlp.fc1", "mlp.fc1"), ("mlp.fc2", "mlp.fc2")):
                out[t + f"{b}.{part}"] = sd[s + f"{a}.{part}"]
        if s + "layer_scale1.lambda1" in sd:
            out[t + "ls1.gamma"] = sd[s + "layer_scale1.lambda1"]
            out[t + "ls2.gamma"] = sd[s + "layer_scale2.lambda1"]
    return out


def _unchunk(sd: dict) -> dict:
    """Hub models built with block_chunks > 0 name blocks `blocks.{chunk}.{i}.`: flatten them."""
    if not any(re.match(r"blocks\.\d+\.\d+\.", k) for k in sd):
        return sd
    return {re.sub(r"^blocks\.\d+\.(\d+)\.", r"blocks.\1.", k): v for k, v in sd.items()}


def load_backbone(path, setting: str = "backbone") -> DinoV2:
    """A frozen DinoV2 from a HF folder (config.json + model.safetensors | pytorch_model.bin),
    a torch.hub-format state dict file (.pth/.pt) or an ONNX export of a HF Dinov2Model
    (.onnx, gsa.features.onnx_dinov2)."""
    p = _require(path, setting)
    eps, heads = 1e-6, None
    if p.suffix.lower() == ".onnx":
        from gsa.features.onnx_dinov2 import hf_state_dict_from_onnx

        try:
            sd = hf_to_hub(hf_state_dict_from_onnx(p))
        except KeyError as exc:
            raise WeightsError(f"{setting}: {p} is not a Dinov2Model export (missing {exc})") from exc
    elif p.is_dir():
        files = [p / "model.safetensors", p / "pytorch_model.bin"]
        found = next((f for f in files if f.exists()), None)
        if found is None:
            raise WeightsError(
                f"{setting}: {p} is a folder but holds neither model.safetensors "
                "nor pytorch_model.bin (expected a Hugging Face Dinov2 folder)"
            )
        sd = read_safetensors(found) if found.suffix == ".safetensors" else _torch_load(found, setting)
        if (p / "config.json").exists():
            conf = json.loads((p / "config.json").read_text())
            eps = float(conf.get("layer_norm_eps", eps))
            heads = conf.get("num_attention_heads")
        try:
            sd = hf_to_hub(sd)
        except KeyError as exc:
            raise WeightsError(f"{setting}: {found} is not a Dinov2Model state dict (missing {exc})") from exc
    else:
        sd = _unchunk(_torch_load(p, setting))
    if "cls_token" not in sd or "patch_embed.proj.weight" not in sd:
        raise WeightsError(f"{setting}: {p} is not a DINOv2 state dict (no cls_token / patch_embed)")
    cfg = _config_from_hub(sd)
    cfg = VitConfig(**{**cfg.__dict__, "layer_norm_eps": eps, "num_heads": int(heads or cfg.num_heads)})
    model = DinoV2(cfg)
    sd = dict(sd)
    sd.setdefault("mask_token", torch.zeros(1, cfg.embed_dim))
    missing, unexpected = model.load_state_dict(sd, strict=False)
    if missing or unexpected:
        raise WeightsError(
            f"{setting}: {p} does not match a DINOv2 ViT: missing {missing[:5]}, unexpected {unexpected[:5]}"
        )
    return model.eval().requires_grad_(False)


def load_sphere_head(path, embed_dim: int | None = None, setting: str = "head") -> nn.Sequential:
    """The sphere-mapper head from the authors' checkpoint (keys `sphere_mapper.{0,2,3}.*`,
    other entries ignored) or a bare head state dict (keys `0.*, 2.*, 3.*`). Sizes come from
    the tensors; `embed_dim` (the backbone's width), when given, is checked against them."""
    p = _require(path, setting)
    if p.is_dir():
        raise WeightsError(f"{setting}: {p} is a folder; expected the head checkpoint file")
    sd = _torch_load(p, setting)
    if any(k.startswith("sphere_mapper.") for k in sd):
        sd = {k[len("sphere_mapper.") :]: v for k, v in sd.items() if k.startswith("sphere_mapper.")}
    if "0.weight" not in sd or "3.weight" not in sd:
        raise WeightsError(
            f"{setting}: {p} holds no sphere_mapper weights (expected keys "
            "sphere_mapper.0.weight ... sphere_mapper.3.bias)"
        )
    hidden, d = sd["0.weight"].shape
    if embed_dim is not None and d != embed_dim:
        raise WeightsError(f"{setting}: head expects {d}-d tokens but the backbone gives {embed_dim}")
    head = sphere_mapper_head(d, hidden)
    try:
        head.load_state_dict(sd, strict=True)
    except RuntimeError as exc:
        raise WeightsError(f"{setting}: {p} does not match the sphere_mapper layout: {exc}") from exc
    return head.eval().requires_grad_(False)


IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


def to_input(images: np.ndarray, size: int) -> torch.Tensor:
    """(B,H,W,3) float [0,1] -> (B,3,size,size) ImageNet-normalised tensor (bilinear resize)."""
    x = torch.as_tensor(np.ascontiguousarray(images, np.float32)).permute(0, 3, 1, 2)
    x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
    mean = torch.as_tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.as_tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (x - mean) / std
