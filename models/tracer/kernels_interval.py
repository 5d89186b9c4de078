"""t-interval traversal (the default): a ray's cost follows the hits it blends, not everything behind them.

The ray is walked in windows of its parameter t, front to back. A window (t_lo, D] is one ``wp.bvh_query_ray``
started at t_lo (the origin moved there, so boxes the ray has left are skipped) with ``max_dist`` reaching D
(boxes entered beyond D are skipped): it visits only the nodes overlapping the window, in Warp's fast
traversal. Each Gaussian is evaluated once: in the window its box is entered in ("entry" < D + margin); its
accepted hit either lies in that window (t* <= D) or later, and is then CARRIED (kept in the top replay slots)
to the window it belongs to, while later windows skip the boxes entered before their start with a cheap AABB
test. A window's hits go to the replay slots after the blended prefix, are sorted by (t, id) and blended front
to back; the ray stops as soon as T < threshold, and one more accepted hit (a carried one, the window's next, or
a probe's) settles the tail rule. The hits blended, and their order, are exactly those of the single traversal
and of the PyTorch reference: a hit's max-response point t* lies in its Gaussian's box (entry <= t*), and
consecutive windows partition t.

Window length: a ray that starts inside the Gaussians' core box (a camera or a reflection vertex in a room:
``TraceParams.core_lo/hi``, the 0.5-99.5 % box of the Gaussians' bounds grown by one median box diagonal, so that
one large Gaussian reaching past a camera outside a cloud does not count it inside: benchmark (d) 70 -> 190
candidates per blended hit when the union box decided) takes all of itself as its first window
(``TraceParams.inside_whole``, TracerConfig.inside_whole_window): it crosses empty space to a surface and the opaque cut (below) ends the window there; windows of one box diagonal, x4
after each empty one, took 3.6-4.2 BVH queries per ray to cross the air of the demo room (forward -11 %
measured on its training batches). A ray entering the box from outside (a camera looking at an object or a
cloud) starts with ``TraceParams.window`` (world units: a multiple of the median Gaussian box diagonal, divided
by |d| for the ray parameter): where hits lie densely from the entry on, a long window evaluates, in BVH order,
hits far beyond where the ray turns opaque (benchmark (b): 3.5 -> 4.8 candidates per blended hit with a window
of a quarter of the ray), and a short one costs a BVH query from the root per window: most of a window's cost is
the query's node tests (profiled on (b), one CPU thread: the node loop was about half of the forward kernel). The
default 2.5 median box diagonals (was 1) takes (b)'s rays to opacity in one window (1.05 windows per ray against
2.23) at 2.86 candidates per blended hit (2.79), forward -20 %; (d) at 48x48 rays 21.3 -> 19.8 candidates per
blended hit, 147 -> 127 ms; at 4, 8, 16 both cost more again. Either way the hits and their order are the same;
windows after the first are sized
per ray to take T to the threshold at the optical-depth rate seen so far
(x1/2 .. x4). After a window with no hit of its own: x4, or, when it carried hits, only as far as the nearest
of them plus one window length (a dense stretch behind a short empty one is not swallowed whole).

Near child first: Warp's ``bvh_query_ray`` visits a node's two children in a fixed order (the one with the larger
coordinates first), nearer first only for rays going down the split axis. With the octant trees
(``TracerConfig.octant_bvh``; ``TraceParams.octants``) each window's query runs on the tree of the ray's direction
octant, built over the bounds mirrored so that the ray goes down every axis (``octant_query``; models/tracer/bvh.py):
the hits stored first are the near ones, so a window turns opaque, and its cut shrinks the query, after fewer boxes
(benchmark (b) 3.51 -> 2.79 candidates per blended hit, (d) at 48x48 rays 70.5 -> 21.3). The boxes visited and
every t are those of the plain tree. On a CPU the wide tree (``TracerConfig.wide_bvh``, ``TraceParams.wide``;
models/tracer/wide_bvh.py) answers the window queries instead of both: eight child boxes per SIMD test, the nearer
children first in any direction; the same boxes again (forward -23..-28 % on benchmark (a), (b), (c), one CPU thread).

Opaque windows: once the hits stored in a window take T below the threshold (their product, in any order),
the window is the ray's last. Its hits are sorted once and cut after the hit where T crosses the threshold plus
one more (the tail rule's witness); D shrinks to that witness, so the rest of the query skips boxes entered
beyond it, and each later hit before D is inserted in order and the cut recomputed. ``hit_count`` of a
truncated ray is therefore ``blended + 1`` (the tail rule needs no more), the same whatever the BVH's shape.

Bounded working set:
the free replay slots after the blended prefix hold the window's hits (from the bottom) and the carried ones
(from the top). When they meet, the carried hits are dropped first (the next window then re-examines every box
it overlaps: skipping is only used while the carried set is complete); when the window's own hits fill the
slots, it keeps its nearest hits and shrinks D to the farthest kept (max_dist shrinks, which Warp allows). No
window overflows; only a blended prefix longer than the buffer needs more slots (with the default threshold at
most ~920 hits).
"""

from __future__ import annotations

import warp as wp

from models.tracer.blend import blend_slot, blend_start, write_outputs
from models.tracer.hit import eval_packed, hit_less
from models.tracer.kernels_ordered import safe_inv
from models.tracer.structs import GaussianData, RayOutputs, Replay, TraceParams
from models.tracer.wide_bvh import WideBvh, wide_next, wide_start

ID_MAX = wp.constant(2147483647)
FAR = wp.constant(3.0e38)


@wp.func
def margin(t: float) -> float:
    """Float slack of the window bounds (ray-parameter units)."""
    return 1.0e-4 * (1.0 + wp.abs(t))


@wp.func
def slab(o: wp.vec3, inv: wp.vec3, lo: wp.vec3, hi: wp.vec3):
    """(entry, exit) t of the ray in the box [lo, hi], two scalars; entry > exit when it misses. (A vec2 read back
    after two scalar stores stalled store-to-load forwarding once per candidate: ~4 % of benchmark (b)'s forward.)"""
    ta = wp.cw_mul(lo - o, inv)
    tb = wp.cw_mul(hi - o, inv)
    t0 = wp.max(wp.max(wp.min(ta[0], tb[0]), wp.min(ta[1], tb[1])), wp.min(ta[2], tb[2]))
    t1 = wp.min(wp.min(wp.max(ta[0], tb[0]), wp.max(ta[1], tb[1])), wp.max(ta[2], tb[2]))
    return t0, t1


@wp.func
def in_box(p: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> int:
    """1 when p lies in the box [lo, hi]."""
    if p[0] < lo[0] or p[1] < lo[1] or p[2] < lo[2] or p[0] > hi[0] or p[1] > hi[1] or p[2] > hi[2]:
        return 0
    return 1


@wp.func
def store(rep: Replay, ray: int, slot: int, t: float, gid: int, alpha: float):
    rep.t[ray, slot] = t
    rep.ids[ray, slot] = gid
    rep.alpha[ray, slot] = alpha


@wp.func
def move(rep: Replay, ray: int, dst: int, src: int):
    store(rep, ray, dst, rep.t[ray, src], rep.ids[ray, src], rep.alpha[ray, src])


@wp.func
def insert_sorted(rep: Replay, ray: int, base: int, m: int, t: float, gid: int, alpha: float):
    """Insert into the sorted slots base..base+m-1; slot base+m is overwritten (free, or the dropped farthest)."""
    j = base + m
    while j > base and hit_less(t, gid, rep.t[ray, j - 1], rep.ids[ray, j - 1]) != 0:
        move(rep, ray, j, j - 1)
        j -= 1
    store(rep, ray, j, t, gid, alpha)


@wp.func
def sort_slots(rep: Replay, ray: int, base: int, m: int):
    """Insertion sort of the slots base..base+m-1 by (t, id)."""
    for k in range(1, m):
        insert_sorted(rep, ray, base, k, rep.t[ray, base + k], rep.ids[ray, base + k], rep.alpha[ray, base + k])


@wp.func
def window_to(rep: Replay, ray: int, slot: int, shift: float):
    """A full window ends at the hit in ``slot`` (the farthest kept): its (d_t, d_id) and the query's max_dist."""
    t = rep.t[ray, slot]
    return t, rep.ids[ray, slot], t - shift + 2.0 * margin(t)


@wp.func
def opaque_cut(rep: Replay, ray: int, base: int, m: int, trans: float, threshold: float) -> int:
    """Index (from base) of the first of the sorted slots after which T < threshold, blending them in order from
    ``trans`` with the same arithmetic as blend_slot; m when T stays above it."""
    cut = m
    j = int(0)
    while j < m:
        trans = trans * (1.0 - rep.alpha[ray, base + j])
        if trans < threshold:
            cut = j
            j = m
        j += 1
    return cut


@wp.func
def cut_opaque(rep: Replay, ray: int, base: int, m: int, trans: float, threshold: float, shift: float, d_t: float,
               d_id: int, max_dist: float, last: int):
    """An opaque window's sorted hits: keep them up to the crossing hit + the tail witness and end the window at the
    witness. Returns (m, last, d_t, d_id, max_dist), unchanged while the crossing hit is the last one kept."""
    cut = opaque_cut(rep, ray, base, m, trans, threshold)
    if cut + 2 <= m:
        m = cut + 2
        last = 0
        d_t, d_id, max_dist = window_to(rep, ray, base + m - 1, shift)
    return m, last, d_t, d_id, max_dist


@wp.func
def later(t: float, gid: int, t_ref: float, id_ref: int) -> int:
    """(t, gid) after (t_ref, id_ref) in the hit order (by t, ties by id)."""
    return hit_less(t_ref, id_ref, t, gid)


@wp.func
def octant_query(prm: TraceParams, o: wp.vec3, d: wp.vec3):
    """A ray query from ``o`` along ``d``: with octant trees, tree k of d's octant with o and d mirrored like
    it, so that every node puts its nearer child first (bvh.py); the same boxes, crossings and t."""
    if prm.octants == 0:
        return wp.bvh_query_ray(prm.bvh, o, d)
    k = int(0)
    fx = float(1.0)
    fy = float(1.0)
    fz = float(1.0)
    if d[0] > 0.0:
        k += 1
        fx = -1.0
    if d[1] > 0.0:
        k += 2
        fy = -1.0
    if d[2] > 0.0:
        k += 4
        fz = -1.0
    f = wp.vec3(fx, fy, fz)
    return wp.bvh_query_ray(prm.octant_bvh[k], wp.cw_mul(f, o), wp.cw_mul(f, d))


@wp.func
def probe_beyond(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, t_lo: float,
                 id_lo: int) -> wp.vec3:
    """(1 if an accepted hit lies after (t_lo, id_lo), candidates evaluated, of them in their ellipsoid): the tail
    rule of a ray that became opaque exactly at the end of what was examined."""
    shift = wp.max(t_lo - margin(t_lo), 0.0)
    query = octant_query(prm, o + shift * d, d)
    gid = int(0)
    found = int(0)
    cand = int(0)
    inside = int(0)
    while found == 0 and wp.bvh_query_next(query, gid, 1.0e30):
        cand += 1
        h_t, h_a, h_in = eval_packed(o, d, g.packed[gid], prm.kernel_p, prm.alpha_min,
                                     prm.alpha_max, prm.t_min, prm.obb_test)
        if h_in > 0.0:
            inside += 1
        if h_a > 0.0 and later(h_t, gid, t_lo, id_lo) != 0:
            found = 1
    return wp.vec3(float(found), float(cand), float(inside))


@wp.func
def forward_interval(ray: int, o: wp.vec3, d: wp.vec3, g: GaussianData, prm: TraceParams, rep: Replay,
                     outs: RayOutputs, wb: WideBvh) -> int:
    """Windows of t front to back. Returns 0 when the blended prefix outgrows the replay buffer."""
    acc = blend_start()
    n_acc = int(0)
    cand = int(0)
    obb = int(0)
    inv = wp.vec3(safe_inv(d[0]), safe_inv(d[1]), safe_inv(d[2]))
    scene_in, t_end = slab(o, inv, prm.scene_lo, prm.scene_hi)
    done = int(0)
    if scene_in > t_end or t_end <= prm.t_min:
        done = 1  # the ray misses every Gaussian's box
    t_lo = prm.t_min     # hits after (t_lo, id_lo) are still to come: the last blended, or the last window's end
    id_lo = int(-1)
    delta = prm.window / wp.length(d)
    if prm.inside_whole != 0 and scene_in <= prm.t_min:
        if in_box(o + d * prm.t_min, prm.core_lo, prm.core_hi) != 0:
            delta = t_end - prm.t_min  # a ray from inside the Gaussians' core box: one window (module docstring)
    examined = float(-FAR)  # boxes entered before this were examined (while skip_ok): their hits blended or carried
    skip_ok = int(0)
    carried = int(0)        # carried hits, in slots capacity - carried .. capacity - 1
    cap = prm.capacity
    while done == 0:
        base = acc.blended
        room = cap - base
        if room < 2:
            outs.needed[ray] = 2 * cap
            outs.candidates[ray] = cand
            outs.obb_candidates[ray] = obb
            return 0
        d_t = wp.max(t_lo, scene_in) + delta   # the window ends at (d_t, d_id)
        d_id = int(ID_MAX)
        last = int(0)
        if d_t >= t_end:
            d_t = float(FAR)  # the rest of the ray
            last = 1
        entered = d_t + margin(d_t)  # boxes entered before this are examined in this window
        m = int(0)
        # carried hits that belong to this window move down to the window's slots
        i = int(0)
        while i < carried:
            s = cap - 1 - i
            if later(rep.t[ray, s], rep.ids[ray, s], d_t, d_id) == 0:
                tt = rep.t[ray, s]
                ii = rep.ids[ray, s]
                aa = rep.alpha[ray, s]
                move(rep, ray, s, cap - carried)
                carried -= 1
                store(rep, ray, base + m, tt, ii, aa)
                m += 1
            else:
                i += 1
        next_skip_ok = int(1)
        full = int(0)
        opaque = int(0)         # the window's hits take T below the threshold: it is the ray's last
        w_trans = acc.trans     # T behind every hit stored in this window (any order; until full)
        for j in range(m):
            w_trans = w_trans * (1.0 - rep.alpha[ray, base + j])
        shift = wp.max(t_lo - margin(t_lo), 0.0)
        max_dist = float(1.0e30)
        if last == 0:
            max_dist = entered - shift + margin(entered)
        if m == room:
            # the carried hits alone fill the window: full (see below)
            sort_slots(rep, ray, base, m)
            full = 1
            next_skip_ok = 0
            last = 0
            d_t, d_id, max_dist = window_to(rep, ray, base + m - 1, shift)
        elif m > 0 and w_trans < prm.trans_threshold:
            # the carried hits alone make the window opaque (see below)
            sort_slots(rep, ray, base, m)
            full = 1
            opaque = 1
            next_skip_ok = 0
            m, last, d_t, d_id, max_dist = cut_opaque(rep, ray, base, m, acc.trans, prm.trans_threshold, shift, d_t,
                                                      d_id, max_dist, last)
        o_q = o + shift * d
        query = octant_query(prm, o_q, d)  # (not read when the wide tree answers)
        if prm.wide != 0:
            wide_start(wb)

        gid = int(0)
        gq = int(0)
        more = int(1)
        while more != 0:
            if prm.wide != 0:
                gid = wide_next(wb, o_q, inv, max_dist)
            elif wp.bvh_query_next(query, gq, max_dist):
                gid = gq
            else:
                gid = -1
            if gid < 0:
                more = 0
                continue
            entry, _exit = slab(o, inv, prm.lowers[gid], prm.uppers[gid])
            if (last != 0 or entry < entered) and (skip_ok == 0 or entry >= examined):
                cand += 1
                h_t, h_a, h_in = eval_packed(o, d, g.packed[gid], prm.kernel_p, prm.alpha_min, prm.alpha_max,
                                             prm.t_min, prm.obb_test)
                if h_in > 0.0:
                    obb += 1
                if h_a > 0.0:
                    if later(h_t, gid, t_lo, id_lo) != 0:
                        if later(h_t, gid, d_t, d_id) == 0:  # in this window
                            if m + carried >= room and carried > 0:
                                carried = 0  # make room: the next window re-examines what they came from
                                next_skip_ok = 0
                            if opaque != 0:
                                # the ray ends in this window: keep its sorted hits up to the cut + the tail witness
                                if m < room:
                                    insert_sorted(rep, ray, base, m, h_t, gid, h_a)
                                    m += 1
                                else:
                                    insert_sorted(rep, ray, base, m - 1, h_t, gid, h_a)  # drops the farthest
                                    # the window now ends at the farthest kept hit: were the crossing hit the last
                                    # slot, the dropped one (the tail witness) lies beyond the window's end and the
                                    # probe finds it (seen: seed 2110809220 at replay_capacity 3)
                                    last = 0
                                    d_t, d_id, max_dist = window_to(rep, ray, base + m - 1, shift)
                                m, last, d_t, d_id, max_dist = cut_opaque(rep, ray, base, m, acc.trans,
                                                                          prm.trans_threshold, shift, d_t, d_id,
                                                                          max_dist, last)
                            elif m < room:
                                store(rep, ray, base + m, h_t, gid, h_a)
                                m += 1
                                w_trans = w_trans * (1.0 - h_a)
                                if m == room and full == 0:
                                    # full: sort once, then keep the nearest hits and shrink the window to them
                                    sort_slots(rep, ray, base, m)
                                    full = 1
                                    next_skip_ok = 0
                                    last = 0
                                    d_t, d_id, max_dist = window_to(rep, ray, base + m - 1, shift)
                                elif full == 0 and w_trans < prm.trans_threshold:
                                    # opaque: the window's hits, in any order, take T below the threshold. Sort them
                                    # once, cut after the hit where T crosses it (plus one more hit for the tail
                                    # rule) and shrink the window to that hit: the BVH query stops looking beyond
                                    sort_slots(rep, ray, base, m)
                                    full = 1
                                    opaque = 1
                                    next_skip_ok = 0
                                    m, last, d_t, d_id, max_dist = cut_opaque(rep, ray, base, m, acc.trans,
                                                                              prm.trans_threshold, shift, d_t, d_id,
                                                                              max_dist, last)
                            else:
                                insert_sorted(rep, ray, base, m - 1, h_t, gid, h_a)  # drops the farthest
                                d_t, d_id, max_dist = window_to(rep, ray, base + m - 1, shift)
                        elif full == 0 and m + carried < room:
                            carried += 1  # a later window's hit: carried there
                            store(rep, ray, cap - carried, h_t, gid, h_a)
                        else:
                            next_skip_ok = 0  # not kept: the next window re-examines its box
        if full == 0:
            sort_slots(rep, ray, base, m)
        depth = float(0.0)  # optical depth blended in this window: sum of -ln(1 - alpha)
        for j in range(m):
            if done == 0:
                if acc.trans < prm.trans_threshold:
                    done = 1
                    n_acc = acc.blended + 1  # an accepted hit left unblended: the tail rule (see hit_count)
                else:
                    a = rep.alpha[ray, base + j]
                    acc = blend_slot(acc, g, rep, ray, base + j)
                    depth -= wp.log(1.0 - a)
        if done == 0:
            t_lo = d_t
            id_lo = d_id
            examined = entered
            skip_ok = next_skip_ok
            if skip_ok == 0:
                carried = 0  # incomplete: the next window re-examines everything it overlaps (no duplicates)
            n_acc = acc.blended + wp.min(carried, 1)
            if last != 0:
                done = 1  # every hit of the ray was in this window
            elif acc.trans < prm.trans_threshold:
                done = 1
                if carried == 0:
                    # opaque exactly at the end of what was examined: does one more accepted hit exist?
                    found = probe_beyond(ray, o, d, g, prm, t_lo, id_lo)
                    n_acc = acc.blended + int(found[0])
                    cand += int(found[1])
                    obb += int(found[2])
            elif m == 0:
                grow = delta * 4.0
                if carried > 0:
                    t_near = float(FAR)
                    for i in range(carried):
                        t_near = wp.min(t_near, rep.t[ray, cap - 1 - i])
                    grow = wp.min(grow, wp.max(t_near - d_t, 0.0) + delta)
                delta = grow
            else:
                # the next window: the length that takes T to the threshold at this window's optical-depth rate
                # (measured from its first hit), x1/2 .. x4 of this one
                span = wp.max(d_t - rep.t[ray, base], 1.0e-6 * delta)
                need = wp.log(acc.trans / prm.trans_threshold) + 0.1
                delta = wp.clamp(1.25 * need * span / wp.max(depth, 1.0e-6), 0.5 * delta, 4.0 * delta)
    outs.candidates[ray] = cand
    outs.obb_candidates[ray] = obb
    write_outputs(ray, n_acc, acc, outs)
    return 1
