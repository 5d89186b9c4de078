"""Scoring: image metrics (``image.py``), HDR peak / tonemap / saturation (``hdr.py``), renders against a capture's test split (``scoring.py``), edits
against their ground truth (``edits.py``), speed / quality Pareto fronts (``pareto.py``)."""

from .edits import (CHANGED_FILTER, CHANGED_THRESHOLD, changed_region_gains, changed_region_metrics,
                    changed_region_pooled_gain, evaluate_edit)
from .image import SSIM_DEFINITION, mse_to_psnr, psnr, ssim
from .pareto import pareto_front, recommend
from .scoring import DEFINITIONS, evaluate_renders, ground_truth, region_mask, score_layer

__all__ = ["CHANGED_FILTER", "CHANGED_THRESHOLD", "DEFINITIONS", "SSIM_DEFINITION", "changed_region_gains", "changed_region_pooled_gain",
           "changed_region_metrics", "evaluate_edit", "evaluate_renders", "ground_truth", "mse_to_psnr", "pareto_front", "psnr", "recommend",
           "region_mask", "score_layer", "ssim"]
