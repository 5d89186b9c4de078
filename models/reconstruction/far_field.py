"""Far-field Gaussians: a coarse shell that reflections can hit beyond the captured geometry.

Reference recipe: M points, positions N(0, 1) clamped to +-3, times 4 x camera
extent; points near the cameras removed (here: inside the sphere of radius
``extent`` around the cameras' centre, where the captured scene lives); scale =
0.1 x nearest-neighbour distance, opacity 0.1, diffuse 0.2, normal 0, F0 0.04,
roughness 0.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from models.gaussians import Gaussians


def far_field_gaussians(count: int, centre: np.ndarray, extent: float, seed: int, dtype=torch.float32) -> Gaussians:
    rng = np.random.default_rng(seed)
    pos = np.clip(rng.normal(size=(count, 3)), -3, 3) * 4 * extent
    pos = pos[np.linalg.norm(pos, axis=1) > extent] + centre
    dist, _ = cKDTree(pos).query(pos, k=2)
    scale = np.maximum(0.1 * dist[:, 1], 1e-6)
    n = len(pos)
    t = dict(dtype=dtype)
    return Gaussians(
        means=torch.tensor(pos, **t),
        quats=torch.tensor([[1.0, 0, 0, 0]], **t).repeat(n, 1),
        log_scales=torch.tensor(np.log(scale), **t)[:, None].repeat(1, 3),
        opacity_logits=torch.full((n,), float(np.log(0.1 / 0.9)), **t),
        diffuse=torch.full((n, 3), 0.2, **t),
        normals=torch.zeros((n, 3), **t),
        roughness=torch.zeros((n,), **t),
        f0=torch.full((n, 3), 0.04, **t),
    )
