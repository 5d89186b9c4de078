"""``init`` stage: dense Gaussian initialisation from the training views' depth + diffuse buffers."""

from .dense import InitConfig, dense_init, unproject_views

__all__ = ["InitConfig", "dense_init", "unproject_views"]
