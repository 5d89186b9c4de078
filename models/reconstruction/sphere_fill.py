"""Sphere completion: Gaussians on the unseen far sides of round shiny objects.

Training cameras that circle one side of a chrome ball, a metal bowl or a silver sphere see half of it; nothing is
reconstructed behind, so a test view from the other side looks at the BACKS of the seen half's surfels: normals
pointing away from it (zoo_spheres ``test_001``: shiny normals off by a median 66 degrees) and a reflection of the
wrong half of the room. A round object's far side is what a prior can say: fit a sphere to what was seen and
cover the rest of it.

1. Shiny pixel points (F0 > ``min_f0`` on the brightest channel, not light sources) of the training views'
   buffers, grouped into connected pieces (points closer than ``link`` join).
2. A sphere per piece of at least ``min_points`` points: least squares on p = c + r n (the buffers' normals
   point out of a sphere's centre), then on |p - c| = r (Gauss-Newton) over the points within 10 % of r.
   Kept only when it IS a sphere: the points' radial residual (median <= 2 % of r, 90th percentile <= 6 %),
   their normals against the radial direction (median <= 8 degrees), r below a quarter of the room's size, and
   the piece spans at least 60 degrees of arc (a gently curved patch fits a sphere of any size). A planar mirror,
   a cylinder or a cube fails these: nothing is added for them.
3. Candidates: a Fibonacci lattice on each kept sphere (spacing ``h`` = pi r / 24), farther than 1.5 h from every
   pixel point (unseen) and not seen to be empty by any training view (``seen_empty``: a view that looked past
   the point saw through it: what rests on the floor keeps its contact, a lattice point outside the true
   silhouette goes).
4. One isotropic Gaussian per candidate (scale 0.8 h, opacity 0.9, like the plane fill's), normal = the sphere's
   radial direction, diffuse / F0 / roughness = medians over the 16 nearest seen points of the piece.

The trainer adds them after the plane fill's (the prior's Gaussians: never pruned for want of blending weight)
when ``reconstruct.sphere_fill`` is on, and holds them FIXED: no parameter of theirs trains (the trainer's
``fixed`` rows). Trained like the plane fill's (colour, material and opacity free), the far sides turned
see-through (opacity 0.9 -> a median 0.16-0.30 on zoo_spheres' four balls) and showed the backs of the seen
halves' surfels again. Off by default: on the zoo (fast preset, one run per room) it finds exactly the balls
(zoo_spheres' four at r 0.280 +- 0.001, and none of the copper cube, the metal cylinders, the mirrors, the metal
walls); held fixed, zoo_spheres' ``test_001`` (the balls' far sides) goes 19.35 -> 22.02 dB final tonemapped
(its shiny pixels 13.4 -> 16.7 dB, far-side normals 66 -> 8 degrees off), but the rooms as a whole do not move
beyond the draws: zoo_spheres 23.31 -> 23.70, zoo_corridor 22.71 -> 23.08, zoo_lshape 27.97 -> 28.03,
zoo_mirror_only 26.33 -> 25.86, zoo_mirror_metal 29.02 -> 28.22 (README, thirteenth session).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from models.gaussians import Gaussians

from .plane_fill import _surfels
from .reflection_fill import seen_empty

MAX_RESIDUAL_MEDIAN = 0.02   # x r: a sphere's points lie on it
MAX_RESIDUAL_P90 = 0.06
MAX_NORMAL_DEG = 8.0         # median angle between a point's normal and the sphere's radial direction there
MIN_ARC_DEG = 60.0           # the piece spans at least this much of the sphere (seen from its centre)
LATTICE = 24                 # lattice spacing h = pi r / LATTICE (48 points round the equator)


def fit_sphere(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(centre, radius) of the sphere through ``points`` [n, 3] whose outward normals are ``normals``, or None.
    Linear least squares on p = c + r n, then Gauss-Newton on |p - c| = r over the points within 10 % of r."""
    n = len(points)
    if n < 10:
        return None
    a = np.zeros((3 * n, 4))
    a[:, :3] = np.tile(np.eye(3), (n, 1))
    a[:, 3] = normals.reshape(-1)
    sol = np.linalg.lstsq(a, points.reshape(-1), rcond=None)[0]
    c, r = sol[:3], float(sol[3])
    if not (r > 0 and np.isfinite(r)):
        return None
    for _ in range(5):
        d = points - c
        dist = np.linalg.norm(d, axis=1)
        use = np.abs(dist - r) <= 0.1 * r
        if use.sum() < 10:
            return None
        u = d[use] / np.maximum(dist[use, None], 1e-12)
        jac = np.concatenate([-u, -np.ones((int(use.sum()), 1))], axis=1)  # d(|p - c| - r) / d(c, r)
        step = np.linalg.lstsq(jac, -(dist[use] - r), rcond=None)[0]
        c, r = c + step[:3], r + float(step[3])
        if not (r > 0 and np.isfinite(r)):
            return None
        if np.abs(step).max() < 1e-7 * r:
            break
    return c, r


def sphere_check(points: np.ndarray, normals: np.ndarray, c: np.ndarray, r: float) -> dict:
    """How well the sphere (c, r) explains the piece: residuals (x r), normal angle, arc spanned."""
    d = points - c
    dist = np.linalg.norm(d, axis=1)
    radial = d / np.maximum(dist[:, None], 1e-12)
    res = np.abs(dist - r) / r
    angle = np.degrees(np.arccos(np.clip((radial * normals).sum(1), -1.0, 1.0)))
    mean_dir = radial.mean(0)
    spread = np.degrees(np.arccos(np.clip(radial @ (mean_dir / max(np.linalg.norm(mean_dir), 1e-12)), -1, 1)))
    return {"residual_median": float(np.median(res)), "residual_p90": float(np.quantile(res, 0.9)),
            "normal_deg": float(np.median(angle)), "arc_deg": float(2 * np.quantile(spread, 0.95))}


def find_spheres(src: dict, link: float, size: float, min_f0: float = 0.3,
                 min_points: int = 200) -> tuple[list[dict], list[str]]:
    """Spheres fitted to the shiny pieces of the pixel points ``src`` (``plane_fill.pixel_points``). Returns
    (kept [{"centre", "radius", "members" (indices into src), "check"}], one log line per piece tried)."""
    shiny = (src["f0"].max(axis=1) > min_f0) & ~src["emitting"]
    idx = np.nonzero(shiny)[0]
    notes: list[str] = []
    if len(idx) < min_points:
        return [], notes
    pts, nrm = src["points"][idx], src["normals"][idx]
    pairs = cKDTree(pts).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
    _, labels = connected_components(graph, directed=False)
    counts = np.bincount(labels)
    kept, unfit = [], 0
    for lab in np.nonzero(counts >= min_points)[0]:
        members = np.nonzero(labels == lab)[0]
        p, n = pts[members], nrm[members]
        where = f"piece of {len(members)} shiny points at {np.round(p.mean(0), 2).tolist()}"
        fit = fit_sphere(p, n)
        if fit is None:
            unfit += 1
            continue
        c, r = fit
        chk = sphere_check(p, n, c, r)
        why = [w for w, bad in (
            (f"radius {r:.2f} > a quarter of the room", r > 0.25 * size),
            (f"residual median {chk['residual_median']:.3f} r", chk["residual_median"] > MAX_RESIDUAL_MEDIAN),
            (f"residual p90 {chk['residual_p90']:.3f} r", chk["residual_p90"] > MAX_RESIDUAL_P90),
            (f"normals {chk['normal_deg']:.1f} deg off radial", chk["normal_deg"] > MAX_NORMAL_DEG),
            (f"spans {chk['arc_deg']:.0f} deg of arc", chk["arc_deg"] < MIN_ARC_DEG)) if bad]
        if why:
            notes.append(f"{where}: not a sphere ({'; '.join(why)})")
            continue
        notes.append(f"{where}: sphere r {r:.3f} at {np.round(c, 3).tolist()} (residual {chk['residual_median']:.4f} r, "
                     f"normals {chk['normal_deg']:.1f} deg, arc {chk['arc_deg']:.0f} deg)")
        kept.append({"centre": c, "radius": r, "members": idx[members], "check": chk})
    if unfit:
        notes.append(f"{unfit} shiny piece(s) of >= {min_points} points with no sphere through them (normals that "
                     "do not meet: planar mirrors, metal walls)")
    return kept, notes


def point_spacing(points: np.ndarray) -> float:
    """The median distance from a point of ``points`` [n, 3] (a subset of at most ~20,000) to its nearest other
    point: the pixel points' spacing, whose 3x links the pieces ``find_spheres`` groups."""
    return float(np.median(cKDTree(points).query(points[:: max(1, len(points) // 20000)], k=2)[0][:, 1]))


def fibonacci_sphere(count: int) -> np.ndarray:
    """[count, 3] unit vectors spread evenly over the sphere."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = math.pi * (3 - math.sqrt(5)) * i
    s = np.sqrt(np.maximum(1 - z * z, 0))
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


@torch.no_grad()
def sphere_fill_gaussians(src: dict | None, rays, size: float, opacity: float = 0.9, min_f0: float = 0.3,
                          dtype=torch.float32) -> tuple[Gaussians | None, dict]:
    """Gaussians on the unseen parts of the spheres that the shiny pixel points ``src`` (``pixel_points``) fit
    (module docstring); ``size``: the room's size (the points' box), ``rays``: the training rays (their views'
    depth decides what was seen to be empty). Returns (Gaussians or None, {"spheres", "added", "notes"})."""
    stats = {"spheres": 0, "added": 0, "notes": []}
    if src is None or len(src["points"]) < 100:
        return None, stats
    pts = src["points"]
    tree = cKDTree(pts)
    spheres, notes = find_spheres(src, link=3.0 * point_spacing(pts), size=size, min_f0=min_f0)
    stats["notes"] = notes
    parts = []
    for s in spheres:
        c, r = s["centre"], s["radius"]
        h = math.pi * r / LATTICE
        dirs = fibonacci_sphere(int(math.ceil(4 * math.pi * r * r / (h * h))))
        cand = c + r * dirs
        keep = tree.query(cand, k=1)[0] > 1.5 * h
        cand, dirs = cand[keep], dirs[keep]
        if len(cand):
            keep = ~seen_empty(torch.from_numpy(cand), rays.views).numpy()
            cand, dirs = cand[keep], dirs[keep]
        if not len(cand):
            continue
        members = s["members"]
        k = min(16, len(members))
        _, near = cKDTree(pts[members]).query(cand, k=k)
        near = members[np.asarray(near).reshape(len(cand), k)]
        med = lambda a: np.median(a[near], axis=1)  # noqa: E731
        parts.append(_surfels(cand, dirs, h, opacity, med(src["diffuse"]), med(src["roughness"]).reshape(-1),
                              med(src["f0"]), dtype))
        stats["spheres"] += 1
    if not parts:
        return None, stats
    fill = Gaussians.cat(parts)
    stats["added"] = len(fill)
    return fill, stats
