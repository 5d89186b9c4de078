"""How long a reflection path a scene needs (the trainer's path-length decision, Trainer._decide_path_length).

The paper's paths have 3 segments: the camera ray, two reflections, then the diffuse layer of what the last one
hits (the radiance cache). That is exact where a reflection ends on a matte surface. Where mirror-like surfaces
face each other (two metal walls, a mirror facing a chrome sphere) the cache is read on a mirror-like surface,
whose diffuse is ~0 for a metal: the reflection goes dark after two bounces. The test here is view-independent:
reflections leave points on the mirror-like surfaces in cosine-distributed directions (what some viewpoint
sees there), are traced through the scene, and ``carried_throughput`` gives, per reflection segment, the
throughput each still carries; ``needed_length`` is the shortest length after which few of them still carry
much.

A reflection that meets a surface from behind (the blended normal where it ends points along the ray) goes on
through it. Such a hit is, nearly always, the surface the reflection left: a mirror is a layer of Gaussians a few
centimetres thick (round blobs of the dense initialisation, 1-2 cm across on mirror_book's mirror after
training), and a reflection leaving it obliquely meets the next blob of the same mirror. Counted as a
reflection of the mirror in itself, that hit carried on at F0 0.95 and made a single wall mirror in a matte
room look like a hall of mirrors (mirror_book: 24 % of the reflections still carried light after 3 segments,
0.2 % without such hits; the decision took the limit, 8).
"""

from __future__ import annotations

import dataclasses
import math

import torch

from models.gaussians import Gaussians
from models.pathtrace.paths import PathConfig, TraceFn, trace_paths
from models.pathtrace.sampling import tangent_frame


def cosine_directions(normals: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """[M, 3] unit directions, cosine-distributed around the unit ``normals`` [M, 3]."""
    t, b = tangent_frame(normals)
    u1 = torch.rand(len(normals), generator=generator, dtype=normals.dtype)
    u2 = torch.rand(len(normals), generator=generator, dtype=normals.dtype)
    r, phi = u1.sqrt(), 2.0 * math.pi * u2
    up = (1.0 - u1).clamp_min(0.0).sqrt()
    return (r * phi.cos())[:, None] * t + (r * phi.sin())[:, None] * b + up[:, None] * normals


def front_hits_only(trace_fn: TraceFn, offset: float, stats: dict | None = None, max_skips: int = 4) -> TraceFn:
    """``trace_fn`` whose segments go on through what they meet from behind (blended normal . ray direction > 0):
    such a ray is traced again from ``offset`` past that hit, up to ``max_skips`` times (depth stays measured from
    the first origin); one still meeting a surface from behind after that gets no normal, so a path stops there
    (trace_paths' normal-agreement test). ``stats["back"]`` counts the segments that met a surface from behind,
    ``["rays"]`` all. No gradients (the decision only)."""

    def trace(origins: torch.Tensor, dirs: torch.Tensor, scene: Gaussians):
        with torch.no_grad():
            seg = trace_fn(origins, dirs, scene)
            back = (seg.normal * dirs).sum(-1) > 0
            if stats is not None:
                stats["back"] = stats.get("back", 0) + int(back.sum())
                stats["rays"] = stats.get("rays", 0) + len(back)
            shift = torch.zeros(len(dirs), dtype=dirs.dtype, device=dirs.device)
            for _ in range(max_skips):
                index = back.nonzero().reshape(-1)
                if len(index) == 0:
                    break
                shift[index] += (seg.depth[index] / seg.opacity()[index, 0]).to(shift.dtype) + offset
                again = trace_fn(origins[index] + shift[index, None] * dirs[index], dirs[index], scene)
                fields = {}
                for f in dataclasses.fields(seg):
                    old, new = getattr(seg, f.name), getattr(again, f.name)
                    if isinstance(old, torch.Tensor) and isinstance(new, torch.Tensor) and len(old) == len(dirs):
                        old = old.clone()
                        old[index] = new.to(old.dtype)
                    fields[f.name] = old
                seg = dataclasses.replace(seg, **fields)
                # depth from the first origin: the conditional depth grows by the shift
                seg.depth[index] = seg.depth[index] + shift[index].to(seg.depth.dtype) * seg.opacity()[index, 0]
                if seg.front_depth is not None:
                    f = seg.front_depth[index]
                    seg.front_depth[index] = torch.where(f > 0, f + shift[index].to(f.dtype), f)
                back = torch.zeros_like(back).index_put((index,), (again.normal * dirs[index]).sum(-1) > 0)
            return dataclasses.replace(seg, normal=torch.where(back[:, None], torch.zeros_like(seg.normal),
                                                               seg.normal))

    return trace


def carried_throughput(points: torch.Tensor, normals: torch.Tensor, trace_fn: TraceFn, scene: Gaussians,
                       path: PathConfig, max_length: int, generator: torch.Generator,
                       stats: dict | None = None) -> list[torch.Tensor]:
    """Reflections from ``points`` [M, 3] on mirror-like surfaces (unit ``normals`` [M, 3] on the side they are
    seen from) in cosine-distributed directions, traced through ``scene`` as the reflection segments of camera
    paths of up to ``max_length`` segments (``path``: origin offset, Fresnel, sampler, min_throughput). Returns
    ``carried``: ``carried[j]`` [M] (CPU, float64) is the throughput (max over RGB) a path carries into segment
    j + 3 of its camera path (0 once it has stopped), for j up to max_length - 2 (into segment max_length + 1);
    the list ends early where every path has stopped. A segment goes on through a surface it meets from behind
    (``front_hits_only``: the surface it left; ``stats["back"]`` counts those segments, ``stats["rays"]`` all)."""
    dirs = cosine_directions(normals.cpu(), generator).to(points.device)  # drawn where the generator lives
    # segment 1 here is the camera path's 2; one more than max_length - 1 so that carried[max_length - 2] (what
    # goes on after max_length camera segments) is measured too
    cfg = dataclasses.replace(path, max_path_length=max(max_length, 2))
    origins = points + cfg.origin_offset * dirs
    with torch.no_grad():
        out = trace_paths(front_hits_only(trace_fn, cfg.origin_offset, stats), origins, dirs, scene, cfg,
                          generator)
    return [c.double().cpu() for c in out.throughput]


def going_on(carried: list[torch.Tensor], length: int, throughput: float) -> float:
    """Fraction of the reflections still carrying more than ``throughput`` after ``length`` camera-path segments."""
    k = length - 2
    return float((carried[k] > throughput).double().mean()) if 0 <= k < len(carried) else 0.0


def needed_length(carried: list[torch.Tensor], base: int, limit: int, throughput: float, fraction: float) -> int:
    """The shortest length in [base, limit] after which at most ``fraction`` of the reflections still carry more
    than ``throughput`` (``limit`` when none is)."""
    length = base
    while length < limit and going_on(carried, length, throughput) > fraction:
        length += 1
    return length
