"""The sRGB transfer pair (IEC 61966-2-1), the one place the curve is written.

Captures, Gaussians and renders are linear radiance. 8-bit images (photos, PNG outputs, SfM point colours, the
viewer's colour pickers) are sRGB-encoded. The display tonemap of the PNGs and of the "tonemapped" metrics is
``linear_to_srgb``: clamp to [0, 1], then the sRGB curve. Decoding computes in float64; encoding keeps a float
input's precision (float32 renders tonemap in float32, as the PNGs always were), anything else in float64.
"""

from __future__ import annotations

import numpy as np


def _float(x) -> np.ndarray:
    a = np.asarray(x)
    return a if a.dtype.kind == "f" else a.astype(np.float64)


def srgb_to_linear(x) -> np.ndarray:
    """sRGB-encoded values in [0, 1] (clipped) -> linear."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x) -> np.ndarray:
    """Linear values -> sRGB-encoded in [0, 1]: clamp to [0, 1], then the sRGB curve (the display tonemap)."""
    x = np.clip(_float(x), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
