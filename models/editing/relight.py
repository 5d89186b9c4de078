"""Light that follows an edit: a moved, duplicated or deleted object takes its shadow (and the light it bounces)
with it.

A Gaussian stores the diffuse RADIANCE the captured scene sent from it: a Lambertian surface of albedo a under
irradiance E sends L = a E / pi. Move an object and the floor where its shadow lay stays dark, the floor where it
now stands stays lit: a stored radiance does not follow. ``relight`` scales it by the change of the light,

    L_after = L_before x E_after / E_before        (per RGB channel; the albedo a cancels),

E / pi estimated as the cosine-weighted mean, over the hemisphere of the Gaussian's normal, of the diffuse radiance
that the first surface along each ray holds (the model's primary segment, ``max_path_length`` 1: lamps and windows
are emitting Gaussians, a shadow is their occlusion; light that arrives through mirrors is counted in neither
model): in the unedited model where the Gaussian was, in the edited model where it is. Both estimates use the SAME
directions (one seeded generator, the same Gaussians in the same order; ``models.pathtrace.irradiance``), so a
Gaussian whose hemisphere the edit does not reach keeps its radiance exactly, and where it does, the ratio's noise
is that of the rays that changed.

Which Gaussians:
- those within ``REACH`` x the edited geometry's size (the diagonal of the box of what the ops moved, created or
  deleted, before the edit) of that geometry, before or after the edit, and the moved or created ones themselves
  (lit where they now stand; a duplicate's light before the edit is its original's);
- not those whose diffuse an op set (``DIFFUSE_OPS``: the user's value, and set_albedo's is lit where it is);
- not lights: a Gaussian that sends more than ``LIGHT_RATIO`` x the light it receives emits (a Lambertian surface
  sends at most what it receives, a = L / E_cos <= 1), and emission does not follow the light; "the light it
  receives" at least the median over the relit Gaussians, since under an object almost nothing arrives and the
  guess stored there sends more than that.

The ratio is clamped to [1 / MAX_RATIO, MAX_RATIO]. A Gaussian the edit uncovers (under where an object stood)
received almost no light, and what it stores there is a guess: where the light grows more than ``UNCOVERED`` x,
the Gaussian takes the median albedo (L / E_before) of its lit neighbours facing the same way, x E_after
(``_uncovered``).

``auto`` (the edit spec's ``relight``, default) relights after the ops that move geometry (``GEOMETRY_OPS``). Not
after a recolour (``DIFFUSE_OPS``; ``relight: true`` asks for it): the estimate counts the first surface's diffuse
only, so a metal made diffuse (zoo_spheres' gold_to_paint) starts lighting its neighbours while the light it
reflected before is not taken away (that edit's gain +9.23 -> +8.84 dB when relit); a moved metal is black in both
models, which cancels. Roughness and F0 change only the specular, which the renders trace anyway.

One segment, not two: with the first surface's reflection traced too (one GGX sample; longer paths draw their later
samples per surviving ray, which differ between the two models), the demo's move_ball gained +8.78 dB over the
unedited render instead of +9.00, zoo_thin's duplicate_chair +5.31 instead of +5.71, zoo_corridor's move_ball +0.72
instead of +0.55, three more edits within 0.07 dB.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch
from scipy.spatial import cKDTree

from models.gaussians import Gaussians
from models.pathtrace.irradiance import cosine_mean_radiance, ray_offsets
from models.pathtrace.paths import PathConfig, TraceFn

from .albedo import shading_normals

GEOMETRY_OPS = frozenset({"translate", "rotate", "scale", "duplicate", "delete"})  # auto relights after these
DIFFUSE_OPS = frozenset({"set_diffuse", "set_albedo", "shift_diffuse_hsv"})
REACH = 3.0         # relit: Gaussians within this x the edited geometry's size of it
LIGHT_RATIO = 2.0   # a Gaussian sending more than this x the light it receives is a light: left as it is
MAX_RATIO = 8.0     # E_after / E_before clamped to [1 / MAX_RATIO, MAX_RATIO]
UNCOVERED = 2.0     # a Gaussian whose light grows more than this is one the edit uncovered: neighbours' albedo
NEIGHBOURS = 16
SAMPLES = 64        # cosine-distributed rays per Gaussian (each model)
SEED = 1
MAX_REGION_POINTS = 50000  # edited points the distance query keeps (a random subset beyond)


def _normals_offsets(g: Gaussians, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Shading normals and ray offsets of the Gaussians ``rows`` [k] (indices, repeats allowed) of ``g``."""
    unique, inverse = torch.unique(rows.cpu(), return_inverse=True)
    mask = torch.zeros(len(g), dtype=torch.bool)
    mask[unique] = True  # mask order = sorted unique rows = ``unique``
    mask = mask.to(g.means.device)
    normals = shading_normals(g, mask)
    offsets = ray_offsets(g, mask, normals)
    inverse = inverse.to(normals.device)
    return normals[inverse], offsets[inverse]


def _uncovered(points: torch.Tensor, normals: torch.Tensor, diffuse: torch.Tensor, e_before: torch.Tensor,
               e_after: torch.Tensor, keep: torch.Tensor):
    """(rows, albedo [k, 3]) of the relit Gaussians the edit uncovered (light up by more than ``UNCOVERED`` x: under
    where an object stood, a guess no camera checked), their albedo the median albedo (L / E_before) of the
    ``NEIGHBOURS`` nearest relit Gaussians that were lit before (up by at most ``UNCOVERED`` x) and face the same way
    (normals within ~25 degrees); None where there are none. ``keep`` [n]: neither (lights, and what the ops moved
    or created: they carry their own albedo)."""
    gain = (e_after / e_before.clamp_min(1e-8)).amax(-1)
    up = (gain > UNCOVERED) & ~keep
    donors = (gain <= UNCOVERED) & ~keep & (e_before.amax(-1) > 1e-8)
    if not bool(up.any()) or int(donors.sum()) < NEIGHBOURS:
        return None
    d_idx = donors.nonzero().reshape(-1)
    albedo = diffuse[d_idx] / e_before[d_idx].clamp_min(1e-8)
    u_idx = up.nonzero().reshape(-1)
    _, near = cKDTree(points[d_idx].numpy()).query(points[u_idx].numpy(), k=NEIGHBOURS)
    near = torch.from_numpy(np.asarray(near).reshape(len(u_idx), NEIGHBOURS))
    facing = (normals[d_idx][near] * normals[u_idx][:, None, :]).sum(-1) > 0.9  # [k, NEIGHBOURS]
    ok = facing.any(1)
    if not bool(ok.any()):
        return None
    cand = albedo[near]  # [k, NEIGHBOURS, 3]
    cand = torch.where(facing[..., None], cand, torch.full_like(cand, float("nan")))
    med = cand.nanmedian(dim=1).values.clamp(0.0, 1.0)
    return u_idx[ok], med[ok]


@torch.no_grad()
def relight(before: Gaussians, after: Gaussians, source: torch.Tensor, edited_before: torch.Tensor,
            edited_after: torch.Tensor, fixed: torch.Tensor, trace_fn: TraceFn, path: PathConfig | None = None,
            samples: int = SAMPLES) -> tuple[Gaussians, dict]:
    """``after`` with the diffuse radiance of the Gaussians near the edit scaled by E_after / E_before (module doc).
    ``source`` [M]: the row of ``before`` each row of ``after`` comes from; ``edited_before`` [N] / ``edited_after``
    [M] bool: what the ops moved, created or deleted, before / after the edit; ``fixed`` [M] bool: rows whose diffuse
    an op set. ``path``: the model's path settings (its hole fill and diffuse lobe; one segment is traced).
    Returns (Gaussians, statistics for the edit's report)."""
    start = time.perf_counter()
    stats = {"relit": 0, "changed": 0, "lights": 0, "samples": samples}
    means_before, means_after = before.means.detach().double().cpu(), after.means.detach().double().cpu()
    edited_before, edited_after, fixed = edited_before.cpu(), edited_after.cpu(), fixed.cpu()
    pts = torch.cat([means_before[edited_before], means_after[edited_after]])
    if len(pts) == 0:
        return after, stats
    obj = means_before[edited_before]
    obj = obj if len(obj) else pts
    size = float((obj.amax(0) - obj.amin(0)).norm())
    reach = max(REACH * size, 1e-6)
    if len(pts) > MAX_REGION_POINTS:
        pts = pts[torch.randperm(len(pts), generator=torch.Generator().manual_seed(SEED))[:MAX_REGION_POINTS]]
    dist, _ = cKDTree(pts.numpy()).query(means_after.numpy(), k=1, distance_upper_bound=reach)
    region = (torch.from_numpy(np.isfinite(dist)) | edited_after) & ~fixed
    rows = region.nonzero().reshape(-1)
    stats.update(relit=int(len(rows)), reach=round(reach, 4))
    if len(rows) == 0:
        return after, stats
    one = dataclasses.replace(path or PathConfig(), max_path_length=1)
    src = source.cpu()[rows]
    n_before, o_before = _normals_offsets(before, src)
    n_after, o_after = _normals_offsets(after, rows)
    e_before = cosine_mean_radiance(trace_fn, before, before.means.detach()[src], n_before, o_before, samples, one,
                                    torch.Generator().manual_seed(SEED))
    e_after = cosine_mean_radiance(trace_fn, after, after.means.detach()[rows], n_after, o_after, samples, one,
                                   torch.Generator().manual_seed(SEED))
    diffuse = after.diffuse.detach()[rows].double().cpu()
    lit = e_before > 1e-8
    ratio = torch.where(lit, e_after / e_before.clamp_min(1e-8), torch.ones_like(e_before))
    ratio = ratio.clamp(1.0 / MAX_RATIO, MAX_RATIO)
    # a light sends more than it receives, and more than the light a typical relit Gaussian receives (where almost
    # no light arrives, under an object, a guess sends more than that little too)
    typical = float(e_before.amax(-1).median())
    light = diffuse.amax(-1) > LIGHT_RATIO * e_before.amax(-1).clamp_min(typical)
    ratio[light] = 1.0
    out = diffuse * ratio
    uncovered = _uncovered(means_after[rows], n_after.double().cpu(), diffuse, e_before, e_after,
                           light | edited_after[rows])
    if uncovered is not None:
        idx, albedo = uncovered
        out[idx] = albedo * e_after[idx]
        stats["uncovered"] = int(len(idx))
    stats.update(lights=int(light.sum()), changed=int(((ratio - 1).abs().amax(-1) > 0.05).sum()),
                 mean_ratio=round(float(ratio[~light].mean()) if bool((~light).any()) else 1.0, 4),
                 seconds=round(time.perf_counter() - start, 1))
    new = after.diffuse.detach().clone()
    new[rows] = out.to(new)
    params = {k: v.detach() for k, v in after.params().items()}
    params["diffuse"] = new
    return Gaussians(**params), stats
