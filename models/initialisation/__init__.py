"""Gaussian initialisation: dense from the training views' depth + diffuse buffers (``dense.py``), or from the
capture's SfM points when it has no depth (``sfm.py``)."""

from .dense import InitConfig, dense_init, gaussians_from_points, unproject_views
from .sfm import has_depth, initialise, sfm_init

__all__ = ["InitConfig", "dense_init", "gaussians_from_points", "has_depth", "initialise", "sfm_init",
           "unproject_views"]
