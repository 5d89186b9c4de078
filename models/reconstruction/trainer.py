"""Optimisation of ONE Gaussian scene: diffuse + G-buffer losses on the first segment, specular on paths.

Paper Eq. 4-7 with the reference schedule: L1 losses in linear space, warm-up with
primary rays only, then reflections (and far-field Gaussians when reflections can
see past the captured geometry), Adam with per-parameter learning rates,
exponential position decay, pruning by accumulated blending weight, clamps.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from models.capture import Capture
from models.capture.layers import GBUFFER, RADIANCE
from models.gaussians import Gaussians
from models.metrics.image import psnr
from models.pathtrace.paths import PathConfig, trace_paths
from models.settings import config_hash, to_dict
from models.tracer.output import TraceOutput
from models.trained import ModelSettings

from .config import ReconstructConfig
from .data import RaySet, build_rayset
from .far_field import far_field_gaussians
from .mirror_stereo import mirror_stereo_gaussians
from .reflection_fill import highlight_fill_gaussians, mirror_rays, reflection_fill_gaussians

log = logging.getLogger("models.reconstruction")

PARAM_LR = {  # Gaussians field -> LearningRates field
    "means": "position_init", "quats": "rotation", "log_scales": "scale", "opacity_logits": "opacity",
    "diffuse": "diffuse", "normals": "normal", "roughness": "roughness", "f0": "f0",
}
REFERENCE_HEIGHT = 768  # image height the reference pruning threshold is stated at


class Backend:
    """What the trainer needs from a tracer: refit/rebuild on new parameters, then differentiable traces."""

    def update(self, gaussians: Gaussians) -> None: ...

    def trace(self, origins: torch.Tensor, dirs: torch.Tensor, gaussians: Gaussians) -> TraceOutput: ...


class Trainer:
    def __init__(self, capture: Capture, init: Gaussians, config: ReconstructConfig, backend: Backend):
        self.config = config
        self.backend = backend
        self.rays: RaySet = build_rayset(capture, "train", config.radiance_clamp)
        self.extent = capture.camera_extent()
        self.units = capture.meta.units
        self.centre = np.mean([v.camera.origin for v in self.rays.views], axis=0)
        self.decisions: list[str] = []
        self.weights = self._active_losses()
        self.reflections = self._needs_reflections()
        self.far_field = self._needs_far_field(init)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.step = 0
        self.far_field_added = False
        self.params = {k: v.detach().clone().requires_grad_(True) for k, v in init.params().items()}
        self.optimizer = self._make_optimizer()
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
        self.decisions.append(f"reflections: on after step {self.config.warmup}, "
                              f"max path length {self.config.max_path_length}")
        return True

    def _needs_far_field(self, init: Gaussians) -> bool:
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
        if escaped > self.config.far_field_escape:
            self.decisions.append(
                f"far field: on, {escaped:.1%} of mirror-like reflection rays leave the initial geometry"
            )
            return True
        self.decisions.append(
            f"far field: off, closed scene ({escaped:.1%} of mirror-like reflection rays escape the initial geometry)"
        )
        return False

    @torch.no_grad()
    def _escaping_reflections(self, init: Gaussians, max_rays: int = 16384) -> float:
        """Fraction of perfect-mirror reflections of shiny training pixels (F0 > 0.3, roughness < 0.3, from the
        buffers) that hit none of the initial Gaussians: what reflections would see beyond the captured geometry.
        (Not a transmittance test: initial Gaussians are faint, opacity 0.1, so walls are semi-transparent.)"""
        found = mirror_rays(self.rays, max_rays)
        if found is None:
            return 0.0
        x, r, _ = found
        out = self.backend.trace(x + 0.01 * r, r, init)
        return float((out.hit_count.reshape(-1) == 0).float().mean())

    # ----------------------------------------------------------------- parameters
    def gaussians(self) -> Gaussians:
        return Gaussians(**self.params)

    def _make_optimizer(self) -> torch.optim.Adam:
        groups = [{"params": [p], "name": k, "lr": self._base_lr(k)} for k, p in self.params.items()]
        return torch.optim.Adam(groups, eps=self.config.adam_eps)

    def _base_lr(self, name: str) -> float:
        lr = getattr(self.config.lr, PARAM_LR[name])
        return lr * self.extent if name == "means" else lr

    def position_lr(self, step: int) -> float:
        lr = self.config.lr
        t = min(step / max(self.config.iterations, 1), 1.0)
        return self.extent * math.exp((1 - t) * math.log(lr.position_init) + t * math.log(lr.position_final))

    def _replace(self, keep: torch.Tensor | None = None, extra: Gaussians | None = None) -> None:
        """Prune (``keep`` [N] bool) and/or append ``extra`` Gaussians, keeping Adam's state aligned."""
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
                add = getattr(extra, name).to(value.dtype)
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
    def _clamp(self) -> None:
        self.params["diffuse"].clamp_(min=0.0)
        self.params["roughness"].clamp_(0.0, 1.0)
        self.params["f0"].clamp_(0.0, 1.0)

    # ----------------------------------------------------------------- steps
    def sample_batch(self) -> RaySet:
        n = self.config.rays_per_step
        if n <= 0:
            view = int(torch.randint(len(self.rays.views), (1,), generator=self.generator))
            return self.rays.view_rays(view)
        return self.rays.subset(torch.randint(len(self.rays), (n,), generator=self.generator))

    def losses(self, batch: RaySet, reflections: bool) -> tuple[torch.Tensor, dict]:
        g = self.gaussians()
        self.backend.update(g)
        path_cfg = self.config.path() if reflections else PathConfig(max_path_length=1, sampler=self.config.sampler)
        out = trace_paths(self.backend.trace, batch.origins, batch.dirs, g, path_cfg, self.generator)
        terms = {}
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
            if layer in GBUFFER:  # G-buffer values exist only where the ray hits geometry
                err = err[m] if m.any() else err[:0]
            terms[layer] = w * err.mean() if err.numel() else pred.sum() * 0
        total = sum(terms.values())
        metrics = {f"loss_{k}": v.item() for k, v in terms.items()}
        metrics["loss"] = total.item()
        metrics["psnr_diffuse"] = psnr(out.primary.diffuse.detach(), batch.targets["diffuse"])
        if reflections and "specular" in batch.targets:
            metrics["psnr_specular"] = psnr(out.specular.detach(), batch.targets["specular"])
        return total, metrics

    def _add_fill(self, fill: Gaussians | None, stats: dict, message: str) -> None:
        """Append a fill's Gaussians (if any), log ``message % stats`` and keep it among the decisions (with
        each of ``stats["notes"]``: what a fill could not decide well)."""
        if fill is not None:
            self._replace(extra=fill)
        log.info("step %d: added %s", self.step, message % stats)
        self.decisions.append(f"step {self.step}: added {message % stats}")
        for note in stats.get("notes", ()):
            log.warning("step %d: %s", self.step, note)
            self.decisions.append(f"step {self.step}: {note}")

    def train_step(self) -> dict:
        cfg = self.config
        reflections = self.reflections and self.step >= cfg.warmup
        if reflections and self.far_field and not self.far_field_added:
            # the fills look at the captured scene alone: its box, and its transmittance (not the far shell's)
            scene = self.gaussians()
            ff = far_field_gaussians(cfg.far_field_count, self.centre, self.extent, cfg.seed)
            self._replace(extra=ff)
            self.far_field_added = True
            log.info("step %d: added %d far-field Gaussians", self.step, len(ff))
            if cfg.reflection_fill_count > 0:
                self._add_fill(*reflection_fill_gaussians(self.rays, self.backend.trace, scene,
                                                          cfg.reflection_fill_count, seed=cfg.seed),
                               "%(added)d Gaussians (%(unseen)d candidates unseen by the cameras) along "
                               "%(open_rays)d open mirror reflections (of %(mirror_rays)d mirror rays)")
            if cfg.mirror_stereo_count > 0:
                self._add_fill(*mirror_stereo_gaussians(self.rays, self.backend.trace, scene,
                                                        cfg.mirror_stereo_count, seed=cfg.seed),
                               "%(added)d Gaussians where the reflections of %(planes)d planar mirrors (in "
                               "%(planar_views)d views, %(pixels)d open mirror pixels; %(ignored)d curved or "
                               "non-planar shiny regions ignored) agree in depth (%(kept)d pixels matched)")
            if cfg.highlight_fill:
                self._add_fill(*highlight_fill_gaussians(self.rays, self.backend.trace, scene, seed=cfg.seed),
                               "%(added)d emitting Gaussians where %(highlight_rays)d open highlight reflections "
                               "(of %(mirror_rays)d mirror rays) end together (box scale %(box_scale).2f, searched "
                               "%(box_scale_range)s)")
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = self.position_lr(self.step)
        total, metrics = self.losses(self.sample_batch(), reflections)
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        for name, p in self.params.items():
            if p.grad is not None and not torch.isfinite(p.grad).all():
                raise FloatingPointError(f"step {self.step}: non-finite gradient in {name}")
        self.optimizer.step()
        self._clamp()
        self.step += 1
        if cfg.prune_every > 0 and self.step >= cfg.prune_from and self.step % cfg.prune_every == 0:
            metrics["pruned"] = self.prune()
        metrics["step"] = self.step
        metrics["gaussians"] = len(self.params["means"])
        return metrics

    def blending_weights(self, views: list[int], reflections: bool = False) -> torch.Tensor:
        """[N] accumulated blending weight per Gaussian, averaged over ``views`` (d sum(diffuse_R) / d diffuse_i,R);
        with ``reflections``, plus its weight in the traced reflections (d sum(specular_R) / d diffuse_i,R:
        bounce Gaussians are the radiance cache), so what the views see only in mirrors is kept too."""
        acc = torch.zeros(len(self.params["means"]))
        path_cfg = self.config.path()
        for v in views:
            g = Gaussians(**{k: p.detach().clone().requires_grad_(k == "diffuse") for k, p in self.params.items()})
            self.backend.update(g)
            rays = self.rays.view_rays(v)
            if reflections:
                out = trace_paths(self.backend.trace, rays.origins, rays.dirs, g, path_cfg, self.generator)
                seen = out.primary.diffuse[:, 0].sum() + out.specular[:, 0].sum()
            else:
                seen = self.backend.trace(rays.origins, rays.dirs, g).diffuse[:, 0].sum()
            (grad,) = torch.autograd.grad(seen, g.diffuse, allow_unused=True)
            if grad is not None:
                acc += grad[:, 0]
        return acc / max(len(views), 1)

    def prune(self) -> int:
        n_views = min(self.config.prune_views, len(self.rays.views))
        views = torch.randperm(len(self.rays.views), generator=self.generator)[:n_views].tolist()
        height = self.rays.views[0].camera.height
        threshold = self.config.prune_min_weight * (height / REFERENCE_HEIGHT) ** 2
        reflections = self.reflections and self.step >= self.config.warmup
        keep = self.blending_weights(views, reflections) >= threshold
        removed = int((~keep).sum())
        if removed and keep.any():
            self._replace(keep=keep)
        return removed

    def settings(self) -> ModelSettings:
        """How the trained model renders (stored as its model.yaml): this run's tracer and path settings."""
        return ModelSettings(tracer=self.config.tracer, path=self.config.path(), units=self.units,
                             training={"config_hash": config_hash(to_dict(self.config, runtime=False)), "steps": self.step,
                                       "gaussians": len(self.params["means"])})

    # ----------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        return {
            "step": self.step,
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "far_field_added": self.far_field_added,
        }

    def load_state_dict(self, state: dict) -> None:
        self.step = state["step"]
        self.far_field_added = state["far_field_added"]
        self.params = {k: v.clone().requires_grad_(True) for k, v in state["params"].items()}
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])

    def save_checkpoint(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
        torch.save(self.state_dict(), tmp)
        os.replace(tmp, path)

    def load_checkpoint(self, path: Path) -> None:
        self.load_state_dict(torch.load(path, weights_only=False))


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
    return metrics
