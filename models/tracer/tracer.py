"""Tracer: holds the BVH and launches the Warp kernels; autograd and fused entry points.

    tracer = Tracer(TracerConfig(), device="cpu")
    out = tracer.trace(origins, dirs, gaussians)            # differentiable TraceOutput
    out, loss = tracer.trace_fused(origins, dirs, gaussians, targets, weights)  # fills .grad

Rays may start anywhere (camera or reflection vertices); dirs need not be unit length
(depth is then the ray parameter t, not a distance).
"""

from __future__ import annotations

import contextlib
import logging
import math
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

import models.tracer.kernels as kernels
from models.gaussians.scene import PARAM_SHAPES, Gaussians
from models.profiling import NO_TIMER
from models.tracer.autograd import TraceFunction
from models.tracer.bvh import GaussianBvh
from models.tracer.chain import clear_touched_kernel, gather_args, gather_kernel, gather_touched_kernel
from models.tracer.checks import ZERO_DIRS_MESSAGE, DeferredChecks
from models.tracer.config import TRAVERSALS, TracerConfig
from models.tracer.interop import is_alias, to_torch, to_warp, torch_device_for
from models.tracer.launch import (
    RAY_GRAD_FIELDS,
    GradRows,
    LaunchViews,
    ReplayArrays,
    allocate_outputs,
    empty_ordered,
    outputs_view,
    ray_chunks,
    ray_grads_struct,
    ray_grads_view,
    run_chunks,
    thread_stripes,
)
from models.tracer.ordered_bvh import OrderedBvh, OrderedBvhBuilder
from models.tracer.output import LAYERS, TraceOutput
from models.tracer.structs import GaussianData, L1Loss, TraceParams
from models.tracer.wide_bvh import WideTree, empty_wide

log = logging.getLogger(__name__)
# rays traced since the last update() from which auto octant trees pay for their refits (Tracer._octants_for)
OCTANT_RAYS = 65536
# a CPU backward whose rows flagged fewer than this share of the Gaussians is gathered over those alone (the dense
# gather reads and clears every Gaussian's row whether a ray reached it or not; the sparse one visits in the order
# the rays first reached them, so randomly). Chosen, not tuned: (d) 1M Gaussians at ~4 % reached gains, (a)-(c)
# (most reached) keep the dense gather (README, twenty-fifth session)
SPARSE_GATHER_SHARE = 0.25


def _accumulate_grads(pairs: list[tuple[torch.Tensor, torch.Tensor]]) -> None:
    """``tensor.grad += gradient`` for each pair, as ``torch.autograd.backward`` would: a leaf without hooks directly
    (the gradient, freshly made, becomes ``.grad`` when there is none: autograd would copy it, ~84 MB per call at 1M
    Gaussians, as the caller still holds it), anything else through autograd."""
    rest = []
    for t, g in pairs:
        if t.is_leaf and not t._backward_hooks and not getattr(t, "_post_accumulate_grad_hooks", None):
            if t.grad is None:
                t.grad = g
            else:
                t.grad.add_(g)
        else:
            rest.append((t, g))
    if rest:
        torch.autograd.backward([t for t, _ in rest], [g for _, g in rest])


def _quantile(x: torch.Tensor, q: float) -> torch.Tensor:
    """``x.quantile(q, dim=0)`` (linear interpolation, the same bits) from the few order statistics it needs: a
    top-k of the tail instead of sorting every column (0.78 -> 0.07 ms on 4k rows, twice per update: every
    training step)."""
    n = x.shape[0]
    rank = torch.tensor(q, dtype=x.dtype) * (n - 1)
    below, above = int(rank.floor()), int(rank.ceil())
    if below < n - 1 - above:  # the low tail: ascending
        v = x.topk(above + 1, dim=0, largest=False, sorted=True).values
        low, high = v[below], v[above]
    else:  # the high tail: descending, order statistic i at n - 1 - i
        v = x.topk(n - below, dim=0, largest=True, sorted=True).values
        low, high = v[n - 1 - below], v[n - 1 - above]
    return torch.lerp(low, high, rank - below)


class Tracer:
    """Gaussian ray tracer on one Warp device ("cpu" or "cuda[:i]").

    Holds the BVH of the last update() and a CPU thread pool; not safe to call from several
    Python threads at once. Each trace() keeps its replay buffer alive for its backward.
    """

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
        # (the ordered traversal keeps the wp.Bvh too: rays whose node heap overflows fall back to it)
        self.bvh = GaussianBvh(self.device, constructor=self.config.bvh_constructor)
        self.ordered = OrderedBvhBuilder(self.device, self.config.ordered_leaf_size) \
            if self.config.traversal == "ordered" else None
        self._no_ordered = empty_ordered(self.device)
        self._no_octants = wp.zeros(1, dtype=wp.uint64, device=self.device)
        self._rays_since_update = 0  # rays traced since the last update() (the octant trees' amortisation)
        self._octants = False        # this launch queries the octant trees (_octants_for)
        self._wide = False           # this launch queries the wide tree (_wide_for)
        self._wide_tree = WideTree(self.device)
        self._no_wide = empty_wide(self.device)
        self.capacity = self.config.replay_capacity
        self.scene_box = self.core_box = (wp.vec3(0.0), wp.vec3(0.0))
        self.scene_box_values = (0.0,) * 12  # the scene and core boxes as floats (part of the launch parameters' key)
        self.scene_diagonal = 1.0
        self.box_diagonal = 1.0
        self._built_box_diagonal = 0.0  # box_diagonal at the last rebuild (BVH.moved_far)
        self._prm, self._prm_key = None, None  # the last launch parameters (_params)
        threads = self.config.num_threads if self.is_cpu else 1
        self._pool = ThreadPoolExecutor(threads, thread_name_prefix="tracer") if threads > 1 else None
        self._threads = threads
        self._scene_key = None
        self._aliases: dict[tuple, wp.array] = {}  # Warp views of the parameters of the last update()
        self._grad_rows: GradRows | None = None  # the backward's per-thread accumulators, kept between passes
        self._loaded = False
        self.last_overflow_rays = 0
        self._checks: DeferredChecks | None = None  # inside deferred_checks(): the traces' flags, not read back
        self._keep_replay = True   # the next _forward's replay buffer is kept for a backward (trace sets it)
        self._spare_replay: ReplayArrays | None = None  # CPU: the buffer of the last trace that kept none (_replay)
        self.timer = NO_TIMER  # a models.profiling.SectionTimer while a benchmark profiles

    @property
    def torch_device(self) -> torch.device:
        """Where tensors alias this tracer's arrays without copies (the CPU for a CUDA device that torch cannot
        reach: then every call copies)."""
        return torch_device_for(self.device) or torch.device("cpu")

    def close(self) -> None:
        """Stop the CPU worker threads (also done when the tracer is garbage collected)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False)
            self._pool = None
            self._threads = 1

    def __del__(self):
        pool = getattr(self, "_pool", None)
        if pool is not None:
            pool.shutdown(wait=False)

    # ------------------------------------------------------------------ BVH
    def update(self, gaussians: Gaussians, rebuild: bool = False) -> None:
        """Recompute the ellipsoid bounds; refit the BVH, or rebuild it when the number of
        Gaussians changed, `rebuild` is set or config.always_rebuild."""
        if not isinstance(gaussians, Gaussians):
            raise TypeError(f"gaussians must be a Gaussians, got {type(gaussians).__name__}")
        key = self._key(gaussians)
        if self._scene_key is None or any(a[0] is not b[0] for a, b in zip(self._scene_key, key)):
            self._aliases.clear()  # other tensors: drop the views of the old ones (and their memory)
            # another scene of the same size: a new tree
            rebuild = rebuild or self.bvh.moved_far(gaussians.means, self._built_box_diagonal)
        with self.timer.section("tracer_host"), self.timer.section("bvh_update"):
            self.bvh.update(gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits,
                            self.config.kernel_p, self.config.alpha_min, rebuild=rebuild or self.config.always_rebuild,
                            run=lambda jobs: run_chunks(self._pool, jobs), n_chunks=self._threads,
                            convert=self._param_array)
            if self.ordered is not None and self.bvh.count > 0:
                if self.bvh.last_was_rebuild:
                    self.ordered.rebuild(self.bvh.lowers, self.bvh.uppers, self.bvh.packed)
                else:
                    self.ordered.refit(self.bvh.packed)
        self._wide_tree.current = False  # refitted (or collapsed) when a trace needs it (_wide_for)
        self._rays_since_update = 0
        with self.timer.section("tracer_host"):
            self._scene_key = key
            self._scene_box()
            if self.bvh.last_was_rebuild:
                self._built_box_diagonal = self.box_diagonal

    def _scene_box(self) -> None:
        """The union of the Gaussians' world bounds (the interval traversal clips rays to it). Reduced where the
        bounds live; one read-back of 8 numbers."""
        if self.bvh.count > 0:
            dev = torch_device_for(self.device) or torch.device("cpu")
            lowers, uppers = to_torch(self.bvh.lowers, dev), to_torch(self.bvh.uppers, dev)
            stride = max(1, self.bvh.count // 4096)  # a strided sample: cheap at every training step
            diagonals = (uppers[::stride] - lowers[::stride]).norm(dim=1)
            # over the Gaussians that can be hit: one below alpha_min has an empty box (a point), and a median of
            # zero made the first window empty and every later one too (x4 of nothing): the ray never advanced
            box_diagonal = torch.where(diagonals > 0, diagonals, torch.nan).nanmedian()
            lo, hi = lowers.min(0).values, uppers.max(0).values  # (faster than amin / amax over [N, 3] on a CPU)
            scene = (hi - lo).norm()
            box_diagonal = torch.where(box_diagonal.isnan(), scene.clamp_min(1e-6), box_diagonal)
            # the core box (where a ray starts "inside": interval traversal's first window), from the same sample:
            # the union box above grows with any one large Gaussian, e.g. to hold a camera looking at a cloud
            core_lo = torch.maximum(_quantile(lowers[::stride], 0.005) - box_diagonal, lo)
            core_hi = torch.minimum(_quantile(uppers[::stride], 0.995) + box_diagonal, hi)
            values = torch.cat([lo, hi, box_diagonal.reshape(1), scene.reshape(1), core_lo, core_hi]).tolist()
            if not all(math.isfinite(v) for v in values):  # (NaN propagates through min / max)
                raise FloatingPointError("non-finite Gaussian bounds (NaN / Inf in means, quats or log_scales): "
                                         "the BVH traversal would not end")
            self.scene_box = (wp.vec3(*values[:3]), wp.vec3(*values[3:6]))
            self.core_box = (wp.vec3(*values[8:11]), wp.vec3(*values[11:14]))
            self.scene_box_values = tuple(values[:6]) + tuple(values[8:14])
            self.box_diagonal, self.scene_diagonal = values[6], values[7]
        else:
            self.scene_box = self.core_box = (wp.vec3(0.0), wp.vec3(0.0))
            self.scene_box_values = (0.0,) * 12
            self.scene_diagonal = 1.0

    @staticmethod
    def _key(g: Gaussians):
        # strong references (not ids, which Python reuses) + in-place modification counters
        return tuple((t, t._version) for t in g.params().values())

    def _ensure_updated(self, gaussians: Gaussians) -> None:
        """update() unless these exact tensors, unmodified, were the last ones updated."""
        if not isinstance(gaussians, Gaussians):
            raise TypeError(f"gaussians must be a Gaussians, got {type(gaussians).__name__}")
        key = self._key(gaussians)
        old = self._scene_key
        if old is None or len(old) != len(key) or any(a[0] is not b[0] or a[1] != b[1] for a, b in zip(old, key)):
            self.update(gaussians)

    @contextlib.contextmanager
    def deferred_checks(self):
        """Traces inside do not read back replay overflow or zero-length directions (a host-device sync each, on
        a GPU): they collect device flags in the yielded ``DeferredChecks`` (see models/tracer/checks.py).
        ``trace_fused`` still checks at once: it accumulates gradients, which a redo would add twice."""
        if self._checks is not None:
            raise RuntimeError("deferred_checks() is already active on this tracer")
        checks = DeferredChecks(self.torch_device, lambda most: self._grow(most, None))
        self._checks = checks
        try:
            yield checks
        finally:
            self._checks = None

    # ------------------------------------------------------------------ entry points
    def trace(self, origins: torch.Tensor, dirs: torch.Tensor, gaussians: Gaussians) -> TraceOutput:
        """Trace R rays. origins, dirs: [R, 3]. Differentiable wrt the Gaussian parameters
        (diffuse, depth, normal, roughness, f0 and transmittance outputs)."""
        with self.timer.section("tracer_host"):
            origins, dirs = self._check_rays(origins, dirs, deferred=self._checks is not None)
            self._ensure_updated(gaussians)
            params = gaussians.params().values()
            # no backward can follow (no_grad, or nothing requires grad): the replay buffer may be reused (_replay)
            self._keep_replay = torch.is_grad_enabled() and any(p.requires_grad for p in params)
            res = TraceFunction.apply(self, origins, dirs, *params)
        diffuse, depth, normal, rough, f0, trans, front, hits, blended, cand, obb = res
        return TraceOutput(diffuse=diffuse, depth=depth, normal=normal, roughness=rough, f0=f0,
                           transmittance=trans, front_depth=front, hit_count=hits, blended_count=blended,
                           candidates=cand, obb_candidates=obb, overflow_rays=self.last_overflow_rays,
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
        inputs = list(gaussians.params().values())
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

        o, d = to_warp(origins, wp.vec3, self.device), to_warp(dirs, wp.vec3, self.device)

        tv, uv = ray_grads_struct(tgt), ray_grads_view(up, 0, n_rays)
        views = LaunchViews(n_rays, lambda: self._ordered_struct(0, n_rays))

        def launch(prm, rep, outs, a, b, grads, wb):
            rv, ov, ob = views.of(rep, outs)
            wp.launch(kernels.fused_kernel, dim=b - a, device=self.device,
                      inputs=[o, d, gdata, prm, rv, ov, tv, loss_prm, uv, ray_loss, grads, ob, wb, a])

        outs, rep, grads = self._run(n_rays, len(gaussians), gdata, launch, with_grads=True)
        out = self._outputs_to_torch(outs, gaussians)
        out = TraceOutput(**{k: (v.detach() if isinstance(v, torch.Tensor) else v) for k, v in vars(out).items()})
        loss = to_torch(ray_loss, torch.device("cpu")).double().sum().to(gaussians.device)
        pairs = [(t, gt) for t, gt in zip(inputs, self._grads_to_torch(inputs)) if t.requires_grad]
        _accumulate_grads(pairs)
        return out, loss

    # ------------------------------------------------------------------ internals
    def _check_rays(self, origins, dirs, deferred: bool = False):
        for name, t in (("origins", origins), ("dirs", dirs)):
            if not isinstance(t, torch.Tensor):
                raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
            if t.ndim != 2 or t.shape[1] != 3:
                raise ValueError(f"{name} must have shape [R, 3], got {tuple(t.shape)}")
        if origins.shape != dirs.shape:
            raise ValueError(f"origins {tuple(origins.shape)} and dirs {tuple(dirs.shape)} differ in shape")
        if deferred:  # no read-back now: counted on the device, settled by the caller
            if dirs.shape[0]:
                self._checks.zero_dirs.append((dirs.detach().norm(dim=1) == 0).sum())
        elif dirs.shape[0] and bool((dirs.detach().norm(dim=1) == 0).any()):
            raise ValueError(ZERO_DIRS_MESSAGE)
        return origins.detach(), dirs.detach()

    def _params(self, gid: int) -> TraceParams:
        """The launch parameters. The struct is kept while none of its values changes (setting a field costs ~7 us
        of Python, and every trace launches twice); it holds the bound arrays, so their ids are not reused."""
        c = self.config
        key = (gid, self.capacity, self.box_diagonal, self.scene_box_values, id(self.bvh.lowers), id(self.bvh.uppers),
               c.kernel_p, c.alpha_min, c.alpha_max, c.transmittance_threshold, c.t_min, c.k, c.world_aabb_only,
               c.traversal, c.window, c.inside_whole_window, self._octants, id(self.bvh.octant_ids), self._wide)
        if key == self._prm_key:
            return self._prm
        prm = TraceParams()
        prm.bvh = wp.uint64(gid)
        prm.octants = 1 if self._octants else 0
        prm.wide = 1 if self._wide else 0
        prm.octant_bvh = self.bvh.octant_ids if self._octants else self._no_octants
        prm.kernel_p = c.kernel_p
        prm.alpha_min = c.alpha_min
        prm.alpha_max = c.alpha_max
        prm.trans_threshold = c.transmittance_threshold
        prm.t_min = c.t_min
        prm.k = c.k
        prm.capacity = self.capacity
        prm.obb_test = 0 if c.world_aabb_only else 1
        prm.traversal = TRAVERSALS.index(c.traversal)
        prm.window = c.window * self.box_diagonal
        prm.inside_whole = 1 if c.inside_whole_window else 0
        prm.scene_lo, prm.scene_hi = self.scene_box
        prm.core_lo, prm.core_hi = self.core_box
        prm.lowers, prm.uppers = self.bvh.lowers, self.bvh.uppers
        self._prm, self._prm_key = prm, key
        return prm

    def _wide_for(self) -> bool:
        """Whether this launch queries the wide tree (wide_bvh.py), refreshing it if so: the interval traversal on a
        CPU with ``wide_bvh`` on, unless the tree cannot be collapsed (then Warp's, with a warning)."""
        if not (self.is_cpu and self.config.wide_bvh and self.config.traversal == "interval" and self.bvh.count > 0):
            return False
        with self.timer.section("tracer_host"), self.timer.section("bvh_update"):
            return self._wide_tree.refresh(self.bvh.bvh, self.bvh.lowers, self.bvh.uppers, self.bvh.count,
                                           self._threads, run=lambda jobs: run_chunks(self._pool, jobs))

    def _wide_struct(self, i: int):
        """Launch thread i's wide tree (its own stack), or the placeholder."""
        return self._wide_tree.structs[i] if self._wide else self._no_wide

    def _octants_for(self, n_rays: int) -> bool:
        """Whether this launch of ``n_rays`` queries the octant trees (bvh.py), refreshing them if so. auto: once
        the rays traced since the last update() reach OCTANT_RAYS, about what seven refits cost in rays traced
        (50k Gaussians, 2 CPU cores: ~17 ms against ~4.6 us per ray), or when they are current anyway."""
        mode = self.config.octant_bvh
        self._rays_since_update += n_rays
        if self.config.traversal != "interval" or mode == "never" or self.bvh.count <= 0 or self._wide:
            return False
        if mode == "auto" and not self.bvh.octants_current and self._rays_since_update < OCTANT_RAYS:
            return False
        with self.timer.section("tracer_host"), self.timer.section("bvh_update"):
            self.bvh.refresh_octants(run=lambda jobs: run_chunks(self._pool, jobs))
        return True

    def _ordered_struct(self, a: int, b: int) -> OrderedBvh:
        """The ordered BVH with rows a..b of the per-ray heap scratch (placeholder when unused)."""
        if self.ordered is None or self.ordered.struct is None:
            return self._no_ordered
        src, out = self.ordered.struct, OrderedBvh()
        for name in ("node_lo", "node_hi", "order", "lowers", "uppers", "sorted_lowers", "sorted_uppers",
                     "sorted_packed", "n_leaves", "leaf_size", "count"):
            setattr(out, name, getattr(src, name))
        out.heap_keys, out.heap_nodes = self._heap[0][a:b], self._heap[1][a:b]
        return out

    def _param_array(self, t: torch.Tensor, dtype) -> wp.array:
        """``to_warp(t, dtype)``; an alias of a parameter of the last update() is made once and reused (it stays
        valid while the optimiser updates the tensor in place), so a step converts no parameter again."""
        key = (t.data_ptr(), tuple(t.shape), t.dtype, t.device, dtype)
        array = self._aliases.get(key)
        if array is None:
            array = to_warp(t, dtype, self.device)
            if is_alias(array, t):
                self._aliases[key] = array
        return array

    def _gaussian_data(self, inputs: list[torch.Tensor]) -> GaussianData:
        """inputs: the raw parameters in PARAM_SHAPES order; geometry comes from update()."""
        diffuse, normals, rough, f0 = inputs[4:]
        g = GaussianData()
        g.packed = self.bvh.packed  # geometry (mean, M, opacity, cutoff) from the last update()
        g.diffuse = self._param_array(diffuse, wp.vec3)
        g.normal = self._param_array(normals, wp.vec3)
        g.roughness = self._param_array(rough, float)
        g.f0 = self._param_array(f0, wp.vec3)
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
        stripes = thread_stripes(n_rays, self._threads)
        grads = None
        if self.ordered is not None:
            h = self.config.ordered_heap_size
            self._heap = (wp.empty((n_rays, h), dtype=float, device=self.device),
                          wp.empty((n_rays, h), dtype=wp.int32, device=self.device))
        self._wide = self._wide_for()
        self._octants = self._octants_for(n_rays)
        while True:
            rep = self._replay(n_rays, reusable=with_grads or not self._keep_replay)
            grads = self._rows(n_gaussians).take() if with_grads else None
            if n_rays == 0 or n_gaussians == 0 or self.bvh.count == 0:
                outs["transmittance"].fill_(1.0)
                break
            prm = self._params(self.bvh.id)
            jobs = [(lambda i=i, chunks=chunks: [launch(prm, rep, outs, a, b, grads[i] if grads else None,
                                                        self._wide_struct(i)) for a, b in chunks])
                    for i, chunks in enumerate(stripes)]
            with self.timer.section("tracer_forward"):
                run_chunks(self._pool, jobs)
            needed = to_torch(outs["needed"], torch_device_for(self.device) or torch.device("cpu"))
            if self._checks is not None and not with_grads:  # trace(): settled by the caller after its read-back
                self._checks.needed.append(needed.max())
                break
            n_over, most = (int(v) for v in torch.stack([(needed > 0).sum(), needed.max().long()]).tolist())
            if n_over == 0:
                break
            self.last_overflow_rays += n_over
            self._grow(most, n_over)
        return outs, rep, grads

    def _replay(self, n_rays: int, reusable: bool) -> ReplayArrays:
        """The launch's replay buffer. On a CPU, a trace whose buffer nobody keeps (trace_fused, which replays it
        in the same launch; trace() when no backward can follow: renders, evaluation) takes the spare one of the
        last such trace when it has the same shape: a fresh [rays, capacity] buffer is touched page by page
        (16 MB at 16k rays x 64 slots; ~7 % of benchmark (b)'s forward on 2 threads). A CUDA device's
        allocator pools anyway: always fresh there."""
        if not (reusable and self.is_cpu):
            return ReplayArrays.allocate(n_rays, self.capacity, self.device)
        if self._spare_replay is None or self._spare_replay.ids.shape != (n_rays, self.capacity):
            self._spare_replay = None  # the old one goes before the new one is made
            self._spare_replay = ReplayArrays.allocate(n_rays, self.capacity, self.device)
        return self._spare_replay

    def _grow(self, most: int, n_over: int | None) -> None:
        """A ray needed ``most`` replay slots: at least double the capacity (within max_replay_capacity)."""
        ceiling = self.config.max_replay_capacity
        if ceiling is not None and most > ceiling:
            raise RuntimeError(
                f"replay buffer overflow: a ray needs {most} slots > max_replay_capacity "
                f"{ceiling}; raise TracerConfig.max_replay_capacity (or set it to null: no ceiling)")
        grown = max(2 * self.capacity, most) if ceiling is None else min(ceiling, max(2 * self.capacity, most))
        log.info("replay buffer overflow on %s rays (needed %d > %d slots): re-running with %d",
                 "some" if n_over is None else n_over, most, self.capacity, grown)
        self.capacity = grown

    def _forward(self, origins, dirs, inputs):
        n_rays = origins.shape[0]
        gdata = self._gaussian_data(inputs)
        o, d = to_warp(origins, wp.vec3, self.device), to_warp(dirs, wp.vec3, self.device)

        views = LaunchViews(n_rays, lambda: self._ordered_struct(0, n_rays))

        def launch(prm, rep, outs, a, b, _grads, wb):
            rv, ov, ob = views.of(rep, outs)
            wp.launch(kernels.forward_kernel, dim=b - a, device=self.device,
                      inputs=[o, d, gdata, prm, rv, ov, ob, wb, a])

        outs, rep, _ = self._run(n_rays, inputs[0].shape[0], gdata, launch, with_grads=False)
        return {"o": o, "d": d, "gdata": gdata, "outs": outs, "rep": rep, "capacity": self.capacity}

    def _backward(self, state, upstream: dict[str, torch.Tensor], inputs) -> list[torch.Tensor]:
        n_rays = state["o"].shape[0]
        n = inputs[0].shape[0]
        stripes = thread_stripes(n_rays, self._threads)
        rows_ = self._rows(n)
        # the rows list the Gaussians they reach only when the gather may use the list (no more than the hits)
        track = rows_.track and int(to_torch(state["outs"]["blended"], torch.device("cpu")).sum()) < (
            SPARSE_GATHER_SHARE * n)
        grads = rows_.take(track=track)
        if n_rays and n and self.bvh.count > 0:
            up = {k: to_warp(upstream[k], dt, self.device) for k, dt in RAY_GRAD_FIELDS.items()}
            saved_cap, self.capacity = self.capacity, state["capacity"]
            prm = self._params(self.bvh.id)
            self.capacity = saved_cap
            outs, rep, gdata = state["outs"], state["rep"], state["gdata"]

            rv, ov, uv = rep.view(0, n_rays), outputs_view(outs, 0, n_rays), ray_grads_view(up, 0, n_rays)

            def job(i, a, b):
                wp.launch(kernels.backward_kernel, dim=b - a, device=self.device,
                          inputs=[state["o"], state["d"], gdata, prm, rv, ov, uv, grads[i], a])

            with self.timer.section("tracer_backward"):
                run_chunks(self._pool, [(lambda i=i, chunks=chunks: [job(i, a, b) for a, b in chunks])
                                        for i, chunks in enumerate(stripes)])
        return self._grads_to_torch(inputs)

    def _rows(self, n: int) -> GradRows:
        rows_ = self._grad_rows
        if rows_ is None or rows_.n != n:  # (threads and device are the tracer's own)
            rows_ = self._grad_rows = GradRows(n, self._threads, self.device)
        return rows_

    def _grads_to_torch(self, inputs) -> list[torch.Tensor]:
        """The backward's per-thread rows (wrt the activated values) -> gradients wrt the raw parameters
        (PARAM_SHAPES order), in one gather launch per CPU thread (no sums in torch); the rows are left zero for
        the next pass. On a CPU, when the rows flagged few of the Gaussians (under ``SPARSE_GATHER_SHARE`` of
        them), each thread's launch visits the Gaussians its row listed and the others' gradients are zero
        without a visit; otherwise each visits its share of every Gaussian."""
        means, quats, log_scales, logits = inputs[:4]
        n = means.shape[0]
        tdev = torch_device_for(self.device)
        dev = tdev or torch.device("cpu")
        rows_ = self._rows(n) if n else None
        ids = [rows_.row_ids(k) for k in range(rows_.threads)] if n and rows_.tracking else None
        sparse = ids is not None and sum(len(a) for a in ids) < SPARSE_GATHER_SHARE * n
        outs = [torch.empty((n, *PARAM_SHAPES[k]), dtype=torch.float32, device=dev) for k in PARAM_SHAPES]
        # each CPU thread's share of the Gaussians (a CPU launch runs on one core)
        parts = ray_chunks(n, self._threads) if n >= 4096 * self._threads else [(0, n)]
        if sparse:  # the gather leaves the Gaussians no ray reached alone: zero first, a share per CPU thread
            with self.timer.section("tracer_backward"):
                run_chunks(self._pool, [(lambda a=a, b=b: [t[a:b].zero_() for t in outs]) for a, b in parts])
        if n:
            dtypes = [{(): wp.float32, (3,): wp.vec3, (4,): wp.vec4}[shape] for shape in PARAM_SHAPES.values()]
            arrays = [wp.from_torch(t, dtype=dt, requires_grad=False) if tdev is not None
                      else wp.empty(n, dtype=dt, device=self.device) for t, dt in zip(outs, dtypes)]
            fixed = [n, self._threads]
            args = gather_args(self._param_array(quats, wp.vec4), self._param_array(log_scales, wp.vec3),
                               self._param_array(logits, float), rows_.flat, arrays)
            if sparse:  # one launch per row over the Gaussians it listed (each gathered by the first that did)
                jobs = [(lambda k=k, a=a: wp.launch(gather_touched_kernel, dim=len(a), device=self.device,
                                                    inputs=[*fixed, k, a, rows_.touched, args]))
                        for k, a in enumerate(ids) if len(a)]
            else:  # one launch per CPU thread over its share of every Gaussian
                jobs = [(lambda a=a, b=b: wp.launch(gather_kernel, dim=b - a, device=self.device,
                                                    inputs=[*fixed, a, args]))
                        for a, b in parts]
            with self.timer.section("tracer_backward"):
                run_chunks(self._pool, jobs)
                if ids is not None:  # the flags back to zero (each row its own, after every gather has read them)
                    run_chunks(self._pool, [
                        (lambda k=k, a=a: wp.launch(clear_touched_kernel, dim=len(a), device=self.device,
                                                    inputs=[a, rows_.touched[k * n:(k + 1) * n]]))
                        for k, a in enumerate(ids) if len(a)])
                    rows_.touched_count.zero_()
            rows_.dirty = False
            if tdev is None:
                outs = [to_torch(a, dev) for a in arrays]
        return [g.reshape(like.shape).to(device=like.device, dtype=like.dtype) for g, like in zip(outs, inputs)]

    def _outputs_to_torch(self, outs: dict[str, wp.array], gaussians: Gaussians) -> TraceOutput:
        dev, dt = gaussians.device, gaussians.dtype
        t = {k: to_torch(v, dev) for k, v in outs.items()}
        f = {k: (t[k].to(dt) if t[k].dtype == torch.float32 else t[k]) for k in t}
        return TraceOutput(diffuse=f["diffuse"], depth=f["depth"], normal=f["normal"], roughness=f["roughness"],
                           f0=f["f0"], transmittance=f["transmittance"], front_depth=f["front_depth"],
                           hit_count=f["hit_count"],
                           blended_count=f["blended"], candidates=f["candidates"],
                           obb_candidates=f["obb_candidates"], overflow_rays=self.last_overflow_rays,
                           replay_capacity=self.capacity)
