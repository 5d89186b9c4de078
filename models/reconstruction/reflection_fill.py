"""Gaussians in the reflected frusta: geometry that the training views see only in mirrors.

The dense initialisation unprojects what the cameras see directly, so an object (or a light) seen only
through a mirror has no Gaussians, and the far-field shell (``far_field.py``) sits far behind it. At the end
of warm-up, for the mirror-like training pixels (F0 > 0.3, roughness < 0.3 in the buffers) whose perfect
reflection still passes through the scene (transmittance > ``open_transmittance`` through the warmed-up
Gaussians), Gaussians are spread along the reflected ray between the mirror and where the ray leaves the
scene's box (the current Gaussians' box padded by 5 %), ``per_ray`` of them at jittered, stratified
distances. Positions in space a training camera sees to be empty (in its frustum, in front of its depth
buffer) are dropped (``seen_empty``): a Gaussian there would cloud the direct views. What remains lies where
no camera looked: behind surfaces or outside every frustum, where objects seen only in mirrors are. Across
views the reflected rays of one unseen point cross there, so training keeps the Gaussians near the crossing
(they explain several views' reflections) and prunes the rest.

Each starts with the colour the reflection needs, ``specular / F0`` of its pixel (a mirror's specular is
F0 times the reflected radiance), opacity 0.1, the material of what no view looks at (``unseen_material``: the
room's matte roughness, F0 0), its normal facing back along the reflected ray it was found on (the side it was seen
from: a view that later looks at it directly then traces its sheen, where a zero normal would stop every
path there and leave its specular black), scale half the spacing along its ray.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from models.gaussians import Gaussians
from models.pathtrace.brdf import reflect

SHINY_F0 = 0.3
SHINY_ROUGHNESS = 0.3
HIGHLIGHT_BRIGHTNESS = 3.0  # a reflection this many times brighter than the views' lit surfaces shows a light
PURITY_RADIUS = 0.03  # on_fill_purity: the neighbourhood of a highlight's end on the fill, x the fill's largest side
PLANE_OFFSET = 0.002  # on_fill_plane: an emitter's distance in front of its plane, x the fill's largest side (1 cm
# in a 5 m room; along a ray 15 degrees above the plane, 4 cm: the box step, 1/1000 of a box that may hold the far
# field, is centimetres)
ON_FILL_NOTE = 10  # highlight reflections ending on the plane fill from which the highlight fill notes it
LUMINANCE = (0.2126, 0.7152, 0.0722)
LOBE_WIDTH = 2.0  # footprint_angle: a GGX lobe's width, x alpha: the reflected directions within which its D stays
# above a quarter of its peak (half-vector angle atan(alpha), doubled on reflection)


def scene_box(gaussians: Gaussians) -> tuple[torch.Tensor, torch.Tensor, float]:
    """(lo, hi, step): the box of the Gaussians' means padded by 5 % of its largest side, and 1/1000 of that
    side (the small offset the fills step off surfaces and box faces by)."""
    means = gaussians.means.detach()
    lo, hi = means.min(0).values, means.max(0).values
    pad = 0.05 * (hi - lo).max()
    lo, hi = lo - pad, hi + pad
    return lo, hi, float((hi - lo).max()) * 1e-3


MATTE_ROUGHNESS, MATTE_F0 = 1.0, 0.04  # the material of fill Gaussians in a scene with no matte Gaussians yet


@torch.no_grad()
def matte_material(gaussians: Gaussians) -> tuple[float, float]:
    """(roughness, F0): the medians over the scene's Gaussians that are not mirror-like (``shiny``), i.e. the
    material that training from the buffers gave the room's ordinary surfaces; (1, 0.04) when there are none.
    Fill Gaussians take it: what is seen only in mirrors is most likely made of what the room is made of."""
    rough, f0 = gaussians.roughness.detach().reshape(-1), gaussians.f0.detach()
    matte = ~shiny(f0, rough[:, None])
    if not bool(matte.any()):
        return MATTE_ROUGHNESS, MATTE_F0
    return float(rough[matte].clamp(0, 1).median()), float(f0[matte].mean(-1).clamp(0, 1).median())


def unseen_material(gaussians: Gaussians) -> tuple[float, float]:
    """(roughness, F0) of what a fill places where no training view looks (mirror stereo, the reflection fill,
    room closing): the room's matte roughness (``matte_material``) and F0 0. Nothing supervises their material
    (the G-buffer loss needs a view of them, and the trainer holds a mirror fill's material fixed: fill_matte),
    and the room's median F0 can be its glossy floor's: room closing's walls reflected zoo_thin's window and lamps
    (specular 28.03 -> 22.88 dB), where the truth reflects nothing. F0 0 reflects nothing (F90 follows F0); the
    reflections that show them still train their colour. (On the zoo the median was 0 already: mirror stereo's
    Gaussians trained the same bits with this.)"""
    return matte_material(gaussians)[0], 0.0


def matte_gaussians(pos: torch.Tensor, scale: torch.Tensor, opacity: float, colour: torch.Tensor,
                    dtype=torch.float32, facing: torch.Tensor | None = None,
                    material: tuple[float, float] = (MATTE_ROUGHNESS, MATTE_F0)) -> Gaussians:
    """Isotropic Gaussians at ``pos`` [N, 3] with per-Gaussian ``scale`` [N], ``opacity`` and diffuse ``colour``
    [N, 3], matte (``material``: roughness, F0). ``facing`` [N, 3]: the directions they were seen along; their
    normals point back along them. Without it the normal is 0, which stops every reflection path there (for
    lights, whose own radiance dwarfs what they would reflect)."""
    n, f = len(pos), dict(dtype=dtype)
    normals = torch.zeros((n, 3), **f) if facing is None else \
        -torch.nn.functional.normalize(facing.to(**f).reshape(n, 3), dim=-1)
    rough, f0 = material
    return Gaussians(
        means=pos.to(**f),
        quats=torch.tensor([[1.0, 0, 0, 0]], **f).repeat(n, 1),
        log_scales=torch.log(scale).reshape(n, 1).repeat(1, 3).to(**f),
        opacity_logits=torch.full((n,), math.log(opacity / (1 - opacity)), **f),
        diffuse=colour.to(**f),
        normals=normals,
        roughness=torch.full((n,), rough, **f),
        f0=torch.full((n, 3), f0, **f),
    )


def shiny(f0, roughness):
    """Mirror-like pixels (bool, works on numpy and torch): mean F0 > SHINY_F0 and roughness < SHINY_ROUGHNESS;
    ``f0`` [..., 3], ``roughness`` [..., 1]."""
    return (f0.mean(-1) > SHINY_F0) & (roughness[..., 0] < SHINY_ROUGHNESS)


def diffuse_level(rays, gen: torch.Generator) -> float:
    """The 99th percentile of the luminance of the training views' diffuse radiance (200,000 random valid pixels
    drawn with ``gen``; at least 1e-6) on the pixels that show no light (the views' ``emission`` layer, where they
    have one): the brightest lit surface they see. A reflection brighter than ``HIGHLIGHT_BRIGHTNESS`` x this
    shows a light. (With the lights' own pixels counted, a window or lamp filling 2-3 % of the frames set the
    level to the lights' radiance, 6.0-9.5 against 0.34-0.45 without them, and no reflection counted as a
    highlight: zoo_lamps, zoo_lshape, zoo_thin and zoo_mirror_metal had 0 highlight rays.)"""
    t = rays.targets
    direct = torch.nonzero(rays.mask & ~torch.from_numpy(emitting_rays(rays))).reshape(-1)
    direct = direct[torch.randperm(len(direct), generator=gen)[:200000]]
    lum = torch.tensor(LUMINANCE, dtype=t["diffuse"].dtype)
    return max(float(torch.quantile(t["diffuse"][direct] @ lum, 0.99)) if len(direct) else 0.0, 1e-6)


def emitting_rays(rays) -> np.ndarray:
    """[R] bool: the rays whose pixel shows a light (``emission`` > 0 in its view's buffers); none for views without
    that layer, or for a ray set that is not its views' pixels in order (``build_rayset``; a subset)."""
    parts = []
    for view in rays.views:
        n = view.camera.width * view.camera.height
        em = view.buffers.get("emission")
        parts.append(np.zeros(n, bool) if em is None else np.asarray(em).reshape(n, -1).max(-1) > 0)
    if not parts or sum(len(p) for p in parts) != len(rays):
        return np.zeros(len(rays), dtype=bool)
    return np.concatenate(parts)


def mirror_rays(rays, max_rays: int, seed: int = 0,
                select=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """(points on the mirrors [M, 3], unit reflected directions [M, 3], ray indices [M]) for up to
    ``max_rays`` random mirror-like training pixels (from the depth / normal / F0 / roughness buffers), or
    None when the capture lacks those buffers or has no such pixel. ``select(f0, roughness)``: other pixels than
    the mirror-like ones (``shiny``)."""
    t = rays.targets
    if not all(k in t for k in ("depth", "normal", "f0", "roughness")):
        return None
    index = torch.nonzero(rays.mask & (select or shiny)(t["f0"], t["roughness"])).reshape(-1)
    if len(index) == 0:
        return None
    index = index[torch.randperm(len(index), generator=torch.Generator().manual_seed(seed))[:max_rays]]
    d = rays.dirs[index]
    n = torch.nn.functional.normalize(t["normal"][index], dim=-1)
    x = rays.origins[index] + d * t["depth"][index].reshape(-1, 1)
    r = torch.nn.functional.normalize(reflect(d, n), dim=-1)
    return x, r, index


def reflection_spread(rays, index: torch.Tensor) -> torch.Tensor:
    """[M] the angle (radians) between the perfect reflection of each ray ``index`` and those of its four
    neighbouring pixels that lie on the same mirror-like surface (``shiny``, valid, depth within 5 % of its own);
    the largest of them, 0 where none does. At a distance L along the reflection one pixel of the mirror spans
    about L x this: a flat mirror's pixels keep the camera's pixel angle (~0.01 rad at 128 pixels over 60
    degrees), a chrome ball's spread it tens of times (zoo_corridor: adjacent pixels of its balls' reflections
    land 0.37-0.40 m apart on the ceiling). Needs ``rays`` to be its views' pixels in order (``build_rayset``);
    otherwise 0."""
    t = rays.targets
    index = index.reshape(-1).cpu()
    out = torch.zeros(len(index), dtype=rays.dirs.dtype)
    sizes = [v.camera.width * v.camera.height for v in rays.views]
    if sum(sizes) != len(rays) or not len(index) or not all(k in t for k in ("depth", "normal", "f0", "roughness")):
        return out
    starts = torch.tensor(np.cumsum([0] + sizes[:-1]), dtype=torch.int64)
    widths = torch.tensor([v.camera.width for v in rays.views], dtype=torch.int64)
    heights = torch.tensor([v.camera.height for v in rays.views], dtype=torch.int64)
    view = torch.searchsorted(starts, index, right=True) - 1
    local = index - starts[view]
    row, col, w, h = local // widths[view], local % widths[view], widths[view], heights[view]

    def reflected(i):
        n = torch.nn.functional.normalize(t["normal"][i].cpu(), dim=-1)
        return torch.nn.functional.normalize(reflect(rays.dirs[i].cpu(), n), dim=-1)

    r0, z0 = reflected(index), t["depth"][index].reshape(-1).cpu()
    for ok, j in ((col > 0, index - 1), (col < w - 1, index + 1), (row > 0, index - w), (row < h - 1, index + w)):
        j = torch.where(ok, j, index)
        zj = t["depth"][j].reshape(-1).cpu()
        same = ok & rays.mask[j].cpu() & shiny(t["f0"][j].cpu(), t["roughness"][j].cpu()) & ((zj - z0).abs() <= 0.05 * z0)
        angle = torch.arccos((r0 * reflected(j)).sum(-1).clamp(-1.0, 1.0))
        out = torch.where(same, torch.maximum(out, angle), out)
    return out


def footprint_angle(rays, index: torch.Tensor) -> torch.Tensor:
    """[M] the angle (radians) a mirror-like pixel's reflection covers: its pixel's spread
    (``reflection_spread``) plus its glossy lobe, ``LOBE_WIDTH`` x GGX alpha (roughness^2 in the buffers): a
    brushed-metal fridge (roughness 0.25) blurs a window it reflects over ~0.13 rad round the perfect
    reflection, and its highlight pixels' centre rays end up to that far beside the window (zoo_lshape: 1,839 of
    its 2,219 highlight pixels are the fridge's, 322 its pot's, roughness 0.2, 51 the chrome ball's)."""
    index = index.reshape(-1).cpu()
    rough = rays.targets["roughness"][index].reshape(-1).cpu().to(rays.dirs.dtype)
    return reflection_spread(rays, index) + LOBE_WIDTH * rough.clamp(0.0, 1.0) ** 2


def light_points(rays) -> np.ndarray | None:
    """[K, 3] the points of the lights the training views see directly (``emitting_rays``: pixels whose
    ``emission`` > 0, at their depth), or None when there are none or the rays carry no depth."""
    if "depth" not in rays.targets:
        return None
    lit = torch.from_numpy(emitting_rays(rays)) & rays.mask.cpu()
    if not bool(lit.any()):
        return None
    i = torch.nonzero(lit).reshape(-1)
    return (rays.origins[i] + rays.dirs[i] * rays.targets["depth"][i].reshape(-1, 1)).double().numpy()


def near_seen_light(ends: torch.Tensor, starts: torch.Tensor, spread: torch.Tensor, lights) -> torch.Tensor:
    """[M] bool: a reflection from ``starts`` [M, 3] (on the mirror) ending at ``ends`` [M, 3] whose footprint
    there, its length x ``spread`` (``footprint_angle``: one pixel's width and its glossy lobe), holds a light the cameras see
    directly (``lights`` [K, 3], ``light_points``). Its pixel showed that light, which has its own Gaussians: a
    brushed-metal or curved reflector's highlight pixel whose centre ray lands beside a window (zoo_lshape:
    emitters up to 0.4 m round its window, on the wall no training view sees, glowing 2-4x the wall's radiance in
    the test views)."""
    if lights is None or not len(ends):
        return torch.zeros(len(ends), dtype=torch.bool)
    radius = ((ends - starts).norm(dim=-1) * spread.to(ends.dtype)).detach().cpu().double().numpy()
    dist, _ = cKDTree(lights).query(ends.detach().cpu().double().numpy(), k=1)
    return torch.from_numpy(dist <= radius)


def box_exit(x: torch.Tensor, r: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """[M] distance along the unit rays ``x + t r`` (x inside the box) to the axis-aligned box's boundary."""
    safe = torch.where(r.abs() < 1e-12, torch.full_like(r, 1e-12), r)
    t_far = torch.maximum((lo - x) / safe, (hi - x) / safe)
    return t_far.min(dim=-1).values.clamp_min(0.0)


def seen_empty(points: torch.Tensor, views, margin: float = 0.9) -> torch.Tensor:
    """[N] bool: the point lies inside some view's frustum, nearer than ``margin`` x that pixel's depth (the
    capture's depth is the distance along the ray), or on a pixel that hits nothing: space seen to be empty."""
    empty = torch.zeros(len(points), dtype=torch.bool)
    p = points.detach().double().cpu().numpy()
    for view in views:
        cam = view.camera
        u, v, z = cam.project(p)
        col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        inside = (z > 1e-9) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        if not inside.any() or "depth" not in view.buffers:
            continue
        r, c = row[inside], col[inside]
        depth = view.buffers["depth"][r, c, 0]
        hit = view.buffers["mask"][r, c, 0] > 0.5 if "mask" in view.buffers else depth > 0
        dist = np.linalg.norm(p[inside] - cam.origin, axis=1)
        seen = ~hit | (dist < margin * depth)
        idx = np.nonzero(inside)[0][seen]
        empty[torch.from_numpy(idx)] = True
    return empty


HIDDEN_SLACK = 0.05  # seen_by_cameras: a point this share of the pixel's depth behind its surface is still on it
HIDDEN_REACH = 2.0  # ... and this many times its Gaussian's largest scale (a large one reaches out of hiding)


def seen_by_cameras(points: torch.Tensor, sizes: torch.Tensor, views, slack: float = HIDDEN_SLACK,
                    reach: float = HIDDEN_REACH) -> torch.Tensor:
    """[N] bool: some view's camera sees the point (a Gaussian's mean, ``sizes`` [N] its largest scale): it lies
    in the view's frame, and either the view has no depth there (no depth buffer, masked out, a pixel that hits
    nothing) or it is not behind the surface the pixel shows by more than ``slack`` x that depth + ``reach`` x its
    size. The rest are hidden from every camera: behind the objects they see, under them, inside them, outside
    every frame."""
    seen = torch.zeros(len(points), dtype=torch.bool)
    p = points.detach().double().cpu().numpy()
    size = sizes.detach().double().cpu().numpy().reshape(-1)
    for view in views:
        cam = view.camera
        u, v, z = cam.project(p)
        col, row = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        inside = (z > 1e-9) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        if not inside.any():
            continue
        idx = np.nonzero(inside)[0]
        if "depth" not in view.buffers:
            seen[torch.from_numpy(idx)] = True
            continue
        r, c = row[idx], col[idx]
        depth = view.buffers["depth"][r, c, 0].astype(np.float64)
        known = np.isfinite(depth) & (depth > 0)
        if "mask" in view.buffers:
            known &= view.buffers["mask"][r, c, 0] > 0.5
        dist = np.linalg.norm(p[idx] - cam.origin, axis=1)
        ok = ~known | (dist <= (1.0 + slack) * np.where(known, depth, 0.0) + reach * size[idx])
        seen[torch.from_numpy(idx[ok])] = True
    return seen


@torch.no_grad()
def reflection_fill_gaussians(rays, trace_fn, gaussians: Gaussians, count: int, seed: int = 0,
                              per_ray: int = 8, open_transmittance: float = 0.5,
                              dtype=torch.float32) -> tuple[Gaussians | None, dict]:
    """Up to ``count`` Gaussians along the open mirror reflections of the training rays (module docstring).
    ``trace_fn(origins, dirs, gaussians) -> TraceOutput`` traces against the current (warmed-up) model.
    Returns (Gaussians or None, statistics for the log)."""
    stats = {"mirror_rays": 0, "open_rays": 0, "unseen": 0, "added": 0}
    found = mirror_rays(rays, max_rays=max(8 * count // per_ray, 1), seed=seed)
    if found is None or count < per_ray:
        return None, stats
    x, r, index = found
    stats["mirror_rays"] = len(index)
    lo, hi, step = scene_box(gaussians)
    inside = torch.nonzero(((x > lo) & (x < hi)).all(-1)).reshape(-1)
    x, r, index = x[inside], r[inside], index[inside]
    out = trace_fn(x + step * r, r, gaussians)
    keep = torch.nonzero(out.transmittance.reshape(-1) > open_transmittance).reshape(-1)
    stats["open_rays"] = len(keep)
    if len(keep) == 0:
        return None, stats
    x, r, index = x[keep], r[keep], index[keep]
    t_min = 20 * step
    t_max = box_exit(x, r, lo, hi).clamp_min(2 * t_min)
    gen = torch.Generator().manual_seed(seed + 1)
    u = (torch.arange(per_ray, dtype=x.dtype) + torch.rand(len(x), per_ray, generator=gen, dtype=x.dtype)) / per_ray
    t = t_min + u * (t_max - t_min)[:, None]  # [M, K] stratified, jittered
    pos = (x[:, None, :] + t[..., None] * r[:, None, :]).reshape(-1, 3)
    spacing = ((t_max - t_min) / per_ray)[:, None].expand(-1, per_ray).reshape(-1)
    index = index[:, None].expand(-1, per_ray).reshape(-1)
    r = r[:, None, :].expand(-1, per_ray, -1).reshape(-1, 3)
    unseen = torch.nonzero(~seen_empty(pos, rays.views)).reshape(-1)
    unseen = unseen[torch.randperm(len(unseen), generator=gen)[:count]].sort().values
    stats["unseen"] = len(unseen)
    if len(unseen) == 0:
        return None, stats
    pos, spacing, index, r = pos[unseen], spacing[unseen], index[unseen], r[unseen]
    targets = rays.targets
    colour = targets["specular"][index] / targets["f0"][index].clamp_min(0.05) if "specular" in targets \
        else torch.full((len(index), 3), 0.2, dtype=pos.dtype)
    stats["added"] = len(pos)
    return matte_gaussians(pos, 0.5 * spacing.clamp_min(1e-6), 0.1, colour.clamp(0.0, 100.0), dtype, facing=r,
                           material=unseen_material(gaussians)), stats


def _exit_purity(x, r, b, lo, hi, s: float, k: int) -> float:
    from scipy.spatial import cKDTree

    centre, half = (lo + hi) / 2, (hi - lo) / 2
    exits = (x + box_exit(x, r, centre - s * half, centre + s * half)[:, None] * r).double().cpu().numpy()
    kk = min(k + 1, len(exits))
    if b.sum() == 0 or kk < 2:
        return 0.0
    _, nn = cKDTree(exits).query(exits[b], k=kk)
    return float(b[nn[:, 1:]].mean())


SWEEP_STEP = 0.1  # sweep_box_scale's step in box scale
SNAP_STEPS = 2    # an emitter this many sweep steps short of a placed wall moves onto it
BEYOND_NOTE = 50  # emitters beyond a plane the buffers show, from which (and 10 % of them) a note says so


def snap_to_planes(pos: torch.Tensor, r: torch.Tensor, planes: list, before, offset: float, past: float = 0.0,
                   offset_along_ray: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Moves the points ``pos`` [M, 3] along their unit rays ``r`` onto the one of ``planes`` ((n, s): n . p = s, n
    pointing out of the room) that the ray heads out through and crosses nearest to the point, among those the point
    lies short of by at most ``before`` (a float, or [3] per-axis tolerances taken as ``before`` . |n|) or past by
    less than ``past``; it stops ``offset`` in front of the plane, measured along the ray (never moving back) with
    ``offset_along_ray``, else along the normal. Returns the moved points (a new tensor) and which moved ([M] bool).

    The highlight fill's sweep snaps the emitters it placed a little short of a wall onto it (along the ray,
    nothing past the wall). ``on_fill_plane`` moves the emitters placed at the plane fill's front (its Gaussians'
    support, a few cm short of the plane: a grazing ray meets it 10-20 cm short of where it crosses the plane, so
    emitters placed there tile a patch beside the light, zoo_mirror_metal's ceiling lamp: up to 0.2 m past its
    rim, towards the mirror) onto the plane under the fill, from either side, the offset along the normal."""
    best = torch.full((len(pos),), float("inf"), dtype=pos.dtype, device=pos.device)
    step = torch.zeros(len(pos), dtype=pos.dtype, device=pos.device)
    for n, s in planes:
        n = torch.as_tensor(np.asarray(n), dtype=pos.dtype, device=pos.device)
        gap = float(s) - pos @ n  # > 0: the plane lies beyond the point
        cos = r @ n
        t = gap / cos.clamp_min(0.05)  # along the ray to the plane
        tol = float(before @ n.abs()) if torch.is_tensor(before) else float(before)
        ok = (cos > 0.05) & (gap > -past) & (gap <= tol) & (t.abs() < best)
        go = (t - offset).clamp_min(0) if offset_along_ray else (gap - offset) / cos.clamp_min(0.05)
        best = torch.where(ok, t.abs(), best)
        step = torch.where(ok, go, step)
    moved = torch.isfinite(best)
    return pos + step[:, None] * r, moved


def _note_beyond_known(pos: torch.Tensor, known: list, tol: float, stats: dict) -> None:
    """Counts (``stats["beyond_known"]``) the emitters ``pos`` [M, 3] that lie more than ``tol`` beyond one of the
    ``known`` planes ((n, s), n pointing out of the room) and notes the plane most of them passed."""
    worst = None
    beyond_any = torch.zeros(len(pos), dtype=torch.bool, device=pos.device)
    for n, s in known:
        past = pos @ torch.as_tensor(np.asarray(n), dtype=pos.dtype, device=pos.device) - float(s)
        out = past > tol
        beyond_any |= out
        count = int(out.sum())
        if count and (worst is None or count > worst[0]):
            worst = (count, np.asarray(n), float(past[out].max()))
    stats["beyond_known"] = int(beyond_any.sum())
    if worst is not None and worst[0] >= max(BEYOND_NOTE, 0.1 * len(pos)):
        stats["notes"].append(
            f"highlight fill: {worst[0]} of the {len(pos)} emitters the box sweep placed lie beyond a plane of the "
            f"room the buffers show (its outward normal {(np.round(worst[1], 2) + 0.0).tolist()}), up to "
            f"{worst[2]:.2f} past it: their reflections crossed it, so the light they show may hang on it, where the "
            "plane fill blocks such reflections (reconstruct.highlight_on_fill)")


def sweep_box_scale(x: torch.Tensor, r: torch.Tensor, bright: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                    scales=tuple(1.0 + SWEEP_STEP * i for i in range(21)), k: int = 8,
                    max_scale: float = 20.0) -> tuple[float, list[float], list[str]]:
    """The box scale at which the open mirror rays ``x + t r`` (``bright`` [M] bool: highlight or dark) leave the
    box (``lo``, ``hi`` scaled about its centre) most consistently: for each scale, the mean fraction of
    highlight exits among the ``k`` nearest exits of each highlight exit (a plane sweep). At the light's true
    distance the highlight rays of all views end on the light's patch and the dark ones around them; nearer or
    farther, rays of different views end interleaved. A best scale at the far end of ``scales`` is not a
    minimum: the range is extended (5 % steps) until the purity falls past the best or ``max_scale`` is
    reached. Returns (best scale, the scales tried, purity per scale, notes): a note says when the best
    still lies on the range's edge (the light may be farther, or inside the box)."""
    b = bright.cpu().numpy()
    scales = list(scales)
    purity = [_exit_purity(x, r, b, lo, hi, s, k) for s in scales]
    while int(np.argmax(purity)) == len(purity) - 1 and scales[-1] < max_scale and max(purity) > 0:
        for _ in range(10):  # past the edge: on until the purity has clearly turned
            scales.append(min(scales[-1] * 1.05, max_scale))
            purity.append(_exit_purity(x, r, b, lo, hi, scales[-1], k))
            if scales[-1] >= max_scale:
                break
    best = int(np.argmax(purity))
    notes = []
    if max(purity) <= 0:
        notes.append("highlight fill: no scale of the box makes the highlight reflections meet")
    elif best == len(purity) - 1:
        notes.append(f"highlight fill: box scale {scales[best]:.2f} is the edge of the search (max_scale "
                     f"{max_scale:g}): the light may lie farther; its emitters sit on that box")
    elif best == 0:
        notes.append(f"highlight fill: box scale {scales[0]:.2f} is the near edge of the search: the light "
                     "may lie inside the scene's box; its emitters sit on the box")
    return float(scales[best]), scales, purity, notes


@torch.no_grad()
def highlight_fill_gaussians(rays, trace_fn, gaussians: Gaussians, brightness: float = HIGHLIGHT_BRIGHTNESS,
                             opacity: float = 0.5,
                             max_count: int = 4000, seed: int = 0,
                             dtype=torch.float32, fill: torch.Tensor | None = None,
                             on_fill: bool = False, walls: Gaussians | None = None,
                             planes: list | None = None, known: list | None = None,
                             on_fill_purity: float = 0.0,
                             on_fill_planes: list | None = None,
                             skip_seen_lights: bool = False) -> tuple[Gaussians | None, dict]:
    """Emitters seen only in mirrors: one Gaussian per HIGHLIGHT mirror ray, where the light is.

    A light that no camera sees directly (a ceiling lamp above an orbit of cameras) has no Gaussians, and
    lights are what glossy surfaces reflect most. A highlight ray is a mirror-like training pixel whose
    reflected radiance ``specular / F0`` is brighter (luminance) than ``brightness`` x the 99th percentile of
    the training views' diffuse radiance (brighter than any lit surface they see); a dark one is dimmer than
    that percentile. Only reflections still open through the warmed-up model (transmittance > 0.5) count.
    The light's distance along a highlight ray is not known from one view; across views it is where the
    highlight rays end together and the dark ones around them: ``sweep_box_scale`` scales the box of the
    current Gaussians (padded 5 %) about its centre and keeps the scale at which the exits are most
    consistent (measured on the demo: the lamp 0.56 m above that box, found within 0.2 m; at the unscaled box
    the emitters sat below it and, inconsistent across views, trained to black: -1.1 dB). Each Gaussian sits
    where its highlight ray leaves that box, emitting the pixel's reflected radiance (diffuse colour), with
    ``opacity``, matte (roughness 1, F0 0.04), normal 0, and scale the distance to its nearest neighbour (so
    they tile the light's patch). Positions a training camera sees to be empty are dropped (``seen_empty``).

    ``fill`` [N] bool, the plane fill's Gaussians in ``gaussians``: the highlight reflections that are blocked
    only by them (open without them) are counted (``on_fill``): they show a light on an unseen part of the
    room's planes (a ceiling light above or behind every camera), which training rarely grows from the fill's
    dim colour (README, nineteenth session: zoo_corridor's ceiling strips kept emitters only on the part the
    cameras see). With ``on_fill`` each of them gets an emitter too, where the ray meets the fill (its front,
    ``front_depth``, traced through the fill alone), one box step short of it: the plane gives the light's
    distance, so no sweep is needed, and the emitters of different views land on the same patch. Off here by
    default; the trainer's ``reconstruct.highlight_on_fill`` is on since the forty-ninth session (alone it
    measured worse, zoo_mirror_only -0.5 to -0.9 dB at two seeds, README twenty-third session; with the plane
    snap ``planes``, highlight_growth_all and plane_hold fourteen zoo pairs +0.20 dB, forty-ninth). Without
    it, from ``ON_FILL_NOTE`` of them, a note says they got none. The fill of a mirror-like plane (``shiny``) does
    not count: a highlight that ends there is that plane reflecting the light (zoo_corridor's metal walls got
    emitters on their unseen parts: 23.11 -> 22.60; without them 22.95, README, fortieth session).

    ``on_fill_purity`` > 0: a highlight that ends on the fill gets its emitter only where at least that share of
    the reflections ending within ``PURITY_RADIUS`` x the fill's largest side of it are highlights too (the dark
    ones blocked only by the fill traced as well), the sweep's rule on the plane: a light's patch gathers the
    highlights of several views and few dark reflections, where a rough reflector's blurred highlights scatter
    over ceiling its sharp mirrors show dark (``on_fill_impure`` counts those dropped).

    ``on_fill_planes``: the room's planes as (n, s), n . p = s ON the plane (not ``planes``' grid spacing inside
    it), n pointing out of the room; those emitters move along their rays from the fill's front onto the nearest
    one within ``PURITY_RADIUS`` x the fill's largest side, ``PLANE_OFFSET`` x that
    side in front of it (``snap_to_planes``).

    ``walls``: more of the room's planes placed since warm-up (room closing's walls, the fill grown where the
    mirrors show the room), with ``on_fill`` traced as plane fill but not counted in the box: a highlight that
    would have left through them ends on them, so each light is placed once, on the room's planes, rather than
    on a swept box past (or short of) the wall that holds it.

    ``planes``: the walls room closing placed, as (n, s) with n . p = s on the wall and n pointing out of the room.
    An emitter that the sweep leaves short of one, by at most ``SNAP_STEPS`` of the sweep's steps (the box's
    half-extent along n x 0.1), moves along its ray onto the wall's room side (``snap_to_planes``): the sweep
    tells the light's distance to ~10-30 cm, biased short (its purity is flat over 2-3 steps: the demo's ceiling
    lamp, 2.49 m up, got emitters at 2.22-2.31, zoo_spheres' at 2.18), the wall, fitted to thousands of sharp
    reflections, better (the demo's refined ceiling: 2.47); a lamp hanging farther below it stays where the sweep
    put it. ``snapped`` in the statistics counts them (``reconstruct.highlight_to_walls``), ``snapped_rows`` [n]
    (bool, None without emitters) marks them among the returned Gaussians.

    ``known``: the room's planes the buffers show, in ``planes``' form (``room_closing.shown_planes``). Emitters the
    sweep left beyond one of them (their reflections crossed it: a light above the ceiling, past the box) are only
    reported (``beyond_known``, a note): zoo_mirror_only's ceiling light got 1,373 emitters at the box's back face,
    up to 0.6 m above its ceiling, and none where 2,119 more of its reflections end on the ceiling's fill; moved
    onto the plane, and with ``on_fill``, the whole light was placed and the unseen floor under it went from 0.79-0.90
    to 0.84-0.92 of the truth, but no score rose (README, forty-first session).

    ``skip_seen_lights``: a highlight whose pixel's footprint where its emitter would go (``near_seen_light``: the
    reflection's length x ``footprint_angle``, the angle to its neighbouring pixels' reflections plus its glossy
    lobe) holds a light the training views see directly gets no emitter: that light has its own Gaussians, and the emitter would land beside it, where a
    curved mirror's pixel centre pointed (``seen_light`` counts them, placed and on the fill)."""
    stats = {"mirror_rays": 0, "highlight_rays": 0, "added": 0, "box_scale": 1.0, "box_scale_range": "none",
             "box_scale_inside": False,
             "on_fill": 0, "on_fill_added": 0, "on_fill_impure": 0, "on_plane": 0, "snapped": 0, "snapped_rows": None,
             "beyond_known": 0, "seen_light": 0,
             "notes": []}
    t = rays.targets
    found = mirror_rays(rays, max_rays=len(rays), seed=seed)
    if found is None or "specular" not in t or "diffuse" not in t:
        return None, stats
    x, r, index = found
    stats["mirror_rays"] = len(index)
    lum = torch.tensor(LUMINANCE, dtype=t["diffuse"].dtype)
    gen = torch.Generator().manual_seed(seed + 2)
    level = diffuse_level(rays, gen)
    radiance = t["specular"][index] / t["f0"][index].clamp_min(0.05)
    bright = (radiance @ lum) > brightness * level
    lo, hi, step = scene_box(gaussians)
    if on_fill and walls is not None and len(walls) and fill is not None:
        walls = walls.to(gaussians.means.device, gaussians.means.dtype)
        fill = torch.cat([fill.to(gaussians.means.device), torch.ones(len(walls), dtype=torch.bool,
                                                                     device=gaussians.means.device)])
        gaussians = Gaussians.cat([gaussians, walls])
    use = ((x > lo) & (x < hi)).all(-1) & (bright | ((radiance @ lum) < level))
    if not bright[use].any():
        return None, stats
    x, r, radiance, bright, index = x[use], r[use], radiance[use], bright[use], index.cpu()[use.cpu()]
    lights = light_points(rays) if skip_seen_lights else None
    out = trace_fn(x + step * r, r, gaussians)
    open_ = (out.transmittance.reshape(-1) > 0.5).cpu()
    fill_pos = x[:0]
    fill_radiance = radiance[:0]
    if fill is not None:
        # a light hangs on a matte surface: a highlight that ends on a mirror-like plane's fill is that plane
        # reflecting the light, not the light (zoo_corridor: emitters on its metal walls' unseen parts)
        fill = fill.to(gaussians.means.device) & ~shiny(gaussians.f0, gaussians.roughness.reshape(-1, 1))
    if fill is not None and bool(fill.any()):
        purity = on_fill and on_fill_purity > 0
        blocked = torch.nonzero((bright | purity) & ~open_).reshape(-1)  # with the purity test the dark ones too
        if len(blocked):
            rest = gaussians.subset(~fill.to(gaussians.means.device))
            without = trace_fn((x + step * r)[blocked], r[blocked], rest)
            every = blocked[(without.transmittance.reshape(-1) > 0.5).cpu()]
            ends = every[bright[every]]
            stats["on_fill"] = len(ends)
            if on_fill and len(ends):
                ends = ends[torch.randperm(len(ends), generator=torch.Generator().manual_seed(seed + 3))[:max_count]]
                dark = every[~bright[every]]
                pick = torch.randperm(len(dark), generator=torch.Generator().manual_seed(seed + 4))
                # each kept end stands for this many (the two drawn at their own rates): the purity's share weighs them
                drawn = pick[:4 * max_count]
                weight_lit, weight_dark = stats["on_fill"] / len(ends), len(dark) / max(len(drawn), 1)
                dark = dark[drawn]
                both = torch.cat([ends, dark])
                start = x[both] + step * r[both]
                hit = trace_fn(start, r[both], gaussians.subset(fill.to(gaussians.means.device)))
                front = (hit.front_depth if hit.front_depth is not None else hit.depth).reshape(-1).cpu()
                met = (hit.transmittance.reshape(-1).cpu() < 0.5) & (front > step)
                at = start + (front - step)[:, None] * r[both]
                n_b = len(ends)
                room = gaussians.means[fill.to(gaussians.means.device)].detach().cpu()
                side = float((room.amax(0) - room.amin(0)).max())  # the room's size (the box may hold a far field)
                if purity:
                    radius = PURITY_RADIUS * side
                    lit, unlit = at[:n_b][met[:n_b]], at[n_b:][met[n_b:]]
                    near_lit = (torch.cdist(at[:n_b], lit) < radius).sum(1)
                    near_dark = (torch.cdist(at[:n_b], unlit) < radius).sum(1) if len(unlit) else 0 * near_lit
                    lit_share, dark_share = weight_lit * near_lit, weight_dark * near_dark
                    pure = lit_share >= on_fill_purity * (lit_share + dark_share)
                    stats["on_fill_impure"] = int((met[:n_b] & ~pure).sum())
                    met = torch.cat([met[:n_b] & pure, met[n_b:]])
                if on_fill_planes:
                    at[:n_b], on = snap_to_planes(at[:n_b], r[ends], on_fill_planes, PURITY_RADIUS * side,
                                                  PLANE_OFFSET * side, past=PURITY_RADIUS * side,
                                                  offset_along_ray=False)
                    stats["on_plane"] = int((on & met[:n_b]).sum())  # among those placed
                if lights is not None:
                    seen = near_seen_light(at[:n_b], x[ends], footprint_angle(rays, index[ends]), lights)
                    stats["seen_light"] += int((seen & met[:n_b]).sum())
                    met = torch.cat([met[:n_b] & ~seen, met[n_b:]])
                fill_pos = at[:n_b][met[:n_b]]
                fill_radiance = radiance[ends][met[:n_b]]
        if stats["on_fill"] >= ON_FILL_NOTE and not on_fill:
            stats["notes"].append(
                f"highlight fill: {stats['on_fill']} of {int(bright.sum())} highlight reflections end on the plane "
                "fill (the unseen parts of the room's planes): a light there gets no emitters and is left to "
                "training, which rarely grows one")
    x, r, radiance, bright, index = x[open_], r[open_], radiance[open_], bright[open_], index[open_]
    keep = torch.nonzero(bright).reshape(-1)
    keep = keep[torch.randperm(len(keep), generator=gen)[:max_count]]
    stats["highlight_rays"] = len(keep)
    pos = x[:0]
    snapped = torch.zeros(0, dtype=torch.bool)
    if len(keep):
        scale_box, scales, _, notes = sweep_box_scale(x, r, bright, lo, hi)
        stats["notes"] += notes
        stats["box_scale"], stats["box_scale_range"] = scale_box, f"{scales[0]:.1f}-{scales[-1]:.2f}"
        stats["box_scale_inside"] = scales[0] < scale_box < scales[-1]  # a minimum, not an edge of the search
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        lo, hi = centre - scale_box * half, centre + scale_box * half
        x, r, radiance = x[keep], r[keep], radiance[keep]
        pos = x + (box_exit(x, r, lo, hi) - 2 * step)[:, None] * r
        if lights is not None:  # (before the snap onto walls: its footprint where the sweep put it)
            seen = near_seen_light(pos, x, footprint_angle(rays, index[keep]), lights)
            stats["seen_light"] += int(seen.sum())
            x, r, radiance, pos = x[~seen], r[~seen], radiance[~seen], pos[~seen]
        snapped = torch.zeros(len(pos), dtype=torch.bool)
        if known:
            _note_beyond_known(pos, known, 2 * step, stats)
        if planes:
            pos, snapped = snap_to_planes(pos, r, planes, SNAP_STEPS * SWEEP_STEP * half, 2 * step)
            snapped = snapped.cpu()
            stats["snapped"] = int(snapped.sum())
    else:
        radiance = radiance[:0]
    pos, radiance = torch.cat([pos, fill_pos]), torch.cat([radiance, fill_radiance])
    snapped = torch.cat([snapped, torch.zeros(len(fill_pos), dtype=torch.bool)])
    unseen = ~seen_empty(pos, rays.views)
    stats["on_fill_added"] = int(unseen[len(pos) - len(fill_pos):].sum())
    pos, radiance = pos[unseen], radiance[unseen]
    stats["snapped_rows"] = snapped[unseen.cpu()]  # [n] bool: which emitters a wall took
    n = len(pos)
    stats["added"] = n - stats["on_fill_added"]
    if n == 0:
        return None, stats
    if n > 1:
        d = torch.cdist(pos, pos)
        d.fill_diagonal_(float("inf"))
        scale = d.min(dim=1).values.clamp(step, 100 * step)  # at most 1/10 of the box
    else:
        scale = torch.full((1,), 10 * step, dtype=pos.dtype)
    return matte_gaussians(pos, scale, opacity, radiance.clamp(0.0, 1000.0), dtype), stats
