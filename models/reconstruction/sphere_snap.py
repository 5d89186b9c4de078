"""Sphere snap: after the last step, each round shiny object the training views show is replaced by a fine
lattice of discs on the sphere fitted to it.

What training makes of a chrome ball is a shell of ~2,400 semi-transparent Gaussians (zoo_spheres: opacity a
median 0.08, 0.26-0.28 m from the centre of a ball of r 0.28) whose blended normals are right where the training
cameras looked (0.5 degrees) and wrong elsewhere: the far side is missing (the ray meets the seen half from
inside), the sides seen at grazing angles are a few degrees off, and a mirror ball shows every degree twice over.
A test view that walks round the ball sees a reflection of the wrong part of the room.

1. Spheres are fitted as for the sphere completion (``sphere_fill.find_spheres``: shiny pixel points of the
   training views grouped into pieces, a sphere kept only where the piece IS one: radial residual, normals, arc).
2. Each sphere's material is the medians of the capture's buffers over its piece (diffuse, F0, roughness: what
   the training targets say the ball is).
3. The model's Gaussians of the ball go: every one inside 0.9 r of the centre (nothing there can be seen), and
   the shiny ones (mean F0 above half the fit's threshold) within ``BAND`` r of it. What touches the ball (the
   floor it rests on, a plinth) is matte and stays.
4. In their place, ``4 pi / step^2`` discs (Fibonacci lattice, spacing ``step`` r: ``STEP``, or ``PIXEL_SHARE``
   of a pixel of the training view that sees the ball largest where that is coarser; each 0.8 x the spacing across
   and ``THICKNESS`` x that thick, tangent to the sphere, ``SINK`` spacings inside it, opacity ``OPACITY``) with
   the sphere's radial normal and the material of step 2. They are a prior's Gaussians, held fixed.
5. A fit that the training views contradict is not snapped: when more than ``MAX_EMPTY`` of the lattice,
   pulled in to ``PROBE`` r of the centre, lies where a training view saw empty space
   (``reflection_fill.seen_empty`` at ``EMPTY_MARGIN``), the ball keeps its trained Gaussians and the decisions
   log says so. (Pulled in: a point ON the sphere near a view's silhouette falls on a background pixel as often
   as not, 24-33 % of the lattice over zoo_spheres' 18 views; at 0.7 r every point of a right fit projects well
   inside the ball.)

After training, not before: the room the ball reflects is trained through the ball the model made (the twelfth
session's replacement at the end of warm-up, isotropic blobs at pi r / 32 trained on, lost 2.3 dB on
zoo_spheres); snapped afterwards, the same trained room is reflected by the exact sphere. Measured on the
thirty-seventh session's trained models (fast preset, tonemapped final, antialiased renders; README): zoo_spheres
24.82 -> 28.46 (specular 22.10 -> 27.14), the demo 36.48 -> 36.79, zoo_corridor +0.18, zoo_mirror_only +0.11,
zoo_lshape +0.09, zoo_mirror_metal +0.01 (the rooms without a ball unchanged).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch

from models.gaussians import Gaussians
from models.initialisation.dense import quats_z_to

from .reflection_fill import seen_empty
from .sphere_fill import fibonacci_sphere, find_spheres, point_spacing

log = logging.getLogger(__name__)

STEP = 0.05          # lattice spacing, x r (5,027 discs per sphere)
THICKNESS = 0.2      # a disc's thickness, x its width
OPACITY = 0.99
BAND = 1.25          # shiny Gaussians within this x r of the centre belong to the ball
INSIDE = 0.9         # every Gaussian nearer than this x r to the centre goes
MAX_EMPTY = 0.05     # a fit with more of its lattice seen to be empty than this is not snapped
EMPTY_MARGIN = 0.8   # ... seen empty: nearer than this x a training pixel's depth, or on a pixel that hits nothing
PROBE = 0.7          # ... of the lattice pulled in to this x r
PIXEL_SHARE = 0.4    # the spacing is at least this x the nearest training view's pixel there (a small or far ball
                     # gets fewer discs: a bead of r 3 cm 2 m from a 128 px wide 60 degree view, ~210 instead of
                     # 5,027; no zoo or demo ball: their nearest views resolve them finer than 0.05 r at 0.4 px)
MAX_STEP = 0.5       # ... and at most this x r (50 discs)
SINK = 0.4           # the lattice lies this x its spacing inside the sphere: a disc reaches ~0.9 x the spacing
                     # from its centre, so discs near a view's silhouette carry the ball's outline past r


def _discs(points: np.ndarray, normals: np.ndarray, h: float, diffuse: np.ndarray, roughness: float,
           f0: np.ndarray, dtype) -> Gaussians:
    """Discs at ``points`` [n, 3] tangent to the planes of ``normals`` [n, 3] (unit): local z along the normal,
    0.8 h across, ``THICKNESS`` x that thick, opacity ``OPACITY``, one material for all."""
    n = len(points)
    q = quats_z_to(normals)  # as the init's discs
    scale = np.full((n, 3), math.log(0.8 * h))
    scale[:, 2] += math.log(THICKNESS)
    f = dict(dtype=dtype)
    return Gaussians(
        means=torch.tensor(points, **f),
        quats=torch.tensor(q, **f),
        log_scales=torch.tensor(scale, **f),
        opacity_logits=torch.full((n,), math.log(OPACITY / (1 - OPACITY)), **f),
        diffuse=torch.tensor(np.maximum(diffuse, 0.0), **f).reshape(1, 3).repeat(n, 1),
        normals=torch.tensor(normals, **f),
        roughness=torch.full((n,), float(np.clip(roughness, 0.0, 1.0)), **f),
        f0=torch.tensor(np.clip(f0, 0.0, 1.0), **f).reshape(1, 3).repeat(n, 1),
    )


def _nearest_footprint(point: np.ndarray, views) -> float:
    """The width of one pixel at ``point`` [3] in the training view that sees it largest (distance / focal length,
    over the views whose frame it is in front of and inside); inf when none does."""
    best = math.inf
    for view in views:
        cam = view.camera
        u, v, z = cam.project(point[None])
        if z[0] > 1e-9 and 0 <= u[0] < cam.width and 0 <= v[0] < cam.height:
            best = min(best, float(np.linalg.norm(point - cam.origin)) / max(cam.fl_x, cam.fl_y))
    return best


@torch.no_grad()
def snap_spheres(gaussians: Gaussians, src: dict | None, views, size: float, min_f0: float = 0.3,
                 ) -> tuple[torch.Tensor, Gaussians | None, dict]:
    """The round shiny objects of ``gaussians`` replaced by lattices on the spheres fitted to the shiny pixel points
    ``src`` (``plane_fill.pixel_points``; module docstring). ``views``: the training views (what they saw to be
    empty); ``size``: the room's size. Returns (keep [N] bool: the Gaussians that stay, the lattices' Gaussians or
    None, {"spheres", "snapped", "removed", "added", "notes"})."""
    n = len(gaussians)
    keep = torch.ones(n, dtype=torch.bool)
    stats = {"spheres": 0, "snapped": 0, "removed": 0, "added": 0, "notes": []}
    if src is None or len(src["points"]) < 100 or n == 0:
        return keep, None, stats
    pts = src["points"]
    spheres, _ = find_spheres(src, link=3.0 * point_spacing(pts), size=size, min_f0=min_f0)
    stats["spheres"] = len(spheres)
    means = gaussians.means.detach().double().cpu().numpy()
    shiny = gaussians.f0.detach().mean(-1).cpu().numpy() > 0.5 * min_f0
    dtype = gaussians.means.dtype
    parts = []
    lo, hi = np.quantile(pts, [0.005, 0.995], axis=0)
    for s in spheres:
        c, r = np.asarray(s["centre"], dtype=np.float64), float(s["radius"])
        # in the room's terms (the decisions read the same at every scale; the log has scene units)
        where = (f"the sphere of radius {r / size:.3f} x the room size at "
                 f"{np.round((c - lo) / np.maximum(hi - lo, 1e-12), 2).tolist()} of its box")
        log.info("sphere snap: sphere r %.4f at %s", r, np.round(c, 4).tolist())
        pixel = _nearest_footprint(c, views)
        step = min(max(STEP, PIXEL_SHARE * pixel / r), MAX_STEP) if math.isfinite(pixel) else STEP  # x r
        dirs = fibonacci_sphere(int(math.ceil(4 * math.pi / step ** 2)))
        lattice = c + r * (1.0 - SINK * step) * dirs
        empty = seen_empty(torch.from_numpy(c + PROBE * r * dirs), views, margin=EMPTY_MARGIN).numpy()
        if empty.mean() > MAX_EMPTY:
            stats["notes"].append(f"sphere snap: {where} left as trained: {100 * empty.mean():.0f} % of its lattice "
                                  f"lies where a training view saw empty space (at most {100 * MAX_EMPTY:g} %)")
            continue
        d = np.linalg.norm(means - c, axis=1)
        ball = (d < INSIDE * r) | ((d < BAND * r) & shiny)
        members = s["members"]
        diffuse = np.median(src["diffuse"][members], axis=0)
        f0 = np.median(src["f0"][members], axis=0)
        roughness = float(np.median(src["roughness"][members]))
        keep &= torch.from_numpy(~ball)
        parts.append(_discs(lattice, dirs, step * r, diffuse, roughness, f0, dtype))
        stats["snapped"] += 1
        stats["notes"].append(f"sphere snap: {where}: {int(ball.sum())} Gaussians replaced by {len(lattice)} discs (F0 "
                              f"{np.round(f0, 2).tolist()}, roughness {roughness:.2f})")
    stats["removed"] = int((~keep).sum())
    if not parts:
        return keep, None, stats
    lattice = Gaussians.cat(parts)
    stats["added"] = len(lattice)
    return keep, lattice, stats
