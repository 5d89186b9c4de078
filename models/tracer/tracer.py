"""Tracer: holds the BVH and launches the Warp kernels; autograd and fused entry points.

    tracer = Tracer(TracerConfig(), device="cpu")
    out = tracer.trace(origins, dirs, gaussians)            # differentiable TraceOutput
    out, loss = tracer.trace_fused(origins, dirs, gaussians, targets, weights)  # fills .grad

Rays may start anywhere (camera or reflection vertices); dirs need not be unit length
(depth is then the ray parameter t, not a distance).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

import models.tracer.kernels as kernels
from models.gaussians.activations import quats_to_rotmats
from models.gaussians.scene import Gaussians
from models.tracer.bvh import GaussianBvh
from models.tracer.config import TracerConfig
from models.tracer.interop import to_torch, to_warp
from models.tracer.launch import (
    RAY_GRAD_FIELDS,
    ReplayArrays,
    allocate_grads,
    allocate_outputs,
    grads_struct,
    outputs_view,
    ray_chunks,
    ray_grads_view,
    run_chunks,
)
from models.tracer.output import LAYERS, TraceOutput
from models.tracer.structs import GaussianData, L1Loss, RayGrads, TraceParams, vec16

_GRAD_TO_INPUT = ["means", "w2l", "opacity", "diffuse", "normal", "roughness", "f0"]


class Tracer:
    """Gaussian ray tracer on one Warp device ("cpu" or "cuda[:i]")."""

    def __init__(self, config: TracerConfig | None = None, device: str = "cpu"):
        if config is not None and not isinstance(config, TracerConfig):
            raise TypeError(f"config must be a TracerConfig, got {type(config).__name__}")
        self.config = config or TracerConfig()
        wp.config.quiet = True
        wp.init()
        try:
            self.device = str(wp.get_device(device))
        except (RuntimeError, ValueError) as exc:
            raise ValueError(f"unknown or unavailable Warp device {device!r}: {exc}") from exc
        self.is_cpu = wp.get_device(self.device).is_cpu
        self.bvh = GaussianBvh(self.device)
        self.capacity = self.config.replay_capacity
        threads = self.config.num_threads if self.is_cpu else 1
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="tracer") if threads > 1 else None
        self._threads = threads
        self._scene_key = None
        self._cutoff: wp.array | None = None
        self._loaded = False
        self.last_overflow_rays = 0

    # ------------------------------------------------------------------ BVH
    def update(self, gaussians: Gaussians, rebuild: bool = False) -> None:
        """Recompute the oriented-box bounds; refit the BVH, or rebuild it when the number of
        Gaussians changed, `rebuild` is set or config.always_rebuild."""
        if not isinstance(gaussians, Gaussians):
            raise TypeError(f"gaussians must be a Gaussians, got {type(gaussians).__name__}")
        with torch.no_grad():
            cutoff = self.bvh.update(
                gaussians.means, quats_to_rotmats(gaussians.quats), torch.exp(gaussians.log_scales),
                gaussians.opacities(), self.config.kernel_p, self.config.alpha_min,
                rebuild=rebuild or self.config.always_rebuild)
        self._cutoff = to_warp(cutoff, float, self.device)
        self._scene_key = self._key(gaussians)

    @staticmethod
    def _key(g: Gaussians):
        return tuple((id(t), t._version) for t in g.params().values())

    def _ensure_updated(self, gaussians: Gaussians) -> None:
        if not isinstance(gaussians, Gaussians):
            raise TypeError(f"gaussians must be a Gaussians, got {type(gaussians).__name__}")
        if self._scene_key != self._key(gaussians):
            self.update(gaussians)

    # ------------------------------------------------------------------ entry points
    def trace(self, origins: torch.Tensor, dirs: torch.Tensor, gaussians: Gaussians) -> TraceOutput:
        """Trace R rays. origins, dirs: [R, 3]. Differentiable wrt the Gaussian parameters
        (diffuse, depth, normal, roughness, f0 and transmittance outputs)."""
        origins, dirs = self._check_rays(origins, dirs)
        self._ensure_updated(gaussians)
        w2l, opac = gaussians.world_to_local(), gaussians.opacities()
        res = _TraceFunction.apply(self, origins, dirs, gaussians.means, w2l, opac, gaussians.diffuse,
                                   gaussians.normals, gaussians.roughness, gaussians.f0)
        diffuse, depth, normal, rough, f0, trans, hits, blended, cand, obb = res
        return TraceOutput(diffuse=diffuse, depth=depth, normal=normal, roughness=rough, f0=f0,
                           transmittance=trans, hit_count=hits, blended_count=blended, candidates=cand,
                           obb_candidates=obb, overflow_rays=self.last_overflow_rays,
                           replay_capacity=self.capacity)

    def trace_fused(self, origins: torch.Tensor, dirs: torch.Tensor, gaussians: Gaussians,
                    targets: dict[str, torch.Tensor], weights: dict[str, float]) -> tuple[TraceOutput, torch.Tensor]:
        """Forward + per-pixel L1 loss + backward in the same launches.

        loss = sum_layer weights[layer] * mean |out_layer - targets[layer]| (mean over rays and
        channels); targets[layer]: [R, C] or [R] for C = 1. Gradients are ACCUMULATED into the
        .grad of the Gaussian parameters that require grad. Returns (detached outputs, loss).
        """
        origins, dirs = self._check_rays(origins, dirs)
        n_rays = origins.shape[0]
        for name in list(targets) + list(weights):
            if name not in LAYERS:
                raise ValueError(f"unknown layer {name!r}; expected one of {list(LAYERS)}")
        for name in weights:
            if name not in targets:
                raise ValueError(f"weight given for layer {name!r} but no target")
        self._ensure_updated(gaussians)
        with torch.enable_grad():
            w2l, opac = gaussians.world_to_local(), gaussians.opacities()
        inputs = [gaussians.means, w2l, opac, gaussians.diffuse, gaussians.normals, gaussians.roughness, gaussians.f0]
        gdata = self._gaussian_data(inputs)

        tgt = {}
        for name, ch in RAY_GRAD_FIELDS.items():
            if name in targets and float(weights.get(name, 0.0)) != 0.0:
                value = targets[name]
                if not isinstance(value, torch.Tensor):
                    raise TypeError(f"targets[{name!r}] must be a tensor, got {type(value).__name__}")
                c = LAYERS[name]
                if value.numel() != n_rays * c:
                    raise ValueError(f"targets[{name!r}] has shape {tuple(value.shape)}, expected [{n_rays}, {c}]")
                tgt[name] = to_warp(value.reshape(n_rays, c) if c > 1 else value.reshape(n_rays), ch, self.device)
            else:
                tgt[name] = wp.zeros(1, dtype=ch, device=self.device)  # never read (weight 0)
        loss_prm = L1Loss()
        loss_prm.weights = wp.array([float(weights.get(k, 0.0)) for k in LAYERS], dtype=float, device=self.device)
        loss_prm.inv_rays = 1.0 / max(n_rays, 1)
        up = {k: wp.zeros(n_rays, dtype=dt, device=self.device) for k, dt in RAY_GRAD_FIELDS.items()}
        ray_loss = wp.zeros(n_rays, dtype=float, device=self.device)

        def launch(prm, rep, outs, a, b, grads):
            tviews = {k: (v[a:b] if v.shape[0] == n_rays else v) for k, v in tgt.items()}
            wp.launch(kernels.fused_kernel, dim=b - a, device=self.device,
                      inputs=[self._o[a:b], self._d[a:b], gdata, prm, rep.view(a, b), outputs_view(outs, a, b),
                              _ray_grads(tviews),
                              loss_prm, ray_grads_view(up, a, b), ray_loss[a:b], grads_struct(grads)])

        self._o, self._d = to_warp(origins, wp.vec3, self.device), to_warp(dirs, wp.vec3, self.device)
        outs, rep, grads = self._run(n_rays, len(gaussians), gdata, launch, with_grads=True)
        out = self._outputs_to_torch(outs, gaussians)
        out = TraceOutput(**{k: (v.detach() if isinstance(v, torch.Tensor) else v) for k, v in vars(out).items()})
        loss = to_torch(ray_loss, torch.device("cpu")).double().sum().to(gaussians.device)
        gouts = self._grads_to_torch(grads, inputs)
        pairs = [(t, gt) for t, gt in zip(inputs, gouts) if t.requires_grad]
        if pairs:
            torch.autograd.backward([p[0] for p in pairs], [p[1] for p in pairs])
        return out, loss

    # ------------------------------------------------------------------ internals
    def _check_rays(self, origins, dirs):
        for name, t in (("origins", origins), ("dirs", dirs)):
            if not isinstance(t, torch.Tensor):
                raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
            if t.ndim != 2 or t.shape[1] != 3:
                raise ValueError(f"{name} must have shape [R, 3], got {tuple(t.shape)}")
        if origins.shape != dirs.shape:
            raise ValueError(f"origins {tuple(origins.shape)} and dirs {tuple(dirs.shape)} differ in shape")
        if dirs.shape[0] and bool((dirs.detach().norm(dim=1) == 0).any()):
            raise ValueError("dirs contains zero-length directions")
        return origins.detach(), dirs.detach()

    def _params(self, gid: int) -> TraceParams:
        c = self.config
        prm = TraceParams()
        prm.bvh = wp.uint64(gid)
        prm.kernel_p = c.kernel_p
        prm.alpha_min = c.alpha_min
        prm.alpha_max = c.alpha_max
        prm.trans_threshold = c.transmittance_threshold
        prm.t_min = c.t_min
        prm.k = c.k
        prm.capacity = self.capacity
        prm.obb_test = 0 if c.world_aabb_only else 1
        prm.repeated_kbuffer = 1 if c.repeated_kbuffer else 0
        return prm

    def _gaussian_data(self, inputs: list[torch.Tensor]) -> GaussianData:
        means, w2l, opac, diffuse, normals, rough, f0 = inputs
        g = GaussianData()
        g.means = to_warp(means, wp.vec3, self.device)
        g.w2l = to_warp(w2l.reshape(-1, 3, 3), wp.mat33, self.device)
        g.opacity = to_warp(opac, float, self.device)
        g.cutoff = self._cutoff
        g.diffuse = to_warp(diffuse, wp.vec3, self.device)
        g.normal = to_warp(normals, wp.vec3, self.device)
        g.roughness = to_warp(rough, float, self.device)
        g.f0 = to_warp(f0, wp.vec3, self.device)
        with torch.no_grad():
            cutoff = to_torch(self._cutoff, means.device).reshape(-1, 1).to(torch.float32)
            zeros = torch.zeros_like(cutoff)
            packed = torch.cat([means.float(), w2l.float().reshape(-1, 9), opac.float().reshape(-1, 1), cutoff,
                                zeros, zeros], 1)
        g.packed = to_warp(packed.reshape(-1, 16), vec16, self.device)
        return g

    def _load(self) -> None:
        if not self._loaded:  # compile once before threads launch concurrently
            wp.load_module(kernels, device=self.device)
            self._loaded = True

    def _run(self, n_rays: int, n_gaussians: int, gdata: GaussianData, launch, with_grads: bool):
        """Launch over ray chunks; on replay overflow grow the capacity and re-run everything."""
        self._load()
        outs = allocate_outputs(n_rays, self.device)
        self.last_overflow_rays = 0
        chunks = ray_chunks(n_rays, self._threads)
        grads = None
        while True:
            rep = ReplayArrays.allocate(n_rays, self.capacity, self.device)
            grads = [allocate_grads(n_gaussians, self.device) for _ in chunks] if with_grads else None
            if n_rays == 0 or n_gaussians == 0 or self.bvh.bvh is None:
                outs["transmittance"].fill_(1.0)
                break
            prm = self._params(self.bvh.id)
            jobs = [(lambda a=a, b=b, i=i: launch(prm, rep, outs, a, b, grads[i] if grads else None))
                    for i, (a, b) in enumerate(chunks)]
            run_chunks(self._pool, jobs)
            needed = to_torch(outs["needed"], torch.device("cpu"))
            n_over = int((needed > 0).sum())
            if n_over == 0:
                break
            self.last_overflow_rays += n_over
            most = int(needed.max())
            if most > self.config.max_replay_capacity:
                raise RuntimeError(
                    f"replay buffer overflow: a ray needs {most} slots > max_replay_capacity "
                    f"{self.config.max_replay_capacity}; raise TracerConfig.max_replay_capacity")
            self.capacity = min(self.config.max_replay_capacity, max(2 * self.capacity, most))
        if grads is not None:
            grads = _sum_grads(grads)
        return outs, rep, grads

    def _forward(self, origins, dirs, inputs):
        n_rays = origins.shape[0]
        gdata = self._gaussian_data(inputs)
        o, d = to_warp(origins, wp.vec3, self.device), to_warp(dirs, wp.vec3, self.device)

        def launch(prm, rep, outs, a, b, _grads):
            wp.launch(kernels.forward_kernel, dim=b - a, device=self.device,
                      inputs=[o[a:b], d[a:b], gdata, prm, rep.view(a, b), outputs_view(outs, a, b)])

        outs, rep, _ = self._run(n_rays, inputs[0].shape[0], gdata, launch, with_grads=False)
        return {"o": o, "d": d, "gdata": gdata, "outs": outs, "rep": rep, "capacity": self.capacity}

    def _backward(self, state, upstream: dict[str, torch.Tensor], inputs) -> list[torch.Tensor]:
        n_rays = state["o"].shape[0]
        n = inputs[0].shape[0]
        chunks = ray_chunks(n_rays, self._threads)
        grads = [allocate_grads(n, self.device) for _ in chunks]
        if n_rays and n and self.bvh.bvh is not None:
            up = {k: to_warp(upstream[k], dt, self.device) for k, dt in RAY_GRAD_FIELDS.items()}
            saved_cap, self.capacity = self.capacity, state["capacity"]
            prm = self._params(self.bvh.id)
            self.capacity = saved_cap
            outs, rep, gdata = state["outs"], state["rep"], state["gdata"]

            def job(i, a, b):
                wp.launch(kernels.backward_kernel, dim=b - a, device=self.device,
                          inputs=[state["o"][a:b], state["d"][a:b], gdata, prm, rep.view(a, b),
                                  outputs_view(outs, a, b), ray_grads_view(up, a, b), grads_struct(grads[i])])

            run_chunks(self._pool, [(lambda i=i, a=a, b=b: job(i, a, b)) for i, (a, b) in enumerate(chunks)])
        return self._grads_to_torch(_sum_grads(grads), inputs)

    def _grads_to_torch(self, grads: dict[str, wp.array], inputs) -> list[torch.Tensor]:
        out = []
        for key, like in zip(_GRAD_TO_INPUT, inputs):
            g = to_torch(grads[key], like.device).reshape(like.shape).to(like.dtype)
            out.append(g)
        return out

    def _outputs_to_torch(self, outs: dict[str, wp.array], gaussians: Gaussians) -> TraceOutput:
        dev, dt = gaussians.device, gaussians.dtype
        t = {k: to_torch(v, dev) for k, v in outs.items()}
        f = {k: (t[k].to(dt) if t[k].dtype == torch.float32 else t[k]) for k in t}
        return TraceOutput(diffuse=f["diffuse"], depth=f["depth"], normal=f["normal"], roughness=f["roughness"],
                           f0=f["f0"], transmittance=f["transmittance"], hit_count=f["hit_count"],
                           blended_count=f["blended"], candidates=f["candidates"],
                           obb_candidates=f["obb_candidates"], overflow_rays=self.last_overflow_rays,
                           replay_capacity=self.capacity)


def _ray_grads(views: dict[str, wp.array]) -> RayGrads:
    s = RayGrads()
    for k in RAY_GRAD_FIELDS:
        setattr(s, k, views[k])
    return s


def _sum_grads(per_thread: list[dict[str, wp.array]]) -> dict[str, wp.array]:
    """Sum per-thread gradient buffers into the first (CPU atomics are not safe across
    concurrent launches). Only CPU launches are split over threads."""
    total = per_thread[0]
    for other in per_thread[1:]:
        assert total["means"].device.is_cpu
        for k in total:
            wp.to_torch(total[k], requires_grad=False).add_(wp.to_torch(other[k], requires_grad=False))
    return total


class _TraceFunction(torch.autograd.Function):
    """Inputs: activated means [N,3], w2l [N,3,3], opacity [N], diffuse [N,3], normals [N,3],
    roughness [N], f0 [N,3]; torch autograd chains them to the raw parameters."""

    @staticmethod
    def forward(ctx, tracer: Tracer, origins, dirs, means, w2l, opac, diffuse, normals, rough, f0):
        inputs = [means, w2l, opac, diffuse, normals, rough, f0]
        state = tracer._forward(origins, dirs, inputs)
        out = tracer._outputs_to_torch(state["outs"], _Like(means))
        ctx.tracer, ctx.state = tracer, state
        ctx.save_for_backward(means, w2l, opac, diffuse, normals, rough, f0)
        ints = (out.hit_count, out.blended_count, out.candidates, out.obb_candidates)
        ctx.mark_non_differentiable(*ints)
        return (out.diffuse, out.depth, out.normal, out.roughness, out.f0, out.transmittance, *ints)

    @staticmethod
    def backward(ctx, g_diffuse, g_depth, g_normal, g_rough, g_f0, g_trans, *_):
        inputs = list(ctx.saved_tensors)
        up = {"diffuse": g_diffuse, "depth": g_depth, "normal": g_normal, "roughness": g_rough, "f0": g_f0,
              "transmittance": g_trans}
        grads = ctx.tracer._backward(ctx.state, up, inputs)
        return (None, None, None, *grads)


class _Like:
    """Minimal stand-in exposing device/dtype for _outputs_to_torch."""

    def __init__(self, t: torch.Tensor):
        self.device, self.dtype = t.device, t.dtype
