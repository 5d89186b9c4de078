"""Random but plausible Gaussian scenes for tests and benchmarks."""

from __future__ import annotations

import math

import torch

from models.gaussians.scene import Gaussians


def random_gaussians(n: int, generator: torch.Generator, extent: float = 1.0, scale: float = 0.1,
                     dtype=torch.float32) -> Gaussians:
    """n Gaussians uniformly in a cube [-extent, extent]^3, anisotropic scales around `scale`."""
    g = generator
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * extent
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    log_scales = math.log(scale) + 0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    return _with_features(n, g, means, quats, log_scales, dtype)


def room_gaussians(n: int, generator: torch.Generator, half_size: float = 1.0,
                   opacity_logit_mean: float = -1.0, dtype=torch.float32) -> Gaussians:
    """n flat Gaussians on the six inner faces of a cube [-half_size, half_size]^3 (a room),
    plus a quarter of them in a few floating blobs, sized so that a ray from inside crosses
    tens of Gaussians before the wall becomes opaque. Opacity logits ~ N(opacity_logit_mean, 1)."""
    g = generator
    n_wall = n - n // 4
    face = torch.randint(0, 6, (n_wall,), generator=g)
    axis, sign = face // 2, (face % 2) * 2 - 1
    uv = (torch.rand(n_wall, 3, generator=g, dtype=torch.float64) * 2 - 1) * half_size
    means_wall = uv.clone()
    means_wall[torch.arange(n_wall), axis] = sign.double() * half_size
    means_wall += 0.02 * half_size * torch.randn(n_wall, 3, generator=g, dtype=torch.float64)
    # spacing on the walls ~ sqrt(area / n); size ~ 1.5 spacing in-plane, thin across the wall
    spacing = math.sqrt(24 * half_size**2 / max(n_wall, 1))
    ls_wall = torch.full((n_wall, 3), math.log(1.5 * spacing), dtype=torch.float64)
    ls_wall[torch.arange(n_wall), axis] = math.log(0.2 * spacing)
    ls_wall += 0.2 * torch.randn(n_wall, 3, generator=g, dtype=torch.float64)
    # small in-plane jitter of the orientation around identity
    q_wall = torch.cat([torch.ones(n_wall, 1, dtype=torch.float64),
                        0.1 * torch.randn(n_wall, 3, generator=g, dtype=torch.float64)], dim=1)
    n_blob = n - n_wall
    centers = (torch.rand(4, 3, generator=g, dtype=torch.float64) * 1.2 - 0.6) * half_size
    which = torch.randint(0, 4, (n_blob,), generator=g)
    means_blob = centers[which] + 0.15 * half_size * torch.randn(n_blob, 3, generator=g, dtype=torch.float64)
    ls_blob = math.log(0.6 * spacing) + 0.3 * torch.randn(n_blob, 3, generator=g, dtype=torch.float64)
    q_blob = torch.randn(n_blob, 4, generator=g, dtype=torch.float64)
    out = _with_features(n, g, torch.cat([means_wall, means_blob]), torch.cat([q_wall, q_blob]),
                         torch.cat([ls_wall, ls_blob]), dtype)
    # semi-transparent, as after dense initialisation (opacity ~0.1-0.5): tens of blended hits
    out.opacity_logits = (opacity_logit_mean + torch.randn(n, generator=g, dtype=torch.float64)).to(dtype)
    return out


def _with_features(n, g, means, quats, log_scales, dtype) -> Gaussians:
    f64 = torch.float64
    return Gaussians(
        means=means.to(dtype),
        quats=quats.to(dtype),
        log_scales=log_scales.to(dtype),
        opacity_logits=(torch.randn(n, generator=g, dtype=f64) * 1.5).to(dtype),
        diffuse=torch.rand(n, 3, generator=g, dtype=f64).to(dtype),
        normals=torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=f64), dim=1).to(dtype),
        roughness=torch.rand(n, generator=g, dtype=f64).to(dtype),
        f0=(0.04 + 0.9 * torch.rand(n, 3, generator=g, dtype=f64)).to(dtype),
    )
