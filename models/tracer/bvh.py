"""BVH over the world bounds of the Gaussians' cut-off ellipsoids (wp.Bvh).

Each Gaussian's support is {mean + R S u : |u| <= s}, the ball of its local frame scaled by the
opacity-adaptive cutoff s (alpha > alpha_min exactly there); its world AABB has half extent s |row i of R S|
along axis i (prepare.py; until 2026-11 the AABB of the oriented cube |u|_inf <= s, up to sqrt(3) wider).
Refit when only the parameters moved; rebuild when the number of Gaussians changes,
on request, or always (ablation `always_rebuild`). The tracer also asks for a rebuild when it is handed other
tensors of the same count whose Gaussians mostly moved farther than their own size (``moved_far``): a refit
keeps the old tree's topology, and a tree built for another scene made a training step 5x slower.
"""

from __future__ import annotations

import time

import torch
import warp as wp

from models.tracer.interop import to_warp
from models.tracer.launch import ray_chunks
from models.tracer.prepare import prepare_kernel
from models.tracer.structs import vec16


class GaussianBvh:
    """Holds the wp.Bvh, the bound arrays it references (refit reads them in place) and
    the packed per-Gaussian records [N] (see structs.vec16) of the last update."""

    def __init__(self, device: str, use_wp_bvh: bool = True, constructor: str = "auto"):
        self.device = device
        self.constructor = None if constructor == "auto" else constructor  # wp.Bvh's (None: Warp's default)
        self.use_wp_bvh = use_wp_bvh  # False: only bounds + packed records (ordered traversal)
        self.bvh: wp.Bvh | None = None
        self.lowers: wp.array | None = None
        self.uppers: wp.array | None = None
        self.packed: wp.array | None = None
        self.count = -1
        self.last_update_s = 0.0   # wall time of the last update
        self.last_was_rebuild = False
        self._built_means: torch.Tensor | None = None  # the means the tree was built for (moved_far)

    def update(self, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
               opacity_logits: torch.Tensor, kernel_p: int, alpha_min: float, rebuild: bool = False,
               run=None, n_chunks: int = 1, convert=None) -> None:
        """Raw parameters [N,3], [N,4], [N,3], [N] -> packed records, bounds; refit or rebuild.
        run(jobs) executes the chunk launches (e.g. concurrently); default: in turn. convert(tensor, dtype) makes
        the Warp arrays of the parameters (default ``to_warp`` on this device; the tracer passes its cached views)."""
        run = run or (lambda jobs: [job() for job in jobs])
        convert = convert or (lambda t, dtype: to_warp(t, dtype, self.device))
        start = time.perf_counter()
        n = means.shape[0]
        self.last_was_rebuild = rebuild or self.packed is None or n != self.count
        if n == 0:
            self.bvh, self.count = None, 0
            self.packed = wp.zeros(0, dtype=vec16, device=self.device)
            self.last_update_s = time.perf_counter() - start
            return
        if self.last_was_rebuild:
            self.lowers = wp.empty(n, dtype=wp.vec3, device=self.device)
            self.uppers = wp.empty(n, dtype=wp.vec3, device=self.device)
            self.packed = wp.empty(n, dtype=vec16, device=self.device)
        raw = [convert(means, wp.vec3), convert(quats, wp.vec4), convert(log_scales, wp.vec3),
               convert(opacity_logits, float)]
        outs = [self.packed, self.lowers, self.uppers]

        def prepare(a: int, b: int) -> None:
            wp.launch(prepare_kernel, dim=b - a, device=self.device,
                      inputs=[*(x[a:b] for x in raw), kernel_p, alpha_min, *(x[a:b] for x in outs)])

        # CPU: split over the tracer's threads (a launch uses one core), in chunks of >= 8192 Gaussians (~1 ms of
        # kernel: a smaller scene is one launch); no atomics involved
        run([(lambda a=a, b=b: prepare(a, b)) for a, b in ray_chunks(n, min(n_chunks, -(-n // 8192)))])
        if not self.use_wp_bvh:
            self.bvh, self.count = None, n
        elif self.last_was_rebuild:
            self.bvh = wp.Bvh(self.lowers, self.uppers, constructor=self.constructor)
            self.count = n
            self._built_means = means.detach().float().clone()
        else:
            self.bvh.refit()
        self.last_update_s = time.perf_counter() - start

    def moved_far(self, means: torch.Tensor, size: float) -> bool:
        """Whether most of ``means`` [N, 3] (the same count as the tree) lie farther than ``size`` (the tracer
        passes the median box diagonal at the build) from where the tree was built: a refit would keep a topology
        made for another scene. One device read-back; the tracer asks only when it is handed other tensors (an
        optimiser step never does)."""
        if self._built_means is None or len(means) != self.count or self._built_means.device != means.device:
            return False
        drift = (means.detach().float() - self._built_means).norm(dim=1).median()
        return bool(drift > size)

    @property
    def id(self) -> int:
        return 0 if self.bvh is None else int(self.bvh.id)
