"""An 8-wide BVH for the CPU interval traversal: eight child boxes tested at once, nearer children first.

Profiled on benchmark (b) (one CPU thread), about half of the forward kernel was Warp's ``bvh_query_next`` node
loop: a binary tree whose children are pushed untested and each tested, one scalar slab test and one hard-to-predict
branch per popped node. This tree is Warp's own (its SAH build, its refit), collapsed: each node of the wide tree
takes the binary tree's node and replaces its largest-area internal child by that child's two children until it
holds eight (``collapse``, once per build), and a refit copies the binary nodes' refitted boxes into the wide nodes'
slots (``refit_wide_kernel``, every update). A node stores its eight child boxes as six planes of eight floats
(lo x, lo y, lo z, hi x, hi y, hi z), so one node is one SIMD slab test of eight boxes (``wide_next``: clang vector
extensions in a native snippet); the children hit within ``max_dist`` are pushed farthest first, so the nearest is
visited next (what the octant trees do for the binary tree, without seven more trees to refit), each with its entry
t, and a popped entry whose box starts beyond the (possibly shrunk) ``max_dist`` is dropped. "Nearest" is the
midpoint of the box's stretch of the ray (max(entry, 0) + exit), where its hits lie, not its entry: the boxes that
hold the window's start all enter before it (benchmark (b), 4 wide: 36.2 -> 35.0 candidates per ray; the octant
trees 34.8). Eight wide rather than four (AVX: one 8-lane test; without it two 4-lane ones): one CPU thread, best
of 7, wide / Warp's tree: (b) 0.78 -> 0.72, (a) 0.81 -> 0.77, (c) 0.81 -> 0.74.

A query returns exactly the boxes the ray (origin, 1 / direction) meets at some t in [0, max_dist) with exit t >= 0:
the test of Warp's ray query, so the interval traversal sees the same set of candidates, in another order, and its
outputs (the hits blended and their order) do not depend on it. CPU only (``TracerConfig.wide_bvh``): the snippet
compiles to a stub on CUDA, where Warp's traversal runs. The stack is per launch thread (``WideBvh.stack`` of the
struct that thread's launches get): a CPU launch runs its rays one after the other, so one stack of depth
7 x (tree depth) + 1 serves them all and stays in the first-level cache.
"""

from __future__ import annotations

import logging

import warp as wp

from models.tracer.launch import ray_chunks

log = logging.getLogger(__name__)
EMPTY = -2147483648  # a child slot that holds nothing


@wp.struct
class WideBvh:
    box: wp.array(dtype=float)        # [M * 48]: node m's child boxes, planes lo x, lo y, lo z, hi x, hi y, hi z
    child: wp.array(dtype=wp.int32)   # [M * 8]: >= 0 a wide node; EMPTY; else a leaf: -(start << 4 | count) - 1
    prims: wp.array(dtype=wp.int32)   # [N]: the binary tree's primitive order (leaves index into it)
    lowers: wp.array(dtype=wp.vec3)   # [N] the Gaussians' world bounds (a leaf of several is tested per item)
    uppers: wp.array(dtype=wp.vec3)
    stack: wp.array(dtype=wp.int32)   # [S] this launch thread's traversal stack: node or leaf entries
    stack_t: wp.array(dtype=float)    # [S] their entry t
    state: wp.array(dtype=wp.int32)   # [4] stack size, leaf cursor, leaf end


COLLAPSE = r"""
wp::BVH bvh = wp::bvh_get(bvh_id);
const wp::BVHPackedNodeHalf* L = bvh.node_lowers;
const wp::BVHPackedNodeHalf* U = bvh.node_uppers;
int* child = out_child.data;
int* src = out_src.data;
int* q = queue.data;
int* dep = depth.data;
for (int i = 0; i < n_items; ++i) out_prims.data[i] = bvh.primitive_indices[i];
int root = *bvh.root;
int nw = 1;
int max_dep = 1;
int bad = 0;
q[0] = root;
dep[0] = 1;
for (int w = 0; w < nw; ++w) {
    int c[8];
    int nc = 0;
    int b = q[w];
    if (L[b].b) { c[0] = b; nc = 1; } else { c[0] = L[b].i; c[1] = U[b].i; nc = 2; }
    while (nc < 8) {
        int best = -1;
        float best_area = -1.0f;
        for (int k = 0; k < nc; ++k) {
            int x = c[k];
            if (!L[x].b) {
                float ex = U[x].x - L[x].x, ey = U[x].y - L[x].y, ez = U[x].z - L[x].z;
                float area = ex * ey + ey * ez + ez * ex;
                if (area > best_area) { best_area = area; best = k; }
            }
        }
        if (best < 0) break;
        int x = c[best];
        c[best] = L[x].i;
        c[nc++] = U[x].i;
    }
    for (int k = 0; k < 8; ++k) {
        int slot = w * 8 + k;
        if (k >= nc) { child[slot] = -2147483647 - 1; src[slot] = -1; continue; }
        int x = c[k];
        src[slot] = x;
        if (L[x].b) {
            int start = L[x].i;
            int count = U[x].i - start;
            if (count < 1 || count > 15) bad = 1;
            child[slot] = -((start << 4) | count) - 1;
        } else {
            if (nw >= max_nodes) { bad = 1; child[slot] = -2147483647 - 1; continue; }
            child[slot] = nw;
            q[nw] = x;
            dep[nw] = dep[w] + 1;
            if (dep[nw] > max_dep) max_dep = dep[nw];
            ++nw;
        }
    }
}
info.data[0] = nw;
info.data[1] = max_dep;
info.data[2] = bad;
"""


@wp.func_native(COLLAPSE)
def collapse_native(bvh_id: wp.uint64, n_items: int, max_nodes: int, out_child: wp.array(dtype=wp.int32),
                    out_src: wp.array(dtype=wp.int32), out_prims: wp.array(dtype=wp.int32),
                    queue: wp.array(dtype=wp.int32), depth: wp.array(dtype=wp.int32),
                    info: wp.array(dtype=wp.int32)):
    ...


@wp.kernel
def collapse_kernel(bvh_id: wp.uint64, n_items: int, max_nodes: int, out_child: wp.array(dtype=wp.int32),
                    out_src: wp.array(dtype=wp.int32), out_prims: wp.array(dtype=wp.int32),
                    queue: wp.array(dtype=wp.int32), depth: wp.array(dtype=wp.int32),
                    info: wp.array(dtype=wp.int32)):
    collapse_native(bvh_id, n_items, max_nodes, out_child, out_src, out_prims, queue, depth, info)


NODE_BOX = r"""
wp::BVH bvh = wp::bvh_get(bvh_id);
float* b = box.data + (size_t)(slot >> 3) * 48 + (slot & 7);
if (node < 0) {
    b[0] = 0.0f; b[8] = 0.0f; b[16] = 0.0f; b[24] = 0.0f; b[32] = 0.0f; b[40] = 0.0f;
    return;
}
const wp::BVHPackedNodeHalf lo = bvh.node_lowers[node];
const wp::BVHPackedNodeHalf hi = bvh.node_uppers[node];
b[0] = lo.x; b[8] = lo.y; b[16] = lo.z; b[24] = hi.x; b[32] = hi.y; b[40] = hi.z;
"""


@wp.func_native(NODE_BOX)
def copy_node_box(bvh_id: wp.uint64, node: int, slot: int, box: wp.array(dtype=float)):
    ...


@wp.kernel
def refit_wide_kernel(bvh_id: wp.uint64, src: wp.array(dtype=wp.int32), box: wp.array(dtype=float), offset: int):
    """Slot i of the wide tree takes the (refitted) box of binary node src[i]."""
    i = wp.tid() + offset
    copy_node_box(bvh_id, src[i], i, box)


WIDE_NEXT = r"""
#if defined(__CUDA_ARCH__)
return -1;
#else
typedef float v8f __attribute__((vector_size(32), aligned(4)));
typedef int v8i __attribute__((vector_size(32), aligned(4)));
int* st = wb.stack.data;
float* stt = wb.stack_t.data;
int* s = wb.state.data;
int sp = s[0];
int cur = s[1];
int end = s[2];
const float ox = o[0], oy = o[1], oz = o[2];
const float ix = inv[0], iy = inv[1], iz = inv[2];
const v8f OX = {ox, ox, ox, ox, ox, ox, ox, ox};
const v8f OY = {oy, oy, oy, oy, oy, oy, oy, oy};
const v8f OZ = {oz, oz, oz, oz, oz, oz, oz, oz};
const v8f IX = {ix, ix, ix, ix, ix, ix, ix, ix};
const v8f IY = {iy, iy, iy, iy, iy, iy, iy, iy};
const v8f IZ = {iz, iz, iz, iz, iz, iz, iz, iz};
const v8f MD = {max_dist, max_dist, max_dist, max_dist, max_dist, max_dist, max_dist, max_dist};
const v8f ZERO = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
const int none = -2147483647 - 1;
const v8i NONE = {none, none, none, none, none, none, none, none};
int result = -1;
for (;;) {
    if (cur < end) {
        const int p = wb.prims.data[cur++];
        const wp::vec3 lo = wb.lowers.data[p];
        const wp::vec3 hi = wb.uppers.data[p];
        float a0 = (lo[0] - ox) * ix, a1 = (hi[0] - ox) * ix;
        float b0 = (lo[1] - oy) * iy, b1 = (hi[1] - oy) * iy;
        float c0 = (lo[2] - oz) * iz, c1 = (hi[2] - oz) * iz;
        float t0 = wp::max(wp::max(wp::min(a0, a1), wp::min(b0, b1)), wp::min(c0, c1));
        float t1 = wp::min(wp::min(wp::max(a0, a1), wp::max(b0, b1)), wp::max(c0, c1));
        if (t1 >= 0.0f && t1 >= t0 && t0 < max_dist) { result = p; break; }
        continue;
    }
    if (sp == 0) break;
    --sp;
    const int e = st[sp];
    if (!(stt[sp] < max_dist)) continue;
    if (e < 0) {
        const int v = -(e + 1);
        const int start = v >> 4;
        const int count = v & 15;
        if (count == 1) { result = wb.prims.data[start]; break; }
        cur = start;
        end = start + count;
        continue;
    }
    const float* b = wb.box.data + (size_t)e * 48;
    const v8f tx0 = (*(const v8f*)(b) - OX) * IX, tx1 = (*(const v8f*)(b + 24) - OX) * IX;
    const v8f ty0 = (*(const v8f*)(b + 8) - OY) * IY, ty1 = (*(const v8f*)(b + 32) - OY) * IY;
    const v8f tz0 = (*(const v8f*)(b + 16) - OZ) * IZ, tz1 = (*(const v8f*)(b + 40) - OZ) * IZ;
    const v8f tmin = __builtin_elementwise_max(__builtin_elementwise_max(__builtin_elementwise_min(tx0, tx1),
        __builtin_elementwise_min(ty0, ty1)), __builtin_elementwise_min(tz0, tz1));
    const v8f tmax = __builtin_elementwise_min(__builtin_elementwise_min(__builtin_elementwise_max(tx0, tx1),
        __builtin_elementwise_max(ty0, ty1)), __builtin_elementwise_max(tz0, tz1));
    const v8i ch = *(const v8i*)(wb.child.data + (size_t)e * 8);
    const v8i hit = (tmax >= ZERO) & (tmax >= tmin) & (tmin < MD) & (ch != NONE);
    // the hit children, farthest first (by the midpoint key): pushed in that order, the nearest is popped next
    int n = 0;
    int ci[8];
    float ct[8];
    float ck[8];
    const v8f key = __builtin_elementwise_max(tmin, ZERO) + tmax;
    for (int k = 0; k < 8; ++k) {
        if (hit[k]) {
            const float t = key[k];
            int j = n;
            while (j > 0 && ck[j - 1] < t) { ck[j] = ck[j - 1]; ct[j] = ct[j - 1]; ci[j] = ci[j - 1]; --j; }
            ck[j] = t;
            ct[j] = tmin[k];
            ci[j] = ch[k];
            ++n;
        }
    }
    for (int k = 0; k < n; ++k) { st[sp] = ci[k]; stt[sp] = ct[k]; ++sp; }
}
s[0] = sp;
s[1] = cur;
s[2] = end;
return result;
#endif
"""


@wp.func_native(WIDE_NEXT)
def wide_next(wb: WideBvh, o: wp.vec3, inv: wp.vec3, max_dist: float) -> int:
    ...


@wp.func
def wide_start(wb: WideBvh):
    """A new query from the wide tree's root (node 0)."""
    wb.state[0] = 1
    wb.state[1] = 0
    wb.state[2] = 0
    wb.stack[0] = 0
    wb.stack_t[0] = -3.0e38


def empty_wide(device: str) -> WideBvh:
    """Placeholder for launches that do not use the wide tree (never read)."""
    w = WideBvh()
    w.box = wp.zeros(48, dtype=float, device=device)
    w.child = wp.full(8, EMPTY, dtype=wp.int32, device=device)
    w.prims = wp.zeros(1, dtype=wp.int32, device=device)
    w.lowers = wp.zeros(1, dtype=wp.vec3, device=device)
    w.uppers = wp.zeros(1, dtype=wp.vec3, device=device)
    w.stack = wp.zeros(1, dtype=wp.int32, device=device)
    w.stack_t = wp.zeros(1, dtype=float, device=device)
    w.state = wp.zeros(4, dtype=wp.int32, device=device)
    return w


class WideTree:
    """The wide tree of one wp.Bvh: collapsed when that tree is new (a build), refitted after each update, and one
    WideBvh struct per launch thread (each with its own stack)."""

    def __init__(self, device: str):
        self.device = device
        self.for_bvh = None          # the wp.Bvh the topology was collapsed from
        self.current = False         # the boxes hold the last update's
        self.usable = False          # the tree of for_bvh could be collapsed
        self.nodes = 0
        self.depth = 0
        self.child = self.src = self.prims = self.box = None
        self.structs: list[WideBvh] = []

    def refresh(self, bvh: wp.Bvh, lowers: wp.array, uppers: wp.array, n: int, threads: int, run=None) -> bool:
        """Make the tree hold the last update; False when ``bvh`` cannot be collapsed (a leaf of more than 15
        items: the caller queries ``bvh`` itself)."""
        run = run or (lambda jobs: [job() for job in jobs])
        if bvh is not self.for_bvh:
            self.usable = self._collapse(bvh, lowers, uppers, n, threads)
            self.current = False
        if not self.usable:
            return False
        if self.current:
            return True
        slots = self.nodes * 8
        parts = ray_chunks(slots, threads if slots >= 65536 else 1)
        run([(lambda a=a, b=b: wp.launch(refit_wide_kernel, dim=b - a, device=self.device,
                                         inputs=[wp.uint64(bvh.id), self.src, self.box, a])) for a, b in parts])
        self.current = True
        return True

    def _collapse(self, bvh: wp.Bvh, lowers: wp.array, uppers: wp.array, n: int, threads: int) -> bool:
        max_nodes = max(1, n)
        dev = self.device
        child = wp.empty(max_nodes * 8, dtype=wp.int32, device=dev)
        src = wp.empty(max_nodes * 8, dtype=wp.int32, device=dev)
        prims = wp.empty(max(n, 1), dtype=wp.int32, device=dev)
        queue = wp.empty(max_nodes, dtype=wp.int32, device=dev)
        depth = wp.empty(max_nodes, dtype=wp.int32, device=dev)
        info = wp.zeros(3, dtype=wp.int32, device=dev)
        wp.launch(collapse_kernel, dim=1, device=dev,
                  inputs=[wp.uint64(bvh.id), n, max_nodes, child, src, prims, queue, depth, info])
        nodes, tree_depth, bad = (int(v) for v in info.numpy())
        self.for_bvh = bvh
        if bad:
            log.warning("wide BVH: the binary tree of %d items has a leaf of more than 15 items (or more than %d "
                        "internal nodes): its traces query it directly", n, max_nodes)
            return False
        self.nodes, self.depth = nodes, tree_depth
        self.child, self.src, self.prims = child[: nodes * 8], src[: nodes * 8], prims
        self.box = wp.empty(nodes * 48, dtype=float, device=dev)
        stack_size = 7 * tree_depth + 2
        self.structs = []
        for _ in range(threads):
            w = WideBvh()
            w.box, w.child, w.prims, w.lowers, w.uppers = self.box, self.child, self.prims, lowers, uppers
            w.stack = wp.zeros(stack_size, dtype=wp.int32, device=dev)
            w.stack_t = wp.zeros(stack_size, dtype=float, device=dev)
            w.state = wp.zeros(4, dtype=wp.int32, device=dev)
            self.structs.append(w)
        return True

