"""Split path tracer (Mitsuba 3, ``llvm_ad_rgb``): one pass writes RGB, diffuse, specular,
emission and the first-hit G-buffers of a pinhole view.

A custom wavefront loop over Mitsuba's scene queries (``ray_intersect``,
``sample_emitter_direction``, BSDF ``eval_pdf`` / ``sample``) with next-event
estimation and BSDF sampling combined by MIS (balance heuristic) at every vertex.

Layers (per sample, averaged over the pixel with a box filter):

* ``emission``: radiance of a light hit directly by the camera ray (depth 0 only).
* At the first vertex the same sampled path feeds three throughputs:
  ``rgb`` uses Mitsuba's full BSDF value / sample weight, ``diffuse`` the diffuse
  lobe only, ``specular`` the specular lobes only, both for NEE and for the
  continued path (every later vertex multiplies all three the same way).
  Routing by material (``mitsuba_scene.route_of``):
  - ``diffuse``, and ``principled`` with metallic = 0 and specular = 0 (Mitsuba's
    specular lobe is identically 0 there: eta = 1): everything -> diffuse;
  - ``conductor`` (smooth or rough), and ``principled`` with metallic = 1 (Mitsuba's
    diffuse weight is 1 - metallic = 0): everything -> specular;
  - other ``principled``: Mitsuba ignores lobe selection for it, so both lobes are
    evaluated separately (``lobes.py``: Disney diffuse + retro, and GGX specular with
    Mitsuba's principled Fresnel), while RGB keeps Mitsuba's own full value / weight.
  Hence R,G,B = diffuse + specular + emission, and for split principled surfaces this
  is a real check that the two lobe evaluations add up to Mitsuba's evaluation
  (per-sample relative error ~5e-7 measured). For routed materials it checks that the
  separately accumulated estimators agree.
* G-buffers at the first hit: ``depth`` = distance along the (unit) ray, ``normal`` =
  world-space shading normal flipped to face the camera, ``roughness`` (perceptual),
  ``f0``, ``mask`` = fraction of the pixel's samples that hit geometry. Depth,
  normal, roughness and F0 are averaged over the samples that hit (the normal is
  renormalised); pixels with no hit get 0.

Camera rays are generated here (not by a Mitsuba sensor) in the capture format's
convention: pixel (u, v) with jitter (jx, jy) in [0, 1)^2 has camera-space
direction ((u + jx - cx) / fl_x, -(v + jy - cy) / fl_y, -1), rotated by c2w[:3, :3],
origin c2w[:3, 3]; the pixel centre (jx = jy = 0.5) is exactly
``Camera.ray_directions()``.
"""

from __future__ import annotations

import numpy as np

from models.capture.layers import COLOUR as COLOR_LAYERS

from .lobes import principled_diffuse_eval, principled_specular_eval
from .mitsuba_scene import ROUTE_DIFFUSE, ROUTE_SPECULAR, ROUTE_SPLIT, MaterialEntry, mitsuba


def _first_hit_material(mi, dr, scene, si, valid, materials: dict[str, MaterialEntry]):
    """Per-lane route, roughness, F0, principled lobe parameters and the surface colour (texture or base
    colour: the albedo guide of the denoiser) at the first hit."""
    route = dr.full(mi.UInt32, ROUTE_DIFFUSE, dr.width(valid))
    rough = mi.Float(0.0)
    f0 = mi.Color3f(0.0)
    base = mi.Color3f(0.0)
    p_rough = mi.Float(0.0)
    metal = mi.Float(0.0)
    spec = mi.Float(0.0)
    albedo = mi.Color3f(0.0)
    for shape in scene.shapes():
        e = materials[shape.id()]
        m = valid & (si.shape == mi.ShapePtr(shape))
        route = dr.select(m, e.route, route)
        rough = dr.select(m, e.roughness, rough)
        color = e.texture.eval(si, m) if e.texture is not None else mi.Color3f(*e.base_color)
        f0 = dr.select(m, mi.Color3f(*e.f0_const) + e.f0_tex_weight * color, f0)
        albedo = dr.select(m, color, albedo)
        if e.principled:
            base = dr.select(m, color, base)
            p_rough = dr.select(m, e.roughness, p_rough)
            metal = dr.select(m, e.metallic, metal)
            spec = dr.select(m, e.specular, spec)
    return route, rough, f0, base, p_rough, metal, spec, albedo


def trace(scene, ray, rng, materials: dict[str, MaterialEntry], max_depth: int) -> dict:
    """Trace one sample per lane. Returns Dr.Jit arrays: rgb, diffuse, specular, emission
    (Color3f), depth, hit (Float), normal (Vector3f), roughness (Float), f0, albedo (Color3f)."""
    mi = mitsuba()
    import drjit as dr

    ctx = mi.BSDFContext()
    n = dr.width(ray.o)

    def next_2d():
        return mi.Point2f(rng.next_float32(), rng.next_float32())

    # ---- first hit: G-buffers and directly seen emission -----------------------------------
    si = scene.ray_intersect(ray, dr.full(mi.Bool, True, n))
    valid = si.is_valid()
    normal = si.sh_frame.n
    normal = dr.select(dr.dot(normal, ray.d) > 0, -normal, normal)
    normal = dr.select(valid, normal, mi.Vector3f(0.0))
    depth = dr.select(valid, si.t, 0.0)
    route, rough, f0, base, p_rough, metal, spec, albedo = _first_hit_material(mi, dr, scene, si, valid, materials)
    emission = si.emitter(scene).eval(si, valid)

    L = {k: mi.Color3f(0.0) for k in COLOR_LAYERS}
    beta = {k: mi.Color3f(1.0) for k in COLOR_LAYERS}
    active = mi.Bool(valid)
    prev_si = dr.zeros(mi.SurfaceInteraction3f, n)
    prev_pdf = mi.Float(1.0)
    prev_delta = mi.Bool(True)
    is_diff, is_spec = route == ROUTE_DIFFUSE, route == ROUTE_SPECULAR
    is_split = route == ROUTE_SPLIT

    for bounce in range(max_depth + 1):
        # ---- emitter hit by a BSDF-sampled ray (bounce >= 1), MIS-weighted ------------------
        if bounce > 0:
            si = scene.ray_intersect(ray, active)
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            em_pdf = scene.pdf_emitter_direction(prev_si, ds, active & ~prev_delta)
            mis = dr.select(prev_delta, 1.0, prev_pdf / dr.maximum(prev_pdf + em_pdf, 1e-30))
            le = dr.select(active, si.emitter(scene).eval(si, active) * mis, 0.0)
            for k in COLOR_LAYERS:
                L[k] += beta[k] * le
            active &= si.is_valid()
        if bounce == max_depth:
            break
        bsdf = si.bsdf(ray)

        # ---- next-event estimation -----------------------------------------------------------
        active_em = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds, em_w = scene.sample_emitter_direction(si, next_2d(), True, active_em)
        active_em &= ds.pdf != 0.0
        wo = si.to_local(ds.d)
        f_full, f_pdf = bsdf.eval_pdf(ctx, si, wo, active_em)
        mis_em = dr.select(ds.delta, 1.0, ds.pdf / dr.maximum(ds.pdf + f_pdf, 1e-30))
        nee = dr.select(active_em, em_w * mis_em, 0.0)

        # ---- BSDF sampling ---------------------------------------------------------------------
        bs, w = bsdf.sample(ctx, si, rng.next_float32(), next_2d(), active)

        if bounce == 0:
            # Split the first vertex into diffuse / specular lobes (see module docstring).
            # RGB uses Mitsuba's full value; diffuse / specular use separately evaluated lobes.
            f_d_split = principled_diffuse_eval(si.wi, wo, base, p_rough, metal, active_em & is_split)
            f_s_split = principled_specular_eval(si.wi, wo, base, p_rough, metal, spec, active_em & is_split)
            f_d = dr.select(is_diff, f_full, dr.select(is_split, f_d_split, 0.0))
            f_s = dr.select(is_spec, f_full, dr.select(is_split, f_s_split, 0.0))
            L["rgb"] += f_full * nee
            L["diffuse"] += f_d * nee
            L["specular"] += f_s * nee
            ok = (bs.pdf > 0.0) & dr.any(w != 0.0)
            split_ok = active & is_split & ok
            wd_split = principled_diffuse_eval(si.wi, bs.wo, base, p_rough, metal, split_ok)
            ws_split = principled_specular_eval(si.wi, bs.wo, base, p_rough, metal, spec, split_ok)
            inv_pdf = dr.select(ok, dr.rcp(bs.pdf), 0.0)
            beta["rgb"] = mi.Color3f(w)
            beta["diffuse"] = dr.select(is_diff, w, dr.select(is_split, wd_split * inv_pdf, 0.0))
            beta["specular"] = dr.select(is_spec, w, dr.select(is_split, ws_split * inv_pdf, 0.0))
        else:
            for k in COLOR_LAYERS:
                L[k] += beta[k] * f_full * nee
                beta[k] *= w

        # ---- continue the path ------------------------------------------------------------------
        ray = si.spawn_ray(si.to_world(bs.wo))
        prev_si = si
        prev_pdf = bs.pdf
        prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        active &= (bs.pdf > 0.0) & dr.any(w != 0.0)
        dr.eval(ray, prev_si, prev_pdf, prev_delta, active, L, beta)

    L["emission"] = emission
    L["rgb"] = L["rgb"] + emission
    return dict(L, depth=depth, hit=dr.select(valid, 1.0, 0.0), normal=normal, roughness=rough, f0=f0,
                albedo=albedo)


def _np(x, channels: int) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if channels == 1:
        return a.reshape(-1, 1)
    return a.T if a.shape[0] == channels and a.ndim == 2 else a.reshape(-1, channels)


def render_view(scene, materials: dict[str, MaterialEntry], camera, spp: int, seed: int,
                max_depth: int = 5, spp_chunk: int = 64) -> dict[str, np.ndarray]:
    """Render one view. ``camera``: anything with width, height, fl_x, fl_y, cx, cy, c2w (OpenGL).
    Returns layer -> float32 [H, W, C] (rgb, diffuse, specular, emission, depth, normal,
    roughness, f0, mask) and ``albedo`` (first-hit surface colour, the denoiser's guide; not a capture
    layer)."""
    mi = mitsuba()
    import drjit as dr

    w_px, h_px = int(camera.width), int(camera.height)
    npx = w_px * h_px
    c2w = np.asarray(camera.c2w, dtype=np.float64)
    rot, origin = c2w[:3, :3], c2w[:3, 3]
    sums = {k: np.zeros((npx, 3)) for k in ("rgb", "diffuse", "specular", "emission", "normal", "f0", "albedo")}
    sums.update({k: np.zeros((npx, 1)) for k in ("depth", "roughness", "hit")})

    # Per-view / per-pass scalars are opaque JIT variables, so the traced kernels are identical
    # across passes and views and Dr.Jit's kernel cache is hit instead of recompiling.
    def opaque(x):
        return dr.opaque(mi.Float, float(x))

    cx, cy, fx, fy = opaque(camera.cx), opaque(camera.cy), opaque(camera.fl_x), opaque(camera.fl_y)
    r = [[opaque(rot[i, j]) for j in range(3)] for i in range(3)]
    o = mi.Point3f(*(opaque(x) for x in origin))
    done = 0
    while done < spp:
        ns = min(spp_chunk, spp - done)
        idx = dr.arange(mi.UInt32, npx * ns)
        pix = idx // ns
        u, v = mi.Float(pix % w_px), mi.Float(pix // w_px)
        state = dr.opaque(mi.UInt64, (seed * 1_000_003 + done) % 2**63)
        rng = mi.PCG32(size=npx * ns, initstate=state, initseq=mi.UInt64(idx))
        jx, jy = rng.next_float32(), rng.next_float32()
        dx = (u + jx - cx) / fx
        dy = -(v + jy - cy) / fy
        d = mi.Vector3f(
            r[0][0] * dx + r[0][1] * dy - r[0][2],
            r[1][0] * dx + r[1][1] * dy - r[1][2],
            r[2][0] * dx + r[2][1] * dy - r[2][2],
        )
        ray = mi.Ray3f(o, dr.normalize(d))
        out = trace(scene, ray, rng, materials, max_depth)
        dr.eval(out)
        hit = _np(out["hit"], 1)
        for k in ("rgb", "diffuse", "specular", "emission"):
            sums[k] += _np(out[k], 3).reshape(npx, ns, 3).sum(1)
        for k, c in (("normal", 3), ("f0", 3), ("albedo", 3), ("depth", 1), ("roughness", 1)):
            sums[k] += (_np(out[k], c) * hit).reshape(npx, ns, c).sum(1)
        sums["hit"] += hit.reshape(npx, ns, 1).sum(1)
        done += ns

    nhit = np.maximum(sums["hit"], 1.0)
    buffers = {k: sums[k] / spp for k in ("rgb", "diffuse", "specular", "emission")}
    for k in ("depth", "roughness", "f0", "albedo"):
        buffers[k] = sums[k] / nhit
    nrm = sums["normal"]
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    buffers["normal"] = np.where(length > 0, nrm / np.maximum(length, 1e-30), 0.0)
    buffers["mask"] = sums["hit"] / spp
    return {k: np.ascontiguousarray(b.reshape(h_px, w_px, -1), dtype=np.float32) for k, b in buffers.items()}
