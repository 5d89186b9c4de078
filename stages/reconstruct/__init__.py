"""``reconstruct`` stage: optimise one Gaussian scene with path-traced reflections."""

from .config import ReconstructConfig
from .trainer import Trainer, train

__all__ = ["ReconstructConfig", "Trainer", "train"]
