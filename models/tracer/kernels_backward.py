"""Backward from the replay buffer: the blended hits in reverse order, no traversal."""

from __future__ import annotations

import warp as wp

from models.tracer.hit import hit_grad_geometry
from models.tracer.structs import GaussianData, GaussianGrads, RayGrads, RayOutputs, Replay, TraceParams


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
        if grads.track != 0:
            if grads.touched[gid] == 0:  # (the row is this launch's alone: no atomics needed)
                grads.touched[gid] = 1
                c = grads.touched_count[0]
                grads.touched_ids[c] = gid
                grads.touched_count[0] = c + 1
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
        rec = g.packed[gid]
        hit_grad_geometry(o, d, wp.vec3(rec[0], rec[1], rec[2]),
                          wp.mat33(rec[3], rec[4], rec[5], rec[6], rec[7], rec[8], rec[9], rec[10], rec[11]),
                          rec[12], a, prm.kernel_p, prm.alpha_max,
                          dl_dalpha, w * gz, grads.means, grads.w2l, grads.opacity, gid)
