"""``set_albedo``: make the selected Gaussians Lambertian of a given albedo, lit by the rest of the model.

A Gaussian stores outgoing diffuse RADIANCE, not albedo; a user knows the albedo. A Lambertian surface of albedo
``a`` under irradiance E sends L_o = (a / pi) E, and E = integral of L_i cos over the hemisphere of the normal
= pi E_cos[L_i] (the mean of L_i over cosine-distributed directions). So

    L_o = a * E_cos[L_i],    estimated per Gaussian with ``samples`` cosine-distributed rays.

L_i is the model's own radiance: what a camera ray from the Gaussian in that direction renders, i.e. the path
tracer (``models.pathtrace.paths.trace_paths``) with the model's path settings: the hit Gaussians' diffuse
radiance plus their reflected specular (one GGX sample per ray; averaging over the rays averages it too). A
metal or mirror neighbour holds almost no diffuse radiance; dropping its specular would darken the result.

Choices (tests/test_edit_albedo.py checks all but the offset):

- the selected Gaussians are left out of the traced scene: their old radiance (a metal's, or 100) must not
  light them, nor their old geometry shadow them. Exact for a convex selection (its hemispheres never meet
  itself); a concave one misses its own inter-reflection and self-shadowing.
- rays start at the Gaussian's centre moved along the normal by 3 standard deviations of the Gaussian along
  that normal (||S R^T n||: past its own kernel, and past coplanar neighbours of similar thickness), at least
  1e-4 x the diagonal of the bounds of all means.
- a normal shorter than ``MIN_NORMAL`` (0.5; accumulated normals that cancel) is replaced by the mean unit
  normal of the ``NEIGHBOURS`` nearest selected Gaussians with reliable normals; where there are none, or
  their mean cancels too, by the direction from the selection's centre to the Gaussian (outward), and +y for a
  Gaussian at that centre.
- directions are Latin-hypercube stratified over the cosine-weighted disk (Malley), one random
  stratification per Gaussian, from a generator seeded with ``SEED``: the same edit gives the same model.
"""

from __future__ import annotations


import numpy as np
import torch
from scipy.spatial import cKDTree

from models.gaussians import Gaussians
from models.pathtrace.irradiance import cosine_mean_radiance, ray_offsets
from models.pathtrace.paths import PathConfig, TraceFn

MIN_NORMAL = 0.5  # shorter stored normals are unreliable
NEIGHBOURS = 8  # selected neighbours whose normals replace an unreliable one
SEED = 0


def shading_normals(g: Gaussians, mask: torch.Tensor) -> torch.Tensor:
    """[n, 3] unit normals of the selected Gaussians (n = mask.sum()), unreliable ones replaced (module doc)."""
    p = g.means.detach()[mask].double().cpu()
    raw = g.normals.detach()[mask].double().cpu()
    length = raw.norm(dim=1)
    good = length >= MIN_NORMAL
    n = raw / length.clamp_min(1e-12)[:, None]
    bad = (~good).nonzero().reshape(-1)
    if len(bad) == 0:
        return n.to(g.means)
    fixed = torch.zeros(len(bad), 3, dtype=torch.float64)
    if good.any():
        k = min(NEIGHBOURS, int(good.sum()))
        _, idx = cKDTree(p[good].numpy()).query(p[bad].numpy(), k=k)
        fixed = n[good][torch.from_numpy(np.asarray(idx).reshape(len(bad), k))].mean(dim=1)
    centre = 0.5 * (p.amin(0) + p.amax(0))
    outward = p[bad] - centre
    outward = torch.where(outward.norm(dim=1, keepdim=True) > 1e-12, outward, outward.new_tensor([0.0, 1.0, 0.0]))
    fixed = torch.where(fixed.norm(dim=1, keepdim=True) >= MIN_NORMAL, fixed, outward)
    n[bad] = fixed / fixed.norm(dim=1, keepdim=True)
    return n.to(g.means)


def albedo_radiance(g: Gaussians, mask: torch.Tensor, value, samples: int, trace_fn: TraceFn | None,
                    path: PathConfig | None = None) -> torch.Tensor:
    """[n, 3] the new diffuse radiance of the selected Gaussians: ``value`` (albedo, RGB in [0, 1]) x E_cos[L_i],
    L_i traced through the other Gaussians with ``trace_fn`` and the model's ``path`` settings (default
    PathConfig())."""
    if trace_fn is None:
        raise ValueError("set_albedo traces the scene to find the light reaching the selection: it needs a tracer "
                         "(apply_edit(..., trace_fn=tracer.trace, path=...), as the edit stage passes)")
    others = ~mask
    if not bool(others.any()):
        raise ValueError("set_albedo selected every Gaussian: nothing is left to light the selection")
    scene = Gaussians(**{k: v.detach()[others].contiguous() for k, v in g.params().items()})
    normals = shading_normals(g, mask)
    offsets = ray_offsets(g, mask, normals)
    generator = torch.Generator().manual_seed(SEED)
    mean_li = cosine_mean_radiance(trace_fn, scene, g.means.detach()[mask], normals, offsets, samples,
                                   path or PathConfig(), generator)
    return torch.tensor(value, dtype=torch.float64) * mean_li
