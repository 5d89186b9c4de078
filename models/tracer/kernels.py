"""Tracer kernels: one source for CPU and CUDA.

forward_kernel: per ray, one BVH traversal stores every accepted hit in the replay
buffer, then rounds of "take the k nearest beyond the last taken" (in-place
selection, so the blended prefix ends up sorted) are composited front to back.
backward_kernel: replays the sorted prefix in reverse, no traversal.
fused_kernel: forward, per-pixel L1 loss gradient and backward in one thread per ray.
Semantics (tail rule, outputs) are those of `output.TraceOutput`.
"""

from __future__ import annotations

import warp as wp

from models.tracer.hit import eval_packed, hit_grad_geometry, hit_less
from models.tracer.structs import (
    GaussianData,
    GaussianGrads,
    L1Loss,
    RayGrads,
    RayOutputs,
    Replay,
    TraceParams,
)


@wp.func
def collect_hits(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                 outs: RayOutputs) -> int:
    """Single traversal: store all accepted hits; returns their count (may exceed capacity)."""
    query = wp.bvh_query_ray(prm.bvh, o, d)
    gid = int(0)
    n = int(0)
    cand = int(0)
    obb = int(0)
    while wp.bvh_query_next(query, gid):
        cand += 1
        h = eval_packed(o, d, g.packed[gid], prm.kernel_p, prm.alpha_min, prm.alpha_max, prm.t_min, prm.obb_test)
        if h[2] > 0.0:
            obb += 1
        if h[1] > 0.0:
            if n < prm.capacity:
                rep.ids[ray, n] = gid
                rep.t[ray, n] = h[0]
                rep.alpha[ray, n] = h[1]
            n += 1
    outs.candidates[ray] = cand
    outs.obb_candidates[ray] = obb
    return n


@wp.func
def write_outputs(ray: int, n_acc: int, blended: int, trans: float, c_diffuse: wp.vec3, c_depth: float,
                  c_normal: wp.vec3, c_rough: float, c_f0: wp.vec3, outs: RayOutputs):
    """Apply the tail rule (truncated: divide by 1 - T_end) and store."""
    scale = float(1.0)
    if blended < n_acc:
        scale = 1.0 / (1.0 - trans)
    outs.diffuse[ray] = scale * c_diffuse
    outs.depth[ray] = scale * c_depth
    outs.normal[ray] = scale * c_normal
    outs.roughness[ray] = scale * c_rough
    outs.f0[ray] = scale * c_f0
    outs.transmittance[ray] = trans
    outs.hit_count[ray] = n_acc
    outs.blended[ray] = blended
    outs.needed[ray] = 0


@wp.func
def forward_single(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                   outs: RayOutputs) -> int:
    """One traversal + sorted rounds of k. Returns 0 on replay overflow (outputs not written)."""
    n = collect_hits(ray, o, d, g, prm, rep, outs)
    if n > prm.capacity:
        outs.needed[ray] = n
        outs.hit_count[ray] = n
        return 0
    trans = float(1.0)
    c_diffuse = wp.vec3(0.0)
    c_normal = wp.vec3(0.0)
    c_f0 = wp.vec3(0.0)
    c_depth = float(0.0)
    c_rough = float(0.0)
    taken = int(0)
    blended = int(0)
    done = int(0)
    while taken < n and done == 0:
        end = wp.min(taken + prm.k, n)
        # take the k nearest beyond the last taken: selection into slots taken..end-1
        for j in range(taken, end):
            best = j
            t_best = rep.t[ray, j]
            id_best = rep.ids[ray, j]
            for m in range(j + 1, n):
                t_m = rep.t[ray, m]
                id_m = rep.ids[ray, m]
                if hit_less(t_m, id_m, t_best, id_best) != 0:
                    best = m
                    t_best = t_m
                    id_best = id_m
            if best != j:
                a_best = rep.alpha[ray, best]
                rep.ids[ray, best] = rep.ids[ray, j]
                rep.t[ray, best] = rep.t[ray, j]
                rep.alpha[ray, best] = rep.alpha[ray, j]
                rep.ids[ray, j] = id_best
                rep.t[ray, j] = t_best
                rep.alpha[ray, j] = a_best
        for j in range(taken, end):
            if done == 0:
                if trans < prm.trans_threshold:
                    done = 1
                else:
                    gid = rep.ids[ray, j]
                    a = rep.alpha[ray, j]
                    w = trans * a
                    c_diffuse += w * g.diffuse[gid]
                    c_normal += w * g.normal[gid]
                    c_f0 += w * g.f0[gid]
                    c_rough += w * g.roughness[gid]
                    c_depth += w * rep.t[ray, j]
                    rep.trans[ray, j] = trans
                    trans = trans * (1.0 - a)
                    blended += 1
        taken = end
    write_outputs(ray, n, blended, trans, c_diffuse, c_depth, c_normal, c_rough, c_f0, outs)
    return 1


@wp.func
def forward_kbuffer(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                    outs: RayOutputs) -> int:
    """Ablation (3DGRT-style): each round re-traverses the BVH keeping the k nearest hits
    beyond the last blended one in an insertion-sorted k-buffer (slots blended..blended+k-1
    of the replay buffer, so the backward is shared). Returns 0 on replay overflow."""
    trans = float(1.0)
    c_diffuse = wp.vec3(0.0)
    c_normal = wp.vec3(0.0)
    c_f0 = wp.vec3(0.0)
    c_depth = float(0.0)
    c_rough = float(0.0)
    blended = int(0)
    n_acc = int(0)
    cand = int(0)
    obb = int(0)
    last_t = float(-1.0e30)
    last_id = int(-1)
    first = int(1)
    done = int(0)
    while done == 0:
        if blended + prm.k > prm.capacity:
            outs.needed[ray] = blended + prm.k
            outs.candidates[ray] = cand
            outs.obb_candidates[ray] = obb
            return 0
        base = blended
        m = int(0)
        query = wp.bvh_query_ray(prm.bvh, o, d)
        gid = int(0)
        while wp.bvh_query_next(query, gid):
            h = eval_packed(o, d, g.packed[gid], prm.kernel_p, prm.alpha_min, prm.alpha_max, prm.t_min, prm.obb_test)
            if first != 0:
                cand += 1
                if h[2] > 0.0:
                    obb += 1
                if h[1] > 0.0:
                    n_acc += 1
            # (Warp evaluates both operands of `and`/`or`: nest the ifs to keep reads in bounds)
            if h[1] > 0.0:
                if hit_less(last_t, last_id, h[0], gid) != 0:
                    insert = int(0)
                    if m < prm.k:
                        insert = 1
                    elif hit_less(h[0], gid, rep.t[ray, base + m - 1], rep.ids[ray, base + m - 1]) != 0:
                        insert = 1
                    if insert != 0:
                        if m < prm.k:
                            m += 1
                        j = m - 1
                        shifting = int(1)
                        while shifting != 0:
                            shifting = 0
                            if j > 0:
                                if hit_less(h[0], gid, rep.t[ray, base + j - 1], rep.ids[ray, base + j - 1]) != 0:
                                    rep.t[ray, base + j] = rep.t[ray, base + j - 1]
                                    rep.ids[ray, base + j] = rep.ids[ray, base + j - 1]
                                    rep.alpha[ray, base + j] = rep.alpha[ray, base + j - 1]
                                    j -= 1
                                    shifting = 1
                        rep.t[ray, base + j] = h[0]
                        rep.ids[ray, base + j] = gid
                        rep.alpha[ray, base + j] = h[1]
        first = 0
        if m < prm.k:
            done = 1
        for j in range(base, base + m):
            if trans < prm.trans_threshold:
                done = 1
            else:
                if blended == j:
                    gj = rep.ids[ray, j]
                    a = rep.alpha[ray, j]
                    w = trans * a
                    c_diffuse += w * g.diffuse[gj]
                    c_normal += w * g.normal[gj]
                    c_f0 += w * g.f0[gj]
                    c_rough += w * g.roughness[gj]
                    c_depth += w * rep.t[ray, j]
                    rep.trans[ray, j] = trans
                    trans = trans * (1.0 - a)
                    blended += 1
                    last_t = rep.t[ray, j]
                    last_id = gj
        if m == 0 or trans < prm.trans_threshold:
            done = 1
    outs.candidates[ray] = cand
    outs.obb_candidates[ray] = obb
    write_outputs(ray, n_acc, blended, trans, c_diffuse, c_depth, c_normal, c_rough, c_f0, outs)
    return 1


@wp.func
def forward_ray(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                outs: RayOutputs) -> int:
    if prm.repeated_kbuffer != 0:
        return forward_kbuffer(ray, o, d, g, prm, rep, outs)
    return forward_single(ray, o, d, g, prm, rep, outs)


@wp.func
def backward_ray(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                 outs: RayOutputs, up: RayGrads, grads: GaussianGrads):
    """Reverse replay of the blended hits. With C = sum w f and out = s C (s = 1/(1 - T_end)
    when truncated, else 1): dL/dalpha_i = s G.(T_i f_i - S_i / (1 - alpha_i)) - A T_end / (1 - alpha_i),
    S_i = sum_{j>i} w_j f_j, A = dL/dT_end (+ G.C s^2 from the tail)."""
    n_blend = outs.blended[ray]
    if n_blend == 0:
        return
    t_end = outs.transmittance[ray]
    scale = float(1.0)
    if n_blend < outs.hit_count[ray]:
        scale = 1.0 / (1.0 - t_end)
    gd = up.diffuse[ray]
    gz = up.depth[ray]
    gn = up.normal[ray]
    gr = up.roughness[ray]
    gf = up.f0[ray]
    a_t = up.transmittance[ray]
    if scale != 1.0:
        # G.C with C = out / scale; dscale/dT_end = scale^2
        g_dot_c = (wp.dot(gd, outs.diffuse[ray]) + gz * outs.depth[ray] + wp.dot(gn, outs.normal[ray])
                   + gr * outs.roughness[ray] + wp.dot(gf, outs.f0[ray])) / scale
        a_t += g_dot_c * scale * scale
    gd = scale * gd
    gz = scale * gz
    gn = scale * gn
    gr = scale * gr
    gf = scale * gf
    suffix = float(0.0)
    for k in range(n_blend):
        i = n_blend - 1 - k
        gid = rep.ids[ray, i]
        a = rep.alpha[ray, i]
        t = rep.t[ray, i]
        t_i = rep.trans[ray, i]
        w = t_i * a
        gdotf = (wp.dot(gd, g.diffuse[gid]) + gz * t + wp.dot(gn, g.normal[gid])
                 + gr * g.roughness[gid] + wp.dot(gf, g.f0[gid]))
        inv_1ma = 1.0 / (1.0 - a)
        dl_dalpha = t_i * gdotf - (suffix + a_t * t_end) * inv_1ma
        suffix += w * gdotf
        wp.atomic_add(grads.diffuse, gid, w * gd)
        wp.atomic_add(grads.normal, gid, w * gn)
        wp.atomic_add(grads.roughness, gid, w * gr)
        wp.atomic_add(grads.f0, gid, w * gf)
        hit_grad_geometry(o, d, g.means[gid], g.w2l[gid], g.opacity[gid], prm.kernel_p, prm.alpha_max,
                          dl_dalpha, w * gz, grads.means, grads.w2l, grads.opacity, gid)


@wp.kernel
def forward_kernel(origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), g: GaussianData,
                   prm: TraceParams, rep: Replay, outs: RayOutputs):
    ray = wp.tid()
    forward_ray(ray, origins[ray], dirs[ray], g, prm, rep, outs)


@wp.kernel
def backward_kernel(origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), g: GaussianData,
                    prm: TraceParams, rep: Replay, outs: RayOutputs, up: RayGrads, grads: GaussianGrads):
    ray = wp.tid()
    backward_ray(ray, origins[ray], dirs[ray], g, prm, rep, outs, up, grads)


@wp.func
def l1_term(out: float, target: float, scale: float) -> wp.vec2:
    """(loss, dloss/dout) of scale * |out - target|; sign(0) = 0 as torch."""
    diff = out - target
    s = float(0.0)
    if diff > 0.0:
        s = 1.0
    elif diff < 0.0:
        s = -1.0
    return wp.vec2(scale * wp.abs(diff), scale * s)


@wp.kernel
def fused_kernel(origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), g: GaussianData,
                 prm: TraceParams, rep: Replay, outs: RayOutputs, targets: RayGrads, loss: L1Loss,
                 up: RayGrads, ray_loss: wp.array(dtype=float), grads: GaussianGrads):
    """Forward, L1 loss gradient into `up` (per ray) and backward, in one thread per ray."""
    ray = wp.tid()
    ok = forward_ray(ray, origins[ray], dirs[ray], g, prm, rep, outs)
    if ok == 0:
        return
    total = float(0.0)
    w_d = loss.weights[0] * loss.inv_rays / 3.0
    w_z = loss.weights[1] * loss.inv_rays
    w_n = loss.weights[2] * loss.inv_rays / 3.0
    w_r = loss.weights[3] * loss.inv_rays
    w_f = loss.weights[4] * loss.inv_rays / 3.0
    gd = wp.vec3(0.0)
    gn = wp.vec3(0.0)
    gf = wp.vec3(0.0)
    gz = float(0.0)
    gr = float(0.0)
    if w_d != 0.0:
        for c in range(3):
            e = l1_term(outs.diffuse[ray][c], targets.diffuse[ray][c], w_d)
            total += e[0]
            gd[c] = e[1]
    if w_z != 0.0:
        e = l1_term(outs.depth[ray], targets.depth[ray], w_z)
        total += e[0]
        gz = e[1]
    if w_n != 0.0:
        for c in range(3):
            e = l1_term(outs.normal[ray][c], targets.normal[ray][c], w_n)
            total += e[0]
            gn[c] = e[1]
    if w_r != 0.0:
        e = l1_term(outs.roughness[ray], targets.roughness[ray], w_r)
        total += e[0]
        gr = e[1]
    if w_f != 0.0:
        for c in range(3):
            e = l1_term(outs.f0[ray][c], targets.f0[ray][c], w_f)
            total += e[0]
            gf[c] = e[1]
    ray_loss[ray] = total
    up.diffuse[ray] = gd
    up.depth[ray] = gz
    up.normal[ray] = gn
    up.roughness[ray] = gr
    up.f0[ray] = gf
    up.transmittance[ray] = 0.0
    backward_ray(ray, origins[ray], dirs[ray], g, prm, rep, outs, up, grads)
