"""Bounce loop: analytic flat mirror, path stopping, gradient routing and scaling."""

import dataclasses
import math

import pytest
import torch

from models.gaussians import Gaussians
from models.pathtrace.brdf import diffuse_view_factor
from models.pathtrace.paths import BACK_NORMALS, PathConfig, back_normal_from_behind, trace_paths
from models.tracer import Tracer, TracerConfig, reference_trace


def scene(mirror_normal=(0.0, 0.0, 1.0), mirror_roughness=0.0, mirror_f0=1.0, dtype=torch.float64):
    """A huge flat opaque Gaussian in the plane z = 0 (the mirror) and one round Gaussian above it."""
    t = dict(dtype=dtype)
    return Gaussians(
        means=torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.2, 1.0]], **t),
        quats=torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]], **t),
        log_scales=torch.tensor([[math.log(50.0), math.log(50.0), math.log(1e-6)], [math.log(0.15)] * 3], **t),
        opacity_logits=torch.tensor([20.0, 2.0], **t),  # opacity -> 0.9999 (clamped alpha), 0.88
        diffuse=torch.tensor([[0.1, 0.1, 0.1], [0.9, 0.5, 0.2]], **t),
        normals=torch.tensor([list(mirror_normal), [1.0, 0.0, 0.0]], **t),
        roughness=torch.tensor([mirror_roughness, 0.8], **t),
        f0=torch.tensor([[mirror_f0] * 3, [0.04] * 3], **t),
    )


def camera_rays(n=12, dtype=torch.float64):
    """Rays from a camera above the mirror looking down at it, tilted toward the object's reflection."""
    eye = torch.tensor([-1.5, -1.5, 1.2], dtype=dtype)
    target = torch.tensor([-0.5, -0.55, 0.0], dtype=dtype)  # where the object's mirror image is seen
    fwd = (target - eye) / (target - eye).norm()
    right = torch.linalg.cross(fwd, torch.tensor([0.0, 0.0, 1.0], dtype=dtype))
    right /= right.norm()
    up = torch.linalg.cross(right, fwd)
    s = torch.linspace(-0.35, 0.35, n, dtype=dtype)
    yy, xx = torch.meshgrid(s, s, indexing="ij")
    d = fwd + xx.reshape(-1, 1) * right + yy.reshape(-1, 1) * up
    d = d / d.norm(dim=-1, keepdim=True)
    return eye.expand_as(d).clone(), d


def reference_fn(config=TracerConfig()):
    return lambda o, d, g: reference_trace(o, d, g, config)


@pytest.mark.parametrize("backend", ["reference", "warp"])
def test_flat_mirror_gives_mirrored_image(backend):
    dtype = torch.float64 if backend == "reference" else torch.float32
    g = scene(dtype=dtype)
    o, d = camera_rays(dtype=dtype)
    fn = reference_fn() if backend == "reference" else Tracer(TracerConfig(num_threads=1)).trace
    # lambert: what the mirror shows is the object's diffuse as the tracer blends it (test_disney_diffuse_* below)
    out = trace_paths(fn, o, d, g, PathConfig(max_path_length=2, diffuse_lobe="lambert"),
                      torch.Generator().manual_seed(1))
    # the mirror image: rays reflected at the plane, traced through the object alone
    t_plane = -o[:, 2] / d[:, 2]
    hit = o + d * t_plane[:, None]
    d_ref = d * torch.tensor([1.0, 1.0, -1.0], dtype=dtype)
    obj = Gaussians(**{k: v[1:] for k, v in g.params().items()})
    expected = reference_trace(hit, d_ref, obj).diffuse.to(dtype)
    assert torch.all(out.primary.hit_count == 1)  # primary rays see only the mirror
    assert expected.amax() > 0.3 and (expected.amax(-1) < 1e-3).any()  # the object, and around it
    assert (out.specular - expected).abs().max() < 1e-3
    opacity = 1 - out.primary.transmittance.reshape(-1)
    assert torch.allclose(out.primary.depth.reshape(-1) / opacity, t_plane, rtol=1e-5)


@pytest.mark.parametrize("backend", ["reference", "warp"])
def test_matte_surface_reflects_nothing_with_schlick_f90(backend):
    """A smooth F0 = 0 plane (the capture's matte materials: no specular lobe at all) under grazing-ish camera
    rays: with F90 = 1 (the paper's Schlick) it still reflects (1 - cos)^5 of the object; with schlick_f90 its
    specular is exactly 0, and a F0 = 0.04 plane (a real dielectric) reflects the same in both modes."""
    dtype = torch.float64 if backend == "reference" else torch.float32
    o, d = camera_rays(dtype=dtype)
    fn = reference_fn() if backend == "reference" else Tracer(TracerConfig(num_threads=1)).trace

    def specular(f0, fresnel):
        cfg = PathConfig(max_path_length=2, fresnel=fresnel)
        return trace_paths(fn, o, d, scene(mirror_f0=f0, dtype=dtype), cfg, torch.Generator().manual_seed(1)).specular

    assert specular(0.0, "schlick").amax() > 1e-3
    assert torch.all(specular(0.0, "schlick_f90") == 0)
    assert torch.equal(specular(0.04, "schlick_f90"), specular(0.04, "schlick"))
    assert specular(0.04, "schlick").amax() > 1e-3
    # "dielectric": the exact Fresnel reflects nothing at F0 = 0 either; at 0.04 it differs from Schlick's
    assert torch.all(specular(0.0, "dielectric") == 0)
    assert not torch.allclose(specular(0.04, "dielectric"), specular(0.04, "schlick_f90"))


@pytest.mark.parametrize("backend", ["reference", "warp"])
def test_truncated_mirror_reflects_from_its_surface(backend):
    """A mirror whose rays stop early (T < threshold with hits left): the tracer's tail rule already
    normalised depth / roughness / F0, so the reflection starts ON the mirror (dividing by 1 - T again put
    it ~1% of the depth behind the surface, under the mirror: the reflection came back black)."""
    dtype = torch.float64 if backend == "reference" else torch.float32
    g = scene(dtype=dtype)
    logit = math.log(0.991 / 0.009)  # T = 0.009 after the mirror: below the 0.01 threshold
    extra = {k: v[:1].clone() for k, v in g.params().items()}
    extra["means"][0, 2] = -1e-3  # a second mirror layer just below: a hit left unblended
    g = Gaussians(**{k: torch.cat([v[:1], extra[k], v[1:]]) for k, v in g.params().items()})
    g.opacity_logits[:2] = logit
    o, d = camera_rays(dtype=dtype)
    fn = reference_fn() if backend == "reference" else Tracer(TracerConfig(num_threads=1)).trace
    out = trace_paths(fn, o, d, g, PathConfig(max_path_length=2, diffuse_lobe="lambert"),
                      torch.Generator().manual_seed(1))
    assert torch.all(out.primary.hit_count > out.primary.blended_count)  # every primary ray truncated
    t_plane = -o[:, 2] / d[:, 2]
    hit = o + d * t_plane[:, None]
    d_ref = d * torch.tensor([1.0, 1.0, -1.0], dtype=dtype)
    obj = Gaussians(**{k: v[2:] for k, v in g.params().items()})
    expected = reference_trace(hit, d_ref, obj).diffuse.to(dtype)
    assert expected.amax() > 0.3
    assert (out.specular - expected).abs().max() < 2e-3


def test_path_length_one_and_short_normals_stop():
    o, d = camera_rays(6)
    gen = torch.Generator().manual_seed(0)
    out = trace_paths(reference_fn(), o, d, scene(), PathConfig(max_path_length=1), gen)
    assert torch.count_nonzero(out.specular) == 0 and out.bounces == []
    short = scene(mirror_normal=(0.0, 0.0, 0.5))  # accumulated normal norm 0.5 < 0.7: path stops
    out = trace_paths(reference_fn(), o, d, short, PathConfig(max_path_length=3), gen)
    assert torch.count_nonzero(out.specular) == 0
    assert not out.alive[0].any()


def test_half_transparent_vertex_with_agreeing_normals_reflects():
    """A mirror of opacity 0.5 with unit normals: its accumulated normal is 0.5 long, but per unit of opacity
    it is 1, so the path goes on (the length test is on normal / opacity, like roughness and F0) and reflects
    as the opaque mirror does (vertex values are conditional on the ray ending there). A zero normal (nothing
    known about the surface) still stops."""
    o, d = camera_rays(12)
    half = scene()
    half.opacity_logits[0] = 0.0  # opacity 0.5
    out = trace_paths(reference_fn(), o, d, half, PathConfig(max_path_length=2), torch.Generator().manual_seed(0))
    full = trace_paths(reference_fn(), o, d, scene(), PathConfig(max_path_length=2), torch.Generator().manual_seed(0))
    assert out.alive[0].all() and full.specular.amax() > 0.3
    assert torch.allclose(out.specular, full.specular, atol=1e-6)
    flat = scene(mirror_normal=(0.0, 0.0, 0.0))
    out = trace_paths(reference_fn(), o, d, flat, PathConfig(max_path_length=2), torch.Generator().manual_seed(0))
    assert not out.alive[0].any() and torch.count_nonzero(out.specular) == 0


def test_specular_gradients_reach_only_bounce_geometry_and_diffuse():
    g = scene().requires_grad_(True)
    o, d = camera_rays(12)
    out = trace_paths(reference_fn(), o, d, g, PathConfig(max_path_length=2), torch.Generator().manual_seed(2))
    out.specular.sum().backward()
    assert g.diffuse.grad[1].abs().sum() > 0  # the reflected object's colour
    assert g.means.grad[1].abs().sum() > 0  # and its geometry
    assert torch.all(g.diffuse.grad[0] == 0)  # the mirror's own colour: no specular gradient
    for name in ("normals", "roughness", "f0"):  # BRDF and normals are constants for the specular loss
        assert torch.all(getattr(g, name).grad == 0), name


def test_roughness_gradient_scaling_keeps_forward():
    o, d = camera_rays(12)
    grads, values = [], []
    for power in (0.0, 3.0):
        g = scene(mirror_roughness=0.5).requires_grad_(True)
        out = trace_paths(reference_fn(), o, d, g, PathConfig(max_path_length=2, grad_roughness_power=power),
                          torch.Generator().manual_seed(3))
        out.specular.sum().backward()
        values.append(out.specular.detach())
        grads.append(g.diffuse.grad[1].clone())
    assert torch.equal(values[0], values[1])
    assert torch.allclose(grads[1], grads[0] * 0.5**3, rtol=1e-10)


@pytest.mark.parametrize("roughness", [0.0, 1.0])
@pytest.mark.parametrize("f0", [0.0, 1.0])
@pytest.mark.parametrize("log_scale", [math.log(1e-6), math.log(1e3), math.log(0.1)])
def test_extremes_finite_values_and_gradients(roughness, f0, log_scale):
    """Grazing views included: rays at 89.4 degrees to the mirror normal; opacity ~1 on the mirror."""
    g = scene(mirror_roughness=roughness, mirror_f0=f0, dtype=torch.float32)
    g.log_scales[1] = log_scale
    g.opacity_logits[1] = 12.0  # opacity 0.999994
    g.requires_grad_(True)
    o, d = camera_rays(10, dtype=torch.float32)
    grazing_o = torch.tensor([[-3.0, 0.0, 0.03]]).repeat(8, 1)
    grazing_d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.05 * i, -0.01] for i in range(8)]), dim=-1)
    o, d = torch.cat([o, grazing_o]), torch.cat([d, grazing_d])
    out = trace_paths(Tracer(TracerConfig(num_threads=2)).trace, o, d, g, PathConfig(max_path_length=3),
                      torch.Generator().manual_seed(4))
    loss = out.final.sum() + out.primary.depth.sum() + out.primary.normal.sum()
    loss.backward()
    assert torch.isfinite(out.final).all() and torch.isfinite(out.primary.depth).all()
    # energy: each reflection segment returns at most the brightest diffuse value (throughput <= 1 for F0 <= 1)
    # times the largest view factor of the (default) Disney diffuse: a rough surface seen at grazing, 1.56
    top = float(diffuse_view_factor(torch.zeros(1), torch.ones(1), torch.ones(1, 3), PathConfig().diffuse_lobe).max())
    assert 1.55 < top < 1.56
    for bounce in out.bounces:
        assert bounce.max() <= g.diffuse.max() * top + 1e-5
    for name, p in g.params().items():
        assert torch.isfinite(p.grad).all(), name


@pytest.mark.parametrize("f0", [0.002, 0.05, 0.9])
def test_min_throughput_stops_only_paths_below_it(f0):
    """One bounce (one draw: the same directions with and without the cut-off): a path is stopped exactly where its
    throughput F(n.wo) is below min_throughput; it loses at most min_throughput x the radiance it would have read,
    every other path is unchanged, and ``stopped`` counts it with its weight."""
    g = scene(mirror_f0=f0)
    o, d = camera_rays()
    threshold = 0.04
    full = trace_paths(reference_fn(), o, d, g, PathConfig(max_path_length=2), torch.Generator().manual_seed(0))
    cut = trace_paths(reference_fn(), o, d, g, PathConfig(max_path_length=2, min_throughput=threshold),
                      torch.Generator().manual_seed(0))
    # Schlick F at the mirror (perfect mirror: the throughput of the bounce), for every camera ray; the default
    # Fresnel's grazing reflectance F90 = min(1, 50 F0)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype)
    cos = (-d @ n).clamp(0, 1)
    schlick = f0 + (min(1.0, 50 * f0) - f0) * (1 - cos) ** 5
    low = full.alive[0] & (schlick < threshold)
    assert torch.equal(cut.alive[0], full.alive[0] & ~low)
    assert torch.equal(cut.specular[~low], full.specular[~low])
    assert (cut.specular[low] == 0).all()
    assert ((full.specular - cut.specular).abs() <= threshold * g.diffuse.amax() + 1e-12).all()
    count, stopped_weight, weight = cut.stopped[0].tolist()
    assert count == int(low.sum())
    assert stopped_weight == pytest.approx(float(schlick[low].sum()), rel=1e-9, abs=1e-12)
    assert weight == pytest.approx(float(schlick[full.alive[0]].sum()), rel=1e-9)
    assert low.any() == (f0 < threshold) and not full.stopped  # (the default cuts nothing, records nothing)
    with pytest.raises(ValueError, match="min_throughput"):
        PathConfig(min_throughput=1.0)


@pytest.mark.parametrize("backend", ["reference", "warp"])
def test_reflections_start_at_the_surfaces_front_not_inside_its_gaussians(backend):
    """A mirror whose Gaussians spread in depth (four planes 2 cm apart, opacity 0.6 each), seen at 60 degrees,
    under a white sky plane. The expected depth lies between the planes (the surface seen at an angle from where no
    training camera stood: zoo_spheres' metal, README): a reflection starting there crosses the planes above it
    and returns a fraction of the sky; from the front depth (the hits blended while T >= 0.5: the top plane) it
    returns the sky itself, as a mirror should."""
    dtype = torch.float64 if backend == "reference" else torch.float32
    t = dict(dtype=dtype)
    z = [0.0, -0.02, -0.04, -0.06]
    n = len(z) + 1
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, h] for h in z] + [[0.0, 0.0, 3.0]], **t),
        quats=torch.tensor([[1.0, 0, 0, 0]] * n, **t),
        log_scales=torch.tensor([[math.log(50.0), math.log(50.0), math.log(1e-6)]] * n, **t),
        opacity_logits=torch.tensor([math.log(0.6 / 0.4)] * len(z) + [20.0], **t),
        diffuse=torch.tensor([[0.0] * 3] * len(z) + [[1.0] * 3], **t),
        normals=torch.tensor([[0.0, 0.0, 1.0]] * n, **t),
        roughness=torch.zeros(n, **t),
        f0=torch.tensor([[1.0] * 3] * len(z) + [[0.04] * 3], **t),
    )
    d = torch.tensor([[math.sin(math.radians(60)), 0.0, -math.cos(math.radians(60))]] * 4, **t)
    o = torch.tensor([[-1.0, y, 1.0] for y in (-0.3, -0.1, 0.1, 0.3)], **t)
    fn = reference_fn() if backend == "reference" else Tracer(TracerConfig(num_threads=1)).trace
    top = 1.0 / math.cos(math.radians(60))  # the ray meets the top plane at t = 2
    spec = {}
    for origin in ("front", "expected"):
        out = trace_paths(fn, o, d, g, PathConfig(max_path_length=2, reflection_origin=origin, diffuse_lobe="lambert"),
                          torch.Generator().manual_seed(0))
        spec[origin] = out.specular.mean(-1)
        torch.testing.assert_close(out.primary.front_depth, torch.full((4,), top, **t), atol=1e-4, rtol=0)
        assert (out.primary.depth / out.primary.opacity()[:, 0] > top + 0.02).all()  # the expected one: inside
    torch.testing.assert_close(spec["front"], torch.ones(4, **t), atol=1e-3, rtol=0)
    assert (spec["expected"] < 0.5).all(), spec["expected"]


@pytest.mark.parametrize("backend", ["reference", "warp"])
def test_disney_diffuse_shades_the_primary_and_every_bounce(backend):
    """``diffuse_lobe="disney"``: the diffuse layer and what a reflection reads are the tracer's diffuse times
    ``diffuse_view_factor`` of the blended normal / roughness / F0 seen along that segment's rays; on a scene
    whose every F0 is 0 (no specular lobe) nothing changes; "lambert" is the paper's."""
    dtype = torch.float64 if backend == "reference" else torch.float32
    g = scene(dtype=dtype)
    o, d = camera_rays(dtype=dtype)
    fn = reference_fn() if backend == "reference" else Tracer(TracerConfig(num_threads=1)).trace

    def run(lobe, gs=g):
        return trace_paths(fn, o, d, gs, PathConfig(max_path_length=2, diffuse_lobe=lobe),
                           torch.Generator().manual_seed(1))

    lam, dis = run("lambert"), run("disney")
    raw = fn(o, d, g)
    assert torch.equal(lam.primary.diffuse, raw.diffuse)
    # primary: the mirror plane (normal z, F0 1, roughness 0) seen along d
    factor = diffuse_view_factor(d[:, 2].abs(), torch.zeros(len(d), dtype=dtype), torch.ones(len(d), 3, dtype=dtype),
                                 "disney")
    assert torch.allclose(dis.primary.diffuse, raw.diffuse * factor, rtol=1e-5, atol=1e-7)
    assert (factor < 0.97).any() and (factor < 0.98).all()
    # the bounce: the object (normal x, F0 0.04, roughness 0.8) seen along the mirrored rays
    t_plane = -o[:, 2] / d[:, 2]
    hit, d_ref = o + d * t_plane[:, None], d * torch.tensor([1.0, 1.0, -1.0], dtype=dtype)
    obj = Gaussians(**{k: v[1:] for k, v in g.params().items()})
    seen = reference_trace(hit, d_ref, obj)
    opacity = seen.opacity()
    f = diffuse_view_factor(d_ref[:, 0].abs(), seen.roughness.reshape(-1) / opacity.reshape(-1),
                            (seen.f0 / opacity).clamp(0, 1), "disney")
    lit = seen.diffuse.amax(-1) > 1e-2
    ratio = dis.specular[lit] / lam.specular[lit]
    assert torch.allclose(ratio, f[lit].to(dtype).expand_as(ratio), rtol=2e-3)
    assert (f[lit] - 1).abs().max() > 1e-3  # the object's factor differs from 1 somewhere seen
    # every F0 = 0: the same paths exactly (the mirror reflects nothing then, so compare the primary too)
    matte = Gaussians(**{**g.params(), "f0": torch.zeros_like(g.f0)})
    a, b = run("lambert", matte), run("disney", matte)
    assert torch.equal(a.primary.diffuse, b.primary.diffuse) and torch.equal(a.specular, b.specular)
    with pytest.raises(ValueError, match="diffuse_lobe"):
        PathConfig(diffuse_lobe="phong")


@pytest.mark.parametrize("backend", ["reference", "warp"])
def test_hole_fill_gives_what_a_ray_blended_at_full_opacity(backend):
    """``hole_fill``: a half-transparent mirror (opacity 0.5) seen over nothing: the primary diffuse and what
    its reflection reads are each the tracer's blend divided by that segment's accumulated opacity, so the
    mirror's own diffuse comes out as the opaque mirror's, and so does the object its rays meet half-covered
    (a bounce segment is filled too); off (the default) they keep the black behind them. A ray that blended
    next to nothing is divided by HOLE_FILL_MIN_OPACITY at most, and one that blended nothing stays 0."""
    from models.pathtrace.paths import HOLE_FILL_MIN_OPACITY, fill_hole

    dtype = torch.float64 if backend == "reference" else torch.float32
    fn = reference_fn() if backend == "reference" else Tracer(TracerConfig(num_threads=1)).trace
    o, d = camera_rays(dtype=dtype)
    half = scene(dtype=dtype)
    half.opacity_logits[:] = 0.0  # mirror and object at opacity 0.5
    full = scene(dtype=dtype)
    full.opacity_logits[:] = 20.0

    def run(g, fill):
        return trace_paths(fn, o, d, g, PathConfig(max_path_length=2, hole_fill=fill, diffuse_lobe="lambert"),
                           torch.Generator().manual_seed(1))

    filled, plain, opaque = run(half, True), run(half, False), run(full, True)
    raw = fn(o, d, half)
    assert torch.equal(plain.primary.diffuse, raw.diffuse)  # off: the paper's background 0
    opacity = 1 - raw.transmittance.reshape(-1, 1)
    assert (opacity - 0.5).abs().max() < 0.02
    assert torch.allclose(filled.primary.diffuse, raw.diffuse / opacity, rtol=1e-5)
    assert torch.allclose(filled.primary.diffuse, opaque.primary.diffuse, atol=2e-3)
    # the reflection reads the half-transparent object filled: the opaque object's radiance, brighter than off
    lit = opaque.specular.amax(-1) > 0.3
    assert lit.any() and (plain.specular[lit] < 0.7 * filled.specular[lit]).all()
    # a faint ray: at most 1 / HOLE_FILL_MIN_OPACITY brighter; nothing blended stays 0
    seg = fn(o, d, half)
    faint = dataclasses.replace(seg, transmittance=torch.full_like(seg.transmittance, 0.99),
                                hit_count=seg.blended_count)
    assert torch.allclose(fill_hole(faint, PathConfig(hole_fill=True)).diffuse, seg.diffuse / HOLE_FILL_MIN_OPACITY)
    empty = dataclasses.replace(seg, diffuse=torch.zeros_like(seg.diffuse), transmittance=torch.ones_like(
        seg.transmittance), hit_count=torch.zeros_like(seg.hit_count), blended_count=torch.zeros_like(seg.hit_count))
    assert torch.count_nonzero(fill_hole(empty, PathConfig(hole_fill=True)).diffuse) == 0


@pytest.mark.parametrize("grazing", [1.0, 0.1])
def test_reflections_start_farther_out_the_more_grazing_they_leave(grazing):
    """A reflection starts ``origin_offset / max(|n . r|, origin_grazing)`` past its surface point along the
    reflected ray r (a grazing one crosses the surface's own Gaussians over thickness / cos); 1 = a fixed distance
    (models trained before the option). The flat mirror at z = 0: the points and angles are known exactly."""
    o, d = camera_rays(dtype=torch.float64)
    d = torch.cat([d, torch.nn.functional.normalize(d * torch.tensor([6.0, 6.0, 1.0], dtype=torch.float64), dim=1)])
    o = torch.cat([o, o])  # the same rays and flatter ones: |cos| 0.03-0.2
    calls = []

    def fn(oo, dd, g):
        calls.append((oo.clone(), dd.clone()))
        return reference_trace(oo, dd, g)

    cfg = PathConfig(max_path_length=2, origin_offset=0.05, origin_grazing=grazing)
    mirror = Gaussians(**{k: v[:1] for k, v in scene().params().items()})  # the mirror alone: every ray meets it
    trace_paths(fn, o, d, mirror, cfg, torch.Generator().manual_seed(0))
    start, r = calls[1]
    # the rows that went on (a path may stop: its Fresnel weight 0): matched by their mirrored direction
    row = torch.cdist(r, d * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)).argmin(1)
    assert len(row) >= len(d) - 2
    assert torch.allclose(r, d[row] * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64), atol=1e-5)
    hit = (o + d * (-o[:, 2] / d[:, 2])[:, None])[row]
    cos = r[:, 2].abs()
    assert (cos < 0.1).any() and (cos > 0.3).any()
    along = ((start - hit) * r).sum(-1)
    torch.testing.assert_close(along, 0.05 / cos.clamp_min(grazing), rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(start, hit + along[:, None] * r, rtol=1e-6, atol=1e-6)  # on the reflected line
    with pytest.raises(ValueError, match="origin_grazing"):
        PathConfig(origin_grazing=0.0)


def test_a_back_facing_normal_mirrored_across_the_ray_is_a_balls_far_side_normal():
    """``back_normal_from_behind``: a ray that enters a ball through its unseen far side meets the inside of the
    seen half at p1, whose normal faces away from the ray. "mirror" gives exactly the normal the ball has where
    the ray should have met it first (p2); "flip" gives -n (a thin sheet's other side); front-facing normals are
    kept by both. Random balls and chords, float64."""
    gen = torch.Generator().manual_seed(3)
    rows = 500
    centre = torch.randn(rows, 3, generator=gen, dtype=torch.float64)
    radius = 0.2 + torch.rand(rows, generator=gen, dtype=torch.float64)
    d = torch.nn.functional.normalize(torch.randn(rows, 3, generator=gen, dtype=torch.float64), dim=1)
    # a chord: its midpoint m = centre + a with a normal to d, |a| < radius
    a = torch.randn(rows, 3, generator=gen, dtype=torch.float64)
    a = torch.nn.functional.normalize(a - (a * d).sum(-1, keepdim=True) * d, dim=1)
    a = a * (radius * torch.rand(rows, generator=gen, dtype=torch.float64) * 0.99)[:, None]
    half = (radius ** 2 - (a * a).sum(-1)).sqrt()
    p1 = centre + a + half[:, None] * d  # the far intersection (the seen half, met from inside)
    p2 = centre + a - half[:, None] * d  # the near one (the unseen far side)
    n1 = (p1 - centre) / radius[:, None]
    n2 = (p2 - centre) / radius[:, None]
    wo = -d
    assert ((n1 * wo).sum(-1) < 0).all()
    mirrored = back_normal_from_behind(n1, wo, "mirror")
    torch.testing.assert_close(mirrored, n2, rtol=0, atol=1e-12)
    torch.testing.assert_close(back_normal_from_behind(n1, wo, "flip"), -n1, rtol=0, atol=0)
    for rule in BACK_NORMALS:  # seen from the front: kept
        torch.testing.assert_close(back_normal_from_behind(n2, wo, rule), n2, rtol=0, atol=0)
    # both face the ray; the reflected directions agree only at the grazing limit
    assert ((mirrored * wo).sum(-1) > 0).all()
    with pytest.raises(ValueError, match="back_normal"):
        back_normal_from_behind(n1, wo, "outward")
    with pytest.raises(ValueError, match="back_normal"):
        PathConfig(back_normal="outward")


@pytest.mark.parametrize("rule", BACK_NORMALS)
def test_a_mirror_seen_from_behind_reflects_by_the_configured_rule(rule):
    """``PathConfig.back_normal`` reaches the bounce: the flat mirror at z = 0 (normal +z) seen from below (every
    vertex back-facing): flip reflects as a mirror facing down, mirror as one whose normal is n - 2 (n . wo) wo."""
    o, d = camera_rays(dtype=torch.float64)
    o, d = o * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64), d * torch.tensor([1.0, 1.0, -1.0],
                                                                                      dtype=torch.float64)
    calls = []

    def fn(oo, dd, g):
        calls.append(dd.clone())
        return reference_trace(oo, dd, g)

    mirror = Gaussians(**{k: v[:1] for k, v in scene().params().items()})
    trace_paths(fn, o, d, mirror, PathConfig(max_path_length=2, back_normal=rule), torch.Generator().manual_seed(0))
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(d)
    normal = -n if rule == "flip" else n + 2.0 * (n * d).sum(-1, keepdim=True) * -d
    want = d - 2.0 * (d * normal).sum(-1, keepdim=True) * normal
    got = calls[1]
    row = torch.cdist(got, want).argmin(1)  # the rows that went on
    assert len(row) >= len(d) - 2
    torch.testing.assert_close(got, want[row], rtol=0, atol=1e-6)
    if rule == "flip":
        assert (got[:, 2] < 0).all()  # back down, away from the mirror's seen side
