"""Own BVH for front-to-back ordered traversal (ablation; TracerConfig.traversal = "ordered").

wp.bvh_query_ray visits leaves in no particular order, so a ray cannot stop early. This
BVH is a complete binary tree (heap layout: children of node k are 2k+1, 2k+2) over leaves
of `leaf_size` Gaussians sorted along a Morton curve of their box centres. The Morton
order is computed at rebuild; refit recomputes every node's bounds bottom-up (one launch
per level) from the same world AABBs as the wp.Bvh.
"""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

from models.tracer.interop import to_warp
from models.tracer.structs import vec16


@wp.struct
class OrderedBvh:
    node_lo: wp.array(dtype=wp.vec3)   # [2P-1] node bounds (empty: lo > hi)
    node_hi: wp.array(dtype=wp.vec3)
    order: wp.array(dtype=wp.int32)    # [N] Gaussian ids in Morton order
    lowers: wp.array(dtype=wp.vec3)    # [N] per-Gaussian world AABB (by Gaussian id)
    uppers: wp.array(dtype=wp.vec3)
    sorted_lowers: wp.array(dtype=wp.vec3)  # [N] the same, in Morton order (a leaf's Gaussians contiguous)
    sorted_uppers: wp.array(dtype=wp.vec3)
    sorted_packed: wp.array(dtype=vec16)    # [N] packed traversal records (structs.vec16) in Morton order
    n_leaves: int                      # P, a power of two
    leaf_size: int                     # Gaussians per leaf (B)
    count: int                         # N
    heap_keys: wp.array2d(dtype=float)     # [R, H] per-ray node heap scratch (entry t)
    heap_nodes: wp.array2d(dtype=wp.int32)  # [R, H] per-ray node heap scratch (node index)


@wp.kernel
def gather_sorted_kernel(b: OrderedBvh, packed: wp.array(dtype=vec16)):
    """The per-Gaussian records a traversal reads, copied into Morton order."""
    k = wp.tid()
    gid = b.order[k]
    b.sorted_lowers[k] = b.lowers[gid]
    b.sorted_uppers[k] = b.uppers[gid]
    b.sorted_packed[k] = packed[gid]


@wp.kernel
def leaf_bounds_kernel(b: OrderedBvh):
    j = wp.tid()
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for i in range(b.leaf_size):
        k = j * b.leaf_size + i
        if k < b.count:
            gid = b.order[k]
            lo = wp.min(lo, b.lowers[gid])
            hi = wp.max(hi, b.uppers[gid])
    b.node_lo[b.n_leaves - 1 + j] = lo
    b.node_hi[b.n_leaves - 1 + j] = hi


@wp.kernel
def level_bounds_kernel(b: OrderedBvh, first: int):
    k = first + wp.tid()
    b.node_lo[k] = wp.min(b.node_lo[2 * k + 1], b.node_lo[2 * k + 2])
    b.node_hi[k] = wp.max(b.node_hi[2 * k + 1], b.node_hi[2 * k + 2])


def _morton_order(centers: np.ndarray) -> np.ndarray:
    """Gaussian ids sorted by a 30-bit Morton code of their (normalised) centres."""
    lo, hi = centers.min(0), centers.max(0)
    q = ((centers - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.int64).clip(0, 1023)
    code = np.zeros(len(centers), dtype=np.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> bit) & 1) << (3 * bit + (2 - axis))
    return np.argsort(code, kind="stable").astype(np.int32)


class OrderedBvhBuilder:
    """Builds (Morton sort) and refits the ordered BVH over existing world AABB arrays."""

    def __init__(self, device: str, leaf_size: int = 4):
        self.device = device
        self.leaf_size = leaf_size
        self.struct: OrderedBvh | None = None

    def rebuild(self, lowers: wp.array, uppers: wp.array, packed: wp.array) -> None:
        n = lowers.shape[0]
        centers = 0.5 * (lowers.numpy() + uppers.numpy())
        n_leaves = 1 << max(0, int(np.ceil(np.log2(max(1, -(-n // self.leaf_size))))))
        b = OrderedBvh()
        b.node_lo = wp.empty(2 * n_leaves - 1, dtype=wp.vec3, device=self.device)
        b.node_hi = wp.empty(2 * n_leaves - 1, dtype=wp.vec3, device=self.device)
        b.order = to_warp(torch.from_numpy(_morton_order(centers)), wp.int32, self.device)
        b.lowers, b.uppers = lowers, uppers
        b.sorted_lowers = wp.empty(n, dtype=wp.vec3, device=self.device)
        b.sorted_uppers = wp.empty(n, dtype=wp.vec3, device=self.device)
        b.sorted_packed = wp.empty(n, dtype=vec16, device=self.device)
        b.n_leaves, b.leaf_size, b.count = n_leaves, self.leaf_size, n
        self.struct = b
        self.refit(packed)

    def refit(self, packed: wp.array) -> None:
        b = self.struct
        wp.launch(gather_sorted_kernel, dim=b.count, inputs=[b, packed], device=self.device)
        wp.launch(leaf_bounds_kernel, dim=b.n_leaves, inputs=[b], device=self.device)
        level = b.n_leaves // 2
        while level >= 1:
            wp.launch(level_bounds_kernel, dim=level, inputs=[b, level - 1], device=self.device)
            level //= 2
