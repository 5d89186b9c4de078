"""Image metrics: PSNR and SSIM (the one implementation of each; linear and tonemapped scores both use them)."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

MSE_FLOOR = 1e-20  # an exact match scores 10 log10(peak^2 / 1e-20) = 200 dB (peak 1)


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def mse_to_psnr(mse: float, peak: float = 1.0) -> float:
    """10 log10(peak^2 / mse), with mse floored at MSE_FLOOR."""
    return float(10 * np.log10(peak**2 / max(float(mse), MSE_FLOOR)))


def psnr(pred, target, mask=None, peak: float = 1.0) -> float:
    """PSNR of ``pred`` against ``target`` (numpy arrays or torch tensors) over the pixels of ``mask`` [H, W]
    (all if None): 10 log10(peak^2 / MSE), the squared error averaged in float64."""
    err = (_np(pred).astype(np.float64) - _np(target).astype(np.float64)) ** 2
    if mask is not None:
        err = err[_np(mask)]
    return mse_to_psnr(float(err.mean()) if err.size else 0.0, peak)


def ssim(pred: np.ndarray, target: np.ndarray, peak: float = 1.0, sigma: float = 1.5) -> float:
    """Mean SSIM (Wang et al. 2004; Gaussian window sigma 1.5, K1 0.01, K2 0.03), channels averaged."""
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    values = []
    for c in range(pred.shape[-1]):
        x = pred[..., c].astype(np.float64)
        y = target[..., c].astype(np.float64)
        mx, my = gaussian_filter(x, sigma), gaussian_filter(y, sigma)
        sxx = gaussian_filter(x * x, sigma) - mx * mx
        syy = gaussian_filter(y * y, sigma) - my * my
        sxy = gaussian_filter(x * y, sigma) - mx * my
        s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
        values.append(s.mean())
    return float(np.mean(values))
