"""Warp structs bundling the arrays a tracer launch reads and writes."""

from __future__ import annotations

import warp as wp

# Packed traversal record per Gaussian (one 64-byte load per candidate):
# [mean (3), M row-major (9), opacity, cutoff s, 0, 0]
vec16 = wp.types.vector(length=16, dtype=wp.float32)


@wp.struct
class GaussianData:
    """Activated per-Gaussian values, N entries each."""

    diffuse: wp.array(dtype=wp.vec3)     # [N]
    normal: wp.array(dtype=wp.vec3)      # [N]
    roughness: wp.array(dtype=float)     # [N]
    f0: wp.array(dtype=wp.vec3)          # [N]
    # [N] geometry: mean, M = S^-1 R^T (x_local = M (x - mean)), opacity, cutoff s (0 = masked)
    packed: wp.array(dtype=vec16)


@wp.struct
class TraceParams:
    bvh: wp.uint64            # wp.Bvh id over the Gaussians' world bounds
    octant_bvh: wp.array(dtype=wp.uint64)  # interval: [8] tree per octant of ray directions (bvh.py)
    octants: int              # 1: the interval traversal queries the octant trees (mirrored rays)
    wide: int                 # 1: the interval traversal queries the wide tree (wide_bvh.py; CPU)
    kernel_p: int             # response exp(-r^(2p) / (2p))
    alpha_min: float
    alpha_max: float
    trans_threshold: float
    t_min: float
    k: int                    # hits per integration round
    capacity: int             # replay slots per ray
    obb_test: int             # 1: test the cut-off ellipsoid (|q| <= s) before the response
    traversal: int            # index into config.TRAVERSALS: 0 interval, 1 single, 2 kbuffer, 3 ordered
    window: float             # interval: first window length (world units; divided by |d| per ray)
    inside_whole: int         # interval: 1 = a ray starting inside the core box takes all of itself as first window
    scene_lo: wp.vec3         # interval: the scene box (union of the Gaussians' world bounds)
    scene_hi: wp.vec3
    core_lo: wp.vec3          # interval: the core box (where most Gaussians' bounds lie; one outlier does not widen it)
    core_hi: wp.vec3
    lowers: wp.array(dtype=wp.vec3)  # [N] the Gaussians' world bounds (the wp.Bvh's items)
    uppers: wp.array(dtype=wp.vec3)


@wp.struct
class Replay:
    """Per-ray replay buffer; after the forward its first `blended` slots are sorted by t."""

    ids: wp.array2d(dtype=wp.int32)   # [R, capacity] Gaussian id
    t: wp.array2d(dtype=float)        # [R, capacity] ray parameter of the max-response point
    alpha: wp.array2d(dtype=float)    # [R, capacity]
    trans: wp.array2d(dtype=float)    # [R, capacity] transmittance in front of the hit (blended only)


@wp.struct
class RayOutputs:
    diffuse: wp.array(dtype=wp.vec3)      # [R]
    depth: wp.array(dtype=float)          # [R]
    normal: wp.array(dtype=wp.vec3)       # [R]
    roughness: wp.array(dtype=float)      # [R]
    f0: wp.array(dtype=wp.vec3)           # [R]
    transmittance: wp.array(dtype=float)  # [R]
    front_depth: wp.array(dtype=float)    # [R] weight-normalised t of the hits blended while T >= 0.5 (blend.py)
    hit_count: wp.array(dtype=wp.int32)   # [R] accepted hits
    blended: wp.array(dtype=wp.int32)     # [R] blended hits
    candidates: wp.array(dtype=wp.int32)  # [R] BVH leaves visited (first traversal)
    obb_candidates: wp.array(dtype=wp.int32)  # [R] candidates whose cut-off ellipsoid the ray meets
    needed: wp.array(dtype=wp.int32)      # [R] replay slots needed when overflowing, else 0


@wp.struct
class RayGrads:
    """dLoss/d(outputs), R entries each (also used for the fused L1 targets)."""

    diffuse: wp.array(dtype=wp.vec3)
    depth: wp.array(dtype=float)
    normal: wp.array(dtype=wp.vec3)
    roughness: wp.array(dtype=float)
    f0: wp.array(dtype=wp.vec3)
    transmittance: wp.array(dtype=float)


@wp.struct
class GaussianGrads:
    """dLoss/d(activated values), N entries each, accumulated with atomics; which of them were reached."""

    means: wp.array(dtype=wp.vec3)
    w2l: wp.array(dtype=wp.mat33)
    opacity: wp.array(dtype=float)
    diffuse: wp.array(dtype=wp.vec3)
    normal: wp.array(dtype=wp.vec3)
    roughness: wp.array(dtype=float)
    f0: wp.array(dtype=wp.vec3)
    # track != 0 (one CPU thread's row, filled by one launch at a time): each Gaussian the row first receives a
    # gradient for is flagged in `touched` and listed in `touched_ids` (touched_count[0] of them), so the gather
    # visits those alone (launch.GradRows); 0 (CUDA: one row, concurrent threads): not kept, a dense gather
    touched: wp.array(dtype=wp.int32)
    touched_ids: wp.array(dtype=wp.int32)
    touched_count: wp.array(dtype=wp.int32)
    track: int


@wp.struct
class L1Loss:
    """Fused per-pixel L1: loss = sum_layer weight * mean |out - target|."""

    weights: wp.array(dtype=float)  # [5] diffuse, depth, normal, roughness, f0 (0 = no target)
    inv_rays: float                 # 1 / total number of rays (all threads)
