"""Launch bookkeeping: per-launch arrays, ray chunks over CPU threads, struct views."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import warp as wp

from models.tracer.ordered_bvh import OrderedBvh
from models.tracer.structs import GaussianGrads, RayGrads, RayOutputs, Replay, vec16

# RayOutputs field -> (Warp dtype, components)
OUT_FIELDS = {
    "diffuse": (wp.vec3, 3), "depth": (float, 1), "normal": (wp.vec3, 3), "roughness": (float, 1),
    "f0": (wp.vec3, 3), "transmittance": (float, 1), "front_depth": (float, 1), "hit_count": (wp.int32, 1),
    "blended": (wp.int32, 1),
    "candidates": (wp.int32, 1), "obb_candidates": (wp.int32, 1), "needed": (wp.int32, 1),
}
GRAD_FIELDS = {
    "means": wp.vec3, "w2l": wp.mat33, "opacity": float, "diffuse": wp.vec3, "normal": wp.vec3,
    "roughness": float, "f0": wp.vec3,
}
RAY_GRAD_FIELDS = {
    "diffuse": wp.vec3, "depth": float, "normal": wp.vec3, "roughness": float, "f0": wp.vec3,
    "transmittance": float,
}


def ray_chunks(n_rays: int, n_threads: int) -> list[tuple[int, int]]:
    """Contiguous, non-empty [start, end) ranges covering n_rays."""
    n = max(1, min(n_threads, n_rays))
    bounds = [round(i * n_rays / n) for i in range(n + 1)]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def rows(a_array: wp.array, a: int, b: int) -> wp.array:
    """Rows a..b of an array: the array itself when that is all of it (a slice costs ~20 us of Python)."""
    return a_array if a == 0 and b == a_array.shape[0] else a_array[a:b]


MIN_CHUNK_RAYS = 256  # a CPU launch costs ~0.1 ms of Python; 256 rays cost ~2-5 ms of kernel


def thread_stripes(n_rays: int, n_threads: int, chunks_per_thread: int = 8,
                   min_chunk: int = MIN_CHUNK_RAYS) -> list[list[tuple[int, int]]]:
    """Ray chunks of at least ``min_chunk`` rays (when there are that many) dealt round-robin to threads
    (balances image regions of unequal cost). One list per thread; each thread launches its chunks in turn with
    its own gradient buffers: a small batch is one launch on one thread, not 16 launches and 2 gradient sums.
    Past one chunk, the count is a multiple of the threads: 600 rays were 3 chunks of 200, two on one thread and
    one on the other (that segment's wall time was 400 rays' instead of 300)."""
    n_chunks = min(n_threads * chunks_per_thread, -(-n_rays // max(min_chunk, 1)))
    if n_threads <= 1 or n_chunks <= 1:
        return [[(0, n_rays)]]
    n_chunks = -(-n_chunks // n_threads) * n_threads
    chunks = ray_chunks(n_rays, n_chunks)
    stripes = [chunks[i::n_threads] for i in range(n_threads)]
    return [s for s in stripes if s] or [[(0, n_rays)]]


@dataclass
class ReplayArrays:
    ids: wp.array
    t: wp.array
    alpha: wp.array
    trans: wp.array

    @staticmethod
    def allocate(n_rays: int, capacity: int, device: str) -> "ReplayArrays":
        shape = (n_rays, capacity)
        return ReplayArrays(wp.empty(shape, dtype=wp.int32, device=device), wp.empty(shape, dtype=float, device=device),
                            wp.empty(shape, dtype=float, device=device), wp.empty(shape, dtype=float, device=device))

    @property
    def capacity(self) -> int:
        return self.ids.shape[1]

    def view(self, a: int, b: int) -> Replay:
        s = Replay()
        s.ids, s.t, s.alpha, s.trans = (rows(x, a, b) for x in (self.ids, self.t, self.alpha, self.trans))
        return s


class LaunchViews:
    """The Replay / RayOutputs structs over the WHOLE arrays of a run, made once per (replay, outputs) pair: every
    chunk of rays is a launch with an offset into them (the kernels' ``offset``), not a slice (~20 us of Python per
    sliced array: 16 launches x 20 arrays were ~7 ms per 16k-ray trace on 2 threads). Holds the pair it made them
    for, so a re-run's new replay buffer (overflow) gets new structs; ``extra()`` is made with them (the ordered
    BVH's per-ray heap, allocated by the run)."""

    def __init__(self, n_rays: int, extra):
        self.n_rays = n_rays
        self.extra = extra
        self._made: tuple | None = None  # (rep, outs, structs), replaced as one (the pool's threads call of())

    def of(self, rep: "ReplayArrays", outs: dict[str, wp.array]) -> tuple:
        """(Replay, RayOutputs, extra()) over the whole arrays of ``rep`` and ``outs``."""
        made = self._made
        if made is None or made[0] is not rep or made[1] is not outs:
            made = (rep, outs, (rep.view(0, self.n_rays), outputs_view(outs, 0, self.n_rays), self.extra()))
            self._made = made
        return made[2]


def allocate_outputs(n_rays: int, device: str) -> dict[str, wp.array]:
    return {k: wp.zeros(n_rays, dtype=dt, device=device) for k, (dt, _) in OUT_FIELDS.items()}


def outputs_view(arrays: dict[str, wp.array], a: int, b: int) -> RayOutputs:
    s = RayOutputs()
    for k in OUT_FIELDS:
        setattr(s, k, rows(arrays[k], a, b))
    return s


def ray_grads_view(arrays: dict[str, wp.array], a: int, b: int) -> RayGrads:
    s = RayGrads()
    for k in RAY_GRAD_FIELDS:
        setattr(s, k, rows(arrays[k], a, b))
    return s


class GradRows:
    """The backward's gradient accumulators wrt the activated values: one row of n entries per CPU thread (CPU
    atomics are not safe across concurrent launches), flat [threads * n] per field. Kept by the tracer between
    backward passes: the gather kernel (models/tracer/chain.py) that sums the rows also sets them back to zero, so
    no pass clears (or allocates) 23 floats per Gaussian and thread, and nothing adds rows in torch.

    On a CPU each row also flags and lists the Gaussians it received a gradient for (``track``): a backward that
    reaches few of many Gaussians (a reflection segment, 2,304 rays into 1M) is gathered over those alone."""

    def __init__(self, n: int, threads: int, device: str):
        self.n = n
        self.threads = threads
        self.track = not str(device).startswith("cuda")
        self.flat = {k: wp.zeros(threads * n, dtype=dt, device=device) for k, dt in GRAD_FIELDS.items()}
        self.touched = wp.zeros(threads * n, dtype=wp.int32, device=device)
        self.touched_ids = wp.zeros(threads * n, dtype=wp.int32, device=device)
        self.touched_count = wp.zeros(threads, dtype=wp.int32, device=device)
        self.structs = [grads_struct({k: v[i * n:(i + 1) * n] for k, v in self.flat.items()},
                                     self.touched[i * n:(i + 1) * n], self.touched_ids[i * n:(i + 1) * n],
                                     self.touched_count[i:i + 1])
                        for i in range(threads)]
        self.dirty = False  # handed to a launch and not gathered since (an error in between): clear before reuse
        self.tracking = False  # the last take() listed what the rows reach

    def take(self, track: bool = True) -> list:
        """The per-thread structs, all zero; listing what they reach when ``track`` (and the device can)."""
        if self.dirty:
            for v in (*self.flat.values(), self.touched, self.touched_count):
                v.zero_()
        self.dirty = True
        self.tracking = self.track and track
        for s in self.structs:
            s.track = int(self.tracking)
        return self.structs

    def row_ids(self, k: int) -> wp.array:
        """The Gaussians row k flagged (tracked rows)."""
        count = int(self.touched_count.numpy()[k])
        return self.touched_ids[k * self.n:k * self.n + count]


def grads_struct(arrays: dict[str, wp.array], touched: wp.array, touched_ids: wp.array,
                 touched_count: wp.array) -> GaussianGrads:
    """One row's struct; it lists nothing until GradRows.take() says so (``track``)."""
    s = GaussianGrads()
    for k in GRAD_FIELDS:
        setattr(s, k, arrays[k])
    s.touched, s.touched_ids, s.touched_count, s.track = touched, touched_ids, touched_count, 0
    return s


def run_chunks(pool: ThreadPoolExecutor | None, jobs: list) -> None:
    """Run callables, concurrently on the pool when given (Warp releases the GIL in CPU launches)."""
    if pool is None or len(jobs) == 1:
        for job in jobs:
            job()
        return
    for f in [pool.submit(job) for job in jobs]:
        f.result()


def ray_grads_struct(views: dict[str, wp.array]) -> RayGrads:
    s = RayGrads()
    for k in RAY_GRAD_FIELDS:
        setattr(s, k, views[k])
    return s


def empty_ordered(device: str) -> OrderedBvh:
    """Placeholder ordered BVH for launches that do not use it (never read)."""
    b = OrderedBvh()
    b.node_lo = wp.zeros(1, dtype=wp.vec3, device=device)
    b.node_hi = wp.zeros(1, dtype=wp.vec3, device=device)
    b.order = wp.zeros(1, dtype=wp.int32, device=device)
    b.lowers = wp.zeros(1, dtype=wp.vec3, device=device)
    b.uppers = wp.zeros(1, dtype=wp.vec3, device=device)
    b.sorted_lowers = wp.zeros(1, dtype=wp.vec3, device=device)
    b.sorted_uppers = wp.zeros(1, dtype=wp.vec3, device=device)
    b.sorted_packed = wp.zeros(1, dtype=vec16, device=device)
    b.n_leaves, b.leaf_size, b.count = 1, 1, 0
    b.heap_keys = wp.zeros((1, 1), dtype=float, device=device)
    b.heap_nodes = wp.zeros((1, 1), dtype=wp.int32, device=device)
    return b
