"""BVH over the world bounds of the Gaussians' cut-off ellipsoids (wp.Bvh).

Each Gaussian's support is {mean + R S u : |u| <= s}, the ball of its local frame scaled by the
opacity-adaptive cutoff s (alpha > alpha_min exactly there); its world AABB has half extent s |row i of R S|
along axis i (prepare.py; until 2026-11 the AABB of the oriented cube |u|_inf <= s, up to sqrt(3) wider).
Refit when only the parameters moved; rebuild when the number of Gaussians changes,
on request, or always (ablation `always_rebuild`). The tracer also asks for a rebuild when it is handed other
tensors of the same count whose Gaussians mostly moved farther than their own size (``moved_far``): a refit
keeps the old tree's topology, and a tree built for another scene made a training step 5x slower.

Octant trees (TracerConfig.octant_bvh, ``refresh_octants``): ``wp.bvh_query_ray`` visits a node's children in a
fixed order (the one holding the larger coordinates first), i.e. nearer child first only for a ray going down the
node's split axis. Seven more trees over the bounds mirrored per octant of ray directions (tree k: along the axes
whose bit is set in k, x: 1, y: 2, z: 4) let a ray with d_a > 0 along those axes query tree k with its origin and
direction mirrored the same way: every node then puts the nearer child first, so a window that turns opaque
stops soon after its cut (kernels_interval.py). The boxes visited and every t are those of the plain tree; only
the order changes. They cost seven more refits per update (or builds after a rebuild), so they are refreshed
lazily, when a trace needs them (the tracer decides: tracer.py ``_octants_for``).
"""

from __future__ import annotations

import time

import torch
import warp as wp

from models.tracer.interop import to_warp
from models.tracer.launch import ray_chunks
from models.tracer.prepare import prepare_kernel
from models.tracer.structs import vec16

N_OCTANTS = 8


@wp.kernel
def mirror_bounds_kernel(lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3), flip: wp.vec3,
                         lo_out: wp.array(dtype=wp.vec3), hi_out: wp.array(dtype=wp.vec3)):
    """Bounds mirrored along the axes where ``flip`` is -1 (x -> -x swaps a box's lower and upper x)."""
    i = wp.tid()
    lo = lowers[i]
    hi = uppers[i]
    a = wp.vec3(0.0)
    b = wp.vec3(0.0)
    for c in range(3):
        if flip[c] < 0.0:
            a[c] = -hi[c]
            b[c] = -lo[c]
        else:
            a[c] = lo[c]
            b[c] = hi[c]
    lo_out[i] = a
    hi_out[i] = b


def octant_flip(k: int) -> wp.vec3:
    """The mirror of octant tree k: -1 along the axes whose bit is set (x: 1, y: 2, z: 4)."""
    return wp.vec3(*(-1.0 if k >> axis & 1 else 1.0 for axis in range(3)))



class GaussianBvh:
    """Holds the wp.Bvh, the bound arrays it references (refit reads them in place) and
    the packed per-Gaussian records [N] (see structs.vec16) of the last update."""

    def __init__(self, device: str, use_wp_bvh: bool = True, constructor: str = "auto"):
        self.device = device
        self.constructor = None if constructor == "auto" else constructor  # wp.Bvh's (None: Warp's default)
        self.use_wp_bvh = use_wp_bvh  # False: only bounds + packed records (ordered traversal)
        self.bvh: wp.Bvh | None = None
        self.mirrored: list[tuple[wp.Bvh, wp.array, wp.array]] = []  # octant trees 1..7 with their mirrored bounds
        self.octant_ids: wp.array | None = None  # [8] uint64: octant tree k's id (0: the plain tree)
        self.octants_current = False  # the octant trees hold the bounds of the last update (refresh_octants)
        self._octants_for = None      # the plain tree they were built for (a rebuild makes new ones)
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
        self.octants_current = False
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

    def refresh_octants(self, run=None) -> None:
        """Make the seven mirrored trees hold the bounds of the last update (module docstring): built when the
        plain tree was (re)built since, refitted otherwise; ``run`` as in update (Warp releases the GIL)."""
        if self.octants_current or self.bvh is None:
            return
        run = run or (lambda jobs: [job() for job in jobs])
        n = self.count
        rebuild = self._octants_for is not self.bvh
        if rebuild:
            self.mirrored = [None] * (N_OCTANTS - 1)

        def refresh(k: int) -> None:
            if rebuild:
                lo = wp.empty(n, dtype=wp.vec3, device=self.device)
                hi = wp.empty(n, dtype=wp.vec3, device=self.device)
            else:
                tree, lo, hi = self.mirrored[k - 1]
            wp.launch(mirror_bounds_kernel, dim=n, device=self.device,
                      inputs=[self.lowers, self.uppers, octant_flip(k), lo, hi])
            if rebuild:
                self.mirrored[k - 1] = (wp.Bvh(lo, hi, constructor=self.constructor), lo, hi)
            else:
                tree.refit()

        run([(lambda k=k: refresh(k)) for k in range(1, N_OCTANTS)])
        if rebuild:
            ids = [self.bvh.id] + [t[0].id for t in self.mirrored]
            self.octant_ids = wp.array(ids, dtype=wp.uint64, device=self.device)
            self._octants_for = self.bvh
        self.octants_current = True

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
