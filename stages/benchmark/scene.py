"""Benchmark scene: a room of Gaussians seen from a pinhole camera inside it."""

from __future__ import annotations

import math

import torch

from models.gaussians import Gaussians, room_gaussians


def pinhole_rays(res: int, fov_deg: float = 70.0, origin=(0.1, -0.05, 0.2),
                 look=(0.3, 0.1, -1.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """res x res unit rays of a pinhole camera. Returns origins, dirs: [res*res, 3]."""
    f = 1.0 / math.tan(math.radians(fov_deg) / 2)
    fwd = torch.nn.functional.normalize(torch.tensor(look, dtype=torch.float32), dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor([0.0, 1.0, 0.0])), dim=0)
    up = torch.linalg.cross(right, fwd)
    u = (torch.arange(res, dtype=torch.float32) + 0.5) / res * 2 - 1
    y, x = torch.meshgrid(-u, u, indexing="ij")
    d = x.reshape(-1, 1) * right + y.reshape(-1, 1) * up + f * fwd
    dirs = torch.nn.functional.normalize(d, dim=1)
    return torch.tensor(origin, dtype=torch.float32).expand_as(dirs).contiguous(), dirs


def benchmark_scene(n: int, seed: int = 0) -> Gaussians:
    """n Gaussians on the walls of [-1, 1]^3 plus floating blobs (see room_gaussians)."""
    return room_gaussians(n, torch.Generator().manual_seed(seed))
