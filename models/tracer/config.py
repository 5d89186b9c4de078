"""Tracer configuration (``reconstruct.tracer`` in the pipeline config; stored with every trained model)."""

from __future__ import annotations

from dataclasses import dataclass

from models.settings import setting

OCTANT_MODES = ("auto", "always", "never")  # TracerConfig.octant_bvh (not on / off: YAML reads those as booleans)
TRAVERSALS = ("interval", "single", "kbuffer", "ordered")  # index = TraceParams.traversal
BVH_CONSTRUCTORS = ("auto", "sah", "lbvh", "median")  # auto: Warp's choice (sah on a CPU, lbvh on a GPU)


@dataclass
class TracerConfig:
    """Gaussian ray tracer settings."""

    kernel_p: int = setting(3, "kernel exponent p of exp(-r^(2p) / (2p)); 1 = plain Gaussian, 3 = flatter top "
                            "(reference)", minimum=1)
    alpha_min: float = setting(0.005, "a hit is accepted when alpha = min(alpha_max, opacity x response) > alpha_min",
                               exclusiveMinimum=0, exclusiveMaximum=1)
    alpha_max: float = setting(0.9999, "upper clamp of alpha, keeps 1 - alpha > 0 for the backward pass",
                               exclusiveMinimum=0, exclusiveMaximum=1)
    transmittance_threshold: float = setting(0.01, "blending stops before a hit whose incoming transmittance is "
                                             "below this threshold", minimum=0, exclusiveMaximum=1)
    t_min: float = setting(0.0, "hits at ray parameter t <= t_min are ignored (near distance; reflection offset)",
                           minimum=0)
    k: int = setting(16, "hits taken per integration round (k nearest beyond the last taken)", minimum=1)
    traversal: str = setting("interval", "interval: windows of the ray parameter front to back, stopping once "
                             "the ray is done (the method); single: one traversal gathering every accepted hit "
                             "(ablation); kbuffer: 3DGRT-style re-traversal per round of k hits (ablation); "
                             "ordered: own BVH traversed best-first (ablation)",
                             enum=["interval", "single", "kbuffer", "ordered"])
    window: float = setting(2.5, "interval traversal: first window length, in median Gaussian box diagonals (then "
                            "sized per ray from the optical depth seen so far); used by rays that enter the "
                            "Gaussians' box from outside (cameras looking at a cloud or an object); only the cost "
                            "depends on it (kernels_interval.py)", exclusiveMinimum=0)
    inside_whole_window: bool = setting(True, "interval traversal: a ray that starts inside the Gaussians' box "
                                        "(a camera or reflection vertex in a room) takes all of itself as its "
                                        "first window (the opaque cut ends it at the first surface) instead of "
                                        "window; only the cost depends on it", runtime=True)
    octant_bvh: str = setting("auto", "interval traversal: seven more BVHs over the bounds mirrored per octant of "
                              "ray directions, so that every node is visited nearer child first and a window that "
                              "turns opaque stops soon after its cut (models/tracer/bvh.py); the hits and their "
                              "order do not depend on it. They cost seven more refits per update: auto = used once "
                              "a tree has traced enough rays since its last update to pay for them (renders, "
                              "whole-view GPU steps; not the CPU's 4096-ray training steps), always, never",
                              enum=list(OCTANT_MODES), runtime=True)
    wide_bvh: bool = setting(True, "interval traversal on a CPU: query an 8-wide tree collapsed from the BVH (eight "
                             "child boxes per SIMD test, nearer children first; models/tracer/wide_bvh.py) instead of "
                             "Warp's binary tree and its octant trees; the hits and their order do not depend on it. "
                             "A CUDA device always uses Warp's", runtime=True)
    replay_capacity: int = setting(64, "replay buffer slots per ray at start (the blended hits, kept for the "
                                   "backward, plus the window being sorted); grows when a ray needs more",
                                   minimum=2)
    max_replay_capacity: int | None = setting(None, "optional ceiling on the replay growth: a ray that needs more "
                                              "slots raises (null: no ceiling, memory permitting)", minimum=2)
    num_threads: int = setting(2, "CPU only: rays are split over this many Python threads (one Warp launch each)",
                               runtime=True, minimum=1)
    bvh_constructor: str = setting("auto", "how the BVH over the Gaussians' boxes is built (Warp): sah (surface area "
                                   "heuristic, on the CPU; a GPU tree is built on the CPU and copied), lbvh (on the "
                                   "GPU, faster to build), median; auto = Warp's choice (sah on a CPU, lbvh on a GPU). "
                                   "The hits and their order do not depend on it", runtime=True,
                                   enum=list(BVH_CONSTRUCTORS))
    world_aabb_only: bool = setting(False, "ablation: skip the per-candidate ellipsoid test before the response "
                                    "(world AABB only)")
    always_rebuild: bool = setting(False, "ablation: rebuild the BVH on every update() instead of refitting it")
    ordered_leaf_size: int = setting(4, "traversal ordered: Gaussians per leaf of its BVH", minimum=1)
    ordered_heap_size: int = setting(128, "traversal ordered: node-heap entries per ray; a ray that needs more "
                                     "falls back to the single traversal (same result, no early exit)", minimum=2)

    def __post_init__(self) -> None:
        if not isinstance(self.kernel_p, int) or self.kernel_p < 1:
            raise ValueError(f"kernel_p must be an int >= 1, got {self.kernel_p!r}")
        if not 0.0 < self.alpha_min < self.alpha_max < 1.0:
            raise ValueError(f"need 0 < alpha_min < alpha_max < 1, got {self.alpha_min}, {self.alpha_max}")
        if not 0.0 <= self.transmittance_threshold < 1.0:
            raise ValueError(f"transmittance_threshold must be in [0, 1), got {self.transmittance_threshold}")
        if self.k < 1:
            raise ValueError(f"k must be >= 1, got {self.k}")
        if self.replay_capacity < 2 or (self.max_replay_capacity is not None
                                        and self.max_replay_capacity < self.replay_capacity):
            raise ValueError(
                f"need 2 <= replay_capacity <= max_replay_capacity, got "
                f"{self.replay_capacity}, {self.max_replay_capacity}"
            )
        if self.traversal not in TRAVERSALS:
            raise ValueError(f"traversal must be one of {', '.join(TRAVERSALS)}, got {self.traversal!r}")
        if self.octant_bvh not in OCTANT_MODES:
            raise ValueError(f"octant_bvh must be one of {', '.join(OCTANT_MODES)}, got {self.octant_bvh!r}")
        if not self.window > 0:
            raise ValueError(f"window must be > 0, got {self.window}")
        if self.bvh_constructor not in BVH_CONSTRUCTORS:
            raise ValueError(f"bvh_constructor must be one of {', '.join(BVH_CONSTRUCTORS)}, "
                             f"got {self.bvh_constructor!r}")
        if self.ordered_heap_size < 2:
            raise ValueError(f"ordered_heap_size must be >= 2, got {self.ordered_heap_size}")
        if self.ordered_leaf_size < 1:
            raise ValueError(f"ordered_leaf_size must be >= 1, got {self.ordered_leaf_size}")
        if self.num_threads < 1:
            raise ValueError(f"num_threads must be >= 1, got {self.num_threads}")
