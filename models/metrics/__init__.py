"""Scoring: image metrics (``image.py``), renders against a capture's test split (``scoring.py``), edits
against their ground truth (``edits.py``), speed / quality Pareto fronts (``pareto.py``)."""

from .edits import CHANGED_FILTER, CHANGED_THRESHOLD, changed_region_metrics, evaluate_edit
from .image import mse_to_psnr, psnr, ssim
from .pareto import pareto_front, recommend
from .scoring import evaluate_renders, region_mask

__all__ = ["CHANGED_FILTER", "CHANGED_THRESHOLD", "changed_region_metrics", "evaluate_edit", "evaluate_renders",
           "mse_to_psnr", "pareto_front", "psnr", "recommend", "region_mask", "ssim"]
