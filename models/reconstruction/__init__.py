"""Reconstruction of ONE Gaussian scene with path-traced reflections (paper Eq. 4-7).

``config.py`` the settings, ``data.py`` training rays and targets, ``trainer.py`` the optimisation (warm-up,
reflections, pruning, checkpoints), ``far_field.py`` the far-field shell, ``reflection_fill.py`` /
``mirror_stereo.py`` Gaussians for what the cameras see only in mirrors.
"""

from .config import LearningRates, LossWeights, ReconstructConfig
from .trainer import Trainer, train

__all__ = ["LearningRates", "LossWeights", "ReconstructConfig", "Trainer", "train"]
