"""The unseen backs of thin surfaces: a second layer behind them, lit as their material would be there.

A Gaussian holds ONE outgoing diffuse radiance, whichever side a ray arrives from. A thin surface the training
cameras see from one side only (a table top from above, a seat, a shelf, a slat) is rendered from its other side
with the radiance of the side they saw: a test camera under a table sees the lit top's colour where the truth
has the top's underside in the table's shadow (zoo_thin ``test_002``: diffuse 0.22 where the truth is 0.12).

After training, every surface-like Gaussian (opacity >= ``MIN_OPACITY``, a stored normal >= ``MIN_NORMAL`` long,
its smallest scale <= ``FLAT`` x its middle one) gets a copy behind it when its back

1. faces space a training view saw empty: a point ``BEHIND`` x the scene's size behind it (any of them) lies
   in front of the depth a training view measured through it and the 8 pixels around, by more than 2 % of the
   distance (the space-carving test on the training depths). A wall, a floor, anything closed behind never passes;
2. is open: a ray from behind the Gaussian along its back normal passes (opacity < 0.5) or ends farther than
   ``OPEN`` x the scene's size. The near side of a post or a leg, whose far side the model holds, does not pass.

The copy sits 3 standard deviations of the Gaussian behind it along the normal (where ``ray_offsets`` starts
rays), faces the other way, keeps its shape, opacity and specular material, and sends the diffuse radiance
``albedo x E_back``: albedo = front radiance / E_front, E the cosine mean of the model's own radiance over the
hemisphere of each side (models/pathtrace/irradiance.py, ``SAMPLES`` rays per side), both averaged over the
``NEIGHBOURS`` nearest such Gaussians before the division; the albedo clamped to [0, 1].

3. A copy a training view sees (blending weight above ``SEEN`` pixels in some training view, traced with the
   copies in place) is dropped: the backs were chosen as what no training view shows, and what the views show
   was trained.

The copies train no further (they are made after the last step). Rooms without thin surfaces seen from one
side get few or none (zoo_thin: 1,149, under the table top and the seat; the other zoo rooms 0-26, their
scores within 0.03 dB; the demo 0).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import minimum_filter
from scipy.spatial import cKDTree

from models.capture import View
from models.gaussians import Gaussians
from models.pathtrace.irradiance import cosine_mean_radiance, ray_offsets
from models.pathtrace.paths import PathConfig, TraceFn

MIN_OPACITY = 0.05
MIN_NORMAL = 0.5
FLAT = 0.5
BEHIND = (0.005, 0.01, 0.02)  # probe distances behind a Gaussian, x the scene's size
CARVE_MARGIN = 0.02  # a probe is empty space when in front of a view's depth by this fraction of its distance
OPEN = 0.02  # x the scene's size: the back's first surface must be farther than this (or not opaque)
SAMPLES = 32  # cosine-distributed rays per side and Gaussian
NEIGHBOURS = 8
SEEN = 0.05  # blending weight (pixels) above which a training view sees a copy
SEED = 0


def surface_candidates(g: Gaussians) -> torch.Tensor:
    """[N] bool: the Gaussians that look like a piece of surface (module doc)."""
    opacity = torch.sigmoid(g.opacity_logits.detach())
    scales = g.log_scales.detach().exp().sort(dim=1).values
    return ((opacity >= MIN_OPACITY) & (g.normals.detach().norm(dim=1) >= MIN_NORMAL)
            & (scales[:, 0] <= FLAT * scales[:, 1]))


def carved(points: np.ndarray, views: list[View], depths: list[np.ndarray], size: float) -> np.ndarray:
    """[P] bool: ``points`` [P, 3] a training view saw empty, i.e. projected inside it, in front of the camera,
    nearer than its depth there (``depths[i]`` [H, W], distance along the ray; 0 = unknown), the least over the
    pixel and its 8 neighbours (a ray grazing a surface measures far within a pixel of near), by more than
    CARVE_MARGIN x the distance (at least CARVE_MARGIN / 4 x ``size``)."""
    empty = np.zeros(len(points), bool)
    for view, depth in zip(views, depths):
        cam = view.camera
        u, v, z = cam.project(points)
        inside = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        col = np.clip(np.floor(u), 0, cam.width - 1).astype(np.int64)
        row = np.clip(np.floor(v), 0, cam.height - 1).astype(np.int64)
        measured = minimum_filter(depth, size=3, mode="nearest")[row, col]
        dist = np.linalg.norm(points - cam.origin, axis=1)
        margin = np.maximum(CARVE_MARGIN * dist, 0.25 * CARVE_MARGIN * size)
        empty |= inside & (measured > 0) & (dist < measured - margin)
    return empty


def unit_normals(g: Gaussians, rows: torch.Tensor) -> torch.Tensor:
    n = g.normals.detach()[rows]
    return n / n.norm(dim=1, keepdim=True).clamp_min(1e-12)


@torch.no_grad()
def open_backs(g: Gaussians, rows: torch.Tensor, trace_fn: TraceFn, size: float) -> torch.Tensor:
    """[len(rows)] bool: a ray from behind each Gaussian along its back normal passes or ends beyond OPEN x size."""
    if not len(rows):
        return torch.zeros(0, dtype=torch.bool)
    mask = torch.zeros(len(g), dtype=torch.bool, device=g.means.device)
    mask[rows] = True
    n = unit_normals(g, rows)
    origins = (g.means.detach()[rows] - ray_offsets(g, mask, n)[:, None] * n).contiguous()
    out = trace_fn(origins, (-n).contiguous(), g)
    opacity = 1.0 - out.transmittance.reshape(-1)
    depth = out.depth.reshape(-1) / opacity.clamp_min(1e-6)
    return ((opacity < 0.5) | (depth > OPEN * size)).cpu()


def seen_weight(g: Gaussians, copies: Gaussians, views: list[View], trace_fn: TraceFn) -> torch.Tensor:
    """[len(copies)] the largest blending weight (pixels) any training view gives each copy, traced with the
    copies behind ``g``: d sum(diffuse_R) / d diffuse_i,R."""
    from .data import view_rays

    scene = Gaussians.cat([g.to(), copies.to(g.means.device, g.dtype)])
    weight = torch.zeros(len(copies), dtype=torch.float64)
    for view in views:
        o, d = view_rays(view)
        probe = Gaussians(**{k: v.detach().clone().requires_grad_(k == "diffuse") for k, v in scene.params().items()})
        out = trace_fn(torch.tensor(np.ascontiguousarray(o), dtype=g.dtype, device=g.means.device),
                       torch.tensor(d, dtype=g.dtype, device=g.means.device), probe)
        (grad,) = torch.autograd.grad(out.diffuse[:, 0].sum(), probe.diffuse)
        weight = torch.maximum(weight, grad[len(g):, 0].detach().double().cpu())
    return weight


def back_fill(g: Gaussians, views: list[View], depths: list[np.ndarray], trace_fn: TraceFn, path: PathConfig,
              size: float, samples: int = SAMPLES) -> tuple[Gaussians | None, dict]:
    """The copies behind the thin surfaces of ``g`` whose backs no training view saw (module doc), or None, and
    what was decided (``candidates``, ``carved``, ``open``, ``seen`` (dropped), ``count``)."""
    stats = {"candidates": 0, "carved": 0, "open": 0, "seen": 0, "count": 0}
    rows = torch.nonzero(surface_candidates(g)).reshape(-1).cpu()
    stats["candidates"] = len(rows)
    if not len(rows):
        return None, stats
    p = g.means.detach()[rows].double().cpu().numpy()
    n = unit_normals(g, rows).double().cpu().numpy()
    empty = np.zeros(len(rows), bool)
    for frac in BEHIND:
        empty |= carved(p - n * frac * size, views, depths, size)
    rows = rows[torch.from_numpy(empty)]
    stats["carved"] = len(rows)
    rows = rows[open_backs(g, rows.to(g.means.device), trace_fn, size)]
    stats["open"] = len(rows)
    if not len(rows):
        return None, stats
    dev = g.means.device
    mask = torch.zeros(len(g), dtype=torch.bool, device=dev)
    mask[rows.to(dev)] = True
    normals = unit_normals(g, rows.to(dev))
    offsets = ray_offsets(g, mask, normals)
    points = g.means.detach()[mask]
    generator = torch.Generator().manual_seed(SEED)
    e_front = cosine_mean_radiance(trace_fn, g, points, normals, offsets, samples, path, generator)
    e_back = cosine_mean_radiance(trace_fn, g, points, -normals, offsets, samples, path, generator)
    # averaged over the nearest such Gaussians (SAMPLES rays each are noisy) before the division
    k = min(NEIGHBOURS, len(rows))
    at = points.double().cpu().numpy()
    _, near = cKDTree(at).query(at, k=k)
    near = torch.from_numpy(np.asarray(near).reshape(len(rows), k))
    e_front, e_back = e_front[near].mean(dim=1), e_back[near].mean(dim=1)
    front = g.diffuse.detach()[mask].double().cpu()
    albedo = (front / e_front.clamp_min(1e-6)).clamp(0.0, 1.0)
    copies = {k2: v.detach()[mask].clone() for k2, v in g.params().items()}
    copies["means"] = points - offsets[:, None] * normals
    copies["normals"] = -g.normals.detach()[mask]
    copies["diffuse"] = (albedo * e_back).to(g.diffuse)
    copies = Gaussians(**copies)
    hidden = seen_weight(g, copies, views, trace_fn) <= SEEN
    stats["seen"] = int((~hidden).sum())
    stats["count"] = int(hidden.sum())
    if not bool(hidden.any()):
        return None, stats
    return copies.subset(hidden), stats
