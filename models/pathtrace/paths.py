"""The bounce loop: primary segment -> diffuse layer + G-buffer; reflection rays read the diffuse radiance cache.

Eq. 3 of the paper: L_o = L_d_hat + integral of L_i f_s cos. The first segment of
a path gives the diffuse layer (supervised by the diffuse buffer) and the G-buffer
(depth, normal, roughness, F0). The reflection ray starts at the expected
termination point (blended depth / accumulated opacity, likewise roughness and F0), is importance sampled from the GGX specular lobe, and every
further segment reads the diffuse layer of the Gaussians it hits, weighted by the
path throughput. Max path length K counts segments: K = 1 is primary only, K = 3
(paper) is two reflection rays.

Gradients (paper Sec. 3.2, REFERENCE.md): the specular estimate gives gradients
only to the geometry and diffuse colour of the Gaussians hit by reflection rays;
throughput, normals and BRDF parameters are constants (detached). Those gradients
are scaled by the throughput (chain rule) and by (1 - roughness of the previous
vertex)^3, which leaves the forward value unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable

import torch

from models.gaussians import Gaussians
from models.pathtrace.brdf import (DEFAULT_FRESNEL, DIFFUSE_LOBES, FRESNEL_MODES, dielectric_weight, diffuse_view_factor,
                                   fresnel, fresnel_f90, reflect)
from models.pathtrace.sampling import sample_specular
from models.tracer.output import TraceOutput

# trace_fn(origins [R, 3], dirs [R, 3], gaussians) -> TraceOutput (differentiable)
TraceFn = Callable[[torch.Tensor, torch.Tensor, Gaussians], TraceOutput]


REFLECTION_ORIGINS = ("front", "expected")
BACK_NORMALS = ("flip", "mirror")

# hole_fill: a ray that blended less opacity than this is divided by it instead (at most 10x brighter): it passed
# beside the scene, or through a faint floater, rather than through a half-covered surface
HOLE_FILL_MIN_OPACITY = 0.1


@dataclass
class PathConfig:
    max_path_length: int = 3  # segments per path: 1 = primary only (no reflections), 3 = paper
    normal_min_norm: float = 0.7  # a path stops where the accumulated normal / accumulated opacity is shorter
    min_roughness: float = 0.01  # roughness clamp at a vertex (GGX alpha = roughness^2); at or below it
    # the vertex is a perfect mirror (delta reflection, weight = Schlick F(n.wo)): the limit, without noise
    origin_offset: float = 0.01  # reflection origin moved this far along the reflected ray (scene units);
    # along the ray, not the normal, so the reflected line is exact (a flat mirror gives the mirrored image)
    origin_grazing: float = 0.1  # ... divided by max(|n . reflected|, this): a reflection leaving at a grazing
    # angle crosses the surface's own Gaussians over thickness / cos, and started at a fixed distance it met them
    # (a chrome ball's ring of self-shadowed reflections seen from where no training camera stood: zoo_spheres
    # 23.48 -> 24.01 dB rendered with 0.1, README); 1 = a fixed distance (models trained before the option read it)
    sampler: str = "vndf"  # vndf (visible normals, default) | ndf (half-vector, as the reference)
    grad_roughness_power: float = 3.0  # bounce gradients scaled by (1 - roughness_prev)^power
    fresnel: str = DEFAULT_FRESNEL  # schlick_f90 (F90 = min(1, 50 mean F0): F0 = 0 reflects nothing) | schlick
    # (F90 = 1, the paper's; models trained before the option read it: models/trained.py) | dielectric (the exact
    # dielectric Fresnel up to F0 0.08, schlick_f90 from 0.2: brdf.dielectric_weight)
    min_throughput: float = 0.0  # a path stops where its throughput (max over RGB) falls below this: 0 = never
    # (renders: the estimate is exact in expectation); training sets it (ReconstructConfig.min_throughput)
    reflection_origin: str = "front"  # where a reflection starts along the ray that met the surface: front (the
    # surface's front half, TraceOutput.front_depth) | expected (the expected depth, the paper's; models trained
    # before the option read it: models/trained.py)
    diffuse_lobe: str = "disney"  # disney (a Gaussian's diffuse radiance follows the viewing angle as Mitsuba's
    # principled diffuse under uniform light, on surfaces with a specular lobe: brdf.diffuse_view_factor; at every
    # segment) | lambert (the same from every side, the paper's; models trained before the option read it)
    hole_fill: bool = False  # the diffuse a segment blends is divided by its accumulated opacity (1 - T_end, at
    # least HOLE_FILL_MIN_OPACITY): the transmittance left at a ray's end takes the colour the ray blended, as
    # if no ray could leave the scene. A closed room seen from where no training camera stood shows surfaces
    # covered by too few Gaussians (mirror-only ones: 12-22 % of a test view's pixels keep T_end > 0.05), and
    # without it the black behind them (the paper's background 0). Off in training; stages.reconstruct turns it on
    # in the model it writes where the training views are opaque (ReconstructConfig.hole_fill)
    back_normal: str = "mirror"  # the normal a reflection takes where the blended normal faces away from the ray
    # (n . wo < 0: the ray met the BACK of what was reconstructed): mirror (n - 2 (n . wo) wo, n mirrored across
    # the plane normal to the ray: exactly a ball's far-side normal where the ray entered it through the side no
    # training camera saw and met the inside of the seen half; back_normal_from_behind) | flip (-n: a thin sheet's
    # other side; the back of a ball's seen half then reflects as a concave bowl, the wrong half of the room, and a
    # reflection that re-entered the Gaussians it left is sent back into them). Training traces flip
    # (ReconstructConfig.path); models trained before the option read flip (models/trained.py)

    def __post_init__(self) -> None:
        if self.max_path_length < 1:
            raise ValueError(f"max_path_length must be >= 1, got {self.max_path_length}")
        if not 0.0 <= self.min_throughput < 1.0:
            raise ValueError(f"min_throughput must be in [0, 1), got {self.min_throughput}")
        if self.fresnel not in FRESNEL_MODES:
            raise ValueError(f"fresnel must be one of {FRESNEL_MODES}, got {self.fresnel!r}")
        if self.sampler not in ("vndf", "ndf"):
            raise ValueError(f"sampler must be 'vndf' or 'ndf', got {self.sampler!r}")
        if self.reflection_origin not in REFLECTION_ORIGINS:
            raise ValueError(f"reflection_origin must be one of {REFLECTION_ORIGINS}, got {self.reflection_origin!r}")
        if not 0.0 < self.origin_grazing <= 1.0:
            raise ValueError(f"origin_grazing must be in (0, 1], got {self.origin_grazing}")
        if self.back_normal not in BACK_NORMALS:
            raise ValueError(f"back_normal must be one of {BACK_NORMALS}, got {self.back_normal!r}")
        if self.diffuse_lobe not in DIFFUSE_LOBES:
            raise ValueError(f"diffuse_lobe must be one of {DIFFUSE_LOBES}, got {self.diffuse_lobe!r}")


def vertex_depth(seg: TraceOutput, origin: str = "front") -> torch.Tensor:
    """[R, 1] (detached) ray parameter of the vertex a segment's reflection starts from. ``expected``: the expected
    depth (blended t / accumulated opacity). ``front`` (default): the surface's front, the mean t of the hits
    blended while T >= 0.5 (TraceOutput.front_depth), where the tracer gives it. Seen at an angle, a surface's
    Gaussians spread its expected depth behind the front: a test view of zoo_spheres (the spheres' sides, seen from
    where no training camera stood) started 10-25 % of its metal pixels' reflections ~3 cm inside the sphere, in
    the sphere's own Gaussians (1 % in the training views), and its reflections came out 2-4x too dark."""
    depth = seg.depth.detach().reshape(-1, 1) / seg.opacity()
    if origin == "front" and seg.front_depth is not None:
        front = seg.front_depth.detach().reshape(-1, 1).to(depth.dtype)
        depth = torch.where(front > 0, front, depth)
    return depth


@dataclass
class Vertex:
    """A segment's blended values conditional on the ray terminating there: sums / accumulated opacity (1 - T),
    except truncated rays, which the tracer's tail rule already normalised (detached: shading constants)."""

    normal: torch.Tensor  # [R, 3] unit blended normal (any direction where the normals cancel)
    length: torch.Tensor  # [R] length of the blended normal
    reflects: torch.Tensor  # [R] bool: the normals agree (length >= normal_min_norm x opacity)
    roughness: torch.Tensor  # [R] blended roughness / opacity, not clamped
    f0: torch.Tensor  # [R, 3] blended F0 / opacity, in [0, 1]


def vertex(seg: TraceOutput, config: PathConfig) -> Vertex:
    """``seg``'s vertex values (``Vertex``): a half-transparent vertex whose Gaussians agree on their normal
    reflects, one whose normals cancel out does not."""
    opacity = seg.opacity()
    n_acc = seg.normal.detach()
    n_len = n_acc.norm(dim=-1)
    return Vertex(normal=n_acc / n_len.clamp_min(1e-12)[:, None], length=n_len,
                  reflects=n_len >= config.normal_min_norm * opacity.reshape(-1),
                  roughness=seg.roughness.detach().reshape(-1) / opacity.reshape(-1),
                  f0=(seg.f0.detach() / opacity).clamp(0.0, 1.0))


def fill_hole(seg: TraceOutput, config: PathConfig) -> TraceOutput:
    """``seg`` with its diffuse divided by its accumulated opacity where ``config.hole_fill`` (``PathConfig``);
    ``seg`` itself otherwise. Truncated rays are already normalised (the tail rule, ``TraceOutput.opacity``)."""
    if not config.hole_fill:
        return seg
    opacity = seg.opacity().clamp_min(HOLE_FILL_MIN_OPACITY).to(seg.diffuse.dtype)
    return dataclasses.replace(seg, diffuse=seg.diffuse / opacity)


def _shade(seg: TraceOutput, dirs: torch.Tensor, config: PathConfig) -> tuple[TraceOutput, Vertex | None]:
    """``shade_diffuse`` and the vertex it computed (None for "lambert", which needs none)."""
    seg = fill_hole(seg, config)
    if config.diffuse_lobe == "lambert":
        return seg, None
    v = vertex(seg, config)
    ok = v.reflects & (v.length > 1e-6)
    cos_o = (v.normal * dirs.to(v.normal.dtype)).sum(-1).abs()
    factor = diffuse_view_factor(cos_o, v.roughness, v.f0, config.diffuse_lobe)
    factor = torch.where(ok[:, None], factor, torch.ones_like(factor)).to(seg.diffuse.dtype)
    return dataclasses.replace(seg, diffuse=seg.diffuse * factor), v


def shade_diffuse(seg: TraceOutput, dirs: torch.Tensor, config: PathConfig) -> TraceOutput:
    """``seg`` with its diffuse layer as seen along ``dirs`` ([R, 3] unit): times ``diffuse_view_factor`` of the
    segment's blended normal, roughness and F0 (``vertex``; detached: a shading constant, as the bounce's BRDF)
    under ``config.diffuse_lobe``; ``seg`` itself for "lambert". Where the blended normals cancel (shorter than
    ``normal_min_norm`` x opacity, as a vertex that does not reflect) the factor is 1. ``fill_hole`` first."""
    return _shade(seg, dirs, config)[0]


@dataclass
class PathOutput:
    primary: TraceOutput  # first segment: diffuse layer + G-buffer, [R] rays
    specular: torch.Tensor  # [R, 3] sum over reflection segments of throughput x diffuse cache
    bounces: list[torch.Tensor] = field(default_factory=list)  # [R, 3] per reflection segment (sum = specular)
    alive: list[torch.Tensor] = field(default_factory=list)  # [R] bool, paths still going at each bounce
    # [R] per bounce: the throughput (max over RGB) a path carries into that reflection segment, 0 where it has
    # stopped (detached): how much of a path's light is still to come there
    throughput: list[torch.Tensor] = field(default_factory=list)
    # per bounce, paths stopped by min_throughput: [count, sum of their throughput, sum over every path that could
    # have gone on] (tensors, no read-back; the last two give the share of the gradient weight not traced)
    stopped: list[torch.Tensor] = field(default_factory=list)

    @property
    def diffuse(self) -> torch.Tensor:
        return self.primary.diffuse

    @property
    def final(self) -> torch.Tensor:
        """[R, 3] diffuse + specular (the composite; not supervised in training)."""
        return self.primary.diffuse + self.specular


def back_normal_from_behind(normal: torch.Tensor, wo: torch.Tensor, rule: str) -> torch.Tensor:
    """[R, 3] the shading normal at a vertex whose unit blended ``normal`` [R, 3] may face away from the unit
    direction back along the ray ``wo`` [R, 3]; front-facing normals are kept. A back-facing one (``PathConfig.
    back_normal``): "flip" gives -n; "mirror" gives n - 2 (n . wo) wo, n mirrored across the plane normal to the
    ray (unit, facing wo). Where a ray enters a ball through its unseen far side and meets the inside of the seen
    half at p1, the seen normal there is (a + s d) / r (a: centre to the chord's midpoint, normal to the ray's
    direction d; s: half the chord); the far side's normal where the ray should have met it is (a - s d) / r, the
    mirrored one. Both give the same reflected direction at a grazing back-facing normal's limit (n . wo -> 0)."""
    cos = (normal * wo).sum(-1, keepdim=True)
    if rule == "flip":
        other = -normal
    elif rule == "mirror":
        other = normal - 2.0 * cos * wo
    else:
        raise ValueError(f"back_normal must be one of {BACK_NORMALS}, got {rule!r}")
    return torch.where(cos < 0, other, normal)


def _scale_grad(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """x in the forward pass, scale * dL/dx in the backward pass."""
    return x.detach() + scale * (x - x.detach())


def trace_paths(
    trace_fn: TraceFn,
    origins: torch.Tensor,  # [R, 3]
    dirs: torch.Tensor,  # [R, 3] unit
    gaussians: Gaussians,
    config: PathConfig = PathConfig(),
    generator: torch.Generator | None = None,
    primary: TraceOutput | None = None,
) -> PathOutput:
    """One path sample per ray. ``primary`` may be passed to reuse a first segment (N spp rendering): the tracer's
    output as it is (``PathOutput.primary`` holds it shaded, ``shade_diffuse``)."""
    if primary is None:
        primary = trace_fn(origins, dirs, gaussians)
    primary, v = _shade(primary, dirs, config)
    rays = origins.shape[0]
    specular = torch.zeros((rays, 3), dtype=origins.dtype, device=origins.device)
    out = PathOutput(primary=primary, specular=specular)
    if config.max_path_length == 1 or rays == 0:
        return out

    index = torch.arange(rays, device=origins.device)  # rays still alive -> row in the full batch
    seg = primary
    o, d = origins, dirs
    throughput = torch.ones((rays, 3), dtype=origins.dtype, device=origins.device)
    for _ in range(config.max_path_length - 1):
        if v is None:  # (shading computed it, unless the lobe is "lambert")
            v = vertex(seg, config)
        keep, f0 = v.reflects, v.f0
        wo = -d
        n = back_normal_from_behind(v.normal, wo, config.back_normal)
        rough = v.roughness.clamp(config.min_roughness, 1.0)
        x = o + d * vertex_depth(seg, config.reflection_origin)
        # drawn where the generator lives (a CPU generator gives the same paths on every device)
        u = torch.rand((len(index), 2), generator=generator, dtype=o.dtype,
                       device=o.device if generator is None else generator.device)
        if u.device != o.device:  # CPU draws for GPU rays: copied from pinned memory, the host does not wait for it
            u = u.pin_memory().to(o.device, non_blocking=True)
        f90, dielectric = fresnel_f90(f0, config.fresnel), dielectric_weight(f0, config.fresnel)
        wi, _, weight, valid = sample_specular(n, wo, rough, f0, u[:, 0], u[:, 1], method=config.sampler, f90=f90,
                                               dielectric=dielectric)
        # (no branch on "any mirror": selecting costs less than a device read-back)
        mirror = v.roughness <= config.min_roughness
        cos_o = (n * wo).sum(-1).clamp(0.0, 1.0)
        wi = torch.where(mirror[:, None], reflect(d, n), wi)
        weight = torch.where(mirror[:, None], fresnel(f0, cos_o, f90, dielectric), weight)
        valid = torch.where(mirror, cos_o > 0, valid)
        keep = keep & valid & (weight.amax(-1) > 0)
        if config.min_throughput > 0:
            # the bounce's value and its gradient (to the Gaussians it hits) are both proportional to the throughput:
            # a path below min_throughput carries at most that share of a mirror's gradient; not traced
            reach = (throughput * weight.detach()).amax(-1)
            low = keep & (reach < config.min_throughput)
            out.stopped.append(torch.stack([low.sum().to(reach.dtype), torch.where(low, reach, 0.0).sum(),
                                            torch.where(keep, reach, 0.0).sum()]))
            keep = keep & ~low
        live = keep.nonzero().reshape(-1)  # the one read-back of a bounce; rows are gathered by index after it
        alive = torch.zeros(rays, dtype=torch.bool, device=origins.device)
        alive[index[live]] = True
        out.alive.append(alive)
        if live.numel() == 0:
            break
        index = index[live]
        throughput = throughput[live] * weight[live].detach()
        out.throughput.append(torch.zeros(rays, dtype=throughput.dtype, device=origins.device)
                              .index_put((index,), throughput.amax(-1)))
        d = wi[live]
        cos_r = (n[live] * d).sum(-1).abs().clamp_min(config.origin_grazing)
        o = x[live] + (config.origin_offset / cos_r)[:, None] * d
        grad_scale = (1.0 - rough[live]).clamp_min(0.0) ** config.grad_roughness_power
        seg, v = _shade(trace_fn(o, d, gaussians), d, config)
        contrib = throughput * _scale_grad(seg.diffuse, grad_scale[:, None])
        bounce = torch.zeros_like(specular).index_put((index,), contrib)
        out.bounces.append(bounce)
        specular = specular + bounce
    out.specular = specular
    return out
