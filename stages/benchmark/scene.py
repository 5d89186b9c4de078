"""Benchmark scenes, generated in memory: the room of the original benchmark and the scene TYPES a ray's cost
depends on (how much lies behind what it blends)."""

from __future__ import annotations

import math

import torch

from models.gaussians import Gaussians, random_gaussians, room_gaussians


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


# name -> (what it is, full-size Gaussian count)
SCENE_TYPES = {
    "room": ("(a) walls + blobs seen from inside (the original benchmark scene)", 50_000),
    "deep": ("(b) random Gaussians filling the camera's frustum: each ray accepts ~150, blends ~12", 50_000),
    "dense_room": ("(c) a closed room at dense-initialisation opacity (~0.1), seen from inside", 80_000),
    "million": ("(d) 1M random Gaussians in the frustum: thousands accepted per ray", 1_000_000),
}


def scene_type(name: str, res: int, n: int | None = None, seed: int = 0):
    """(Gaussians, origins, dirs) of a scene type at ``res`` x ``res`` rays (``n`` Gaussians, default its
    full size)."""
    if name not in SCENE_TYPES:
        raise ValueError(f"unknown scene type {name!r}; known: {', '.join(SCENE_TYPES)}")
    n = n or SCENE_TYPES[name][1]
    g = torch.Generator().manual_seed(seed)
    if name == "room":
        return (benchmark_scene(n, seed), *pinhole_rays(res))
    if name == "dense_room":
        return (room_gaussians(n, g, opacity_logit_mean=-2.2), *pinhole_rays(res, origin=(0.0, 0.2, 0.3),
                                                                          look=(0.2, -0.3, -1.0)))
    # deep / million: a camera outside the cube [-1, 1]^3 looking into it; scale keeps ~the same look
    scale = 0.03 * (50_000 / n) ** (1 / 3) if name == "deep" else 0.04
    gs = random_gaussians(n, g, extent=1.0, scale=scale)
    return (gs, *pinhole_rays(res, fov_deg=40.0, origin=(0.0, 0.0, -1.6), look=(0.0, 0.0, 1.0)))
