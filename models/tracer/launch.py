"""Launch bookkeeping: per-launch arrays, ray chunks over CPU threads, struct views."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import warp as wp

from models.tracer.structs import GaussianGrads, RayGrads, RayOutputs, Replay

# RayOutputs field -> (Warp dtype, components)
OUT_FIELDS = {
    "diffuse": (wp.vec3, 3), "depth": (float, 1), "normal": (wp.vec3, 3), "roughness": (float, 1),
    "f0": (wp.vec3, 3), "transmittance": (float, 1), "hit_count": (wp.int32, 1), "blended": (wp.int32, 1),
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
        s.ids, s.t, s.alpha, s.trans = self.ids[a:b], self.t[a:b], self.alpha[a:b], self.trans[a:b]
        return s


def allocate_outputs(n_rays: int, device: str) -> dict[str, wp.array]:
    return {k: wp.zeros(n_rays, dtype=dt, device=device) for k, (dt, _) in OUT_FIELDS.items()}


def outputs_view(arrays: dict[str, wp.array], a: int, b: int) -> RayOutputs:
    s = RayOutputs()
    for k in OUT_FIELDS:
        setattr(s, k, arrays[k][a:b])
    return s


def ray_grads_view(arrays: dict[str, wp.array], a: int, b: int) -> RayGrads:
    s = RayGrads()
    for k in RAY_GRAD_FIELDS:
        setattr(s, k, arrays[k][a:b])
    return s


def allocate_grads(n: int, device: str) -> dict[str, wp.array]:
    return {k: wp.zeros(n, dtype=dt, device=device) for k, dt in GRAD_FIELDS.items()}


def grads_struct(arrays: dict[str, wp.array]) -> GaussianGrads:
    s = GaussianGrads()
    for k in GRAD_FIELDS:
        setattr(s, k, arrays[k])
    return s


def run_chunks(pool: ThreadPoolExecutor | None, jobs: list) -> None:
    """Run callables, concurrently on the pool when given (Warp releases the GIL in CPU launches)."""
    if pool is None or len(jobs) == 1:
        for job in jobs:
            job()
        return
    for f in [pool.submit(job) for job in jobs]:
        f.result()
