"""Optimisation of ONE Gaussian scene: diffuse + G-buffer losses on the first segment, specular on paths.

Paper Eq. 4-7 with the reference schedule: L1 losses in linear space, warm-up with
primary rays only, then reflections (and far-field Gaussians when reflections can
see past the captured geometry), Adam with per-parameter learning rates,
exponential position decay, pruning by accumulated blending weight, clamps.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree

from models.capture import Capture
from models.capture.layers import GBUFFER, RADIANCE
from models.gaussians import Gaussians
from models.metrics import hdr
from models.metrics.image import mse_to_psnr
from models.pathtrace.irradiance import cosine_mean_radiance
from models.pathtrace.paths import PathConfig, trace_paths
from models.profiling import NO_TIMER
from models.settings import config_hash, to_dict
from models.tracer.output import TraceOutput
from models.trained import ModelSettings

from .anchors import Anchors, facing_surfels
from .batches import RayBatcher
from .config import RENDER_ONLY_PATH, ReconstructConfig
from .data import RaySet, build_rayset
from .far_field import clearance_factors, far_field_gaussians
from .hole_fill import decide as decide_hole_fill
from .hole_fill import open_share, strided
from .mirror_stereo import mirror_stereo_gaussians
from .path_length import carried_throughput, going_on, needed_length
from .plane_fill import (RELIGHT_SAMPLES, extend_plane_fill, hold_on_planes, pixel_points, plane_fill_gaussians,
                         relight_plane_fill, stereo_on_planes)
from .sphere_fill import sphere_fill_gaussians
from .sphere_snap import snap_spheres
from .back_fill import back_fill
from .room_closing import close_behind_lights, close_room, keep_inside, placed_walls, shown_planes
from .reflection_fill import highlight_fill_gaussians, mirror_rays, reflection_fill_gaussians, seen_by_cameras

PRIOR_NEIGHBOURS = 8  # neighbours of a plane-fill Gaussian in the colour-smoothness term (loss.prior_smooth)
log = logging.getLogger("models.reconstruction")

PARAM_LR = {  # Gaussians field -> LearningRates field
    "means": "position_init", "quats": "rotation", "log_scales": "scale", "opacity_logits": "opacity",
    "diffuse": "diffuse", "normals": "normal", "roughness": "roughness", "f0": "f0",
}
REFERENCE_HEIGHT = 768  # image height the reference pruning threshold is stated at
FINITE_CHECK_EVERY = 25  # steps between read-backs of the finiteness flags (trainer.check_finite)


class Backend:
    """What the trainer needs from a tracer: refit/rebuild on new parameters, then differentiable traces; its
    ``torch_device`` (if it has one) is where the trainer keeps parameters, rays and targets (default CPU)."""

    def update(self, gaussians: Gaussians) -> None: ...

    def trace(self, origins: torch.Tensor, dirs: torch.Tensor, gaussians: Gaussians) -> TraceOutput: ...


class Trainer:
    def __init__(self, capture: Capture, init: Gaussians, config: ReconstructConfig, backend: Backend):
        self.config = config
        self.backend = backend
        self.rays: RaySet = build_rayset(capture, "train", config.radiance_clamp)
        self.extent = capture.camera_extent()  # 3DGS's scene extent: position learning rates, far field
        # the size every length threshold is a fraction of: the initial geometry's, not the cameras' (cameras
        # clustered in a big room give a small camera extent)
        self.scene_size = scene_size(init)
        # where max_thickness applies: everywhere until the far field is added, then the captured room's box
        self._thickness_box: tuple[torch.Tensor, torch.Tensor] | None = None
        self.units = capture.meta.units
        self.centre = np.mean([v.camera.origin for v in self.rays.views], axis=0)
        self.decisions: list[str] = []
        self.weights = self._active_losses()
        self.reflections = self._needs_reflections()
        # the tonemapped training scores' peak (as evaluate's: the ground truth's max, here over every training
        # ray's diffuse + emission + specular): a lamp or its reflection at 10 makes the linear PSNR (peak 1)
        # follow the few brightest rays only
        final = self.rays.targets["diffuse"] + self.rays.targets.get("specular", 0.0)
        self.peak = hdr.peak(float(final.max())) if final.numel() else 1.0
        # the far field is decided on what the cameras saw, not on the prior: the plane fill closes a room's box
        # where it can, and what lies outside that box (a wall never seen, behind the cameras) is the far field's
        with_fill, n_prior, n_fixed = self._plane_fill(init)
        self.far_field = self._needs_far_field(init, with_fill)
        init = with_fill
        self.generator = torch.Generator().manual_seed(config.seed)
        self.step = 0
        self.far_field_added = False
        self.plane_fill_relit = False  # _relight_plane_fill has run (once, when reflections turn on)
        # segments per path: the config's until reflections turn on, then what _decide_path_length chose
        self.path_length: int | None = None
        self.hole_fill: bool | None = None  # the renders' hole fill: decided on the trained model (settings())
        # reflected rays of the planar mirrors with their free distance (mirror stereo, loss.stereo_depth): origins,
        # directions, free distance; set when the fills are placed
        self.stereo_rays: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        self.timer = NO_TIMER  # a models.profiling.SectionTimer while a benchmark profiles the step
        # parameters, rays and targets live where the backend traces (a CUDA tracer: on the GPU)
        self.device = getattr(backend, "torch_device", None) or torch.device("cpu")
        self.batches = RayBatcher(self.rays, self.device, jitter=config.jitter)
        # on a GPU the tracer's per-trace read-backs (replay overflow, zero directions) are settled with the step's
        # one metrics read-back instead (see models/tracer/checks.py): the host queues a step's work while the
        # trace kernels run. A backend without deferred_checks, or False here, checks at every trace.
        self.defer_checks = self.device.type == "cuda" and hasattr(backend, "deferred_checks")
        self.params = {k: v.detach().to(self.device).clone().requires_grad_(True) for k, v in init.params().items()}
        self.finite_at = 0  # last step whose parameters were checked finite
        self._nonfinite = torch.zeros(len(self.params), device=self.device)  # per parameter: steps skipped
        self._one = torch.ones((), device=self.device)
        self.optimizer = self._make_optimizer()
        self.anchors = Anchors(self.device, self.params["means"].dtype)  # fill Gaussians kept near their placing
        if config.plane_hold:  # the initialisation's Gaussians flat on a wall, the floor or the ceiling stay flat on it
            self._hold_on_planes(len(self.params["means"]) - n_prior)
        # Gaussians a prior placed where no training view looks (plane_fill.py): never pruned for want of weight
        self.prior = torch.zeros(len(self.params["means"]), dtype=torch.bool, device=self.device)
        self.prior[len(self.prior) - n_prior:] = True
        # pruning (prune): a random cycle through the training views, a block of them per pruning step, and each
        # Gaussian's mean blending weight in the last blocks
        self._prune_order: torch.Tensor | None = None
        self._prune_round = 0
        self.pruned_hidden = 0  # of them, the initialisation's that every camera's view hides (prune_hidden)
        self.prune_memory = torch.zeros((len(self.prior), 0), device=self.device)
        self._prior_rows: torch.Tensor | None = None  # rows of ``prior`` (made when first needed), see _freeze_priors
        self._prior_nbrs: torch.Tensor | None = None  # [P, 8] each prior Gaussian's nearest priors (_prior_smooth)
        # the sphere completion's Gaussians (the last priors): nothing of theirs trains, see _freeze_priors
        self.fixed = torch.zeros_like(self.prior)
        self.fixed[len(self.fixed) - n_fixed:] = True
        self._fixed_rows: torch.Tensor | None = None
        # Gaussians the mirror fills placed (seen only in reflections): no buffer sees their material
        self.reflected = torch.zeros(len(self.params["means"]), dtype=torch.bool, device=self.device)
        self._reflected_rows: torch.Tensor | None = None
        # the far field's Gaussians (far_field_margin keeps them out of the captured room's box)
        self.far = torch.zeros_like(self.reflected)
        self._far_rows: torch.Tensor | None = None
        # each Gaussian's largest log scale allowed (highlight_max_growth: the highlight fill's emitters; inf: none)
        self.scale_cap = torch.full((len(self.params["means"]),), math.inf, device=self.device)
        self._capped_rows: torch.Tensor | None = None
        # what a checkpoint must have been trained from to be resumed (the stage adds its input files' digests)
        self.inputs: dict[str, str] = {}
        for d in self.decisions:
            log.info("decision: %s", d)

    # ----------------------------------------------------------------- decisions
    def _active_losses(self) -> dict[str, float]:
        weights = {}
        for layer in (*RADIANCE, *GBUFFER):
            w = getattr(self.config.loss, layer)
            if w == 0:
                self.decisions.append(f"loss {layer}: weight 0 in config, off")
            elif layer not in self.rays.targets:
                self.decisions.append(f"loss {layer}: the capture has no {layer} buffer, off")
            else:
                weights[layer] = w
        if "diffuse" not in weights:
            raise ValueError("reconstruction needs the diffuse buffer (loss weight > 0 and the layer in the capture)")
        # build_rayset's diffuse target is diffuse + emission (models.capture.layers.diffuse_radiance)
        emitting = [v for v in self.rays.views if "emission" in v.buffers and float(v.buffers["emission"].max()) > 0]
        if emitting:
            peak = max(float(v.buffers["emission"].max()) for v in emitting)
            self.decisions.append(f"loss diffuse: target diffuse + emission (lights seen directly, max {peak:.3g}) "
                                  f"in {len(emitting)} of {len(self.rays.views)} training views")
        return weights

    def _needs_reflections(self) -> bool:
        if self.config.max_path_length <= 1:
            self.decisions.append("reflections: max_path_length 1, primary rays only")
            return False
        if "specular" not in self.weights:
            self.decisions.append("reflections: no specular supervision, primary rays only")
            return False
        peak = float(self.rays.targets["specular"].abs().max())
        if peak < 1e-4:
            self.decisions.append(f"reflections: specular buffers are ~0 (max {peak:.2e}), primary rays only")
            return False
        if self.config.warmup >= self.config.iterations:
            message = (f"reflections: never on (warmup {self.config.warmup} >= iterations "
                       f"{self.config.iterations}): the model learns no reflections; lower reconstruct.warmup")
            log.warning(message)
            self.decisions.append(message)
            return False
        stop = (f", paths stop below throughput {self.config.min_throughput:g} in training (paths_stopped and "
                "stopped_weight in the log)" if self.config.min_throughput > 0 else "")
        longer = (f" (longer, up to {self.config.max_path_length_limit}, where mirror-like surfaces face each "
                  "other: decided when they turn on, halfway and at the end)"
                  if self.config.max_path_length_limit > self.config.max_path_length else "")
        self.decisions.append(f"reflections: on after step {self.config.warmup}, "
                              f"max path length {self.config.max_path_length}{longer}{stop}")
        return True

    def _plane_fill(self, init: Gaussians) -> tuple[Gaussians, int, int]:
        """``init`` with the prior's Gaussians appended: the plane fill's (``plane_fill_count`` > 0), then the
        sphere completion's (``sphere_fill``); their count, and the sphere completion's (the last ones)."""
        self._room = None
        planes = self._planes() if self.config.plane_fill_count > 0 else None
        spheres = self._spheres() if self.config.sphere_fill else None
        fills = [f for f in (planes, spheres) if f is not None]
        if not fills:
            return init, 0, 0
        fill = Gaussians.cat(fills).to(init.device, init.dtype)
        return Gaussians.cat([init.to(), fill]), len(fill), 0 if spheres is None else len(spheres)

    def _shiny_points(self, what: str) -> tuple[dict, float] | None:
        """The training pixels' points (the plane fill's when it ran) and the room's size (their 0.5-99.5 % box) for
        the sphere fits, or None (logged as ``what`` being off) without depth and normals on enough pixels."""
        src = self._room.src if self._room is not None else pixel_points(self.rays, 400000, seed=self.config.seed)
        if src is None or len(src["points"]) < 100:
            self.decisions.append(f"{what}: off, the capture has no depth and normal buffers on enough pixels")
            return None
        lo, hi = np.quantile(src["points"], [0.005, 0.995], axis=0)
        return src, float((hi - lo).max())

    def _spheres(self) -> Gaussians | None:
        """The sphere completion's Gaussians (sphere_fill.py), from the plane fill's pixel points when it ran."""
        found = self._shiny_points("sphere fill")
        if found is None:
            return None
        fill, stats = sphere_fill_gaussians(found[0], self.rays, found[1])
        self.decisions.append(f"sphere fill: {stats['added']} Gaussians on the unseen parts of {stats['spheres']} "
                              "round shiny objects")
        self.decisions.extend(f"sphere fill: {note}" for note in stats["notes"])
        return fill

    def _planes(self) -> Gaussians | None:
        """The plane fill's Gaussians (plane_fill.py); keeps the room it found for the later fills."""
        fill, stats = plane_fill_gaussians(self.rays, self.config.plane_fill_count, seed=self.config.seed)
        self._room = stats["room"]  # the planes and box found, for the fill behind the cameras (extend_plane_fill)
        message = (f"plane fill: {stats['added']} Gaussians on the unseen parts of {stats['bounding']} planes that "
                   f"bound the room (of {stats['planes']} planes in the buffers; {stats.get('duplicates', 0)} more "
                   f"made of a larger one's points left out; grid spacing "
                   f"{stats['spacing_fraction']:.4f} of the room's size)")
        self.decisions.append(message)
        for note in stats.get("notes", ()):
            self.decisions.append(note)
        return fill

    @torch.no_grad()
    def _hold_on_planes(self, count: int) -> None:
        """``plane_hold``: the first ``count`` Gaussians (the initialisation's) that lie flat on one of the room's
        bounding planes turned to face it and anchored there (``plane_fill.hold_on_planes``)."""
        if self._room is None:
            self.decisions.append("plane hold: off, no bounding planes (the plane fill is off, plane_fill_count 0, "
                                  "or found none in the buffers)")
            return
        init = Gaussians(**{k: v[:count].detach().cpu() for k, v in self.params.items()})
        held = hold_on_planes(self._room, init, self.config.plane_hold_depth)
        rows = held["rows"].to(self.device)
        if len(rows):
            self.params["quats"][rows] = held["quats"].to(self.params["quats"])
            self.params["log_scales"][rows] = held["log_scales"].to(self.params["log_scales"])
            cap = held["log_scales"].clone()  # the thin scale at most its initial one; the wide ones free
            cap[:, :2] = math.inf
            self.anchors.hold(rows, self.params["means"][rows].clone(), held["quats"],
                              torch.full((len(rows),), held["depth"]), torch.full((len(rows),), math.inf), cap)
        planes = ", ".join(str(c) for c in held["per_plane"])
        self.decisions.append(f"plane hold: {len(rows)} of the initialisation's {count} Gaussians lie flat on the "
                              f"room's bounding planes ({planes} per plane); they face their plane, move along it "
                              f"and keep within {100 * held['depth'] / self.extent:.2f} % of the scene's extent "
                              "of it along its normal")

    def _needs_far_field(self, init: Gaussians, closed: Gaussians) -> bool:
        """``init``: what the cameras saw (the mirror test); ``closed``: it with the plane fill (the view test)."""
        mode = self.config.far_field
        if mode not in ("auto", "on", "off"):
            raise ValueError(f"far_field must be auto, on or off, got {mode!r}")
        if not self.reflections or mode == "off":
            self.decisions.append(f"far field: off ({'config' if mode == 'off' else 'no reflections'})")
            return False
        if mode == "on":
            self.decisions.append(f"far field: on (config), {self.config.far_field_count} Gaussians")
            return True
        open_pixels = float((~self.rays.mask).float().mean())
        if open_pixels > 0:
            self.decisions.append(
                f"far field: on, {open_pixels:.1%} of training pixels see past the captured geometry"
            )
            return True
        escaped = self._escaping_reflections(init)
        if escaped is None:
            self.decisions.append(
                "far field: off, no mirror-like training pixels (F0 > 0.3 and roughness < 0.3 in the buffers): "
                "mirror stereo and the reflection fills do not run"
            )
            return False
        if escaped > self.config.far_field_escape:
            self.decisions.append(
                f"far field: on, {escaped:.1%} of mirror-like reflection rays leave the initial geometry"
            )
            return True
        # a test view may turn where no training view looked: a ceiling no camera saw (no plane to fill) is a hole
        # the far field's shell must close, or it renders black (zoo_thin: the denser init left 0.2 % of the
        # reflections escaping, the far field went off and the test view looking up saw 49 % of nothing)
        around = self._escaping_views(closed)
        if around > self.config.far_field_escape:
            self.decisions.append(
                f"far field: on, {around:.1%} of rays from the training cameras in random directions leave the "
                f"initial geometry and the plane fill ({escaped:.1%} of mirror-like reflection rays)"
            )
            return True
        self.decisions.append(
            f"far field: off, closed scene ({escaped:.1%} of mirror-like reflection rays escape the initial "
            f"geometry, {around:.1%} of rays from the training cameras in random directions escape it and the "
            f"plane fill)"
        )
        return False

    @torch.no_grad()
    def _escaping_views(self, scene: Gaussians, rays_per_camera: int = 1024) -> float:
        """Fraction of rays from the training cameras' centres in uniformly random directions that hit none of
        ``scene``'s Gaussians: where a view turned anywhere from where the cameras stand looks into nothing."""
        g = torch.Generator().manual_seed(self.config.seed)
        cams = torch.tensor(np.stack([v.camera.origin for v in self.rays.views]), dtype=torch.float32)
        dirs = torch.nn.functional.normalize(torch.randn(len(cams) * rays_per_camera, 3, generator=g), dim=1)
        origins = cams.repeat_interleave(rays_per_camera, 0)
        out = self.backend.trace(origins.to(scene.means.device), dirs.to(scene.means.device), scene)
        return float((out.hit_count.reshape(-1) == 0).float().mean())

    @torch.no_grad()
    def _escaping_reflections(self, init: Gaussians, max_rays: int = 16384) -> float | None:
        """Fraction of perfect-mirror reflections of shiny training pixels (F0 > 0.3, roughness < 0.3, from the
        buffers) that hit none of the initial Gaussians: what reflections would see beyond the captured geometry.
        (Not a transmittance test: initial Gaussians are faint, opacity 0.1, so walls are semi-transparent.)
        None when the buffers have no mirror-like pixel (a network's roughness may never go below 0.3)."""
        found = mirror_rays(self.rays, max_rays)
        if found is None:
            return None
        x, r, _ = found
        # start past the surface's own initial Gaussians (one median initial size; those are scene-relative too)
        offset = max(self.config.path(self.scene_size).origin_offset,
                     float(init.log_scales.detach().exp().amax(1).median()))
        out = self.backend.trace(x + offset * r, r, init)
        return float((out.hit_count.reshape(-1) == 0).float().mean())

    # ----------------------------------------------------------------- parameters
    def gaussians(self) -> Gaussians:
        return Gaussians(**self.params)

    def _make_optimizer(self) -> torch.optim.Adam:
        """Adam over one group per parameter (their learning rates differ), fused (one kernel per group, no
        per-tensor Python) where torch has it for these tensors, else the multi-tensor (foreach) one. Same update
        as the single-tensor Adam up to float rounding."""
        groups = [{"params": [p], "name": k, "lr": self._base_lr(k)} for k, p in self.params.items()]
        try:
            return torch.optim.Adam(groups, eps=self.config.adam_eps, fused=True)
        except RuntimeError:  # fused unsupported on this device / dtype
            return torch.optim.Adam(groups, eps=self.config.adam_eps, foreach=True)

    def _base_lr(self, name: str) -> float:
        lr = getattr(self.config.lr, PARAM_LR[name])
        return lr * self.extent if name == "means" else lr

    def position_lr(self, step: int) -> float:
        lr = self.config.lr
        t = min(step / max(self.config.iterations, 1), 1.0)
        return self.extent * math.exp((1 - t) * math.log(lr.position_init) + t * math.log(lr.position_final))

    def _replace(self, keep: torch.Tensor | None = None, extra: Gaussians | None = None,
                 anchored: bool = False, prior: bool = False, fixed: bool = False, matte: bool = False,
                 far: bool = False, growth: float = 0.0, growth_rows: torch.Tensor | None = None) -> None:
        """Prune (``keep`` [N] bool) and/or append ``extra`` Gaussians (``anchored``: kept near where they are
        now, see anchors.py, and matte; ``prior``: a prior's, see ``self.prior``; ``fixed``: nothing of theirs
        trains; ``matte``: their F0 and roughness stay, see ``_freeze_priors``; ``far``: the far field's; ``growth``
        > 0: each scale of those of them ``growth_rows`` marks ([len(extra)] bool; None: all) stays within that
        many times the median of all their largest scales now, see ``scale_cap``), keeping Adam's state and the
        anchors aligned."""
        if keep is not None:
            self.anchors.keep(keep.to(self.anchors.index.device))
            self.prior = self.prior[keep.to(self.prior.device)]
            self.reflected = self.reflected[keep.to(self.reflected.device)]
            self.fixed = self.fixed[keep.to(self.fixed.device)]
            self.far = self.far[keep.to(self.far.device)]
            self._far_rows = None
            self.scale_cap = self.scale_cap[keep.to(self.scale_cap.device)]
            self._capped_rows = None
            self.prune_memory = self.prune_memory[keep.to(self.prune_memory.device)]
            self._prior_rows = self._reflected_rows = self._fixed_rows = None
        if extra is not None:
            self.prior = torch.cat([self.prior, torch.full((len(extra),), prior, dtype=torch.bool,
                                                           device=self.prior.device)])
            self.reflected = torch.cat([self.reflected, torch.full((len(extra),), anchored or matte,
                                                                   dtype=torch.bool, device=self.reflected.device)])
            self.fixed = torch.cat([self.fixed, torch.full((len(extra),), fixed, dtype=torch.bool,
                                                           device=self.fixed.device)])
            self.far = torch.cat([self.far, torch.full((len(extra),), far, dtype=torch.bool, device=self.far.device)])
            self._far_rows = None
            size = extra.log_scales.detach().amax(dim=1).median() + math.log(growth) if growth > 0 and len(extra) else math.inf
            cap = torch.full((len(extra),), float(size), device=self.scale_cap.device)
            if growth_rows is not None:
                cap[~growth_rows.to(cap.device)] = math.inf
            self.scale_cap = torch.cat([self.scale_cap, cap])
            self._capped_rows = None
            self.prune_memory = torch.cat([self.prune_memory, torch.full((len(extra), self.prune_memory.shape[1]),
                                                                         float("nan"), device=self.prune_memory.device)])
            self._prior_rows = self._reflected_rows = self._fixed_rows = None
        if extra is not None and anchored and self.config.fill_anchor > 0:
            extra = facing_surfels(extra)
            first = len(self.params["means"]) - (0 if keep is None else int((~keep).sum()))
            self.anchors.append(first, extra, self.config.fill_anchor, self.config.fill_spread)
        new_opt_state = {}
        for group in self.optimizer.param_groups:
            name = group["name"]
            old = group["params"][0]
            state = self.optimizer.state.get(old, {})
            value = old.detach()
            moments = {k: state[k] for k in ("exp_avg", "exp_avg_sq") if k in state}
            if keep is not None:
                value = value[keep]
                moments = {k: v[keep] for k, v in moments.items()}
            if extra is not None:
                add = getattr(extra, name).to(value.device, value.dtype)
                value = torch.cat([value, add])
                moments = {k: torch.cat([v, torch.zeros_like(add)]) for k, v in moments.items()}
            new = value.clone().requires_grad_(True)
            self.params[name] = new
            group["params"] = [new]
            if moments:
                new_opt_state[new] = {"step": state["step"], **moments}
        self.optimizer.state.clear()
        self.optimizer.state.update(new_opt_state)

    @torch.no_grad()
    def _clamp_thickness(self) -> None:
        """Each Gaussian's thinnest scale at most ``max_thickness`` x the scene's size, but for the fixed ones and,
        once the far field is added, those outside the captured room's box (which the far field is drawn outside of:
        ``_captured_box``, mirror fills and the walls placed after warm-up included); ``thickness_reflected_only``:
        only the mirror fills' Gaussians (``self.reflected``)."""
        cap = math.log(self.config.max_thickness * self.scene_size)
        ls = self.params["log_scales"]
        thin, axis = ls.min(dim=1)
        over = (thin > cap) & ~self.fixed.to(ls.device)
        if self.config.thickness_reflected_only:
            over &= self.reflected.to(ls.device)
        if self._thickness_box is not None:
            lo, hi = (b.to(ls) for b in self._thickness_box)
            means = self.params["means"]
            over &= ((means >= lo) & (means <= hi)).all(dim=1)
        rows = torch.nonzero(over).reshape(-1)
        if len(rows):
            ls[rows, axis[rows]] = cap

    def _keep_far_field_out(self) -> None:
        """``far_field_margin``: the far field's Gaussians shrunk (``far_field.clearance_factors``) until that many
        of their standard deviations lie outside the captured room's box (``_captured_box``, kept from when the far
        field was added); one that has moved inside shrinks to 1e-4 x the scene's size."""
        if self._far_rows is None:
            self._far_rows = torch.nonzero(self.far).reshape(-1).to(self.params["means"].device)
        rows = self._far_rows
        if not len(rows):
            return
        ls = self.params["log_scales"]
        # in float64, with the box as it was kept: rounded to float32, the box's face moved by ~1e-7 m, enough to
        # leave a Gaussian 1 mm outside it 1e-4 of its margin short (a factor 0.99992 where 1 was due)
        lo, hi = (b.to(device=ls.device, dtype=torch.float64) for b in self._thickness_box)
        factor = clearance_factors(*(self.params[k][rows].double() for k in ("means", "quats", "log_scales")), lo, hi,
                                   self.config.far_field_margin, 1e-4 * self.scene_size)
        ls[rows] += factor.log().to(ls.dtype)[:, None]

    @torch.no_grad()
    def _clamp(self) -> None:
        self.params["diffuse"].clamp_(min=0.0)
        self.params["roughness"].clamp_(0.0, 1.0)
        self.params["f0"].clamp_(0.0, 1.0)
        if self.config.max_thickness > 0:
            self._clamp_thickness()
        if self.config.far_field_margin > 0 and self._thickness_box is not None:
            self._keep_far_field_out()
        if self._capped_rows is None:
            self._capped_rows = torch.nonzero(torch.isfinite(self.scale_cap)).reshape(-1)
        if len(self._capped_rows):
            rows, ls = self._capped_rows, self.params["log_scales"]
            ls[rows] = torch.minimum(ls[rows], self.scale_cap[rows, None].to(ls))
        self.anchors.project(self.params["means"], self.params["quats"], self.params["log_scales"])

    # ----------------------------------------------------------------- steps
    def sample_batch(self) -> RaySet:
        n = self.config.rays_per_step
        if n <= 0:
            view = int(torch.randint(len(self.rays.views), (1,), generator=self.generator))
            return self.batches.view(view, self.generator)
        return self.batches.sample(torch.randint(len(self.rays), (n,), generator=self.generator), self.generator)

    def losses(self, batch: RaySet, reflections: bool) -> tuple[torch.Tensor, dict]:
        g = self.gaussians()
        self.backend.update(g)
        path_cfg = (self.path_config(training=True) if reflections
                    else dataclasses.replace(self.config.path(self.scene_size), max_path_length=1))
        if self.defer_checks:
            rng = self.generator.get_state()
            with self.backend.deferred_checks() as checks:
                with self.timer.section("path_sampling"):
                    out = trace_paths(self.backend.trace, batch.origins, batch.dirs, g, path_cfg, self.generator)
                    stereo = self._stereo_trace(g, reflections)
                with self.timer.section("losses"):
                    total, metrics, flags = self._loss_terms(batch, out, reflections, checks.flags(), stereo)
            if not checks.settle(*flags):
                return total, metrics
            # a ray outgrew its replay buffer (capacity grown): the step again, checked, with the same random numbers
            self.generator.set_state(rng)
        with self.timer.section("path_sampling"):
            out = trace_paths(self.backend.trace, batch.origins, batch.dirs, g, path_cfg, self.generator)
            stereo = self._stereo_trace(g, reflections)
        with self.timer.section("losses"):
            return self._loss_terms(batch, out, reflections, stereo=stereo)[:2]

    def _stereo_trace(self, g: Gaussians, reflections: bool) -> tuple[TraceOutput, torch.Tensor] | None:
        """(trace, free distance [M]) of ``loss.stereo_depth_rays`` reflected rays drawn from ``stereo_rays``, each
        started a tenth of its free distance past its mirror (clear of the mirror's own Gaussians); None when the
        loss is off or no mirror stereo depth exists."""
        loss = self.config.loss
        if not reflections or loss.stereo_depth <= 0 or self.stereo_rays is None:
            return None
        origins, dirs, free = self.stereo_rays
        pick = torch.randint(len(free), (min(loss.stereo_depth_rays, len(free)),), generator=self.generator)
        pick = pick.to(free.device)
        start = 0.1 * free[pick]
        out = self.backend.trace(origins[pick] + start[:, None] * dirs[pick], dirs[pick], g)
        return out, (1.0 - loss.stereo_depth_margin) * free[pick] - start

    def _loss_terms(self, batch: RaySet, out, reflections: bool, flags: torch.Tensor | None = None,
                    stereo: tuple[TraceOutput, torch.Tensor] | None = None) -> tuple[torch.Tensor, dict, list[float]]:
        """(total loss, metrics, the host values of ``flags``: extra device values read back with the metrics)."""
        terms = {}
        if stereo is not None:
            # the expected depth of the rays that end (opacity >= 0.5), wherever it falls in front of the free distance
            ahead = in_front_of(*stereo) * (DEPTH_UNIT_SIZE / self.scene_size)
            terms["stereo_depth"] = self.config.loss.stereo_depth * ahead.mean()
        m = batch.mask
        for layer, w in self.weights.items():
            if layer == "specular":
                if not reflections:
                    continue
                pred = out.specular
            else:
                pred = out.primary.layer(layer)
            target = batch.targets[layer]
            err = (pred - target.reshape(pred.shape)).abs()
            if layer == "depth":  # in units of the scene's size, so a scaled scene trains the same
                err = err * (DEPTH_UNIT_SIZE / self.scene_size)
            if layer in GBUFFER:  # G-buffer values exist only where the ray hits geometry (mean over those)
                count = (m.sum() * err.shape[1]).clamp_min(1)  # on the device: no read-back to branch on
                terms[layer] = w * torch.where(m[:, None], err, 0.0).sum() / count
            else:
                terms[layer] = w * err.mean() if err.numel() else pred.sum() * 0
        if self.config.loss.prior_smooth > 0 and len(self._cached_rows()[0]):
            terms["prior_smooth"] = self.config.loss.prior_smooth * self._prior_smooth()
        total = sum(terms.values())
        names = [*(f"loss_{k}" for k in terms), "loss"]
        values = [*terms.values(), total]
        scored = {"diffuse": (out.primary.diffuse, batch.targets["diffuse"])}
        if reflections and "specular" in batch.targets:
            scored["specular"] = (out.specular, batch.targets["specular"])
            scored["final"] = (out.primary.diffuse + out.specular, batch.targets["diffuse"] + batch.targets["specular"])
        for k, (pred, target) in scored.items():
            names += [f"mse_{k}", f"mse_{k}_tonemapped"]
            values += [_mse(pred, target), _mse(hdr.mu_law(pred, self.peak), hdr.mu_law(target, self.peak))]
        if out.stopped:  # paths stopped by min_throughput: how many, and their share of the bounce gradient weight
            stopped = torch.stack(out.stopped).sum(0)
            names += ["paths_stopped", "stopped_weight"]
            values += [stopped[0], stopped[1] / stopped[2].clamp_min(1e-12)]
        stacked = torch.stack([v.detach().double() for v in values])
        if flags is not None:
            stacked = torch.cat([stacked, flags.double()])
        read = stacked.tolist()  # the step's one read-back
        host = dict(zip(names, read))
        metrics = {k: (round(v, 6) if k == "stopped_weight" else v) for k, v in host.items()
                   if not k.startswith("mse_")}
        for k in scored:  # psnr_<layer>: linear at peak 1 (as in logs before); _tonemapped: mu-law at self.peak
            metrics[f"psnr_{k}"] = mse_to_psnr(host[f"mse_{k}"])
            metrics[f"psnr_{k}_tonemapped"] = mse_to_psnr(host[f"mse_{k}_tonemapped"])
        return total, metrics, read[len(names):]

    def _add_fill(self, fill: Gaussians | None, stats: dict, message: str, anchored: bool = False,
                  prior: bool = False, fixed: bool = False, matte: bool = False, growth: float = 0.0,
                  growth_rows: torch.Tensor | None = None) -> None:
        """Append a fill's Gaussians (if any; ``anchored``: see anchors.py; ``growth``, ``growth_rows``: see
        ``_replace``; ``prior``:
        a prior's, never pruned for want of weight, geometry frozen), log ``message % stats`` and keep it among the decisions (with each
        of ``stats["notes"]``: what a fill could not decide well)."""
        if fill is not None:
            self._replace(extra=fill, anchored=anchored, prior=prior, fixed=fixed, matte=matte, growth=growth,
                          growth_rows=growth_rows)
        depth, spread = self.config.fill_anchor, max(self.config.fill_spread, self.config.fill_anchor)
        if fill is not None and anchored and depth > 0:
            message += (f", anchored (surfels facing the views: along that direction within {depth:g}x their "
                        f"size of where they were put and grown <= {depth:g}x, across it {spread:g}x)")
        log.info("step %d: added %s", self.step, message % stats)
        self.decisions.append(f"step {self.step}: added {message % stats}")
        for note in stats.get("notes", ()):
            log.warning("step %d: %s", self.step, note)
            self.decisions.append(f"step {self.step}: {note}")

    @torch.no_grad()
    def _seen_from_cameras(self, scene: Gaussians, fills: list, points: torch.Tensor,
                           chunk: int = 262144) -> torch.Tensor:
        """[P] the most light that reaches each of ``points`` (outside the captured room) from any training camera
        through ``scene`` and ``fills``: the transmittance of the segment camera -> point, max over the cameras."""
        room = Gaussians.cat([scene.to()] + [f.to(scene.device, scene.dtype) for f in fills if f is not None])
        cams = torch.tensor(np.stack([v.camera.origin for v in self.rays.views]), dtype=points.dtype,
                            device=room.means.device)
        pts = points.to(room.means.device)
        best = torch.zeros(len(pts), dtype=pts.dtype, device=pts.device)
        if not len(pts):
            return best
        per = max(1, chunk // len(pts))
        for i in range(0, len(cams), per):
            c = cams[i:i + per]
            origins = c.repeat_interleave(len(pts), 0)
            dirs = torch.nn.functional.normalize(pts.repeat(len(c), 1) - origins, dim=-1)
            t = self.backend.trace(origins, dirs, room).transmittance.reshape(len(c), len(pts))
            best = torch.maximum(best, t.amax(0).to(best.dtype))
        return best

    def _captured_box(self, scene: Gaussians, fills: list) -> tuple[np.ndarray, np.ndarray]:
        """Where the captured room is, which the far field must stay out of: the 0.5-99.5 % box of the scene's
        Gaussians and of the mirror fills' (what the cameras see only in mirrors, often the half of the room
        behind them), widened to hold every camera (they stand inside it)."""
        means = torch.cat([scene.means.detach().double()] + [f.means.detach().double().cpu() for f in fills
                                                              if f is not None and len(f)])
        lo, hi = torch.quantile(means, torch.tensor([0.005, 0.995], dtype=torch.float64), dim=0).numpy()
        cams = np.stack([v.camera.origin for v in self.rays.views])
        return np.minimum(lo, cams.min(0)), np.maximum(hi, cams.max(0))

    def train_step(self) -> dict:
        cfg = self.config
        reflections = self.reflections and self.step >= cfg.warmup
        if reflections and self.far_field and not self.far_field_added:
            # the fills look at the captured scene alone: its box, and its transmittance (not the far shell's)
            scene = self.gaussians() if self.device.type == "cpu" else self.gaussians().to("cpu")
            plane_fill = (self.prior & ~self.fixed).cpu()  # the plane fill's rows of ``scene``
            fills = []
            if cfg.reflection_fill_count > 0:
                fills.append((*reflection_fill_gaussians(self.rays, self.backend.trace, scene,
                                                         cfg.reflection_fill_count, seed=cfg.seed),
                              "%(added)d Gaussians (%(unseen)d candidates unseen by the cameras) along "
                              "%(open_rays)d open mirror reflections (of %(mirror_rays)d mirror rays)", True))
            stereo = None
            if cfg.mirror_stereo_count > 0:
                stereo = mirror_stereo_gaussians(self.rays, self.backend.trace, scene, cfg.mirror_stereo_count,
                                                 opacity=cfg.mirror_stereo_opacity,
                                                 seed=cfg.seed, min_share=cfg.mirror_stereo_min_share,
                                                 plane_slack=cfg.stereo_plane_slack)
                fills.append((*stereo,
                              "%(added)d Gaussians where the reflections of %(planes)d planar mirrors (in "
                              "%(planar_views)d views, %(pixels)d open mirror pixels; %(ignored)d curved or "
                              "non-planar shiny regions ignored) agree in depth (%(kept)d pixels matched, "
                              "%(completed)d of them flat ones completed from their matched neighbours; %(inconsistent)d dropped: "
                              "no other mirror's depth agrees, or more see through them)", True))
            grown, walls, closed, shown = None, None, None, None
            if self._room is not None and stereo is not None and stereo[0] is not None:
                # the room's planes behind the cameras, where the mirrors show it reaches (plane_fill.py step 6)
                # (and the wall they show on an open side, with what the mirrors could not show of it)
                shown = stereo[0].means.detach().double().cpu().numpy()
                material = tuple(x.detach().double().cpu().numpy() for x in (stereo[0].diffuse, stereo[0].f0,
                                                                              stereo[0].roughness))
                grown = extend_plane_fill(self._room, self.rays, shown, cfg.plane_fill_count, material=material)
            planar = None
            if cfg.stereo_on_planes and self._room is not None and stereo is not None and stereo[0] is not None:
                # those on the room's planes become plane-fill surfels (plane_fill.stereo_on_planes)
                along = stereo[1].get("along") if cfg.stereo_plane_slack > 0 else None
                on, surfels, on_planes = stereo_on_planes(self._room, stereo[0], tol_factor=cfg.stereo_plane_tol,
                                                          along=along)
                if surfels is not None:
                    i = next(k for k, f in enumerate(fills) if f[0] is stereo[0])
                    rest = stereo[0].subset(~on)
                    fills[i] = (rest if len(rest) else None, *fills[i][1:])
                    planar = (surfels, on_planes, "%(added)d of the mirror stereo's Gaussians on the room's planes made "
                              "plane-fill surfels (the plane's F0 and roughness, the colour the mirrors show; %(along)d of "
                              "them where their ray crosses the plane among the depths the sweep could not tell "
                              "apart)")
            if self._room is not None and cfg.close_room:
                # walls no view looks at, where sharp reflections (curved mirrors too) agree on them (room_closing.py),
                # and the plane fill carried out to them
                seen = Gaussians.cat([scene] + [f[0].to(scene.device, scene.dtype) for f in fills if f[0] is not None]
                                     + ([grown[0]] if grown is not None and grown[0] is not None else []))
                wall, points, stats = close_room(self._room, self.rays, self.backend.trace, seen,
                                                 cfg.plane_fill_count, known=shown, seed=cfg.seed,
                                                 refine=cfg.close_room_refine)
                walls = (wall, stats, "%(added)d Gaussians on walls no training view looks at, placed where "
                         "%(rays)d open sharp reflections (then, on the sides still open, %(glossy_rays)d glossy "
                         "ones) agree on them: %(walls)s")
                if points is not None:
                    closed = extend_plane_fill(self._room, self.rays, points, cfg.plane_fill_count)
            placed = [w[0] for w in (walls, grown, closed) if w is not None]
            box = self._captured_box(scene, [f[0] for f in fills] + placed)
            ff = far_field_gaussians(cfg.far_field_count, self.centre, self.extent, cfg.seed, keep_out=box)
            self._thickness_box = tuple(torch.from_numpy(np.asarray(b, dtype=np.float64)) for b in box)
            drawn = len(ff)
            if cfg.far_field_hidden > 0:
                room = [f[0] for f in fills] + placed
                visible = self._seen_from_cameras(scene, room, ff.means) >= cfg.far_field_hidden
                ff = ff.subset(visible)
            self._replace(extra=ff, far=True)
            self.far_field_added = True
            log.info("step %d: added %d far-field Gaussians (outside the cameras' sphere and the captured box "
                     "%s .. %s; %d drawn, those no training camera sees past the room left out)", self.step, len(ff),
                     np.round(box[0], 3).tolist(), np.round(box[1], 3).tolist(), drawn)
            rays = stereo[1].get("rays") if stereo is not None else None
            if cfg.loss.stereo_depth > 0 and rays is not None and len(rays[2]):
                self.stereo_rays = tuple(torch.from_numpy(np.asarray(a)).to(self.device, self.params["means"].dtype)
                                         for a in rays)
                message = (f"step {self.step}: stereo depth loss on {len(self.stereo_rays[2])} reflected rays of the "
                           f"planar mirrors (median free distance {float(self.stereo_rays[2].median()):.3g})")
                log.info(message)
                self.decisions.append(message)
            for fill in fills:
                self._add_fill(*fill)
            if grown is not None:
                self._add_fill(*grown, "%(added)d plane-fill Gaussians where the mirrors show the room reaching past "
                               "the first fill's box (grown: %(grown)s; walls they show: %(walls)s)", prior=True)
            if planar is not None:  # keeping the plane's F0 and roughness (fill_matte: no buffer sees them)
                self._add_fill(*planar, prior=True, matte=True)
            if walls is not None:
                self._add_fill(*walls, prior=True)
            if closed is not None:
                self._add_fill(*closed, "%(added)d plane-fill Gaussians reaching the walls placed (grown: %(grown)s)",
                               prior=True)
            if cfg.highlight_fill:
                later = [f[0] for f in (walls, grown, closed, planar) if f is not None and f[0] is not None]

                def highlights(placed: list):
                    on = (Gaussians.cat([g.to(scene.device, scene.dtype) for g in placed])
                          if placed and cfg.highlight_on_fill else None)  # the planes placed since warm-up
                    planes = placed_walls(self._room) if cfg.highlight_to_walls else None
                    known = shown_planes(self._room)
                    room_planes = ([(n, s + self._room.h) for n, s in known + placed_walls(self._room)]
                                   # ON the planes, the walls placed behind lights too
                                   if cfg.highlight_on_fill_plane and self._room is not None else None)
                    return highlight_fill_gaussians(self.rays, self.backend.trace, scene, seed=cfg.seed,
                                                    fill=plane_fill, on_fill=cfg.highlight_on_fill, walls=on,
                                                    planes=planes, known=known,
                                                    on_fill_purity=cfg.highlight_on_fill_purity,
                                                    on_fill_planes=room_planes,
                                                    skip_seen_lights=cfg.highlight_skip_seen_lights)

                lights, stats = highlights(later)
                behind = None
                if (cfg.close_behind_lights and cfg.close_room and self._room is not None and lights is not None
                        and stats.get("box_scale_inside")):
                    # the sides the sweep left open, closed behind the lights found on them (room_closing.py);
                    # then the lights again, those whose reflections cross a new wall moved onto it
                    wall, points, wstats = close_behind_lights(self._room, self.rays, self.backend.trace, seen,
                                                               lights.means.detach().double().cpu().numpy(),
                                                               cfg.plane_fill_count, known=shown, seed=cfg.seed)
                    if wall is not None:
                        more = extend_plane_fill(self._room, self.rays, points, cfg.plane_fill_count)
                        behind = (wall, wstats, more)
                        lights, stats = highlights(later + [g for g in (wall, more[0]) if g is not None])
                    else:
                        for note in wstats["notes"]:
                            self.decisions.append(f"step {self.step}: {note}")
                stats["inside"] = keep_inside(lights.means, self._room) if lights is not None else 0
                self._add_fill(lights, stats, "%(added)d emitting Gaussians where %(highlight_rays)d open highlight "
                               "reflections (of %(mirror_rays)d mirror rays) end together (box scale %(box_scale).2f, "
                               "searched %(box_scale_range)s; %(snapped)d moved onto a wall placed just beyond; "
                               "%(inside)d moved in front of a wall placed; "
                               "%(on_fill)d more end on the plane fill: %(on_fill_added)d emitting Gaussians there, "
                               "%(on_fill_impure)d left out among dark reflections, %(on_plane)d moved onto a room "
                               "plane; %(seen_light)d left out beside a light the cameras see)",
                               prior=cfg.highlight_frozen, matte=cfg.highlight_frozen,
                               growth=cfg.highlight_max_growth,
                               growth_rows=None if cfg.highlight_growth_all else stats["snapped_rows"])
                if behind is not None:
                    self._add_fill(behind[0], behind[1], "%(added)d Gaussians on walls placed behind the lights the "
                                   "highlight fill found on the room's open sides: %(walls)s", prior=True)
                    self._add_fill(*behind[2], "%(added)d plane-fill Gaussians reaching the walls placed behind the "
                                   "lights (grown: %(grown)s)", prior=True)
        relight_at = cfg.warmup + int(cfg.plane_fill_relight_at * (cfg.iterations - cfg.warmup))
        if (reflections and cfg.plane_fill_relight and self._room is not None and not self.plane_fill_relit
                and self.step >= relight_at):
            self._relight_plane_fill()  # after the fills above: the lights seen only in mirrors are placed
            self.plane_fill_relit = True
        if reflections and (self.path_length is None or self.step == (cfg.warmup + cfg.iterations) // 2):
            self._decide_path_length()
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = self.position_lr(self.step)
        total, metrics = self.losses(self.sample_batch(), reflections)
        self.optimizer.zero_grad(set_to_none=True)
        with self.timer.section("autograd"):
            total.backward()
        with self.timer.section("optimizer"):
            self._freeze_priors()
            self._skip_non_finite()
            self.optimizer.step()
            self._clamp()
        self.step += 1
        if reflections and self.step == cfg.iterations:
            self._decide_path_length()  # the length the model is rendered with, on the trained scene
        if self.step % FINITE_CHECK_EVERY == 0:
            self.check_finite()
        if cfg.prune_every > 0 and self.step >= cfg.prune_from and self.step % cfg.prune_every == 0:
            metrics["pruned"] = self.prune()
            if self.pruned_hidden:
                metrics["pruned_hidden"] = self.pruned_hidden  # so far
        metrics["step"] = self.step
        metrics["gaussians"] = len(self.params["means"])
        return metrics

    @torch.no_grad()
    def _relight_plane_fill(self) -> None:
        """The plane fill's Gaussians (priors that are neither fixed nor a mirror fill's) take their plane's albedo x
        the light the model now sends where they are (plane_fill.relight_plane_fill): at the end of warm-up (every
        fill and the lights seen only in mirrors placed) or later (``plane_fill_relight_at``), traced with the
        model's own paths."""
        rows = torch.nonzero(self.prior & ~self.fixed & ~self.reflected).reshape(-1)
        if not len(rows):
            return
        scene = self.gaussians()
        generator = torch.Generator().manual_seed(self.config.seed)
        path = self.path_config()  # a metal wall's reflection of a lamp lights the floor too (zoo_corridor: one
        # segment saw the facing metal walls black, and the relit fill lost 0.65 dB where the model's paths lose 0.16)

        def irradiance(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
            p = torch.from_numpy(points).to(scene.means)
            nrm = torch.from_numpy(normals).to(scene.means)
            offsets = torch.zeros(len(p), dtype=p.dtype, device=p.device)  # points already lifted off the plane
            return cosine_mean_radiance(self.backend.trace, scene, p, nrm, offsets, RELIGHT_SAMPLES, path,
                                        generator).numpy()

        means = self.params["means"].detach()[rows].double().cpu().numpy()
        diffuse = self.params["diffuse"].detach()[rows].double().cpu().numpy()
        new, stats = relight_plane_fill(self._room, means, diffuse, irradiance, seed=self.config.seed)
        self.params["diffuse"].data[rows] = torch.from_numpy(new).to(self.params["diffuse"])
        message = (f"plane fill relit: {stats['relit']} of its {len(rows)} Gaussians on {stats['planes']} planes take "
                   f"their plane's albedo x the light where they are (median {stats['gain']:.2f}x the nearest seen "
                   "radiance)")
        log.info("step %d: %s", self.step, message)
        self.decisions.append(f"step {self.step}: {message}")

    @torch.no_grad()
    def snap_spheres(self) -> None:
        """After the last step (``sphere_snap``): each round shiny object's Gaussians replaced by a lattice of discs
        on the sphere fitted to it (sphere_snap.py), a prior's fixed Gaussians."""
        found = self._shiny_points("sphere snap")
        if found is None:
            return
        keep, lattice, stats = snap_spheres(self.gaussians(), found[0], self.rays.views, found[1])
        if lattice is not None:
            self._replace(keep=keep.to(self.device), extra=lattice.to(self.device, self.params["means"].dtype),
                          prior=True, fixed=True)
        message = (f"sphere snap: {stats['snapped']} of {stats['spheres']} round shiny objects replaced by discs on "
                   f"their fitted spheres ({stats['removed']} Gaussians replaced by {stats['added']})")
        log.info("step %d: %s", self.step, message)
        self.decisions.append(f"step {self.step}: {message}")
        for note in stats["notes"]:
            self.decisions.append(f"step {self.step}: {note}")

    @torch.no_grad()
    def fill_backs(self) -> None:
        """After the last step (``back_fill``): the lit layer behind thin surfaces seen from one side only
        (back_fill.py), appended as a prior's fixed Gaussians."""
        depths = []
        for i, view in enumerate(self.rays.views):
            rays = self.rays.view_rays(i)
            cam = view.camera
            depth = torch.zeros(cam.height * cam.width)
            if "depth" in rays.targets:  # unknown (0) where masked out or not finite
                d = rays.targets["depth"].reshape(-1).cpu()
                depth = torch.where(rays.mask.cpu() & torch.isfinite(d), d, torch.zeros_like(d))
            depths.append(depth.reshape(cam.height, cam.width).double().cpu().numpy())
        with torch.enable_grad():
            fill, stats = back_fill(self.gaussians().to(), self.rays.views, depths, self.backend.trace,
                                    self.path_config(), self.scene_size)
        self._add_fill(None if fill is None else fill.to(self.device), stats,
                       "%(count)d Gaussians behind thin surfaces seen from one side only (of %(candidates)d surface "
                       "Gaussians: back seen empty %(carved)d, open %(open)d, %(seen)d dropped as a training view "
                       "sees them)", prior=True, fixed=True)

    def path_config(self, training: bool = False) -> PathConfig:
        """The path settings this run trains with (``training``: with the training-only cut-off) and stores with
        the model: the config's, with the path length decided when reflections turned on."""
        cfg = self.config.training_path(self.scene_size) if training else self.config.path(self.scene_size)
        return cfg if self.path_length is None else dataclasses.replace(cfg, max_path_length=self.path_length)

    def _decide_path_length(self) -> None:
        """Segments per path from now on, and for renders: the paper's 3 (two reflections, then the diffuse cache)
        unless mirror-like surfaces face each other. A reflection that ends on a matte surface is exact at 3;
        one that meets another mirror-like surface reads that surface's diffuse cache, ~0 for a metal, so it goes
        dark and training pushes the metal's diffuse up to make up for it (zoo_corridor, two facing metal walls:
        test final 19.2 dB tonemapped at 3, 21.9 at 6). Reflections leave random mirror-like training pixels in
        cosine-distributed directions (any viewpoint, not only the training ones: the test views of a corridor
        look at its walls head-on) and are traced through the current scene for up to
        ``max_path_length_limit`` segments; the length grows while more than ``path_tail_rays`` of them still
        carry more than ``path_tail_throughput`` after it. Called when reflections turn on, halfway and at the
        end (a young model's normals disagree and stop paths early); the length never shrinks. In training,
        paths still stop below ``min_throughput``: a longer length costs only where light does go on."""
        cfg = self.config
        base, limit = cfg.max_path_length, max(cfg.max_path_length, cfg.max_path_length_limit)
        before = self.path_length
        self.path_length = max(base, before or base)
        if limit == base or self.path_length >= limit:
            return
        found = mirror_rays(self.rays, PATH_DECISION_RAYS, seed=cfg.seed + self.step)
        if found is None:
            return
        x, _, index = found
        d = self.rays.dirs[index]
        n = torch.nn.functional.normalize(self.rays.targets["normal"][index], dim=-1)
        n = torch.where(((n * d).sum(-1) > 0)[:, None], -n, n)  # the side the camera saw
        g = self.gaussians()
        self.backend.update(g)
        behind: dict = {}
        carried = carried_throughput(x.to(self.device), n.to(self.device), self.backend.trace, g,
                                     self.config.training_path(self.scene_size), limit,
                                     torch.Generator().manual_seed(cfg.seed + 7919 + self.step), behind)
        self.path_length = max(self.path_length, needed_length(carried, base, limit, cfg.path_tail_throughput,
                                                               cfg.path_tail_rays))

        def going(length: int) -> float:
            return going_on(carried, length, cfg.path_tail_throughput)

        if self.path_length == before:
            return
        message = (f"path length {self.path_length} (max_path_length {base}, limit {limit}): of {len(n)} "
                   f"reflections leaving mirror-like training pixels in random directions, {going(base):.1%} "
                   f"still carry more than {cfg.path_tail_throughput:g} of their light after {base} segments, "
                   f"{going(self.path_length):.1%} after {self.path_length} (allowed: {cfg.path_tail_rays:.0%}; "
                   f"{behind.get('back', 0)} of {behind.get('rays', 0)} segments met a surface from behind, the "
                   "surface they left, and went on through it)")
        if going(self.path_length) > cfg.path_tail_rays:
            message += "; the limit cuts them short (raise reconstruct.max_path_length_limit)"
        log.info("step %d: %s", self.step, message)
        self.decisions.append(f"step {self.step}: {message}")

    def blending_weights(self, views: list[int], reflections: bool = False) -> torch.Tensor:
        """[N] accumulated blending weight per Gaussian, averaged over ``views`` (d sum(diffuse_R) / d diffuse_i,R);
        with ``reflections``, plus its weight in the traced reflections (d sum(specular_R) / d diffuse_i,R:
        bounce Gaussians are the radiance cache), so what the views see only in mirrors is kept too."""
        acc = torch.zeros(len(self.params["means"]), device=self.device)
        path_cfg = self.path_config(training=True)
        for v in views:
            g = Gaussians(**{k: p.detach().clone().requires_grad_(k == "diffuse") for k, p in self.params.items()})
            self.backend.update(g)
            rays = self.batches.view(v)
            primary = self.backend.trace(rays.origins, rays.dirs, g)  # blending weights: not shaded (diffuse_lobe)
            seen = primary.diffuse[:, 0].sum()
            if reflections:
                out = trace_paths(self.backend.trace, rays.origins, rays.dirs, g, path_cfg, self.generator,
                                  primary=primary)
                seen = seen + out.specular[:, 0].sum()
            (grad,) = torch.autograd.grad(seen, g.diffuse, allow_unused=True)
            if grad is not None:
                acc += grad[:, 0]
        return acc / max(len(views), 1)

    def _free_rows(self) -> torch.Tensor:
        """[N] bool: the Gaussians no fill placed (the initialisation's): not a prior, a mirror fill's, fixed, the
        far field's or a capped emitter."""
        return ~(self.prior | self.reflected | self.fixed | self.far | torch.isfinite(self.scale_cap))

    def prune(self) -> int:
        """Remove the Gaussians whose blending weight, averaged over ALL the training views, is below the threshold
        (``prune_min_weight``), the prior's excepted. A pruning step traces ``prune_views`` of them, the next
        block of one random cycle through the views, and each Gaussian remembers its mean weight over the last
        ``ceil(views / prune_views)`` blocks (``prune_memory`` [N, blocks], NaN where not measured yet): it goes
        only once those blocks have covered every view. Drawing the views anew at each step and pruning on them
        alone removed what only a few views see whenever none of them was drawn (zoo_lamps: the table lamp, seen
        by roughly a third of the 24 views (estimated from the orbit), vanished between two runs that differed in nothing it depends on, and the test view
        facing it lost 3.2 dB)."""
        n_all = len(self.rays.views)
        n_views = min(self.config.prune_views, n_all)
        blocks = -(-n_all // n_views)
        if self._prune_order is None:
            self._prune_order = torch.randperm(n_all, generator=self.generator)
        start = (self._prune_round % blocks) * n_views
        views = self._prune_order[torch.arange(start, start + n_views) % n_all].tolist()
        self._prune_round += 1
        height = self.rays.views[0].camera.height
        threshold = self.config.prune_min_weight * (height / REFERENCE_HEIGHT) ** 2
        reflections = self.reflections and self.step >= self.config.warmup
        weights = self.blending_weights(views, reflections)
        if self.prune_memory.shape[1] != blocks:
            self.prune_memory = torch.full((len(weights), blocks), float("nan"), device=weights.device)
        self.prune_memory = torch.cat([self.prune_memory[:, 1:], weights[:, None]], dim=1)
        measured = ~torch.isnan(self.prune_memory).any(dim=1)
        low = measured & (self.prune_memory.nan_to_num(0.0).mean(dim=1) < threshold)
        keep = ~low | self.prior
        if self.config.prune_hidden:
            # the initialisation's Gaussians that every camera's view of the room hides (seen_by_cameras): what
            # reflections alone train, with nothing to hold their depth, floaters for a new view
            free = torch.nonzero(self._free_rows() & keep).reshape(-1)
            size = self.params["log_scales"].detach()[free].amax(dim=1).exp()
            hidden = free[~seen_by_cameras(self.params["means"].detach()[free], size, self.rays.views).to(free.device)]
            keep[hidden] = False
            self.pruned_hidden += len(hidden)
        removed = int((~keep).sum())
        if removed and keep.any():
            self._replace(keep=keep)
        return removed

    @torch.no_grad()
    def _decide_hole_fill(self) -> bool:
        """Whether the model renders with ``PathConfig.hole_fill`` (``ReconstructConfig.hole_fill``; auto: where the
        trained model's training views are opaque, models/reconstruction/hole_fill.py). Decided once, logged."""
        if self.hole_fill is None:
            share = None
            if self.config.hole_fill == "auto":
                valid = self.rays.mask.nonzero().reshape(-1)
                rows = self.batches.sample(valid[strided(len(valid))])
                g = self.gaussians()
                self.backend.update(g)
                share = open_share(self.backend.trace, rows.origins, rows.dirs, g)
            self.hole_fill, why = decide_hole_fill(self.config.hole_fill, share)
            log.info("%s", why)
            self.decisions.append(why)
        return self.hole_fill

    def settings(self) -> ModelSettings:
        """How the trained model renders (stored as its model.yaml): this run's tracer and path settings, the hole
        fill decided on the trained model (``_decide_hole_fill``) and the config's values of the render-only path
        settings (``RENDER_ONLY_PATH``: the grazing offset, the rule for a normal met from behind; training keeps
        fixed ones)."""
        path = dataclasses.replace(self.path_config(), hole_fill=self._decide_hole_fill(),
                                   **{k: getattr(self.config, k) for k in RENDER_ONLY_PATH})
        return ModelSettings(tracer=self.config.tracer, path=path, units=self.units,
                             training={"config_hash": config_hash(to_dict(self.config, runtime=False)), "steps": self.step,
                                       "gaussians": len(self.params["means"])})

    # ----------------------------------------------------------------- checkpoints
    def fingerprint(self) -> dict:
        """What decides the result of a run: the config (without runtime and logging-only keys) and the
        digests of its inputs. A checkpoint resumes only a run with the same fingerprint."""
        config = to_dict(self.config, runtime=False)
        for key in RESUME_IGNORED:
            config.pop(key, None)
        return {"config": config, "inputs": dict(self.inputs)}

    def resume_mismatch(self, state: dict) -> str | None:
        """Why the checkpoint ``state`` cannot be resumed by this run (None when it can)."""
        theirs = state.get("fingerprint")
        if theirs is None:
            return "it records no config (written by an older version)"
        ours = self.fingerprint()
        differences = [f"{key}: {a!r} -> {b!r}" for key, a, b in _flat_differences(theirs["config"], ours["config"])]
        differences += [f"{name} changed" for name in sorted(set(theirs["inputs"]) | set(ours["inputs"]))
                        if theirs["inputs"].get(name) != ours["inputs"].get(name)]
        if not differences:
            return None
        more = f" (+{len(differences) - 4} more)" if len(differences) > 4 else ""
        return "it was written under another config: " + "; ".join(differences[:4]) + more

    def state_dict(self) -> dict:
        return {
            "fingerprint": self.fingerprint(),
            "step": self.step,
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "far_field_added": self.far_field_added,
            "plane_fill_relit": self.plane_fill_relit,
            "path_length": self.path_length,
            "anchors": self.anchors.state_dict(),
            "prior": self.prior.clone(),
            "reflected": self.reflected.clone(),
            "fixed": self.fixed.clone(),
            "far": self.far.clone(),
            "scale_cap": self.scale_cap.clone(),
            "prune_order": self._prune_order, "prune_round": self._prune_round,
            "pruned_hidden": self.pruned_hidden,
            "prune_memory": self.prune_memory.clone(),
            "thickness_box": self._thickness_box,
            "stereo_rays": self.stereo_rays,
        }

    def load_state_dict(self, state: dict) -> None:
        self.step = self.finite_at = state["step"]  # (a checkpoint is written only after a finiteness check)
        self.far_field_added = state["far_field_added"]
        self.plane_fill_relit = state.get("plane_fill_relit", self.far_field_added)
        # checkpoints from before the decision trained with the config's length once reflections were on
        past_warmup = self.reflections and state["step"] > self.config.warmup
        self.path_length = state.get("path_length", self.config.max_path_length if past_warmup else None)
        self.params = {k: v.to(self.device).clone().requires_grad_(True) for k, v in state["params"].items()}
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        self.prior = state.get("prior", torch.zeros(len(self.params["means"]), dtype=torch.bool)).to(self.device)
        self.reflected = state.get("reflected", torch.zeros_like(self.prior)).to(self.device)
        self.fixed = state.get("fixed", torch.zeros_like(self.prior)).to(self.device)
        self.far = state.get("far", torch.zeros_like(self.prior)).to(self.device)
        self.scale_cap = state.get("scale_cap", torch.full((len(self.prior),), math.inf)).to(self.device)
        self._capped_rows = None
        self._prune_order, self._prune_round = state.get("prune_order"), state.get("prune_round", 0)
        self.pruned_hidden = int(state.get("pruned_hidden", 0))
        self._thickness_box = state.get("thickness_box")
        self.stereo_rays = state.get("stereo_rays")
        if self.stereo_rays is not None:
            self.stereo_rays = tuple(a.to(self.device) for a in self.stereo_rays)
        self.prune_memory = state.get("prune_memory", torch.zeros((len(self.prior), 0))).to(self.device)
        self._prior_rows = self._reflected_rows = self._fixed_rows = self._far_rows = None
        self.anchors = Anchors(self.device, self.params["means"].dtype)
        if "anchors" in state:
            self.anchors.load_state_dict(state["anchors"])

    def _cached_rows(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Rows of ``prior`` and of ``reflected`` (and ``self._fixed_rows``), found again only after they change
        (_replace, load_state_dict reset all three: no device read-back per step)."""
        if self._prior_rows is None:
            self._prior_rows = torch.nonzero(self.prior).reshape(-1)
            self._reflected_rows = torch.nonzero(self.reflected).reshape(-1)
            self._fixed_rows = torch.nonzero(self.fixed).reshape(-1)
        return self._prior_rows, self._reflected_rows

    def _prior_smooth(self) -> torch.Tensor:
        """Mean L1 between each prior Gaussian's diffuse colour and the mean of its 8 nearest priors' on the same
        surface (``surface_neighbours``; plane-fill Gaussians: their geometry is frozen, so the neighbours are found
        once; pruning never removes them and appended Gaussians go after them, so the priors keep their order)."""
        rows = self._cached_rows()[0]
        if self._prior_nbrs is None or len(self._prior_nbrs) != len(rows):
            # the fill's Gaussians are round; their normal is the one they were made with (their plane's, a
            # sphere's radial one), which the normal loss never sees (no view looks at them)
            pos, normals = (self.params[k].detach()[rows].double().cpu().numpy() for k in ("means", "normals"))
            idx = surface_neighbours(pos, normals, PRIOR_NEIGHBOURS)
            self._prior_nbrs = torch.as_tensor(idx, device=rows.device)
        c = self.params["diffuse"].index_select(0, rows)
        if self._prior_nbrs.shape[1] == 0:
            return c.sum() * 0
        # index_select, not fancy indexing: its backward is an index_add, not a sort (5.3 -> 3.7 ms per step on
        # the demo's 20k priors, CPU)
        nbrs = c.index_select(0, self._prior_nbrs.reshape(-1)).reshape(*self._prior_nbrs.shape, 3)
        return (c - nbrs.mean(1)).abs().mean()

    def _freeze_priors(self) -> None:
        """The prior's Gaussians (plane_fill.py) keep their place, size and orientation on the plane: their geometry
        gradients are zeroed (Adam's moments stay 0, so they never move). Reflections alone pin down no depth:
        trained free they swelled into blobs (zoo_corridor: a floor Gaussian grew 1 m tall). Their colour,
        material and opacity train; the sphere completion's (``fixed``) keep everything they were made with: a
        ball's far side is seen only in what it reflects, and trained free it turned see-through (zoo_spheres:
        opacity 0.9 -> a median 0.16-0.30 on the four balls), showing the backs of the seen half's surfels.

        With ``fill_matte``, the mirror fills' Gaussians (``reflected``) keep the matte material they were made
        with: the buffers see only what the cameras face, so nothing but the reflections' colour would set their
        F0 and roughness, and that fits a shiny Gaussian in the air as well as a matte one on the wall
        (zoo_mirror_only: mirror-stereo Gaussians in front of the urn became F0 0.45, roughness 0.26, 0.8 m
        across, and the test views looking at the urn saw reflections in the air)."""
        self._cached_rows()
        frozen = [(self._prior_rows, ("means", "quats", "log_scales")), (self._fixed_rows, tuple(self.params))]
        if self.config.fill_matte:
            frozen.append((self._reflected_rows, ("f0", "roughness")))
        for rows, names in frozen:
            if len(rows) == 0:
                continue
            for name in names:
                grad = self.params[name].grad
                if grad is not None:
                    grad.index_fill_(0, rows, 0.0)

    def _skip_non_finite(self) -> None:
        """Flag, on the device (no read-back), the parameters whose gradient holds NaN / Inf, and make this step's
        Adam update a no-op if any does (the fused Adam's ``found_inf``: parameters, moments and step counts stay),
        so a bad gradient never reaches the parameters, hence the tracer. ``check_finite`` reads the flags."""
        flags = torch.zeros(len(self.params), device=self.device)
        for i, p in enumerate(self.params.values()):
            if p.grad is not None:  # GradScaler's check; the gradient is multiplied by 1 (unchanged)
                torch._amp_foreach_non_finite_check_and_unscale_([p.grad], flags[i], self._one)
        self._nonfinite += flags
        found = flags.amax()
        if all(group.get("fused") for group in self.optimizer.param_groups):  # (a loaded state may say otherwise)
            self.optimizer.found_inf = found
        elif found.item():  # the multi-tensor Adam takes no found_inf: a read-back, then no gradient, no update
            self.optimizer.zero_grad(set_to_none=True)

    def check_finite(self) -> None:
        """Raise FloatingPointError if a step since the last check had a non-finite gradient (its update was
        skipped) or a parameter holds NaN / Inf: one read-back, every FINITE_CHECK_EVERY steps and before a
        checkpoint is written (not per step)."""
        n = len(self.params)
        params_finite = torch.stack([torch.isfinite(p).all() for p in self.params.values()]).to(self._nonfinite)
        values = torch.cat([self._nonfinite, 1 - params_finite]).tolist()
        problems = []
        bad_grads = [f"{name} ({int(c)} steps)" for name, c in zip(self.params, values[:n]) if c]
        if bad_grads:
            problems.append(f"non-finite gradient in {', '.join(bad_grads)} since step {self.finite_at} (those "
                            "Adam updates were skipped)")
        bad_params = [name for name, c in zip(self.params, values[n:]) if c]
        if bad_params:
            problems.append(f"non-finite values in {', '.join(bad_params)}")
        if problems:
            raise FloatingPointError(f"step {self.step}: " + "; ".join(problems))
        self.finite_at = self.step

    def save_checkpoint(self, path: Path) -> None:
        self.check_finite()
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
        torch.save(self.state_dict(), tmp)
        os.replace(tmp, path)

    @staticmethod
    def read_checkpoint(path: Path) -> dict:
        # on the CPU: a checkpoint written on a GPU reads anywhere; load_state_dict moves it to the trainer's device
        return torch.load(path, weights_only=False, map_location="cpu")

    def load_checkpoint(self, path: Path) -> None:
        self.load_state_dict(self.read_checkpoint(path))


# depth errors are measured in units of (scene size / DEPTH_UNIT_SIZE): metres in a 4 x 2.5 x 4 m room (the
# paper's synthetic rooms, whose diagonal is ~6 m), and the same loss whatever a capture's scale
DEPTH_UNIT_SIZE = 6.0


def surface_neighbours(pos: np.ndarray, normals: np.ndarray, k: int, max_angle_deg: float = 30.0,
                       candidates: int = 4) -> np.ndarray:
    """[N, k] indices of each point's k nearest points on its own surface: among its ``candidates`` x k nearest,
    those whose normal is within ``max_angle_deg`` of its own (either sign) and that lie within that angle of its
    tangent plane (a zero normal passes both tests); rows with fewer fill up with the point itself (which adds
    nothing to a pull toward the mean). Without it the fill's colour smoothness averaged across a room's corners:
    zoo_corridor's metal walls (true diffuse 0) took the ceiling's and the floor's (their fill's diffuse: 0.001 at
    the end of warm-up, 0.03-0.075 after training; 0.012-0.052 with neighbours on their own wall, the rest is the
    reflections'). Adam moves a parameter whose only gradient is this term at full speed."""
    n = len(pos)
    if n < 2 or k <= 0:
        return np.zeros((n, 0), dtype=np.int64)
    q = min(candidates * k + 1, n)
    _, idx = cKDTree(pos).query(pos, k=q)
    idx = np.asarray(idx, dtype=np.int64).reshape(n, q)[:, 1:]
    length = np.linalg.norm(normals, axis=-1)
    known = length > 0.5
    unit = normals / np.maximum(length, 1e-12)[:, None]
    offset = pos[idx] - pos[:, None]
    along = np.abs(np.einsum("nqc,nc->nq", offset, unit))
    in_plane = ~known[:, None] | (along <= np.sin(np.radians(max_angle_deg)) * np.linalg.norm(offset, axis=-1))
    parallel = ~known[:, None] | ~known[idx] | (np.abs(np.einsum("nqc,nc->nq", unit[idx], unit))
                                                 >= np.cos(np.radians(max_angle_deg)))
    ok = in_plane & parallel
    # the first k that pass, in order of distance (stable sort on "fails")
    order = np.argsort(~ok, axis=1, kind="stable")[:, :k]
    picked = np.take_along_axis(idx, order, 1)
    passed = np.take_along_axis(ok, order, 1)
    out = np.where(passed, picked, np.arange(n)[:, None])
    if out.shape[1] < k:
        out = np.concatenate([out, np.repeat(np.arange(n)[:, None], k - out.shape[1], 1)], 1)
    return out


def in_front_of(traced: TraceOutput, free: torch.Tensor) -> torch.Tensor:
    """[R] how far each ray's expected depth, given that it ends (``TraceOutput.opacity``), falls in front of
    ``free`` [R] (0 behind it), on the rays that mostly end (opacity >= 0.5; 0 on the others: their depth says
    little). Differentiable: what blends in front of ``free`` is pushed back or made clearer."""
    opacity = traced.opacity().reshape(-1)
    ahead = (free - traced.depth.reshape(-1) / opacity).clamp_min(0.0)
    return torch.where(opacity >= 0.5, ahead, 0.0)


def scene_size(gaussians: Gaussians) -> float:
    """Diagonal of the box holding the middle 98% of the Gaussians' centres along each axis (robust to SfM
    outliers); the length every threshold of the reconstruction is a fraction of."""
    means = gaussians.means.detach().cpu().double()
    if len(means) < 2:
        raise ValueError("the initial Gaussians are fewer than 2: no scene size to measure")
    lo, hi = torch.quantile(means, 0.01, dim=0), torch.quantile(means, 0.99, dim=0)
    size = float((hi - lo).norm())
    if not size > 0:
        raise ValueError("the initial Gaussians all sit at one point: no scene size to measure")
    return size


PATH_DECISION_RAYS = 8192  # training rays traced to decide the path length (_decide_path_length)
# how a run reports, what only its model.yaml says (the hole fill: decided after training) and what acts only after
# the last step on what the steps trained (the sphere snap), not what the steps train
RESUME_IGNORED = ("log_every", "checkpoint_every", "hole_fill", "sphere_snap")


def _flat_differences(a: dict, b: dict, prefix: str = "") -> list[tuple[str, object, object]]:
    """(dotted key, a's value, b's value) for every key whose value differs between two nested mappings."""
    out = []
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key), b.get(key)
        if isinstance(x, dict) and isinstance(y, dict):
            out += _flat_differences(x, y, f"{prefix}{key}.")
        elif x != y:
            out.append((f"{prefix}{key}", x, y))
    return out


def _mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error in float64 on the tensors' device (as models.metrics.image.psnr). # [] float64"""
    return (pred.detach().double() - target.detach().double().reshape(pred.shape)).square().mean()


def train(trainer: Trainer, out_dir: Path, progress: bool = True,
          on_step: Callable[[dict], None] | None = None, until: int | None = None) -> dict:
    """Run to ``config.iterations`` (or stop early at step ``until``, checkpointing there), resuming from
    the trainer's step; logs JSON lines and checkpoints."""
    from tqdm import tqdm

    cfg = trainer.config
    out_dir.mkdir(parents=True, exist_ok=True)
    log_path = out_dir / "train_log.jsonl"
    start = time.perf_counter()
    bar = tqdm(total=cfg.iterations, initial=trainer.step, disable=not progress, desc="reconstruct", unit="step")
    metrics: dict = {}
    with log_path.open("a") as log_file:
        end = cfg.iterations if until is None else min(until, cfg.iterations)
        while trainer.step < end:
            metrics = trainer.train_step()
            metrics["time_s"] = round(time.perf_counter() - start, 3)
            bar.update(1)
            bar.set_postfix(loss=f"{metrics['loss']:.4f}", psnr_d=f"{metrics['psnr_diffuse']:.1f}",
                            n=metrics["gaussians"], refresh=False)
            if trainer.step % cfg.log_every == 0 or trainer.step == cfg.iterations or "pruned" in metrics:
                log_file.write(json.dumps(metrics) + "\n")
                log_file.flush()
            if trainer.step % cfg.checkpoint_every == 0 or trainer.step == end:
                trainer.save_checkpoint(out_dir / "checkpoints" / "last.pt")
            if on_step:
                on_step(metrics)
    bar.close()
    if trainer.step >= cfg.iterations and trainer.pruned_hidden:
        message = (f"pruning: {trainer.pruned_hidden} of the initialisation's Gaussians went where every training "
                   "camera's view of the room hides them (prune_hidden)")
        log.info("%s", message)
        trainer.decisions.append(message)
    if trainer.step >= cfg.iterations and cfg.sphere_snap:
        trainer.snap_spheres()
        metrics["gaussians"] = len(trainer.gaussians())
    if trainer.step >= cfg.iterations and cfg.back_fill:
        trainer.fill_backs()
        metrics["gaussians"] = len(trainer.gaussians())
    return metrics
