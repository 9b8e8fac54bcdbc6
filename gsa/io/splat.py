"""antimatter15 `.splat`: 32 bytes per Gaussian, no header, no SH beyond the DC colour.

Layout (little endian): position f32×3, linear scale f32×3, RGBA u8×4 (colour
0.5 + C0·f_dc and sigmoid(opacity), ×255), rotation u8×4 as w, x, y, z mapped by
q·128 + 128. Our own code: gaussforge 0.6.0 fails to read .splat (std::bad_cast) and the
format is a one-line numpy dtype.
"""

from __future__ import annotations

import numpy as np

from gsa.io.ply import ALPHA_EPS
from gsa.model import GaussianModel
from gsa.sh import rgb_to_sh_dc, sh_dc_to_rgb

SPLAT_DTYPE = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def decode_splat(buf: np.ndarray) -> GaussianModel:
    """A model from a (N,) SPLAT_DTYPE array (values not yet checked)."""
    rgba = buf["rgba"].astype(np.float32) / 255.0
    # alpha 0 and 255 (an infinite logit) are read as ALPHA_EPS and 1 − ALPHA_EPS (counted by read_model)
    alpha = np.clip(rgba[:, 3].astype(np.float64), ALPHA_EPS, 1.0 - ALPHA_EPS)
    quats = (buf["rot"].astype(np.float32) - 128.0) / 128.0
    norm = np.linalg.norm(quats, axis=1, keepdims=True)
    quats = np.where(norm > 0, quats / np.maximum(norm, 1e-12), np.array([1.0, 0, 0, 0], np.float32))
    with np.errstate(divide="ignore", invalid="ignore"):
        log_scales = np.log(buf["scale"].astype(np.float32))
    sh = rgb_to_sh_dc(rgba[:, :3])[:, None, :]
    return GaussianModel(
        means=buf["pos"],
        quats=quats,
        log_scales=log_scales,
        opacity_logits=np.log(alpha / (1.0 - alpha)),
        sh=sh,
    )


def encode_splat(model: GaussianModel) -> np.ndarray:
    """The (N,) SPLAT_DTYPE array of a model (SH bands above 0 are dropped)."""
    out = np.empty(len(model), SPLAT_DTYPE)
    out["pos"] = model.means
    out["scale"] = np.exp(model.log_scales)
    rgba = np.empty((len(model), 4), np.float64)
    rgba[:, :3] = sh_dc_to_rgb(model.sh[:, 0, :])
    rgba[:, 3] = model.opacities
    out["rgba"] = np.clip(np.rint(rgba * 255.0), 0, 255).astype(np.uint8)
    q = model.quats / np.linalg.norm(model.quats, axis=1, keepdims=True)
    out["rot"] = np.clip(np.rint(q * 128.0 + 128.0), 0, 255).astype(np.uint8)
    return out
