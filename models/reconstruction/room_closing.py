"""Closing the room where only curved mirrors see: walls the cameras never look at, placed by reflections.

The plane fill (plane_fill.py) covers the unseen parts of the planes the training views' buffers show, and its
box ends at the cameras. A wall that no view looks at -- the wall behind cameras that circle a group of chrome
spheres, a ceiling above the frames' top edge -- is no plane of the buffers; mirror stereo (mirror_stereo.py)
places what PLANAR mirrors show, not what spheres and other curved metal show. So that wall was the far field: a
blur at infinity, which a test view turning to it looks at (zoo_spheres: the poster wall behind the training
cameras).

A room is closed: opposite a bounding plane there is, usually, another. For each bounding plane with no
opposite one (an OPEN side, direction n), a wall facing back (normal -n) is swept along n from the box's face
outwards (``SWEEP``: 40 offsets, 2 % to 3x the room's size beyond the face, 14 % apart; with ``refine`` the chosen
minimum is then refined by a parabola through ``REFINE`` offsets over its two neighbours on each side). At each
offset the sharp mirror reflections of the training pixels (roughness < ``CLOSE_ROUGHNESS``, from the depth /
normal / F0 buffers; open through the warmed-up model) that head that way and land on the hypothetical wall
inside the other bounding planes are binned in cells on it; the radiance each brings (``specular /
Fresnel(F0)``, log luminance) is averaged per (cell, view), and the score is the spread of the views' averages
within a cell (robust: 95th-percentile clipped), relative to the spread of all of them. Where the wall really is,
rays from different views and different curved mirrors that land in one cell saw the same patch: the score has
its minimum there.
(zoo_spheres, measured: the ceiling 0.83 above the box's top, true 0.83; then the poster wall 0.27 beyond the
cameras, true 0.26.)

Sides the sharp reflections leave open (too few of them, or no clear minimum) are swept again with GLOSSY ones:
every pixel below ``GLOSSY_ROUGHNESS`` (0.4) whose F0 is above ``GLOSSY_F0`` (a varnished floor, F0 ~0.03, too).
Blurred, they still point: a ceiling whose lights the floor reflects is where the floor's reflections from
different views agree. (Checked on trained models' scenes, offline: held-out probe_338, cameras look down from
1.7-1.85 m, the ceiling is in no frame and in two small mirror cubes only: 34 open sharp reflections, no wall;
the floor at roughness 0.34 placed the ceiling 0.91 above the box, true 0.89. probe_376: 0.54, true 0.56.
zoo_thin, whose ceiling no view sees: 0.12, true 0.18. The demo keeps its sharp ceiling: with glossy reflections
in the same pass its +y side agreed best at the far edge. In training: probe_338 0.91, zoo_thin 0.15.)
Reflections with Monte Carlo noise mislead the glossy pass more than the sharp one (probe_338 at 4 spp without
the denoiser: 0.34 m low; denoised, 0.08).

A wall is placed only when the minimum is inside the sweep, holds ``MIN_SUPPORT`` (cell, view) pairs, most of the
reflections that land on it there did not pass the box's face on another side still open first
(``_past_open_sides``, ``MAX_PAST``; such a side stays open, and is not swept again in that pass), and it is at
most ``MAX_RATIO`` of the score at the far end of the sweep (the far field is the alternative: a window or an
opening, whose reflections agree best at infinity, stays open; a minimum on the sweep's far edge is logged, not
placed, and so is every side a pass leaves open, with why: too few reflections land on it, or no minimum clear
enough). The far end is the farthest offsets that still hold ``MIN_SUPPORT`` view-cells; where they end within
``SHORT_REACH`` of the room's size beyond the box, there is none to weigh the minimum against, and the wall is
placed at it, a room being closed: zoo_corridor's wall behind the cameras, seen only in two small chrome spheres
far down the corridor, whose reflections hold enough view-cells only 0.18 m past the box; its best, 0.11 (the
wall is 0.9 past it, and the far field stood for it: 22.66 -> 23.11, `test_000`, which faces it, 20.75 ->
21.69; README, fortieth session). Sides are closed
one at a time, the clearest first; each wall found bounds the next sweeps (a front wall ends at the ceiling found
before it). A wall is one Gaussian per grid point of the plane inside the other
bounds (the plane fill's spacing, coarser to fit the budget), not where a training view sees empty space, matte
(``unseen_material``: the roughness of the room's other matte Gaussians and F0 0; a guessed F0, never trained,
lit zoo_thin's closed ceiling with reflections of its window), its colour the median radiance of the 16
nearest landed reflections that show no light (lights are the highlight fill's; training refines the colour); the
points are returned so that the plane fill reaches the new wall (``extend_plane_fill``).

A side both passes leave open can still be closed behind the lights (``close_behind_lights``, after the highlight
fill): a flat-coloured ceiling that only mirror cubes show agrees at every offset (held-out probe_9164: the best
scored 0.72 of the far end's), but the ceiling lights those cubes reflect are found where their reflections meet,
and a light hangs on a wall or a ceiling."""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from models.gaussians import Gaussians

from models.pathtrace.brdf import fresnel_schlick

from .plane_fill import Room, _grid, _surfels, box_corners, open_sides
from .reflection_fill import (HIGHLIGHT_BRIGHTNESS, LUMINANCE, diffuse_level, mirror_rays, scene_box, seen_empty,
                              unseen_material)

CLOSE_ROUGHNESS = 0.15   # reflections sharp enough to say where what they show is
GLOSSY_ROUGHNESS = 0.4   # the second pass, on the sides still open: glossy reflections (blurred, but they point)
GLOSSY_F0 = 0.01         # ... of any surface that reflects at all (a varnished floor: F0 ~0.03)
MAX_RAYS = 200000        # reflections drawn per pass
SWEEP = np.geomspace(0.02, 3.0, 40)  # offsets beyond the box's face, x the room's size
CELLS = 40               # cells across the room's size on the hypothetical wall
MIN_SUPPORT = 200        # (cell, view) pairs in cells that two or more views reach
MAX_RATIO = 0.5          # the minimum's score at most this x the far end's
SHORT_REACH = 0.1        # ... unless the reflections' support ends within this x the room's size beyond the box
REFINE = 33              # offsets of the fine sweep over the coarse minimum's two neighbours on each side


def _score(x: np.ndarray, r: np.ndarray, lum: np.ndarray, view: np.ndarray, n: np.ndarray, s: float,
           bounds: list, tol: float, cell: float) -> tuple[float, int, np.ndarray]:
    """(score, support, landed mask) of the wall n . p = s for the rays x + t r: the within-cell spread of the
    views' mean log radiance relative to the spread of all (module docstring); nan without support."""
    t = (s - x @ n) / (r @ n)
    hit = x + t[:, None] * r
    ok = t > 0
    for n2, d2 in bounds:
        ok &= hit @ n2 - d2 > -tol
    if ok.sum() < 2:
        return math.nan, 0, ok
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    h = hit[ok]
    cells = np.stack([np.floor(h @ u / cell), np.floor(h @ v / cell)], 1).astype(np.int64)
    _, cell_id = np.unique(cells, axis=0, return_inverse=True)
    cell_id = cell_id.reshape(-1)
    pair, pair_id = np.unique(np.stack([cell_id, view[ok]], 1), axis=0, return_inverse=True)
    pair_id = pair_id.reshape(-1)
    count = np.bincount(pair_id)
    mean = np.bincount(pair_id, weights=lum[ok]) / count
    pair_cell = pair[:, 0]
    views_in_cell = np.bincount(pair_cell)
    cell_mean = np.bincount(pair_cell, weights=mean) / views_in_cell
    multi = views_in_cell[pair_cell] >= 2
    if not multi.any():
        return math.nan, 0, ok
    dev = (mean[multi] - cell_mean[pair_cell][multi]) ** 2
    dev = np.minimum(dev, np.quantile(dev, 0.95))
    return float(dev.mean() / max(float(lum[ok].var()), 1e-12)), int(multi.sum()), ok


def _refine(x, r, lum, view, n, s: float, offsets: np.ndarray, bounds: list, tol: float, cell: float,
            support: int) -> tuple[float, int]:
    """(offset, support): the coarse sweep's minimum ``s`` (one of ``offsets``, 14 % apart: ~10 cm at a
    ceiling 0.7 m past the box; the demo's was placed 0.11 m low) refined by the vertex of a parabola
    least-squares fitted to ``REFINE`` scores over its two neighbours on each side. Near the wall the score is flat
    within its noise (zoo_spheres' ceiling: within 7 % from 0.13 m below the true one to 0.02 above), so the fine
    sweep's own minimum would pick noise; the parabola takes the basin's middle. The coarse one stays when the fit
    does not curve up or its vertex leaves the interval."""
    i = int(np.argmin(np.abs(offsets - s)))
    lo, hi = float(offsets[max(i - 2, 0)]), float(offsets[min(i + 2, len(offsets) - 1)])
    fine = np.linspace(lo, hi, REFINE)
    scored = [_score(x, r, lum, view, n, float(f), bounds, tol, cell)[:2] for f in fine]
    value = np.array([v for v, _ in scored])
    ok = np.isfinite(value) & (np.array([sp for _, sp in scored]) >= MIN_SUPPORT)
    if ok.sum() >= 5:
        a, b, _ = np.polyfit(fine[ok], value[ok], 2)
        if a > 0 and lo <= -b / (2 * a) <= hi:
            vertex = float(-b / (2 * a))
            sup = _score(x, r, lum, view, n, vertex, bounds, tol, cell)[1]
            if sup >= MIN_SUPPORT:
                return vertex, sup
    return s, support


def _reflections(rays, trace_fn, gaussians: Gaussians, glossy: bool, seed: int) -> dict | None:
    """The open reflections a pass sweeps with: the training pixels' perfect reflections (from the depth / normal /
    F0 / roughness buffers) on the warmed-up Gaussians' side of the scene box, that leave ``gaussians``; sharp:
    mirror-like pixels below ``CLOSE_ROUGHNESS``; ``glossy``: any pixel below ``GLOSSY_ROUGHNESS`` with mean F0 above
    ``GLOSSY_F0`` (a varnished floor too). None with fewer than MIN_SUPPORT of them. The radiance each brings is
    ``specular / Fresnel(F0)`` (log luminance ``lum``); ``ordinary``: no brighter than a lit surface (module
    docstring)."""
    t = rays.targets
    select = (lambda f0, rough: (rough[..., 0] < GLOSSY_ROUGHNESS) & (f0.mean(-1) > GLOSSY_F0)) if glossy else None
    found = mirror_rays(rays, max_rays=MAX_RAYS, seed=seed + 7, select=select)
    if found is None:
        return None
    x, r, index = found
    if not glossy:
        keep = t["roughness"][index].reshape(-1) < CLOSE_ROUGHNESS
        x, r, index = x[keep], r[keep], index[keep]
    lo, hi, step = scene_box(gaussians)
    inside = ((x > lo) & (x < hi)).all(-1)
    x, r, index = x[inside], r[inside], index[inside]
    if len(index) < MIN_SUPPORT:
        return None
    open_ = trace_fn(x + step * r, r, gaussians).transmittance.reshape(-1) > 0.5
    x, r, index = x[open_], r[open_], index[open_]
    if len(index) < MIN_SUPPORT:
        return {"rays": int(len(index))}
    d = rays.dirs[index].double()
    normal = torch.nn.functional.normalize(t["normal"][index].double(), dim=-1)
    cos = (d * normal).sum(-1).abs().clamp(0.0, 1.0)
    fresnel = fresnel_schlick(t["f0"][index].double().clamp(0.0, 1.0), cos)
    radiance = (t["specular"][index].double() / fresnel.clamp_min(0.05)).clamp_min(0.0)
    lum = np.log1p((radiance @ torch.tensor(LUMINANCE, dtype=torch.float64)).numpy())
    # lights are the highlight fill's (reflection_fill.py): a wall's colour comes from the reflections no brighter
    # than HIGHLIGHT_BRIGHTNESS x the brightest lit surface the views see (a lamp on the demo's ceiling, in the
    # wall's colour and as the highlight fill's emitters too, was lit twice: its glossy box -1.5 dB)
    ordinary = np.expm1(lum) <= HIGHLIGHT_BRIGHTNESS * diffuse_level(rays, torch.Generator().manual_seed(seed))
    return {"rays": int(len(index)), "x": x.double().numpy(), "r": r.double().numpy(), "lum": lum,
            "radiance": radiance.numpy(), "ordinary": ordinary, "view": rays.view_of_ray[index].numpy()}


NEEDED = ("specular", "f0", "roughness", "normal", "depth")  # the buffers the room closing reads


def _side_name(n: np.ndarray) -> str:
    """"+y", "-z", ...: the axis a side's normal ``n`` runs along, with its sign."""
    axis = int(np.argmax(np.abs(n)))
    return ('+' if n[axis] > 0 else '-') + 'xyz'[axis]


def _sides_to_close(room: Room, corners: np.ndarray, known: np.ndarray | None) -> list:
    """The room's open sides (``open_sides``) but those ``known`` points (mirror stereo's) reach past the box's
    face: a side they reach is known, not swept (``close_room``)."""
    sides = open_sides(room)
    if known is not None and len(known) >= 10:
        sides = [n for n in sides if np.quantile(known @ n, 0.995) < (corners @ n).max() - room.tol]
    return sides


def _add_wall(room: Room, corners: np.ndarray, n: np.ndarray, s: float) -> np.ndarray:
    """The wall n . p = s joins ``room.bound``, facing back into the room; returns the box ``corners`` carried out
    to it."""
    room.bound.append((-n, -s, np.zeros(0, dtype=np.int64)))
    grown = np.concatenate([corners, corners + (s - corners @ n)[:, None] * n])
    return box_corners(grown.min(0), grown.max(0))


MAX_PAST = 0.5  # a wall needs at most this share of its landed reflections past another open side's face


def _past_open_sides(hits: np.ndarray, others: list, corners: np.ndarray, tol: float) -> tuple[str, float]:
    """(the open side most of them are past, the share of ``hits`` [M, 3] past the box's face on any side of
    ``others``, the sides still open). The sweep of a side counts every reflection that lands on its hypothetical
    wall inside the room's bounds; one that gets there only beyond another open side's face crosses that side
    first, where the room may end (a ceiling no view sees), and says nothing about this wall. Such reflections made
    held-out probe_9256's back wall, 2.96 beyond the box (the truth 0.18): heading up and back, they land on it
    4-6 m above the box's top, and in the truth meet the flat ceiling 1 m above it (README, fortieth session)."""
    if not len(hits) or not others:
        return "", 0.0
    past = np.stack([hits @ m > float((corners @ m).max()) + tol for m in others], 1)
    worst = int(np.argmax(past.sum(0)))
    return _side_name(others[worst]), float(past.any(1).mean())


def _sweep_sides(refl: dict, sides: list, room: Room, corners: np.ndarray, walls: list, described: list,
                 stats: dict, max_walls: int, label: str, refine: bool = False) -> np.ndarray:
    """Close ``sides`` (removed from the list as they close) one at a time, the clearest first, with the
    reflections ``refl``: each wall found goes to ``walls`` and joins ``room.bound``; returns the box carried out
    to the walls."""
    x, r, lum, view = refl["x"], refl["r"], refl["lum"], refl["view"]
    size = float((room.hi - room.lo).max())
    cell = size / CELLS
    undecided = {}  # side -> why this pass did not close it (its last sweep's), logged at the end
    vetoed = []  # sides whose best offset this pass found past another open side (MAX_PAST): open, not swept again
    while len(walls) < max_walls:
        best = None
        bounds = [(n, dd) for n, dd, _ in room.bound]
        for n in [m for m in sides if not any(m is v for v in vetoed)]:
            going = r @ n > 0.05
            face = float((corners @ n).max())
            offsets = face + size * SWEEP
            scores = [_score(x[going], r[going], lum[going], view[going], n, s, bounds, room.tol, cell)[:2]
                      for s in offsets]
            value = np.array([sc for sc, _ in scores])
            support = np.array([sp for _, sp in scores])
            valid = np.isfinite(value) & (support >= MIN_SUPPORT)
            where = _side_name(n)
            if valid.sum() < 5:
                undecided[where] = (f"room closing: the open side {where}{label}: too few reflections land on it to "
                                    f"sweep it ({int(valid.sum())} of {len(offsets)} offsets hold {MIN_SUPPORT} "
                                    f"view-cells, {int(going.sum())} reflections head that way): not placed")
                continue
            i = int(np.nanargmin(np.where(valid, value, np.nan)))
            last = int(np.nonzero(valid)[0][-1])
            far = float(np.nanmedian(value[np.nonzero(valid)[0][-5:]]))
            ratio = value[i] / max(far, 1e-12)
            if i >= last - 1:
                undecided[where] = (f"room closing: the open side {where} agrees best at the far edge of its "
                                    f"sweep ({SWEEP[-1]:g}x the room's size){label}: left open (the far field)")
                continue
            # the far end the minimum is weighed against is the farthest offsets that still hold enough view-cells;
            # where they end within SHORT_REACH of the room's size, there is no far end to weigh it against
            short = offsets[last] - face < SHORT_REACH * size
            if ratio > MAX_RATIO and not short:
                # the far end the minimum is weighed against is the farthest offsets that still hold enough
                # view-cells: where that support ends early, the sweep could not see its far end
                reach = (f"; the reflections hold {MIN_SUPPORT} view-cells only up to {offsets[last] - face:.2f} "
                         f"beyond the box, of the sweep's {offsets[-1] - face:.2f}" if last < len(offsets) - 5 else "")
                undecided[where] = (f"room closing: the open side {where}{label}: no clear minimum (the best, "
                                    f"{offsets[i] - face:.2f} beyond the box, scores {ratio:.2f} of the far end's; "
                                    f"a wall needs at most {MAX_RATIO:g}{reach}): not placed")
                continue
            undecided.pop(where, None)
            if best is None or ratio < best[0]:
                best = (ratio, n, float(offsets[i]), face, where, int(support[i]),
                        float(offsets[last] - face) if short else None)
        if best is None:
            break
        ratio, n, s, face, where, support, reached = best  # (a candidate: its side's note was dropped above)
        others = [m for m in sides if m is not n]  # every side still open, those vetoed included
        going = r @ n > 0.05
        if refine:
            s, support = _refine(x[going], r[going], lum[going], view[going], n, s, face + size * SWEEP, bounds,
                                 room.tol, cell, support)
        _, _, landed = _score(x[going], r[going], lum[going], view[going], n, s, bounds, room.tol, cell)
        tt = (s - x[going] @ n) / (r[going] @ n)
        past, share = _past_open_sides(x[going][landed] + tt[landed, None] * r[going][landed], others, corners,
                                       room.tol)
        if share > MAX_PAST:
            undecided[where] = (f"room closing: the open side {where}{label}: the best, {s - face:.2f} beyond the "
                                f"box, is where {share:.0%} of the reflections that land on it have passed the "
                                f"box's face on the open side {past} first, where the room may end: not placed")
            vetoed.append(n)
            continue
        sides[:] = others
        keep = landed & refl["ordinary"][going]
        points = (x[going] + tt[:, None] * r[going])[keep]
        colours = refl["radiance"][going][keep]
        if len(points) < 16:
            points, colours = (x[going] + tt[:, None] * r[going])[landed], refl["radiance"][going][landed]
        walls.append((n, s, points, colours))
        corners = _add_wall(room, corners, n, s)
        described.append(f"{where} at {s - face:.2f} beyond the box ({support} view-cells, score {ratio:.2f} of "
                         f"the far end's{label})" if reached is None else
                         f"{where} at {s - face:.2f} beyond the box ({support} view-cells{label}; the reflections "
                         f"reach {reached:.2f} beyond it, no far end to weigh it against: a room is closed)")
    stats["notes"] += [undecided[k] for k in sorted(undecided)]
    return corners


@torch.no_grad()
def close_room(room: Room | None, rays, trace_fn, gaussians: Gaussians, count: int = 20000, opacity: float = 0.9,
               known: np.ndarray | None = None, max_walls: int = 3, seed: int = 0,
               dtype=torch.float32, refine: bool = False) -> tuple[Gaussians | None, np.ndarray | None, dict]:
    """Walls on the room's open sides where sharp reflections agree on them, then, on the sides still open, where
    glossy ones do (module docstring). ``room``: the plane fill's (its bounding planes grow by the walls placed);
    ``gaussians``: the warmed-up scene with what the other fills placed (which reflections are still open);
    ``known``: points mirror stereo placed (a side they reach, the box's face there set by them, is known: not
    swept -- an object seen only in a planar mirror made its depth the sweep's minimum, and a wall across the whole
    room there: mirror_book's book). ``refine``: each wall's offset refined past the coarse sweep (``_refine``;
    ``reconstruct.close_room_refine``). Returns (Gaussians or None, the walls' points [M, 3] or None, statistics:
    ``walls`` (a description), ``added``, ``rays`` (the sharp pass's open reflections), ``glossy_rays`` (the glossy
    pass's; 0 when it did not run), ``notes``)."""
    stats = {"walls": "none", "added": 0, "rays": 0, "glossy_rays": 0, "notes": []}
    t = rays.targets
    if room is None or not all(k in t for k in NEEDED):
        return None, None, stats
    corners = box_corners(room.lo, room.hi)
    sides = _sides_to_close(room, corners, known)
    walls, described = [], []
    for glossy in (False, True):
        if not sides or len(walls) >= max_walls:
            break
        refl = _reflections(rays, trace_fn, gaussians, glossy, seed)
        if refl is not None:
            stats["glossy_rays" if glossy else "rays"] = refl["rays"]
        if refl is None or "x" not in refl:
            continue
        corners = _sweep_sides(refl, sides, room, corners, walls, described, stats, max_walls,
                               ", glossy reflections" if glossy else "", refine=refine)
    if not walls:
        return None, None, stats
    stats["walls"] = "; ".join(described)
    fill, points = _wall_gaussians(walls, room, rays, corners, gaussians, count, opacity, dtype)
    if fill is None:
        return None, None, stats
    stats["added"] = len(fill)
    return fill, points, stats


def _wall_gaussians(walls: list, room: Room, rays, corners: np.ndarray, gaussians: Gaussians, count: int,
                    opacity: float, dtype) -> tuple[Gaussians | None, np.ndarray | None]:
    """The Gaussians of the walls placed (``walls``: (n, s, landed points, their colours) each, already among
    ``room.bound``): one per grid point of each wall inside the room's box carried out to the walls (``corners``)
    and the other bounds, not where a training view sees empty space, matte (``unseen_material``), coloured by the
    median radiance of the 16 nearest landed reflections; the grid coarsens from ``room.h`` to fit ``count``.
    Returns (Gaussians, their centres [M, 3]) or (None, None)."""
    bounds = [(n, dd) for n, dd, _ in room.bound]
    h = room.h
    for _ in range(4):  # the grid coarsens until the walls fit the budget
        grids = []
        for n, s, _, _ in walls:
            # the room's box carried out to every wall, then the other bounds
            g = _grid(n, s, corners.min(0) - room.tol, corners.max(0) + room.tol, h)
            keep = np.ones(len(g), dtype=bool)
            for n2, d2 in bounds:
                keep &= g @ n2 - d2 > -room.tol
            g = g[keep]
            if len(g):
                g = g[~seen_empty(torch.from_numpy(g), rays.views).numpy()]
            grids.append(g)
        if sum(len(g) for g in grids) <= count:
            break
        h *= math.sqrt(sum(len(g) for g in grids) / count) * 1.05
    parts, all_points = [], []
    rough, f0 = unseen_material(gaussians)  # the room's matte roughness, F0 0 (reflection_fill.unseen_material)
    for (n, s, points, colours), g in zip(walls, grids):
        if not len(g):
            continue
        k = min(16, len(points))
        _, near = cKDTree(points).query(g, k=k)
        colour = np.median(colours[np.asarray(near).reshape(len(g), k)], axis=1)
        parts.append(_surfels(g, -n, h, opacity, colour, rough, f0, dtype))
        all_points.append(g)
    if not parts:
        return None, None
    return Gaussians.cat(parts), np.concatenate(all_points)


MIN_LIGHTS = 20  # close_behind_lights: emitters of the highlight fill on an open side needed to place a wall there


@torch.no_grad()
def close_behind_lights(room: Room | None, rays, trace_fn, gaussians: Gaussians, lights: np.ndarray,
                        count: int = 20000, opacity: float = 0.9, known: np.ndarray | None = None, seed: int = 0,
                        dtype=torch.float32) -> tuple[Gaussians | None, np.ndarray | None, dict]:
    """Walls just behind the lights on the sides ``close_room`` left open. A light is mounted on a wall or a
    ceiling: where the highlight fill (reflection_fill.highlight_fill_gaussians) found the lights the cameras see
    only in mirrors (``lights`` [K, 3]: its emitters, on the box it scaled until their reflections met), a side of
    the room that the sweep could not close -- a flat-coloured ceiling, shown only by mirror cubes' tops: every
    offset agrees as well as any other -- is closed one grid spacing behind the emitters on it (at least
    ``MIN_LIGHTS`` of them within 3 tolerances of their farthest on that side, beyond the box). Without it that
    ceiling was the far field and the cubes' tops reflected its blur (held-out probe_9164, README). The wall is
    ``close_room``'s (matte, unseen material), coloured by the ordinary open reflections (sharp, else glossy) that
    land on it. ``known``: as ``close_room``'s. Call it only with a box scale found inside its search (a light on
    the search's edge sits on the box for want of a better place, not where it is). Returns (Gaussians or None, the
    walls' points or None, {"walls": description, "added", "notes"})."""
    stats = {"walls": "none", "added": 0, "notes": []}
    t = rays.targets
    if room is None or lights is None or len(lights) < MIN_LIGHTS or not all(k in t for k in NEEDED):
        return None, None, stats
    lights = np.asarray(lights, dtype=np.float64)
    corners = box_corners(room.lo, room.hi)
    cell = float((room.hi - room.lo).max()) / CELLS  # as close_room's sweep
    walls, described, refl = [], [], {}
    for n in _sides_to_close(room, corners, known):
        where = _side_name(n)
        face = float((corners @ n).max())
        proj = lights @ n
        on = proj >= proj.max() - 3 * room.tol
        if on.sum() < MIN_LIGHTS or proj.max() <= face + room.tol:
            continue
        s = float(proj[on].max()) + room.h
        bounds = [(m, dd) for m, dd, _ in room.bound]
        points = colours = None
        for glossy in (False, True):
            if glossy not in refl:
                refl[glossy] = _reflections(rays, trace_fn, gaussians, glossy, seed)
            r = refl[glossy]
            if r is None or "x" not in r:
                continue
            going = r["r"] @ n > 0.05
            _, _, landed = _score(r["x"][going], r["r"][going], r["lum"][going], r["view"][going], n, s, bounds,
                                  room.tol, cell)
            tt = (s - r["x"][going] @ n) / (r["r"][going] @ n)
            hit = r["x"][going] + tt[:, None] * r["r"][going]
            keep = landed & r["ordinary"][going]
            if keep.sum() >= 16:
                points, colours = hit[keep], r["radiance"][going][keep]
                break
            if landed.sum() >= 16 and points is None:
                points, colours = hit[landed], r["radiance"][going][landed]
        if points is None:
            stats["notes"].append(f"room closing behind the lights: the open side {where}: {int(on.sum())} "
                                  "emitters on it, but too few reflections land there to colour a wall: not placed")
            continue
        walls.append((n, s, points, colours))
        corners = _add_wall(room, corners, n, s)
        described.append(f"{where} at {s - face:.2f} beyond the box, behind {int(on.sum())} of the highlight "
                         f"fill's emitters ({len(points)} reflections colour it)")
    if not walls:
        return None, None, stats
    stats["walls"] = "; ".join(described)
    fill, points = _wall_gaussians(walls, room, rays, corners, gaussians, count, opacity, dtype)
    if fill is None:
        return None, None, stats
    stats["added"] = len(fill)
    return fill, points, stats


def _bound_planes(room: Room | None, shown: bool) -> list:
    """The room's bounding planes the buffers show (``shown``) or the walls ``close_room`` placed (not shown) as
    (n, s): n . p = s one grid spacing on the room's side of the plane, n pointing out of the room; [] without a
    room."""
    if room is None:
        return []
    return [(-np.asarray(m, dtype=np.float64), -float(d) - room.h) for m, d, inl in room.bound
            if bool(len(inl)) == shown]


def placed_walls(room: Room | None) -> list:
    """The walls ``close_room`` placed, as (n, s) (``_bound_planes``), where ``keep_inside`` leaves the lights
    beyond them."""
    return _bound_planes(room, shown=False)


def shown_planes(room: Room | None) -> list:
    """The room's bounding planes the buffers show, in ``placed_walls``' form (the highlight fill reports emitters
    the sweep left beyond them)."""
    return _bound_planes(room, shown=True)


def keep_inside(points: torch.Tensor, room: Room | None) -> int:
    """Moves ``points`` [N, 3] (in place) that lie beyond a wall ``close_room`` placed onto the room's side of it,
    one grid spacing in front of it; returns how many moved. The highlight fill puts the lights seen only in
    mirrors where their reflections end together, on a box it scales: above a ceiling closed later they were
    hidden behind it (the demo's lamp, 2.49 m up, under a ceiling found at 2.47: its mirror-ball view lost 2.7 dB)."""
    if room is None or not len(points):
        return 0
    moved = torch.zeros(len(points), dtype=torch.bool, device=points.device)
    for n, s in placed_walls(room):  # (a plane the buffers show is not one: the highlight rays were open through it)
        n = torch.tensor(n, dtype=points.dtype, device=points.device)
        beyond = points @ n - s
        out = beyond > 0
        points[out] -= beyond[out, None] * n
        moved |= out
    return int(moved.sum())
