"""Objects seen only in planar mirrors, placed by multi-view stereo on their reflections.

A training camera that looks into a planar mirror sees the room behind it as a *virtual* camera, its
reflection about the mirror's plane, would see it directly. So the reflected images of several views are an
ordinary multi-view capture of the part of the scene no camera faces, and a plane sweep finds its depth: for
each open mirror pixel of a reference view (a mirror-like pixel, F0 > 0.3 and roughness < 0.3, whose perfect
reflection leaves the warmed-up Gaussians), candidate points along its reflected ray are reflected about each
other view's mirror plane and projected into that view; where that view sees them in its own open mirror
pixels, the colours of the two reflections (``specular / F0``) are compared. At the object's true depth
they agree in every view that sees it; elsewhere the other views look at different texture. Per pixel, the
cost at each depth is the mean of the other views' relative colour differences (or of their better
``best_fraction``, robust to occlusion but less decisive: on mirror_book at ``ratio`` 0.8, 0.5 kept 132
points on the book where all views kept 410), averaged over a small window of the reference image (textures
match as patches, not pixels). The depth kept is the best one when it is clearly better than every depth
outside its basin (``ratio``), good in itself (``max_cost``), localised (its basin under ``max_basin`` of
the sweep) and textured (``min_contrast``): flat colour has no clear best and adds nothing. Depths that a
training camera sees to be empty (``seen_empty``) are not candidates, nor are those that fewer than ``min_share``
of the other mirrors see (and at least 3; the trainer's ``mirror_stereo_min_share``, 0.3: 6 of 19 other mirrors
in a 20-view room; at 3 zoo_mirror_metal placed ~20 % more stereo Gaussians and its test view from behind the
cameras saw more haze: README, "Tried at a5aa806"). A share, not a count: a capture with fewer views of its mirror
keeps its stereo. A share of the other VIEWS, not of the other mirror planes: the faces of a chrome cube are
mirrors too (probe_mirror_21: 51 planes in 20 views), and counted over planes the rule asked 15 views where at most
the 19 other views of the wall mirror see a depth; only depths just in front of the mirror, which nearly all of
them see, stayed candidates, and the ceiling seen in the mirror was matched 3 m too near (floaters in the room).

The mirrors then check each other (``depth_votes``): a kept point, reflected about another mirror and projected
into its view, lands on that mirror's own kept depth (agrees), on a depth well beyond it (that mirror's
reflection passes through the point: it lies in the air), or on nothing. A point stays when at least
``min_agree`` other mirrors agree and no more see through it than agree. A match in the air is made where
one view's reflected texture happens to line up with others' at a wrong depth (and ``complete_flat`` spreads
it over flat neighbours); such points are rarely consistent with the other views' own depths. They matter:
only the mirrors constrain that space, training grows them into large half-transparent Gaussians, and a
test view that looks at the space directly sees haze in front of the wall (on zoo_mirror_metal the check
drops ~9 % of the matches, 231 of 13,800 clearly in the air before it, ~3 after).

Each kept pixel gives one matte Gaussian there: the reflection's colour as diffuse colour, the size of a pixel
at its virtual distance. The unit is a MIRROR, not a view: a view's mirror-like pixels are split into smooth
connected regions (``planar_components``), and each region whose points and normals fit one plane is a
mirror with its own virtual camera (its least-squares plane). Curved reflectors (a metal cylinder beside the
mirror) and other mirrors in the frame are separate regions: they are ignored, or used as mirrors of their
own, and never switch a view's mirror off.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch
from scipy.ndimage import uniform_filter

from models.gaussians import Gaussians

from .reflection_fill import (LUMINANCE, box_exit, matte_gaussians, scene_box, seen_empty, shiny,
                              unseen_material)

log = logging.getLogger(__name__)


class MirrorView:
    """One training view's planar mirror: its open mirror pixels, their mirror points, normals, reflected
    directions and reflected colours, and the plane (unit normal towards the camera, offset; set by
    ``mirror_views`` once fitted)."""

    def __init__(self, view, open_mask: np.ndarray):
        b, cam = view.buffers, view.camera
        self.camera = cam
        self.open = open_mask  # [H, W] bool
        d = cam.ray_directions()
        n = b["normal"] / np.maximum(np.linalg.norm(b["normal"], axis=-1, keepdims=True), 1e-12)
        self.normals = n  # [H, W, 3] unit, per pixel
        self.points = cam.origin + d * b["depth"]  # [H, W, 3]
        self.dirs = d - 2 * (d * n).sum(-1, keepdims=True) * n
        self.dirs /= np.maximum(np.linalg.norm(self.dirs, axis=-1, keepdims=True), 1e-12)
        self.colour = b["specular"] / np.maximum(b["f0"], 0.05)
        self.distance = b["depth"][..., 0]  # camera to mirror
        self.normal, self.offset = np.zeros(3), 0.0

    def look_up(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(valid [N] bool, colour [N, 3]): where this view sees ``points`` [N, 3] in its open mirror pixels
        (the point in front of the mirror, its reflection about the plane projected into the camera), and the
        reflected colour there, bilinear between the four nearest pixel centres (all four open)."""
        side = points @ self.normal - self.offset
        virtual = points - 2 * side[:, None] * self.normal
        u, v, z = self.camera.project(virtual)
        h, w = self.open.shape
        u, v = u - 0.5, v - 0.5  # pixel centres at integers
        c0, r0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        valid = (side > 0) & (z > 0) & (c0 >= 0) & (c0 < w - 1) & (r0 >= 0) & (r0 < h - 1)
        c0, r0 = np.where(valid, c0, 0), np.where(valid, r0, 0)
        fu, fv = (u - c0)[:, None], (v - r0)[:, None]
        colour = np.zeros((len(points), 3))
        for dr, dc, wt in ((0, 0, (1 - fu) * (1 - fv)), (0, 1, fu * (1 - fv)), (1, 0, (1 - fu) * fv), (1, 1, fu * fv)):
            valid &= self.open[r0 + dr, c0 + dc]
            colour += wt * self.colour[r0 + dr, c0 + dc]
        return valid, colour


def fit_plane(points: np.ndarray, towards: np.ndarray, tol: float) -> tuple[np.ndarray, float] | None:
    """(unit normal facing ``towards``, offset) of the least-squares plane through ``points`` [N, 3], or None
    when the 99th percentile of their distances to it exceeds ``tol`` (not one plane) or N < 3."""
    if len(points) < 3:
        return None
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    if np.quantile(np.abs((points - c) @ n), 0.99) > tol:
        return None
    if (towards - c) @ n < 0:
        n = -n
    return n, float(n @ c)


def planar_components(points: np.ndarray, normals: np.ndarray, mask: np.ndarray, min_pixels: int,
                      edge_deg: float = 8.0, slope: float = 0.2) -> list[np.ndarray]:
    """The connected regions of ``mask`` [H, W] whose neighbouring pixels continue one smooth surface: normals
    [H, W, 3] within ``edge_deg`` of each other and the step between their points [H, W, 3] within ``slope``
    (rise over run) of the first one's tangent plane (a depth jump, e.g. to an object in front of the mirror,
    cuts the region). Each region with at least ``min_pixels`` pixels is returned as a mask; whether it is a
    PLANE is decided by its caller (a curved reflector forms one smooth region too)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    h, w = mask.shape
    index = np.arange(h * w).reshape(h, w)
    cos_edge = math.cos(math.radians(edge_deg))
    rows, cols = [], []
    for a, b in (((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                 ((slice(None, -1), slice(None)), (slice(1, None), slice(None)))):
        step = points[b] - points[a]
        run = np.linalg.norm(step, axis=-1)
        ok = mask[a] & mask[b] & ((normals[a] * normals[b]).sum(-1) > cos_edge)
        ok &= np.abs((normals[a] * step).sum(-1)) <= slope * run
        rows.append(index[a][ok]), cols.append(index[b][ok])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(h * w, h * w))
    _, label = connected_components(graph, directed=False)
    label = np.where(mask.reshape(-1), label, -1)
    ids, counts = np.unique(label[label >= 0], return_counts=True)
    return [(label == i).reshape(h, w) for i in ids[counts >= min_pixels]]


def _width_px(region: np.ndarray) -> float:
    """The narrow extent of an image region: the smaller standard deviation of its pixel coordinates (a strip
    w pixels wide has ~w / 3.5)."""
    rows, cols = np.nonzero(region)
    return float(np.sqrt(max(np.linalg.eigvalsh(np.cov(np.stack([rows, cols]).astype(np.float64)))[0], 0.0)))


def mirror_views(rays, trace_fn, gaussians: Gaussians, min_pixels: int = 64, open_transmittance: float = 0.5,
                 max_normal_deg: float = 10.0, min_width_px: float = 2.0) -> tuple[list[MirrorView], dict]:
    """Every planar mirror of every training view, as a ``MirrorView`` (one view may give several: one per
    mirror). A view's mirror-like pixels are split into smooth connected regions (``planar_components``); a
    region of at least ``min_pixels`` pixels, not a strip (``min_width_px``: the smaller standard deviation of
    its pixel coordinates), is a planar mirror when its points lie on their least-squares plane
    and at least nine tenths of its normals are within ``max_normal_deg`` of that plane's normal. Curved
    reflectors (a metal cylinder, a sphere) and small regions are ignored without affecting the view's other
    regions. Views without the buffers take no part. Statistics: planes, views with a plane, pixels used,
    regions ignored, and a per-view list (for the log)."""
    lo, hi, step = scene_box(gaussians)
    need = ("depth", "normal", "f0", "roughness", "specular")
    tol = float((hi - lo).sum()) * 2e-3
    cos_max = math.cos(math.radians(max_normal_deg))
    out: list[MirrorView] = []
    stats = {"planes": 0, "planar_views": 0, "pixels": 0, "ignored": 0, "per_view": []}
    for v, view in enumerate(rays.views):
        b = view.buffers
        if not all(k in b for k in need):
            continue
        hit = b["mask"][..., 0] > 0.5 if "mask" in b else b["depth"][..., 0] > 0
        shiny_px = hit & shiny(b["f0"], b["roughness"])
        if shiny_px.sum() < min_pixels:
            continue
        cam = view.camera
        whole = MirrorView(view, shiny_px)
        planes = []
        for region in planar_components(whole.points, whole.normals, shiny_px, min_pixels):
            if _width_px(region) < min_width_px:  # a strip (one column of a cylinder): no stereo in it
                stats["ignored"] += 1
                continue
            plane = fit_plane(whole.points[region], cam.origin, tol=tol)
            # the normals must agree with the plane: they say curved where the points look flat
            if plane is None or np.quantile(np.abs(whole.normals[region] @ plane[0]), 0.1) < cos_max:
                stats["ignored"] += 1
                continue
            mv = MirrorView(view, region)
            mv.normal, mv.offset = plane
            if trace_fn is not None:
                x = torch.from_numpy(mv.points[region]).float()
                r = torch.from_numpy(mv.dirs[region]).float()
                t = trace_fn(x + step * r, r, gaussians).transmittance.reshape(-1).numpy()
                mv.open = np.zeros_like(region)
                mv.open[region] = t > open_transmittance
            planes.append(mv)
        if planes:
            pixels = [int(m.open.sum()) for m in planes]
            stats["per_view"].append((v, len(planes), sum(pixels)))
            stats["planes"] += len(planes)
            stats["planar_views"] += 1
            stats["pixels"] += sum(pixels)
            out.extend(planes)
    for v, n, px in stats["per_view"]:
        log.info("mirror stereo: view %d, %d mirror plane(s), %d open mirror pixels", v, n, px)
    return out, stats


def complete_flat(best: np.ndarray, keep: np.ndarray, agg: np.ndarray, pix: np.ndarray, shape: tuple[int, int],
                  max_cost: float, radius: int, min_support: int = 6, max_spread: float = 2.0) -> np.ndarray:
    """Depth indices [P] (-1: none) for the open mirror pixels the sweep could not decide (flat colour matches at
    every depth) from the decided ones around them: the median depth index of the kept pixels within
    ``radius`` pixels of the reference image, taken where at least ``min_support`` of them agree (their spread,
    median absolute deviation, at most ``max_spread`` sweep planes; across an occlusion edge they do not) and
    the other views' colours agree at that depth too (aggregated cost < ``max_cost``). Walls seen only in a
    mirror are mostly flat: without this they stay holes wherever they lack texture."""
    h, w = shape
    fill = np.full(len(pix), -1, dtype=np.int64)
    if not keep.any() or keep.all():
        return fill
    ys, xs = np.divmod(pix, w)
    grid = np.full((h + 2 * radius, w + 2 * radius), -1, dtype=np.int64)  # padded: -1 = no decided pixel
    grid[ys[keep] + radius, xs[keep] + radius] = best[keep]
    windows = np.lib.stride_tricks.sliding_window_view(grid, (2 * radius + 1, 2 * radius + 1))
    big = np.iinfo(np.int64).max
    for part in np.array_split(np.nonzero(~keep)[0], max(1, -(-int((~keep).sum()) // 4096))):
        near = windows[ys[part], xs[part]].reshape(len(part), -1)  # [U, (2r+1)^2] the patch around each pixel
        valid = near >= 0
        n = valid.sum(1)
        ok = n >= min_support
        k = _masked_median(np.where(valid, near, big), n).astype(np.int64)  # int(np.median(near)): floor
        spread = _masked_median(np.where(valid, np.abs(near - k[:, None]), big), n)
        ok &= spread <= max_spread
        rows = part[ok]
        good = agg[rows, k[ok]] < max_cost
        fill[rows[good]] = k[ok][good]
    return fill


def _masked_median(values: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Per row, the median (np.median's: the mean of the middle two for an even count) of its first ``n``
    values after sorting; the masked-out entries hold the dtype's maximum, so they sort last. 0 where n = 0."""
    s = np.sort(values, axis=1)
    rows = np.arange(len(s))
    lo = s[rows, np.maximum(n - 1, 0) // 2].astype(np.float64)
    hi = s[rows, np.maximum(n, 1) // 2].astype(np.float64)
    return np.where(n > 0, np.where(n % 2 == 1, lo, (lo + hi) / 2), 0.0)


def grow_run(agg: np.ndarray, start: np.ndarray, step_ok) -> tuple[np.ndarray, np.ndarray]:
    """(first [P], last [P]) plane indices of the run of planes round ``start`` [P] in each row of the costs
    ``agg`` [P, K]: grown outwards one plane at a time on each side while ``step_ok(cost of the next plane [P],
    cost of the run's current end [P])`` holds (an elementwise bool array)."""
    rows, last = np.arange(len(start)), agg.shape[1] - 1
    left, right = start.copy(), start.copy()
    for _ in range(agg.shape[1]):
        step_l = (left > 0) & step_ok(agg[rows, np.maximum(left - 1, 0)], agg[rows, left])
        step_r = (right < last) & step_ok(agg[rows, np.minimum(right + 1, last)], agg[rows, right])
        if not (step_l.any() or step_r.any()):
            break
        left, right = left - step_l, right + step_r
    return left, right


def sweep_view(ref: MirrorView, others: list[MirrorView], views, lo: np.ndarray, hi: np.ndarray, t_min: float,
               depths: int = 96, window: int = 2, min_views: int = 3, ratio: float = 0.9,
               max_cost: float = 0.2, best_fraction: float = 1.0, min_contrast: float = 0.1,
               max_basin: float = 0.4, complete_radius: int = 6,
               plane_slack: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int, int,
                                                  np.ndarray, np.ndarray, np.ndarray]:
    """Plane sweep of one reference view's open mirror pixels (module docstring). Returns the kept pixels'
    (points [M, 3], colours [M, 3], virtual distances [M], reflected directions [M, 3]), how many otherwise
    clear pixels were dropped because their best depth lies on the edge of the swept range, and how many of
    the kept ones are flat pixels completed from their decided neighbours (``complete_flat`` within
    ``complete_radius`` pixels; 0 turns it off), the kept pixels' flat indices into the reference image, and
    [M, 2] the stretch of the reflected ray round each kept point (distances along it from the point, <= 0 and
    >= 0) over which the sweep cannot tell the depth from the one it chose: the run of swept planes round the
    chosen one whose aggregated cost is at most (1 + ``plane_slack``) x its own, out to half-way to the next plane
    (0: just that half-way). A flat wall seen at 5-6 m of virtual distance matches over many planes (zoo_mirror_metal:
    stereo depths scattered 30 cm in front of its front wall, the cost at the wall within 3 % of the best for
    most of them); a textured object near a wall does not (zoo_mirror_only's urn, 4-10 cm above the floor: the
    cost on the floor 1.13-1.5x the best); last, [M] bool: matched by its own texture (not completed)."""
    h, w = ref.open.shape
    pix = np.nonzero(ref.open.reshape(-1))[0]
    x = ref.points.reshape(-1, 3)[pix]
    r = ref.dirs.reshape(-1, 3)[pix]
    s0 = ref.distance.reshape(-1)[pix]
    t_max = box_exit(torch.from_numpy(x), torch.from_numpy(r), torch.from_numpy(lo), torch.from_numpy(hi)).numpy()
    t_max = np.maximum(t_max, 2 * t_min)
    # uniform in inverse virtual distance (uniform disparity for the virtual cameras)
    k = np.linspace(0.0, 1.0, depths)
    inv = 1 / (s0 + t_min)[:, None] + k[None, :] * (1 / (s0 + t_max) - 1 / (s0 + t_min))[:, None]
    t = 1 / inv - s0[:, None]  # [P, K]
    pts = (x[:, None, :] + t[..., None] * r[:, None, :]).reshape(-1, 3)
    colour = np.repeat(ref.colour.reshape(-1, 3)[pix], depths, axis=0)
    costs = []
    for other in others:
        valid, c = other.look_up(pts)
        diff = np.abs(c - colour).sum(-1) / np.maximum((c + colour).sum(-1), 0.03)
        costs.append(np.where(valid, diff, np.inf))
    costs = np.sort(np.stack(costs), axis=0)  # [U, P*K], invalid (inf) last
    n_valid = np.isfinite(costs).sum(0)
    m = np.maximum(min_views, np.ceil(n_valid * best_fraction)).astype(np.int64)
    cum = np.cumsum(np.where(np.isfinite(costs), costs, 0.0), axis=0)
    cost = cum[np.minimum(m, len(costs)) - 1, np.arange(costs.shape[1])] / m
    cost[(n_valid < min_views) | seen_empty(torch.from_numpy(pts), views).numpy()] = np.nan
    # window aggregation over the reference image (mean of the valid costs around each pixel, per depth)
    grid = np.full((h * w, depths), np.nan)
    grid[pix] = cost.reshape(-1, depths)
    grid = grid.reshape(h, w, depths)
    ok = np.isfinite(grid)
    size = (2 * window + 1, 2 * window + 1, 1)
    total = uniform_filter(np.where(ok, grid, 0.0), size=size, mode="constant")
    count = uniform_filter(ok.astype(np.float64), size=size, mode="constant")
    agg = np.where(ok & (count > 0), total / np.maximum(count, 1e-12), np.inf).reshape(h * w, depths)[pix]
    best = np.argmin(agg, axis=1)
    rows = np.arange(len(pix))
    c1 = agg[rows, best]
    # the basin of the best depth: outwards from it while the cost does not fall; c2 = best cost outside it
    left, right = grow_run(agg, best, lambda nxt, cur: nxt >= cur)
    k = np.arange(depths)[None, :]
    c2 = np.where((k < left[:, None]) | (k > right[:, None]), agg, np.inf).min(1)
    # texture: the relative spread of the reflected luminance over the window (flat colour matches anywhere)
    lum = np.where(ref.open, ref.colour @ np.array(LUMINANCE), 0.0)
    n = np.maximum(uniform_filter(ref.open.astype(np.float64), size=size[:2]), 1e-12)
    mean = uniform_filter(lum, size=size[:2]) / n
    var = uniform_filter(lum ** 2, size=size[:2]) / n - mean ** 2
    contrast = (np.sqrt(np.maximum(var, 0.0)) / np.maximum(mean, 1e-6)).reshape(-1)[pix]
    keep = np.isfinite(c2) & (c1 < max_cost) & (c1 < ratio * c2) & (contrast > min_contrast)
    keep &= (right - left) <= max_basin * depths
    # a best depth on the sweep's first or last plane is not a minimum (the surface may lie beyond): not kept
    edge = keep & ((best == 0) | (best == depths - 1))
    keep &= ~edge
    matched = keep.copy()  # by their own texture (before the completion below)
    filled = 0
    if complete_radius > 0:
        fill = complete_flat(best, keep, agg, pix, (h, w), max_cost, complete_radius)
        fill[edge] = -1
        completed = fill >= 0
        filled = int(completed.sum())
        best = np.where(completed, fill, best)
        keep |= completed
    lo_k, hi_k = best.copy(), best.copy()
    if plane_slack > 0:
        limit = (1 + plane_slack) * agg[rows, best]
        lo_k, hi_k = grow_run(agg, best, lambda nxt, cur: nxt <= limit)
    tb = t[rows, best]
    span = np.stack([(t[rows, np.maximum(lo_k - 1, 0)] + t[rows, lo_k]) / 2 - tb,
                     (t[rows, np.minimum(hi_k + 1, depths - 1)] + t[rows, hi_k]) / 2 - tb], axis=1)
    tk = tb[keep]
    return (x[keep] + tk[:, None] * r[keep], ref.colour.reshape(-1, 3)[pix][keep], (s0[keep] + tk), r[keep],
            int(edge.sum()), filled, pix[keep], span[keep], matched[keep])


def depth_votes(points: np.ndarray, view: MirrorView, depth: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(agree [N] bool, through [N] bool) for ``points`` [N, 3] against another mirror's stereo depths ``depth``
    [H, W] (the path length camera -> mirror -> surface at its kept pixels, NaN elsewhere): the point, reflected
    about that mirror and projected, lands on a kept pixel whose depth is its own within the relative ``tol``
    (agree), or well beyond it (through: that view's reflection passes through the point, so it is empty)."""
    side = points @ view.normal - view.offset
    virtual = points - 2 * side[:, None] * view.normal
    u, v, z = view.camera.project(virtual)
    h, w = depth.shape
    c, r = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    inside = (side > 0) & (z > 0) & (c >= 0) & (c < w) & (r >= 0) & (r < h)
    d = np.full(len(points), np.nan)
    d[inside] = depth[r[inside], c[inside]]
    own = np.linalg.norm(virtual - view.camera.origin, axis=-1)
    ok = np.isfinite(d)
    agree = ok & (np.abs(d - own) <= tol * own)
    through = ok & (d > (1 + tol) * own)
    return agree, through


@torch.no_grad()
def mirror_stereo_gaussians(rays, trace_fn, gaussians: Gaussians, count: int = 6000, far_scale: float = 3.0,
                            opacity: float = 0.3, seed: int = 0, dtype=torch.float32, min_agree: int = 1,
                            agree_tol: float = 0.03, min_share: float = 0.0, plane_slack: float = 0.0,
                            **sweep) -> tuple[Gaussians | None, dict]:
    """Up to ``count`` Gaussians where the plane sweep of every planar mirror (of every view) finds a clear depth
    (module docstring); ``min_share`` > 0: a depth needs that share of the other views (at least 3) to see it.
    Candidates lie between the mirror and where the reflected ray leaves the cube about
    the centre of the current Gaussians' box, ``far_scale`` times its largest side (an object seen only in a
    mirror may lie well outside the box of what the cameras see directly). ``trace_fn(origins, dirs,
    gaussians)`` decides which reflections are open (None: all are). ``plane_slack``: see ``sweep_view``.
    Returns (Gaussians or None, statistics for the log); the statistics' "along" is, per returned Gaussian, (the
    direction [N, 3] of the reflected ray that found it, the stretch [N, 2] of that ray round it the sweep
    cannot tell from it: ``sweep_view``), for ``plane_fill.stereo_on_planes``; its "rays" is, per consistent match
    made by its own texture (placed or not; not the flat pixels completed from their neighbours), (the mirror
    point [M, 3], the reflected direction [M, 3], the distance [M] along it that is free: to the match less the
    stretch in front of it), for the trainer's stereo depth loss."""
    usable, stats = mirror_views(rays, trace_fn, gaussians)
    stats.update(kept=0, added=0, edge=0, completed=0, inconsistent=0)
    if len(usable) < 2 or count <= 0:
        return None, stats
    lo, hi, step = scene_box(gaussians)
    centre, half = (lo + hi) / 2, far_scale * float((hi - lo).max()) / 2
    lo, hi = (centre - half).double().numpy(), (centre + half).double().numpy()
    pos, colour, dist, fl, seen_along, spans, depth, start, matched = [], [], [], [], [], [], [], [], []
    own_all = []
    for i, ref in enumerate(usable):
        others = usable[:i] + usable[i + 1:]
        if min_share > 0:  # at least this share of the other VIEWS must see a depth (module docstring)
            n_views = len({id(o.camera) for o in others if o.camera is not ref.camera})
            sweep["min_views"] = max(3, math.ceil(min_share * n_views - 1e-9))
        p, c, d, r, edge, filled, px, span, own = sweep_view(ref, others, rays.views, lo, hi, 20 * step,
                                                        plane_slack=plane_slack, **sweep)
        stats["edge"] += edge
        stats["completed"] += filled
        own_all.append(own)
        pos.append(p), colour.append(c), dist.append(d), fl.append(np.full(len(d), ref.camera.fl_x))
        seen_along.append(r), spans.append(span), start.append(ref.points.reshape(-1, 3)[px]), matched.append(own)
        dm = np.full(ref.open.size, np.nan)
        dm[px] = d
        depth.append(dm.reshape(ref.open.shape))
    stats["kept"] = int(sum(len(p) for p in pos))
    every = [np.concatenate(a) for a in (start, seen_along)]  # usable holds >= 2 mirrors: never empty
    every_t = np.linalg.norm(np.concatenate(pos) - every[0], axis=-1)
    consistent = [np.ones(len(p), bool) for p in pos]
    if min_agree > 0:  # the mirrors' depths must agree with each other, and none may see through the point
        for i in range(len(usable)):
            agree, through = np.zeros(len(pos[i]), np.int64), np.zeros(len(pos[i]), np.int64)
            for j, other in enumerate(usable):
                if j != i and other.camera is not usable[i].camera:
                    a, t = depth_votes(pos[i], other, depth[j], agree_tol)
                    agree += a
                    through += t
            good = (agree >= min_agree) & (through <= agree)
            consistent[i] = good
            stats["inconsistent"] += int((~good).sum())
            pos[i], colour[i], dist[i], fl[i], seen_along[i], spans[i], start[i], matched[i] = (
                a[good] for a in (pos[i], colour[i], dist[i], fl[i], seen_along[i], spans[i], start[i], matched[i]))
    pos, colour, dist, fl, seen_along, spans, start, matched = (
        np.concatenate(a) for a in (pos, colour, dist, fl, seen_along, spans, start, matched))
    # every consistent match made by its own texture as a reflected ray (mirror point, direction, and the depth in
    # front of which the sweep tells it apart from the one it chose: free space up to there): the trainer's stereo
    # depth loss keeps that space free (ReconstructConfig.loss.stereo_depth). The completed flat pixels are left
    # out: their depth is a neighbour's and can lie behind their own surface
    stats["rays"] = (start[matched], seen_along[matched],
                     (np.linalg.norm(pos - start, axis=-1) + spans[:, 0])[matched])
    if stats["edge"]:
        stats["notes"] = [f"mirror stereo: {stats['edge']} pixels matched best on the edge of the depth sweep "
                          f"(the cube {far_scale:g}x the scene's box): not placed; what they see may lie farther"]
    pick = np.random.default_rng(seed).permutation(len(pos))[:count]
    consistent = np.concatenate(consistent)
    placed = np.zeros(len(consistent), bool)
    placed[np.nonzero(consistent)[0][pick]] = True
    # every match before the mirrors' vote, for a check against the true surfaces (stages/benchmark/stereo.py):
    # mirror point, reflected direction, distance along it, matched by its own texture, placed
    stats["matches"] = {"start": every[0], "dirs": every[1], "t": every_t, "own": np.concatenate(own_all),
                        "placed": placed}
    if len(pos) == 0:
        return None, stats
    pos, colour, scale = pos[pick], colour[pick], dist[pick] / fl[pick]  # a pixel at its virtual distance
    stats["added"] = len(pos)
    stats["along"] = (seen_along[pick], spans[pick])
    return matte_gaussians(torch.from_numpy(pos), torch.from_numpy(scale).clamp_min(1e-6), opacity,
                           torch.from_numpy(colour).clamp(0.0, 100.0), dtype,
                           facing=torch.from_numpy(seen_along[pick]), material=unseen_material(gaussians)), stats
