"""Front-to-back ordered traversal with early termination (ablation; TracerConfig.traversal = "ordered").

Best-first over the ordered BVH (binary min-heap of nodes keyed by their entry t). A hit's
max-response point lies in its Gaussian's box, inside every ancestor's AABB, so its t is
>= the entry t of any node that contains it. Hence stored hits with t below the smallest
entry t of the nodes still in the heap are final: they are composited in order as soon as that holds, and the ray
stops once T < threshold and one more accepted hit (or none anywhere) settles the tail rule.
hit_count then counts the accepted hits found before stopping (<= the full count).
"""

from __future__ import annotations

import warp as wp

from models.tracer.blend import blend_slot, blend_start, write_outputs
from models.tracer.hit import eval_packed, hit_less
from models.tracer.ordered_bvh import OrderedBvh
from models.tracer.structs import GaussianData, RayOutputs, Replay, TraceParams

# The node heap lives in per-ray rows of ob.heap_keys / ob.heap_nodes (global scratch): local
# vectors are values in Warp and made every call of the shared forward_ray ~3x slower.


@wp.func
def box_entry(o: wp.vec3, inv_d: wp.vec3, lo: wp.vec3, hi: wp.vec3, t_min: float) -> float:
    """Entry t of the ray into [lo, hi] (clamped below at t_min), or 1e30 when missed."""
    ta = wp.cw_mul(lo - o, inv_d)
    tb = wp.cw_mul(hi - o, inv_d)
    t0 = wp.max(wp.max(wp.min(ta[0], tb[0]), wp.min(ta[1], tb[1])), wp.min(ta[2], tb[2]))
    t1 = wp.min(wp.min(wp.max(ta[0], tb[0]), wp.max(ta[1], tb[1])), wp.max(ta[2], tb[2]))
    if lo[0] > hi[0] or t1 < t0 or t1 <= t_min:
        return 1.0e30
    return wp.max(t0, t_min)


@wp.func
def safe_inv(x: float) -> float:
    if wp.abs(x) < 1.0e-30:
        if x < 0.0:
            return -1.0e30
        return 1.0e30
    return 1.0 / x


@wp.func
def heap_swap(keys: wp.array(dtype=float), nodes: wp.array(dtype=wp.int32), i: int, j: int):
    """Exchange heap entries i and j."""
    kt = keys[i]
    nt = nodes[i]
    keys[i] = keys[j]
    nodes[i] = nodes[j]
    keys[j] = kt
    nodes[j] = nt


@wp.func
def heap_push(keys: wp.array(dtype=float), nodes: wp.array(dtype=wp.int32), size: int, key: float, node: int):
    """Push (key, node) into the binary min-heap of ``size`` entries (the caller checked the capacity)."""
    j = size
    keys[j] = key
    nodes[j] = node
    rising = int(1)
    while rising != 0:
        rising = 0
        if j > 0:
            parent = (j - 1) // 2
            if keys[parent] > keys[j]:
                heap_swap(keys, nodes, parent, j)
                j = parent
                rising = 1


@wp.func
def heap_pop(keys: wp.array(dtype=float), nodes: wp.array(dtype=wp.int32), size: int):
    """Remove the minimum of the heap of ``size`` entries (read it from keys[0] / nodes[0] first)."""
    last = size - 1
    keys[0] = keys[last]
    nodes[0] = nodes[last]
    i = int(0)
    moving = int(1)
    while moving != 0:
        moving = 0
        smallest = i
        if 2 * i + 1 < last:
            if keys[2 * i + 1] < keys[smallest]:
                smallest = 2 * i + 1
        if 2 * i + 2 < last:
            if keys[2 * i + 2] < keys[smallest]:
                smallest = 2 * i + 2
        if smallest != i:
            heap_swap(keys, nodes, smallest, i)
            i = smallest
            moving = 1


@wp.func
def forward_ordered(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                    outs: RayOutputs, ob: OrderedBvh) -> int:
    """Best-first traversal. The node being expanded (``cur``) descends into its nearer child directly when no
    deferred node is nearer, pushing only the farther child; the heap holds the deferred nodes. Unvisited
    nodes = the heap and ``cur``, so stored hits before min(heap top, cur's entry) are final. Returns 0 on
    replay overflow (needed = twice the capacity) and -1 when the node heap overflowed (the caller falls back
    to the single traversal)."""
    inv_d = wp.vec3(safe_inv(d[0]), safe_inv(d[1]), safe_inv(d[2]))
    keys = ob.heap_keys[ray]
    nodes = ob.heap_nodes[ray]
    heap_cap = keys.shape[0]
    size = int(0)
    cur = int(-1)
    cur_t = box_entry(o, inv_d, ob.node_lo[0], ob.node_hi[0], prm.t_min)
    if cur_t < 1.0e29:
        cur = 0
    acc = blend_start()
    n = int(0)
    done = int(0)
    cand = int(0)
    obb = int(0)
    first_leaf = ob.n_leaves - 1
    while cur >= 0 or size > 0:
        if done != 0 and n > acc.blended:
            break
        if cur < 0:
            cur = nodes[0]
            cur_t = keys[0]
            heap_pop(keys, nodes, size)
            size -= 1
        node = cur
        cur = -1
        cur_t = float(3.0e38)
        if node >= first_leaf:
            leaf = node - first_leaf
            for li in range(ob.leaf_size):
                k = leaf * ob.leaf_size + li
                if k < ob.count:
                    # the leaf's records are contiguous (Morton order): no gather by Gaussian id
                    if box_entry(o, inv_d, ob.sorted_lowers[k], ob.sorted_uppers[k], prm.t_min) < 1.0e29:
                        cand += 1
                        h_t, h_a, h_in = eval_packed(o, d, ob.sorted_packed[k], prm.kernel_p, prm.alpha_min,
                                                     prm.alpha_max, prm.t_min, prm.obb_test)
                        if h_in > 0.0:
                            obb += 1
                        if h_a > 0.0:
                            if n >= prm.capacity:
                                outs.needed[ray] = 2 * prm.capacity
                                return 0
                            # insert into the pending hits [blended, n), kept sorted (hits arrive nearly in order)
                            gid = ob.order[k]
                            j = n
                            while j > acc.blended and hit_less(h_t, gid, rep.t[ray, j - 1], rep.ids[ray, j - 1]) != 0:
                                rep.ids[ray, j] = rep.ids[ray, j - 1]
                                rep.t[ray, j] = rep.t[ray, j - 1]
                                rep.alpha[ray, j] = rep.alpha[ray, j - 1]
                                j -= 1
                            rep.ids[ray, j] = gid
                            rep.t[ray, j] = h_t
                            rep.alpha[ray, j] = h_a
                            n += 1
        else:
            left = 2 * node + 1
            tl = box_entry(o, inv_d, ob.node_lo[left], ob.node_hi[left], prm.t_min)
            tr = box_entry(o, inv_d, ob.node_lo[left + 1], ob.node_hi[left + 1], prm.t_min)
            near = left
            t_near = tl
            t_far = tr
            if tr < tl:
                near = left + 1
                t_near = tr
                t_far = tl
            if t_far < 1.0e29:
                if size >= heap_cap:
                    return -1
                heap_push(keys, nodes, size, t_far, 2 * left + 1 - near)
                size += 1
            if t_near < 1.0e29:
                if size == 0 or t_near <= keys[0]:
                    cur = near  # still the nearest unvisited node: descend without the heap
                    cur_t = t_near
                else:
                    if size >= heap_cap:
                        return -1
                    heap_push(keys, nodes, size, t_near, near)
                    size += 1
        if done == 0:
            # stored hits before every unvisited node's entry (with a float margin) are final
            bound = cur_t
            if size > 0:
                bound = wp.min(bound, keys[0])
            if bound < 1.0e38:
                bound = bound - 1.0e-5 * (1.0 + wp.abs(bound))
            # the pending hits [blended, n) are sorted: blend from the front while they are final
            while done == 0 and acc.blended < n and rep.t[ray, acc.blended] < bound:
                if acc.trans < prm.trans_threshold:
                    done = 1
                else:
                    acc = blend_slot(acc, g, rep, ray, acc.blended)
            if acc.trans < prm.trans_threshold:
                done = 1
    outs.candidates[ray] = cand
    outs.obb_candidates[ray] = obb
    write_outputs(ray, n, acc, outs)
    return 1
