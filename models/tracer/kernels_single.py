"""Single traversal (the method): one BVH query stores every accepted hit in the replay
buffer, then rounds of "take the k nearest beyond the last taken" are selected in place
(so the blended prefix ends up sorted for the backward) and composited front to back."""

from __future__ import annotations

import warp as wp

from models.tracer.blend import blend_slot, blend_start, write_outputs
from models.tracer.hit import eval_packed, hit_less
from models.tracer.structs import GaussianData, RayOutputs, Replay, TraceParams


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
        h_t, h_a, h_in = eval_packed(o, d, g.packed[gid], prm.kernel_p, prm.alpha_min,
                                     prm.alpha_max, prm.t_min, prm.obb_test)
        if h_in > 0.0:
            obb += 1
        if h_a > 0.0:
            if n < prm.capacity:
                rep.ids[ray, n] = gid
                rep.t[ray, n] = h_t
                rep.alpha[ray, n] = h_a
            n += 1
    outs.candidates[ray] = cand
    outs.obb_candidates[ray] = obb
    return n


@wp.func
def forward_single(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                   outs: RayOutputs) -> int:
    """One traversal + sorted rounds of k. Returns 0 on replay overflow (outputs not written)."""
    n = collect_hits(ray, o, d, g, prm, rep, outs)
    if n > prm.capacity:
        outs.needed[ray] = n
        outs.hit_count[ray] = n
        return 0
    acc = blend_start()
    taken = int(0)
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
                if acc.trans < prm.trans_threshold:
                    done = 1
                else:
                    acc = blend_slot(acc, g, rep, ray, j)
        taken = end
    write_outputs(ray, n, acc, outs)
    return 1
