"""Tracer configuration."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class TracerConfig:
    # Kernel exponent p of exp(-r^(2p) / (2p)); 1 = plain Gaussian, 3 = flatter top (reference).
    kernel_p: int = 3
    # A hit is accepted when alpha = min(alpha_max, opacity * response) > alpha_min.
    alpha_min: float = 0.005
    # Upper clamp of alpha, keeps 1 - alpha > 0 for the backward pass.
    alpha_max: float = 0.9999
    # Blending stops before a hit whose incoming transmittance is below this threshold.
    transmittance_threshold: float = 0.01
    # Hits at ray parameter t <= t_min are ignored (near distance; reflection-ray offset).
    t_min: float = 0.0
    # Hits taken per integration round ("k nearest beyond the last taken").
    k: int = 16
    # Replay buffer slots per ray at start (accepted hits stored for integration and backward).
    replay_capacity: int = 64
    # Hard ceiling when the replay buffer grows after an overflow; beyond it trace() raises.
    max_replay_capacity: int = 4096
    # CPU only: rays are split over this many Python threads (one Warp launch each).
    num_threads: int = 2
    # Ablation: 3DGRT-style integration, re-traversing the BVH for each round of k nearest hits.
    repeated_kbuffer: bool = False
    # Ablation: skip the per-candidate oriented-box test (test the world AABB from the BVH only).
    world_aabb_only: bool = False
    # Ablation: rebuild the BVH on every update() instead of refitting it.
    always_rebuild: bool = False
    # Stretch: own Morton-ordered BVH traversed front to back, stopping early once T < threshold
    # (hit_count then counts hits found before stopping). Excludes repeated_kbuffer.
    ordered_traversal: bool = False
    # Gaussians per leaf of the ordered BVH.
    ordered_leaf_size: int = 4
    # Node-heap entries per ray for the ordered traversal; a ray that needs more falls back
    # to the single traversal (same result, no early exit).
    ordered_heap_size: int = 128

    def __post_init__(self) -> None:
        if not isinstance(self.kernel_p, int) or self.kernel_p < 1:
            raise ValueError(f"kernel_p must be an int >= 1, got {self.kernel_p!r}")
        if not 0.0 < self.alpha_min < self.alpha_max < 1.0:
            raise ValueError(f"need 0 < alpha_min < alpha_max < 1, got {self.alpha_min}, {self.alpha_max}")
        if not 0.0 <= self.transmittance_threshold < 1.0:
            raise ValueError(f"transmittance_threshold must be in [0, 1), got {self.transmittance_threshold}")
        if self.k < 1:
            raise ValueError(f"k must be >= 1, got {self.k}")
        if self.replay_capacity < 1 or self.max_replay_capacity < self.replay_capacity:
            raise ValueError(
                f"need 1 <= replay_capacity <= max_replay_capacity, got "
                f"{self.replay_capacity}, {self.max_replay_capacity}"
            )
        if self.ordered_traversal and self.repeated_kbuffer:
            raise ValueError("ordered_traversal and repeated_kbuffer are exclusive; choose one")
        if self.ordered_heap_size < 2:
            raise ValueError(f"ordered_heap_size must be >= 2, got {self.ordered_heap_size}")
        if self.ordered_leaf_size < 1:
            raise ValueError(f"ordered_leaf_size must be >= 1, got {self.ordered_leaf_size}")
        if self.num_threads < 1:
            raise ValueError(f"num_threads must be >= 1, got {self.num_threads}")
