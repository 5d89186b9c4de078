"""The light reaching a point of a Gaussian surface, as the model itself renders it: the cosine-weighted mean of
the radiance ``trace_paths`` returns over the hemisphere of a normal (E / pi; a Lambertian of albedo a sends
a x that). Used by the albedo edit (models/editing/albedo.py) and the back-face fill
(models/reconstruction/back_fill.py).

- rays start at the Gaussian's centre moved along the normal by 3 standard deviations of the Gaussian along
  that normal (||S R^T n||: past its own kernel, and past coplanar neighbours of similar thickness), at least
  1e-4 x the diagonal of the bounds of all means (``ray_offsets``);
- directions are Latin-hypercube stratified over the cosine-weighted disk (Malley), one random
  stratification per point (``cosine_directions``).
"""

from __future__ import annotations

import math

import torch

from models.gaussians import Gaussians, quats_to_rotmats
from models.pathtrace.paths import PathConfig, TraceFn, trace_paths
from models.pathtrace.sampling import tangent_frame

BATCH_RAYS = 65536  # rays per trace_paths call


def ray_offsets(g: Gaussians, mask: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """[n] distance along the normal at which the rays of each selected Gaussian start (module doc)."""
    rot = quats_to_rotmats(g.quats.detach()[mask])  # [n, 3, 3] local -> world
    local = (rot.transpose(1, 2) @ normals[:, :, None]).squeeze(-1)  # the normal in the Gaussian's frame
    sigma = (g.log_scales.detach()[mask].exp() * local).norm(dim=1)
    means = g.means.detach()
    floor = 1e-4 * float((means.amax(0) - means.amin(0)).norm()) if len(means) else 0.0
    return (3.0 * sigma).clamp_min(floor)


def cosine_directions(normals: torch.Tensor, samples: int, generator: torch.Generator) -> torch.Tensor:
    """[n, samples, 3] unit directions about each normal [n, 3], cosine-distributed (pdf cos / pi), Latin-
    hypercube stratified per normal."""
    n = len(normals)
    strata = [torch.rand(n, samples, generator=generator, dtype=torch.float64).argsort(dim=1) for _ in range(2)]
    jitter = torch.rand(n, samples, 2, generator=generator, dtype=torch.float64)
    u1 = (strata[0] + jitter[..., 0]) / samples
    u2 = (strata[1] + jitter[..., 1]) / samples
    r, phi = u1.sqrt(), 2.0 * math.pi * u2
    local = torch.stack([r * phi.cos(), r * phi.sin(), (1.0 - u1).clamp_min(0.0).sqrt()], dim=-1)
    nrm = normals.double().cpu()[:, None, :].expand(n, samples, 3)
    t, b = tangent_frame(nrm)
    d = local[..., 0:1] * t + local[..., 1:2] * b + local[..., 2:3] * nrm
    return torch.nn.functional.normalize(d, dim=-1).to(normals)


@torch.no_grad()
def cosine_mean_radiance(trace_fn: TraceFn, scene: Gaussians, points: torch.Tensor, normals: torch.Tensor,
                         offsets: torch.Tensor, samples: int, path: PathConfig,
                         generator: torch.Generator) -> torch.Tensor:
    """[n, 3] mean of the radiance that ``scene`` renders (``trace_paths`` final) over cosine-distributed
    directions about ``normals`` [n, 3] from ``points + offsets * normals``: E / pi."""
    out = torch.zeros(len(points), 3, dtype=torch.float64)
    per_batch = max(1, BATCH_RAYS // samples)
    for start in range(0, len(points), per_batch):
        sl = slice(start, start + per_batch)
        dirs = cosine_directions(normals[sl], samples, generator)  # [b, s, 3]
        origins = (points[sl] + offsets[sl, None] * normals[sl])[:, None, :].expand_as(dirs)
        o = origins.reshape(-1, 3).to(torch.float32).contiguous()
        d = dirs.reshape(-1, 3).to(torch.float32).contiguous()
        radiance = trace_paths(trace_fn, o, d, scene, path, generator).final.detach()
        out[sl] = radiance.double().cpu().reshape(-1, samples, 3).mean(dim=1)
    return out
