"""Gaussian scene representation: raw parameters, activations, PLY IO."""

from models.gaussians.activations import (
    normalize_quats,
    opacities_from_logits,
    quats_to_rotmats,
    roughness_to_ggx_alpha,
    scales_from_log,
    world_to_local,
)
from models.gaussians.ply import SH_C0, read_ply, write_ply
from models.gaussians.scene import PARAM_SHAPES, Gaussians
from models.gaussians.synthetic import random_gaussians, room_gaussians

__all__ = [
    "Gaussians", "PARAM_SHAPES", "SH_C0", "read_ply", "write_ply",
    "normalize_quats", "quats_to_rotmats", "scales_from_log", "opacities_from_logits",
    "world_to_local", "roughness_to_ggx_alpha", "random_gaussians", "room_gaussians",
]
