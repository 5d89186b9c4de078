"""``evaluate`` stage: per-layer PSNR / SSIM of renders against the capture's test split."""

from .evaluate import evaluate_renders
from .metrics import psnr, ssim

__all__ = ["evaluate_renders", "psnr", "ssim"]
