"""Ablation: 3DGRT-style repeated k-buffer traversal (one BVH query per round of k hits)."""

from __future__ import annotations

import warp as wp

from models.tracer.blend import blend_slot, blend_start, write_outputs
from models.tracer.hit import eval_packed, hit_less
from models.tracer.structs import GaussianData, RayOutputs, Replay, TraceParams


@wp.func
def forward_kbuffer(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                    outs: RayOutputs) -> int:
    """Ablation (3DGRT-style): each round re-traverses the BVH keeping the k nearest hits
    beyond the last blended one in an insertion-sorted k-buffer (slots blended..blended+k-1
    of the replay buffer, so the backward is shared). Returns 0 on replay overflow."""
    acc = blend_start()
    n_acc = int(0)
    cand = int(0)
    obb = int(0)
    last_t = float(-1.0e30)
    last_id = int(-1)
    first = int(1)
    done = int(0)
    while done == 0:
        if acc.blended + prm.k > prm.capacity:
            outs.needed[ray] = acc.blended + prm.k
            outs.candidates[ray] = cand
            outs.obb_candidates[ray] = obb
            return 0
        base = acc.blended
        m = int(0)
        query = wp.bvh_query_ray(prm.bvh, o, d)
        gid = int(0)
        while wp.bvh_query_next(query, gid):
            h_t, h_a, h_in = eval_packed(o, d, g.packed[gid], prm.kernel_p, prm.alpha_min,
                                         prm.alpha_max, prm.t_min, prm.obb_test)
            if first != 0:
                cand += 1
                if h_in > 0.0:
                    obb += 1
                if h_a > 0.0:
                    n_acc += 1
            # (Warp evaluates both operands of `and`/`or`: nest the ifs to keep reads in bounds)
            if h_a > 0.0:
                if hit_less(last_t, last_id, h_t, gid) != 0:
                    insert = int(0)
                    if m < prm.k:
                        insert = 1
                    elif hit_less(h_t, gid, rep.t[ray, base + m - 1], rep.ids[ray, base + m - 1]) != 0:
                        insert = 1
                    if insert != 0:
                        if m < prm.k:
                            m += 1
                        j = m - 1
                        shifting = int(1)
                        while shifting != 0:
                            shifting = 0
                            if j > 0:
                                if hit_less(h_t, gid, rep.t[ray, base + j - 1], rep.ids[ray, base + j - 1]) != 0:
                                    rep.t[ray, base + j] = rep.t[ray, base + j - 1]
                                    rep.ids[ray, base + j] = rep.ids[ray, base + j - 1]
                                    rep.alpha[ray, base + j] = rep.alpha[ray, base + j - 1]
                                    j -= 1
                                    shifting = 1
                        rep.t[ray, base + j] = h_t
                        rep.ids[ray, base + j] = gid
                        rep.alpha[ray, base + j] = h_a
        first = 0
        if m < prm.k:
            done = 1
        for j in range(base, base + m):
            if acc.trans < prm.trans_threshold:
                done = 1
            else:
                if acc.blended == j:
                    last_t = rep.t[ray, j]
                    last_id = rep.ids[ray, j]
                    acc = blend_slot(acc, g, rep, ray, j)
        if m == 0 or acc.trans < prm.trans_threshold:
            done = 1
    outs.candidates[ray] = cand
    outs.obb_candidates[ray] = obb
    write_outputs(ray, n_acc, acc, outs)
    return 1
