"""Colour spaces for comparing 3DGS base colours (SH DC): sRGB, linear RGB, CIELAB.

Linear RGB is where exposure and white balance act (a gain per channel); CIELAB is
where distances approximate perceived differences. A leaf: numpy only.
"""

from __future__ import annotations

import numpy as np

# sRGB (D65) primaries -> CIE XYZ, and the D65 white point.
_RGB_TO_XYZ = np.array(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
)
_WHITE = np.array([0.95047, 1.0, 1.08883])


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) sRGB in [0, 1] (clipped) -> linear RGB."""
    c = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(lin: np.ndarray) -> np.ndarray:
    """(..., 3) linear RGB -> sRGB in [0, 1] (clipped: a gain can push colours past white)."""
    c = np.clip(np.asarray(lin, np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def linear_to_lab(lin: np.ndarray) -> np.ndarray:
    """(N, 3) linear RGB (values above 1 allowed) -> CIELAB (D65)."""
    xyz = np.asarray(lin, np.float64) @ _RGB_TO_XYZ.T / _WHITE
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack([116 * f[:, 1] - 16, 500 * (f[:, 0] - f[:, 1]), 200 * (f[:, 1] - f[:, 2])], axis=1)


def srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) sRGB in [0, 1] -> CIELAB (D65)."""
    return linear_to_lab(srgb_to_linear(rgb))
