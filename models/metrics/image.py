"""Image metrics: PSNR and SSIM (the one implementation of each; linear and tonemapped scores both use them).

SSIM is the definition 3D Gaussian Splatting's ``utils/loss_utils.ssim`` computes and every radiance-field paper
reports: an 11x11 Gaussian window (sigma 1.5, normalised), K1 = 0.01, K2 = 0.03 (C1 = (K1 L)^2, C2 = (K2 L)^2 for a
data range L), the SSIM map averaged over pixels and channels. ``padding="same"`` is 3DGS exactly (``conv2d`` with
``padding = 11 // 2``, zeros outside the image); ``padding="valid"`` keeps only the pixels whose window lies inside
the image, as pytorch-msssim's ``ssim`` (both tested against those references in tests/test_metrics_image.py).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import correlate1d

MSE_FLOOR = 1e-20  # an exact match scores 10 log10(peak^2 / 1e-20) = 200 dB (peak 1)
SSIM_WINDOW = 11  # window side, pixels
SSIM_SIGMA = 1.5  # window Gaussian's standard deviation, pixels
SSIM_K = (0.01, 0.03)  # C1 = (K1 L)^2, C2 = (K2 L)^2
SSIM_DEFINITION = ("3DGS ssim: 11x11 Gaussian window (sigma 1.5), zero padding 11 // 2 ('same'), "
                   "C1 = (0.01 L)^2, C2 = (0.03 L)^2, map averaged over pixels and channels")


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def mse_to_psnr(mse: float, peak: float = 1.0) -> float:
    """10 log10(peak^2 / mse), with mse floored at MSE_FLOOR."""
    return float(10 * np.log10(peak**2 / max(float(mse), MSE_FLOOR)))


def psnr(pred, target, mask=None, peak: float = 1.0) -> float:
    """PSNR of ``pred`` against ``target`` (numpy arrays or torch tensors) over the pixels of ``mask`` [H, W]
    (all if None): 10 log10(peak^2 / MSE), the squared error averaged in float64. No clamping: pass the
    ``peak`` of the data (``models.metrics.hdr.peak`` for radiance)."""
    err = (_np(pred).astype(np.float64) - _np(target).astype(np.float64)) ** 2
    if mask is not None:
        err = err[_np(mask)]
    return mse_to_psnr(float(err.mean()) if err.size else 0.0, peak)


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """[size] float64, sums to 1: exp(-(x - size // 2)^2 / (2 sigma^2)) for x = 0 .. size - 1, normalised."""
    x = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _blur(x: np.ndarray, window: np.ndarray) -> np.ndarray:
    """Separable correlation of [H, W] with ``window`` along both axes, zeros outside (3DGS's conv2d padding)."""
    x = correlate1d(x, window, axis=0, mode="constant", cval=0.0)
    return correlate1d(x, window, axis=1, mode="constant", cval=0.0)


def ssim_map(pred, target, data_range: float = 1.0, window: int = SSIM_WINDOW,
             sigma: float = SSIM_SIGMA) -> np.ndarray:
    """[H, W, C] float64 SSIM map (3DGS definition, zero 'same' padding) of [H, W, C] images; ``data_range`` = L."""
    pred, target = _np(pred).astype(np.float64), _np(target).astype(np.float64)
    if pred.shape != target.shape:
        raise ValueError(f"ssim: shapes differ, {pred.shape} vs {target.shape}")
    if pred.ndim == 2:
        pred, target = pred[..., None], target[..., None]
    c1, c2 = (SSIM_K[0] * data_range) ** 2, (SSIM_K[1] * data_range) ** 2
    w = gaussian_window(window, sigma)
    out = np.empty(pred.shape, dtype=np.float64)
    for c in range(pred.shape[-1]):
        x, y = pred[..., c], target[..., c]
        mx, my = _blur(x, w), _blur(y, w)
        sxx = _blur(x * x, w) - mx * mx
        syy = _blur(y * y, w) - my * my
        sxy = _blur(x * y, w) - mx * my
        out[..., c] = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return out


def ssim(pred, target, peak: float = 1.0, padding: str = "same", window: int = SSIM_WINDOW,
         sigma: float = SSIM_SIGMA) -> float:
    """Mean SSIM of [H, W, C] (or [H, W]) images with data range L = ``peak`` (see the module docstring):
    ``padding="same"`` is 3DGS's ``ssim``, ``"valid"`` pytorch-msssim's (pixels whose window is inside)."""
    if padding not in ("same", "valid"):
        raise ValueError(f"ssim padding must be 'same' or 'valid', got {padding!r}")
    s = ssim_map(pred, target, peak, window, sigma)
    if padding == "valid":
        r = window // 2
        if s.shape[0] <= 2 * r or s.shape[1] <= 2 * r:
            raise ValueError(f"ssim padding 'valid': image {s.shape[:2]} smaller than the {window}x{window} window")
        s = s[r:-r, r:-r]
    return float(s.mean())
