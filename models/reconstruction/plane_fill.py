"""Plane completion: Gaussians on the unseen parts of the planes that bound a room (walls, floor, ceiling).

Training views rarely see all of a room's walls, floor and ceiling: the part of a wall beside and behind the
cameras, the ceiling above the frame's top edge. Nothing is reconstructed there, so a test view that turns to it
looks through the hole at whatever lies beyond (the far field, a fill's stray Gaussian) -- the zoo's corridor
(the metal wall outside every training frustum) and lamps room (the ceiling) lose most of their error there. A
path tracer can train only what exists: where a mirror or a metal wall shows the unseen part, the reflection
losses need Gaussians there to train. Interiors are bounded by a few large planes, so this fill finds them in
the training views' buffers and covers their unseen parts.

1. Planes: for each direction among the normal buffer's (sampled, and their opposites: a ceiling the cameras
   barely see faces the floor they see), the peaks of the histogram of the offsets of the points facing it
   (within 15 degrees; bins of ``tol``) that hold >= ``min_points`` points, refined by least squares.
2. Bounding planes: nothing lies behind them (fewer than 0.5 % of all points farther than 3 ``tol`` on the side
   away from the cameras). A table top has the floor behind it; a wall, the floor, the ceiling have nothing.
   A plane made of another bounding plane's points is not a wall of its own (``distinct``): the pixels where a
   wall meets the floor, or the floor round an object standing on it, fit thin slanted planes (100-400 points,
   every one of them within 3 ``tol`` of the floor or the wall) that have nothing behind them either; filled,
   they put the seam's material on a slab a few cm above the floor (zoo_spheres: 3,113 surfels of F0 0.2-0.3
   hovering 3-8 cm over the matte floor the test views look at). Every zoo room had one to four of them.
3. Candidates: a grid (spacing ``h``) on each bounding plane, inside the scene box (the points' 0.5-99.5 %
   box, widened to hold every camera and every bounding plane's points) and on the room's side of every other
   bounding plane (a floor does not reach past the walls).
4. Unseen: farther than 1.5 h from every pixel point, and not seen to be empty by any training view
   (``seen_empty``: inside its frustum, nearer than 0.9 x that pixel's depth, or on a pixel that hits nothing).
   So a doorway, a window onto the outside, or the room's other leg in view stay open.
5. One Gaussian per unseen grid point: isotropic (scale 0.8 h), opacity ``opacity`` (0.9), normal = the plane's,
   diffuse / F0 / roughness = medians over the plane's 16 nearest points that are not light sources (what its
   seen part is made of: a window or a lamp on a wall is the capture's ``emission``, not the wall's material).
   A wall is opaque: this grid lets < 1 % through at any angle (scale 0.6 h at opacity 0.6 let 22 % through
   head-on, up to 37 %, and a test view looking at an unseen wall saw the far field shine through it; a wall
   above a window took the window's radiance, 10x the wall's: zoo_lshape ``test_002``).

6. Beyond the cameras (``extend_plane_fill``): the box of step 3 ends at the cameras, but a wall mirror shows the
   half of the room behind them. When the mirror stereo has placed what the mirrors show (end of warm-up), the
   box grows to hold those points and the bounding planes are filled in the grown part too (zoo_mirror_only:
   the floor behind the cameras, which a test view turning round looks at). The wall the mirrors show on an open
   side (no plane of the buffers faces it, or none lies that way at all: ``shown_sides``) becomes a bounding
   plane itself, so that what no reflection could show of it, the patch behind an object standing in front of
   it, is covered too (``_shown_walls``), and it is filled inside the first box as well (the first fill did not
   have it).

7. Relit (``relight_plane_fill``, ``plane_fill_relight``): step 5 gives an unseen part the radiance of the nearest
   seen part, but the same material under a lamp sends more. Once the model's lights are placed (the end of
   warm-up, or later: ``plane_fill_relight_at``), each fill Gaussian takes its plane's albedo (seen radiance over
   the irradiance the model sends there) times the irradiance the model sends where it is, both traced.

The trainer adds them before warm-up (step 6's at its end) and never prunes them for want of blending weight (no
training view may see them: what nothing observes is the prior's to say); where reflections see them, training
changes their colour and material, never their place or size.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from models.gaussians import Gaussians
from models.gaussians.activations import normalize_quats, quat_multiply, quats_to_rotmats

from .reflection_fill import emitting_rays, seen_empty

SCALE = 0.8  # the fill's Gaussians' scale, x the grid spacing: with opacity 0.9 a wall lets < 1 % through
COS_NORMAL = math.cos(math.radians(15.0))  # a point's normal within this of the plane's: the plane's point
OPPOSITE = -0.95  # two bounding planes whose normals' dot is below this face each other
DUPLICATE_NEAR = 0.95  # distinct(): a bounding plane with this share of its points within 3 tol of a larger one,
DUPLICATE_OWN = 0.25   # ... and this share of them facing like it or on a seam with a third plane: its duplicate
COS_DUPLICATE = math.cos(math.radians(30.0))  # ... facing like it: normals within this angle
SHOWN_WALL_SHARE = 0.3   # a wall the mirrors show (_wall_at): this share of the points at or beyond the box's face
SHOWN_WALL_MIN = 50      # ... and at least this many
SHOWN_WALL_BEYOND = 0.05  # ... with at most this share of them farther than it
SHOWN_WALL_SPREAD = 3.0  # ... "farther": this many times their spread round it (_wall_at's first try)
SHOWN_WALL_WINDOW = 6.0  # ... the spread measured on the points within this many tol of it


def pixel_points(rays, max_points: int, seed: int = 0) -> dict[str, np.ndarray] | None:
    """The world points of the training pixels that hit something and have a normal (origin + depth x unit
    direction; the capture's depth is the distance along the ray), with their buffers, up to ``max_points``
    sampled: {"points", "normals", "diffuse", "f0", "roughness"} as float64 arrays, and "emitting" (bool: the
    pixel shows a light source, ``emission`` > 0 where its view has that layer); None without depth / normals."""
    t = rays.targets
    if "depth" not in t or "normal" not in t:
        return None
    depth = t["depth"].reshape(-1)
    normal = t["normal"].reshape(-1, 3)
    ok = rays.mask & (depth > 0) & (normal.norm(dim=-1) > 0.5)
    idx = torch.nonzero(ok).reshape(-1)
    if len(idx) > max_points:
        g = torch.Generator().manual_seed(seed)
        idx = idx[torch.randperm(len(idx), generator=g)[:max_points]].sort().values
    pts = rays.origins[idx] + rays.dirs[idx] * depth[idx, None]
    out = {"points": pts, "normals": torch.nn.functional.normalize(normal[idx], dim=-1)}
    n = len(idx)
    out["diffuse"] = t["diffuse"][idx].reshape(n, 3) if "diffuse" in t else torch.full((n, 3), 0.5)
    out["f0"] = t["f0"][idx].reshape(n, 3) if "f0" in t else torch.full((n, 3), 0.04)
    out["roughness"] = t["roughness"][idx].reshape(n) if "roughness" in t else torch.full((n,), 1.0)
    emitting = emitting_rays(rays)[idx.numpy()]
    arrays = {k: v.detach().double().cpu().numpy() for k, v in out.items()}
    arrays["emitting"] = emitting
    return arrays


def find_planes(points: np.ndarray, normals: np.ndarray, tol: float, min_points: int = 100, seeds: int = 256,
                seed: int = 0) -> list[tuple[np.ndarray, float, np.ndarray]]:
    """Planes (module docstring, step 1): [(unit normal, offset d: n . x = d, inlier indices)], most points
    first. ``points``, ``normals``: [M, 3]. Directions: the normals of ``seeds`` sampled points and their
    opposites (a ceiling the cameras barely see faces the floor they see), merged within 15 degrees; per
    direction, the offsets of the points facing it are histogrammed (bins of ``tol``) and every local peak of two
    adjacent bins holding >= ``min_points`` is a plane, refined by least squares over its points."""
    rng = np.random.default_rng(seed)
    m = len(points)
    dirs: list[np.ndarray] = []
    for k in rng.choice(m, size=min(seeds, m), replace=False):
        for cand in (normals[k], -normals[k]):
            if all(cand @ e <= COS_NORMAL for e in dirs):
                dirs.append(cand)
    planes = []
    taken = np.zeros(m, dtype=bool)
    for e in dirs:
        facing = np.nonzero((normals @ e > COS_NORMAL) & ~taken)[0]
        if len(facing) < min_points:
            continue
        off = points[facing] @ e
        edges = np.arange(off.min() - tol, off.max() + 2 * tol, tol)
        hist = np.histogram(off, bins=edges)[0]
        pair = hist[:-1] + hist[1:] if len(hist) > 1 else hist
        for b in np.argsort(-pair):
            if pair[b] < min_points:
                break
            if (b > 0 and pair[b - 1] > pair[b]) or (b + 1 < len(pair) and pair[b + 1] > pair[b]):
                continue  # not a local peak
            inl = facing[np.abs(off - edges[b + 1]) < tol]
            inl = inl[~taken[inl]]
            if len(inl) < min_points:
                continue
            c = points[inl].mean(0)
            normal = np.linalg.svd(points[inl] - c, full_matrices=False)[2][2]
            normal = normal if normal @ e >= 0 else -normal
            d = float(normal @ c)
            inl = facing[(np.abs(points[facing] @ normal - d) < tol) & ~taken[facing]]
            if len(inl) < min_points:
                continue
            planes.append((normal, d, inl))
            taken[inl] = True
    planes.sort(key=lambda p: -len(p[2]))
    return planes


def bounding(planes, points: np.ndarray, normals: np.ndarray, cameras: np.ndarray, tol: float,
             behind_share: float = 0.005):
    """The planes with (next to) nothing behind them (module docstring, step 2), normals turned to face the
    cameras' centre, less those made of another's points (``distinct``): [(normal, d, inliers)]."""
    return distinct(nothing_behind(planes, points, cameras, tol, behind_share), points, normals, tol)


def nothing_behind(planes, points: np.ndarray, cameras: np.ndarray, tol: float, behind_share: float = 0.005):
    """The planes with fewer than ``behind_share`` of the ``points`` farther than 3 ``tol`` on their side away
    from the cameras' centre, normals turned to face it: [(normal, d, inliers)]."""
    centre = cameras.mean(0)
    out = []
    for n, d, inl in planes:
        if n @ centre - d < 0:
            n, d = -n, -d
        behind = float(np.mean(points @ n - d < -3 * tol))
        if behind < behind_share:
            out.append((n, d, inl))
    return out


def distinct(bound: list, points: np.ndarray, normals: np.ndarray, tol: float) -> list:
    """``bound`` [(normal, d, inliers)] less every plane B made of a larger kept plane A's points (module
    docstring, step 2): >= ``DUPLICATE_NEAR`` of B's points within 3 ``tol`` of A, and of those >=
    ``DUPLICATE_OWN`` either facing like A (normal within 30 degrees of A's: a second fit of A, or the floor round
    an object's base) or within 3 ``tol`` of another kept plane too (the seam where A meets it). A wall seen only in
    a thin strip above the floor lies near the floor as well, but faces elsewhere and meets it along one line:
    it stays. On the zoo's seven rooms, the demo, mirror_book and three held-out probes, at plane seeds 0-2, the 49
    planes dropped had 100 % of their points near A and 75-100 % of them A's by one of the two tests; the walls
    kept had up to 95 % near A (probe_338's far wall, seen 0-19 cm above the floor) and at most 13 % facing like it
    or on a seam. The order of ``bound`` is kept."""
    kept: list[int] = []
    for i in sorted(range(len(bound)), key=lambda k: -len(bound[k][2])):
        inl = bound[i][2]
        near = np.array([np.abs(points[inl] @ bound[j][0] - bound[j][1]) <= 3 * tol for j in kept])
        near = near.reshape(len(kept), len(inl))
        planes_near = near.sum(0)  # per point: how many kept planes it lies near
        duplicate = any(len(inl) and near[a].mean() >= DUPLICATE_NEAR
                        and np.mean(near[a] & ((normals[inl] @ bound[j][0] >= COS_DUPLICATE) | (planes_near > 1)))
                        >= DUPLICATE_OWN for a, j in enumerate(kept))
        if not duplicate:
            kept.append(i)
    return [bound[i] for i in sorted(kept)]


def box_corners(lo, hi) -> np.ndarray:
    """The 8 corners [8, 3] of the box [lo, hi]."""
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def open_sides(room: Room) -> list[np.ndarray]:
    """The inward normals of ``room``'s bounding planes that no other bounding plane faces: the room is open
    beyond them, along the normal (a room seen from one end: the wall behind the cameras)."""
    normals = [n for n, _, _ in room.bound]
    return [n for n in normals if not any(float(m @ n) < OPPOSITE for m in normals)]


def _grid(n: np.ndarray, d: float, lo: np.ndarray, hi: np.ndarray, h: float) -> np.ndarray:
    """Points of a square grid (spacing h) on the plane n . x = d inside the box [lo, hi]."""
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    corners = box_corners(lo, hi)
    base = n * d
    cu, cv = (corners - base) @ u, (corners - base) @ v
    a = np.arange(cu.min(), cu.max() + h, h)
    b = np.arange(cv.min(), cv.max() + h, h)
    if len(a) * len(b) > 4_000_000:
        return np.zeros((0, 3))
    aa, bb = np.meshgrid(a, b, indexing="ij")
    pts = base + aa.reshape(-1, 1) * u + bb.reshape(-1, 1) * v
    return pts[((pts >= lo) & (pts <= hi)).all(1)]


def _surfels(pos: np.ndarray, normal: np.ndarray, h: float, opacity: float, diffuse: np.ndarray,
             roughness: np.ndarray | float, f0: np.ndarray | float, dtype) -> Gaussians:
    """Isotropic opaque surfels (scale ``SCALE`` h) at ``pos`` [n, 3] facing ``normal`` ([3] for all, or [n, 3]),
    of the given material (diffuse [n, 3]; roughness [n] and f0 [n, 3], or one value for all)."""
    n = len(pos)
    f = dict(dtype=dtype)
    return Gaussians(
        means=torch.tensor(pos, **f),
        quats=torch.tensor([[1.0, 0, 0, 0]], **f).repeat(n, 1),
        log_scales=torch.full((n, 3), math.log(SCALE * h), **f),
        opacity_logits=torch.full((n,), math.log(opacity / (1 - opacity)), **f),
        diffuse=torch.tensor(diffuse, **f).clamp_min(0.0).reshape(n, 3),
        normals=torch.tensor(normal, **f).reshape(-1, 3).expand(n, 3).clone(),
        roughness=torch.as_tensor(roughness, **f).clamp(0.0, 1.0).expand(n).reshape(n),
        f0=torch.as_tensor(f0, **f).clamp(0.0, 1.0).expand(n, 3).reshape(n, 3),
    )


@dataclasses.dataclass
class Room:
    """What ``plane_fill_gaussians`` found (steps 1-3), kept so that a later fill can reach further
    (``extend_plane_fill``): the seen pixel points (``src``), the bounding planes [(normal, d, inliers)], the box
    the fill covered (``lo``, ``hi``), the plane tolerance and the grid spacing it used."""
    src: dict
    bound: list
    lo: np.ndarray
    hi: np.ndarray
    tol: float
    h: float


def _fill(room: Room, rays, count: int, opacity: float, lo: np.ndarray, hi: np.ndarray, occupied: np.ndarray,
          done: tuple[np.ndarray, np.ndarray] | None, dtype,
          done_planes: int | None = None) -> tuple[Gaussians | None, dict]:
    """Steps 3-5 inside the box [lo, hi]: one Gaussian per unseen grid point of each bounding plane, farther than
    1.5 h from every ``occupied`` point, outside the box ``done`` (a fill already covered it) on the first
    ``done_planes`` planes (all without it: a plane found since that fill was not in it), up to ``count`` (the
    grid coarsens from ``room.h`` to fit). Sets ``room.h`` to the spacing used."""
    stats = {"unseen": 0, "added": 0}
    tol, h, pts, src = room.tol, room.h, room.src["points"], room.src
    tree = cKDTree(occupied)
    for _ in range(4):  # coarsen the grid until the unseen points fit the budget
        cand, owner = [], []
        for i, (n, d, inl) in enumerate(room.bound):
            if not len(inl):  # a wall placed by room_closing.py: no seen points to take a material from; it has its own
                cand.append(np.zeros((0, 3)))
                owner.append(np.zeros(0, dtype=np.int64))
                continue
            g = _grid(n, d, lo - tol, hi + tol, h)
            inside = np.ones(len(g), dtype=bool)
            for j, (n2, d2, _) in enumerate(room.bound):
                if j != i:
                    inside &= g @ n2 - d2 > -tol
            if done is not None and (done_planes is None or i < done_planes):
                inside &= ~((g >= done[0] - tol) & (g <= done[1] + tol)).all(1)
            g = g[inside]
            g = g[tree.query(g, k=1)[0] > 1.5 * h] if len(g) else g
            cand.append(g)
            owner.append(np.full(len(g), i))
        cand, owner = np.concatenate(cand), np.concatenate(owner)
        if len(cand):
            keep = ~seen_empty(torch.from_numpy(cand), rays.views).numpy()
            cand, owner = cand[keep], owner[keep]
        if len(cand) <= count:
            break
        h *= math.sqrt(len(cand) / count) * 1.05
    cand, owner = cand[:count], owner[:count]
    room.h = h
    stats["unseen"] = int(len(cand))
    if not len(cand):
        return None, stats
    parts = []
    for i, (n, d, inl) in enumerate(room.bound):
        sel = owner == i
        if not sel.any():
            continue
        mat = inl[~src["emitting"][inl]]  # the plane's material: its points that are not light sources
        mat = mat if len(mat) else inl
        k = min(16, len(mat))
        _, nearest = cKDTree(pts[mat]).query(cand[sel], k=k)
        nearest = mat[np.asarray(nearest).reshape(int(sel.sum()), k)]
        med = lambda a: np.median(a[nearest], axis=1)  # noqa: E731  [m, 16, ...] -> [m, ...]
        parts.append(_surfels(cand[sel], n, h, opacity, med(src["diffuse"]), med(src["roughness"]).reshape(-1),
                              med(src["f0"]), dtype))
    fill = Gaussians.cat(parts)
    stats["added"] = len(fill)
    return fill, stats


@torch.no_grad()
def plane_fill_gaussians(rays, count: int = 20000, opacity: float = 0.9, tol_fraction: float = 0.01,
                         min_points: int = 100, seed: int = 0,
                         dtype=torch.float32) -> tuple[Gaussians | None, dict]:
    """Up to ``count`` Gaussians on the unseen parts of the room's bounding planes (module docstring), from the
    training rays (a ``RaySet`` with depth and normal targets). Returns (Gaussians or None, statistics);
    ``stats["room"]`` is the ``Room`` found (None without buffers or planes), for ``extend_plane_fill``."""
    stats = {"planes": 0, "bounding": 0, "duplicates": 0, "unseen": 0, "added": 0, "spacing": 0.0,
             "spacing_fraction": 0.0, "notes": [], "room": None}
    src = pixel_points(rays, max_points=400000, seed=seed)
    if src is None or len(src["points"]) < 100:
        stats["notes"] = ["plane fill: off, the capture has no depth and normal buffers on enough pixels"]
        return None, stats
    pts = src["points"]
    lo, hi = np.quantile(pts, [0.005, 0.995], axis=0)
    size = float((hi - lo).max())
    tol = tol_fraction * size
    cams = np.stack([v.camera.origin for v in rays.views])
    lo, hi = np.minimum(lo, cams.min(0)), np.maximum(hi, cams.max(0))
    planes = find_planes(pts, src["normals"], tol, min_points=min_points, seed=seed)
    free = nothing_behind(planes, pts, cams, tol)
    bound = distinct(free, pts, src["normals"], tol)
    stats["planes"], stats["bounding"], stats["duplicates"] = len(planes), len(bound), len(free) - len(bound)
    if not bound:
        return None, stats
    for _, _, inl in bound:  # a plane the cameras barely see (a ceiling) lies outside the points' quantile box
        lo, hi = np.minimum(lo, pts[inl].min(0)), np.maximum(hi, pts[inl].max(0))
    room = Room(src=src, bound=bound, lo=lo, hi=hi, tol=tol, h=size / 100.0)
    stats["room"] = room
    fill, more = _fill(room, rays, count, opacity, lo, hi, pts, None, dtype)
    stats.update(more, spacing=float(room.h), spacing_fraction=float(room.h / size))
    return fill, stats


@torch.no_grad()
def extend_plane_fill(room: Room | None, rays, seen: np.ndarray, count: int = 20000, opacity: float = 0.9,
                      material: tuple | None = None, dtype=torch.float32) -> tuple[Gaussians | None, dict]:
    """The plane fill carried out to where the room is known to reach beyond the first fill's box: ``seen`` [M, 3]
    are points placed from what the cameras see only in mirrors (``mirror_stereo``: the half of a room behind
    cameras that face a wall mirror). The first box holds the seen pixels and the cameras, so it ends at the
    cameras; the floor, walls and ceiling behind them, shown only by the mirror, stayed open (zoo_mirror_only:
    a test view turning round looked through the floor). Here the box grows to the 0.5-99.5 % box of ``seen``
    and the bounding planes are filled in the grown part alone (same spacing, or coarser to fit ``count``),
    away from the seen pixels and from ``seen``; ``room``'s box becomes the grown one (a second call fills only
    beyond it).

    With ``material`` (the points' diffuse [M, 3], F0 [M, 3], roughness [M]), a wall the points show on an open side of the room
    (no bounding plane faces it) becomes a bounding plane too (``_shown_walls``), so the fill covers what the
    mirrors could not show of it: the wall behind an object that stands in front of it in every reflection
    (zoo_mirror_only: a 0.6 x 0.85 m hole behind the urn's pedestal, which a test view looking at the urn saw
    through, black). Returns (Gaussians or None, statistics; ``grown``: the box's sides that moved, or
    "nothing"; ``walls``: the walls added, described)."""
    stats = {"unseen": 0, "added": 0, "grown": "nothing", "walls": "none", "notes": []}
    if room is None or seen is None or len(seen) < 10:
        return None, stats
    seen = np.asarray(seen, dtype=np.float64)
    q_lo, q_hi = np.quantile(seen, [0.005, 0.995], axis=0)
    lo, hi = np.minimum(room.lo, q_lo), np.maximum(room.hi, q_hi)
    grown = [f"{'xyz'[a]} {room.lo[a]:.2f} -> {lo[a]:.2f}" for a in range(3) if lo[a] < room.lo[a] - room.tol] + \
            [f"{'xyz'[a]} {room.hi[a]:.2f} -> {hi[a]:.2f}" for a in range(3) if hi[a] > room.hi[a] + room.tol]
    if not grown:
        return None, stats
    stats["grown"] = ", ".join(grown)
    first = len(room.bound)
    if material is not None:
        stats["walls"] = _shown_walls(room, seen, *(np.asarray(m, dtype=np.float64) for m in material))
    # a wall found here is filled where unseen inside the first box too: the first fill did not have it (a side
    # wall at that box's face, probe_mirror_21's +x: the box's side left open where the first fill ended)
    fill, more = _fill(room, rays, count, opacity, lo, hi, np.concatenate([room.src["points"], seen]),
                       (room.lo, room.hi), dtype, done_planes=first)
    stats.update(more)
    room.lo, room.hi = lo, hi
    return fill, stats


def shown_sides(room: Room) -> list[np.ndarray]:
    """The directions in which ``room`` may have a wall its buffers never showed: its open sides (``open_sides``),
    then both directions along the line two perpendicular bounding planes share, where no bounding plane lies
    either way (a room seen from one end: cameras that face a wall mirror see the floor and that wall, and the
    side walls only in the mirror; probe_mirror_21 found 2 bounding planes, floor and back wall, and its side
    walls, at +-x, were no side at all: a test view turning to one looked through the stereo's haze into nothing)."""
    normals = [n for n, _, _ in room.bound]
    sides = open_sides(room)
    for i, a in enumerate(normals):
        for b in normals[i + 1:]:
            c = np.cross(a, b)
            length = float(np.linalg.norm(c))
            if length < -OPPOSITE:  # not perpendicular
                continue
            for d in (c / length, -c / length):
                if not any(abs(float(m @ d)) > -OPPOSITE for m in normals) and \
                        not any(float(m @ d) > -OPPOSITE for m in sides):
                    sides.append(d)
    return sides


def _wall_at(proj: np.ndarray, face: float, tol: float) -> tuple[float, np.ndarray, float, float] | None:
    """A wall across one side of the room (``_shown_walls``) from ``proj``, the points' offsets along the side's
    direction: (its offset s, which points lie on it, their share, the share behind it) or None. Tried twice:

    1. the points at or beyond the box's ``face`` (from 2 tol inside it: a side wall the seen floor reaches
       stands at the face); the fullest bin (2 tol), refined to the median within 2 tol of it, holds >=
       ``SHOWN_WALL_SHARE`` of them and no more than ``SHOWN_WALL_BEYOND`` lie farther behind it than
       ``SHOWN_WALL_SPREAD`` x their spread round it (1.4826 x the median distance to s of those within
       ``SHOWN_WALL_WINDOW`` tol, at least tol). The stereo's depths of a wall seen obliquely in a mirror scatter
       by ~0.1 m (probe_mirror_21's side walls: 0.11-0.15 m), 2-3 tol: a wall's far half, not a room beyond it.
    2. (as before the first) the points beyond the face + tol, nothing farther than 3 tol behind.

    A doorway or a window the mirror shows, with the room beyond, stays open (the far field's)."""
    for near, spread in ((proj > face - 2 * tol, True), (proj > face + tol, False)):
        if near.sum() < SHOWN_WALL_MIN:
            continue
        pb = proj[near]
        edges = np.arange(pb.min(), pb.max() + 2 * tol, 2 * tol)
        if len(edges) < 2:
            continue
        hist, edges = np.histogram(pb, bins=edges)
        peak = 0.5 * (edges[hist.argmax()] + edges[hist.argmax() + 1])
        s = float(np.median(pb[np.abs(pb - peak) <= 2 * tol]))
        margin = 3 * tol
        if spread:
            window = np.abs(pb - s) <= SHOWN_WALL_WINDOW * tol
            margin = SHOWN_WALL_SPREAD * max(tol, 1.4826 * float(np.median(np.abs(pb[window] - s))))
        on = near & (np.abs(proj - s) <= 2 * tol)
        share, behind = on.sum() / near.sum(), float(np.mean(pb > s + margin))
        if on.sum() >= SHOWN_WALL_MIN and share >= SHOWN_WALL_SHARE and behind <= SHOWN_WALL_BEYOND:
            return s, on, share, behind
    return None


def _shown_walls(room: Room, seen: np.ndarray, diffuse: np.ndarray, f0: np.ndarray, roughness: np.ndarray) -> str:
    """Bounding planes for the walls ``seen`` shows on the room's open sides (``extend_plane_fill``); returns
    their description ("none" without one). On each side n where the buffers showed no wall (``shown_sides``)
    the points' offsets along n are searched for a wall (``_wall_at``). Its points join ``room.src`` with their
    material (the plane's: what the fill's Gaussians there take), facing back into the room."""
    tol = room.tol
    corners = box_corners(room.lo, room.hi)
    described = []
    for n in shown_sides(room):  # (a wall placed here joins room.bound: a later side is tested against it too)
        proj = seen @ n
        face = float((corners @ n).max())
        found = _wall_at(proj, face, tol)
        if found is None:
            continue
        s, on, share, behind = found
        src, k, first = room.src, int(on.sum()), len(room.src["points"])
        pts = seen[on] - (proj[on] - s)[:, None] * n  # onto the plane
        add = {"points": pts, "normals": np.tile(-n, (k, 1)), "diffuse": diffuse.reshape(-1, 3)[on],
               "f0": f0.reshape(-1, 3)[on], "roughness": roughness.reshape(-1)[on], "emitting": np.zeros(k, dtype=bool)}
        for key, value in add.items():
            src[key] = np.concatenate([src[key], value.astype(src[key].dtype)])
        room.bound.append((-n, -s, np.arange(first, first + k)))
        axis = int(np.argmax(np.abs(n)))
        described.append(f"{'+' if n[axis] > 0 else '-'}{'xyz'[axis]} at {s - face:.2f} beyond the box ({k} points "
                         f"on it, {share:.0%} of those there; {behind:.1%} behind the wall)")
    return "; ".join(described) if described else "none"


@torch.no_grad()
def stereo_on_planes(room: Room | None, stereo: Gaussians, opacity: float = 0.9, tol_factor: float = 1.0,
                     along: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[torch.Tensor, Gaussians | None, dict]:
    """The mirror-stereo Gaussians (``stereo``) that lie on one of the room's bounding planes (within its
    tolerance, inside the other planes' half-spaces) made plane-fill surfels: moved onto the plane, the fill's
    size (``room.h``) and opacity, the colour the mirrors showed (the stereo Gaussian's), the plane's F0 and
    roughness (the median of its 16 nearest seen points'; a wall only the mirrors show has theirs). The plane
    fill leaves the places those points hold to them (``extend_plane_fill``'s ``seen``), so without this the
    floor and walls seen only in a mirror are the stereo's matte, free, semi-transparent blobs: a haze in
    front of them and no gloss (zoo_mirror_only's test views, none of whose pixels a training camera sees
    directly: depth 10 % short on 27-45 % of the pixels, the glossy floor's normals 26-41 degrees off).
    ``tol_factor``: "on a plane" is within this x the room's tolerance of it (the stereo's depths scatter more than
    the buffers' points: zoo_mirror_metal's front wall, seen only in the mirror at 5-6 m of virtual distance,
    got stereo points from 30 cm in front of it to 50 cm behind).
    ``along`` (the mirror stereo's statistics' "along": per stereo Gaussian the direction of the reflected ray
    that found it and the stretch of that ray round it the sweep could not tell from its depth): a Gaussian whose
    ray crosses a plane within that stretch (and inside the other planes) joins the plane too, where its ray
    crosses it: the stereo chose among depths it could not tell apart, and the plane is one of them. Unlike a
    wider ``tol_factor`` this does not take a textured object standing near a wall or on the floor.
    Returns ([M] bool: the stereo Gaussians replaced, the surfels or None, {"on_planes": count, "added":
    count, "along": how many joined by ``along`` alone})."""
    m = len(stereo)
    on = np.zeros(m, dtype=bool)
    if room is None or m == 0:
        return torch.from_numpy(on), None, {"on_planes": 0, "added": 0, "along": 0}
    p = stereo.means.detach().double().cpu().numpy()
    by_ray = 0
    colour = stereo.diffuse.detach().double().cpu().numpy()
    src, parts = room.src, []
    for i, (n, d, inl) in enumerate(room.bound):
        if not len(inl):  # a wall placed by room_closing.py: no material of its own
            continue
        dist = p @ n - d
        pos = p - dist[:, None] * n
        near = np.abs(dist) <= tol_factor * room.tol
        sel, cross = near & ~on, np.zeros(m, dtype=bool)
        if along is not None:  # the plane among the depths the sweep could not tell apart: where the ray crosses it
            dirs, span = along
            cos = dirs @ n
            s = -dist / np.where(np.abs(cos) > 1e-6, cos, np.nan)
            cross = ~sel & ~on & (s >= span[:, 0]) & (s <= span[:, 1])
            pos[cross] = p[cross] + s[cross, None] * dirs[cross]
            pos[cross] -= (pos[cross] @ n - d)[:, None] * n
            sel |= cross
        at = np.where(cross[:, None], pos, p)
        for j, (n2, d2, _) in enumerate(room.bound):
            if j != i:
                sel &= at @ n2 - d2 > -room.tol
        if not sel.any():
            continue
        by_ray += int((sel & cross).sum())
        pos = pos[sel]
        mat = inl[~src["emitting"][inl]]
        mat = mat if len(mat) else inl
        k = min(16, len(mat))
        _, nearest = cKDTree(src["points"][mat]).query(pos, k=k)
        nearest = mat[np.asarray(nearest).reshape(len(pos), k)]
        roughness = np.median(src["roughness"][nearest], axis=1).reshape(-1)
        parts.append(_surfels(pos, n, room.h, opacity, colour[sel], roughness, np.median(src["f0"][nearest], axis=1),
                              stereo.dtype))
        on |= sel
    fill = Gaussians.cat(parts) if parts else None
    return torch.from_numpy(on), fill, {"on_planes": int(on.sum()), "added": int(on.sum()), "along": by_ray}


RELIGHT_PROBES = 3000   # relight_plane_fill: points per plane (seen side, fill side) where the irradiance is traced
RELIGHT_SAMPLES = 64    # ... cosine-distributed rays per point
RELIGHT_SMOOTH = 8      # ... a fill Gaussian's irradiance: the mean over this many nearest fill-side points
RELIGHT_NEAR = 16       # ... its albedo: sum of radiance / sum of irradiance over this many nearest seen points


@torch.no_grad()
def relight_plane_fill(room: Room | None, means: np.ndarray, diffuse: np.ndarray, irradiance,
                       seed: int = 0) -> tuple[np.ndarray, dict]:
    """The plane fill's colour as the plane's albedo x the light where each of its Gaussians is, not the radiance
    of the nearest seen part of the plane (``_fill`` step 5): a floor seen only far from the lamp, continued under
    it, is the same material lit more (zoo_lamps: the unseen ceiling and the wall round the floor lamp, 31.5 ->
    33.0 dB at two seeds). It does not cure zoo_mirror_only's dark floor under a light seen only in the mirror:
    at the end of warm-up that light is still weak, and training then fits the mirror's grazing view (README).

    ``means`` [M, 3] and ``diffuse`` [M, 3] are the fill's Gaussians (those on none of ``room``'s planes that have
    seen points keep their colour); ``irradiance(points [K, 3], normals [K, 3]) -> [K, 3]`` (float64 arrays) is
    E / pi, the cosine-weighted mean radiance the model sends onto a point (models/pathtrace/irradiance.py). Per
    plane: E / pi at up to ``RELIGHT_PROBES`` of its seen (non-emitting) points and as many of its fill Gaussians,
    all lifted the same ``3 x SCALE x h`` off the plane into the room (past the fill's own kernels); a seen
    point's albedo is its radiance over that; a fill Gaussian takes the sum of radiance over the sum of E / pi of
    its ``RELIGHT_NEAR`` nearest seen points (clamped to 1: a ratio of sums, robust where E is small) times the
    mean E / pi of its ``RELIGHT_SMOOTH`` nearest fill-side points (64 rays each are noisy). Returns (new diffuse
    [M, 3], {"relit": count, "planes": count, "gain": median new / old radiance})."""
    out = np.array(diffuse, dtype=np.float64, copy=True)
    stats = {"relit": 0, "planes": 0, "gain": 1.0}
    if room is None or not len(means):
        return out, stats
    rng = np.random.default_rng(seed)
    src = room.src
    lift = max(3.0 * SCALE * room.h, 2.0 * room.tol)
    done = np.zeros(len(means), dtype=bool)
    gains = []
    for i, (n, d, inl) in enumerate(room.bound):
        dist = means @ n - d
        sel = (np.abs(dist) <= room.tol) & ~done
        mat = inl[~src["emitting"][inl]] if len(inl) else inl
        if not sel.any() or len(mat) < RELIGHT_NEAR:
            continue
        done |= sel
        seen = rng.choice(mat, size=min(RELIGHT_PROBES, len(mat)), replace=False)
        seen_at = src["points"][seen] - (src["points"][seen] @ n - d)[:, None] * n
        fill_at = means[sel] - dist[sel, None] * n
        probes = rng.choice(len(fill_at), size=min(RELIGHT_PROBES, len(fill_at)), replace=False)
        lifted = np.concatenate([seen_at, fill_at[probes]]) + lift * n
        e = np.asarray(irradiance(lifted, np.tile(n, (len(lifted), 1))), dtype=np.float64)
        e_seen, e_fill = e[:len(seen)], e[len(seen):]
        k = min(RELIGHT_NEAR, len(seen))
        _, near = cKDTree(seen_at).query(fill_at, k=k)
        near = np.asarray(near).reshape(len(fill_at), k)
        albedo = (src["diffuse"][seen][near].sum(1) / np.maximum(e_seen[near].sum(1), 1e-6)).clip(0.0, 1.0)
        k = min(RELIGHT_SMOOTH, len(probes))
        _, near = cKDTree(fill_at[probes]).query(fill_at, k=k)
        light = e_fill[np.asarray(near).reshape(len(fill_at), k)].mean(1)
        new = albedo * light
        old = out[sel]
        gains.append(new.mean(1) / np.maximum(old.mean(1), 1e-6))
        out[sel] = new
        stats["relit"] += int(sel.sum())
        stats["planes"] += 1
    if gains:
        stats["gain"] = float(np.median(np.concatenate(gains)))
    return out, stats


HOLD_COS = math.cos(math.radians(25.0))  # hold_on_planes: a Gaussian's thin axis within this of the plane's normal
HOLD_FLAT = math.log(1.25)  # hold_on_planes: a thin axis at least 1.25x thinner than the next (a round one has none)
# the rotation that puts local axes (t+1, t+2, t) of a frame on its local x, y, z (a cyclic turn about (1, 1, 1))
_THIN_LAST = torch.tensor([[0.5, 0.5, 0.5, 0.5], [0.5, -0.5, -0.5, -0.5], [1.0, 0.0, 0.0, 0.0]],
                          dtype=torch.float64)


@torch.no_grad()
def hold_on_planes(room: Room | None, gaussians: Gaussians, depth_factor: float = 0.5) -> dict:
    """The Gaussians of ``gaussians`` (the initialisation's) that lie flat on one of the room's bounding planes:
    the mean within the room's tolerance of the plane (inside the other planes' half-spaces) and the thinnest
    axis within 25 degrees of its normal (a thin axis: at least 1.25x thinner than the next; a round Gaussian has
    none). For the trainer's ``plane_hold``: they are turned to face the plane exactly, by the smallest turn that
    takes the thin axis onto the normal (the wide axes keep their directions in the plane), the local axes
    renamed so that the thin one is the local z, and then held so, with their mean within
    ``depth_factor`` x the tolerance of where it was along the normal (free along the plane) and their thin
    scale at most what it was. Trained free, a few of them tilted and hung 0.2-0.3 m below zoo_corridor's ceiling
    in front of its light strips (0.2 x 0.8 m, opacity 0.98): a test view looking up saw the strip at a fifth
    of its radiance, and the metal walls reflected half its light (README, forty-third session).
    Returns {"rows": [M] long, "quats": [M, 4] the turned rotations (local z = the plane's normal),
    "log_scales": [M, 3] with the thin one last (the wide ones in the order of their axes), "depth": float,
    "per_plane": [count per bounding plane]}."""
    f = dict(dtype=gaussians.dtype)
    none = {"rows": torch.zeros(0, dtype=torch.long), "quats": torch.zeros((0, 4), **f),
            "log_scales": torch.zeros((0, 3), **f), "depth": 0.0, "per_plane": []}
    if room is None or len(gaussians) == 0:
        return none
    p = gaussians.means.detach().double().cpu().numpy()
    ls = gaussians.log_scales.detach().double().cpu()
    quats = normalize_quats(gaussians.quats.detach().double().cpu())
    rot = quats_to_rotmats(quats)
    thin = ls.argmin(dim=1)
    ordered = ls.sort(dim=1).values
    flat = (ordered[:, 1] - ordered[:, 0] >= HOLD_FLAT).numpy()
    thin_axis = rot[torch.arange(len(p)), :, thin].numpy()  # [N, 3] each Gaussian's thinnest axis (a column)
    taken = np.zeros(len(p), dtype=bool)
    plane_of = np.full(len(p), -1)
    per_plane = []
    for i, (n, d, inl) in enumerate(room.bound):
        if not len(inl):  # a wall placed by room_closing.py: nothing of the initialisation's lies on it
            per_plane.append(0)
            continue
        sel = ~taken & flat & (np.abs(p @ n - d) <= room.tol) & (np.abs(thin_axis @ n) >= HOLD_COS)
        for j, (n2, d2, _) in enumerate(room.bound):
            if j != i:
                sel &= p @ n2 - d2 > -room.tol
        plane_of[sel] = i
        taken |= sel
        per_plane.append(int(sel.sum()))
    rows = np.nonzero(taken)[0]
    if not len(rows):
        return {**none, "per_plane": per_plane}
    axis = np.stack([room.bound[i][0] for i in plane_of[rows]])
    axis *= np.sign((thin_axis[rows] * axis).sum(1))[:, None]  # the normal on the side the thin axis points to
    rows_t = torch.from_numpy(rows)
    # the shortest arc from the thin axis to the normal (within 25 degrees: never opposite), after the Gaussian's
    # own rotation and the renaming of its axes that puts the thin one last
    u, v = torch.from_numpy(thin_axis[rows]), torch.from_numpy(axis)
    arc = normalize_quats(torch.cat([1 + (u * v).sum(1, keepdim=True), torch.cross(u, v, dim=1)], dim=1))
    t = thin[rows_t]
    turned = quat_multiply(arc, quat_multiply(quats[rows_t], _THIN_LAST[t]))
    perm = torch.stack([(t + 1) % 3, (t + 2) % 3, t], dim=1)
    scales = torch.gather(ls[rows_t], 1, perm)
    return {"rows": rows_t, "quats": normalize_quats(turned).to(**f), "log_scales": scales.to(**f),
            "depth": depth_factor * room.tol, "per_plane": per_plane}
