"""Speed / accuracy sweep: what each knob costs in time and buys in PSNR, on one captured scene.

Two kinds of points:

* training points retrain the scene from its dense init with one knob changed from the base schedule
  (max path length, training resolution, voxel size = number of Gaussians, kernel p, transmittance
  threshold); each is saved as a model folder (gaussians.ply + model.yaml) and scored by rendering the test
  views at the base render settings with the model's own settings, as the render stage would;
* render points reuse the base model and change only render-time knobs (samples per pixel with and
  without the denoiser, max path length, replay k, transmittance threshold, primary rays per pixel).

Every point records wall time (training; rendering per test view), PSNR per layer on the test views
(linear, as ``evaluate``), and the Gaussian count. The Pareto front (no other point both faster and
better in final PSNR) gives the recommended settings. The sweep writes JSON; ``python -m stages.report sweep``
draws it. Every step is the library the stages call (models/initialisation, models/reconstruction,
models/rendering, models/metrics).
"""

from __future__ import annotations

import copy
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from models.capture import Capture
from models.capture.resample import downsample_train
from models.initialisation import InitConfig, dense_init
from models.metrics import evaluate_renders, recommend
from models.reconstruction import ReconstructConfig, Trainer, train
from models.rendering import RenderConfig, render_view, write_layers
from models.tracer import Tracer
from models.trained import load_model, save_model
from stages.config import deep_merge


@dataclass
class SweepGrid:
    """The values tried for each knob (the base value of each is the scene config's)."""

    path_length: list[int] = field(default_factory=lambda: [1, 2, 3])
    train_downsample: list[int] = field(default_factory=lambda: [2])  # training resolution = full / factor
    voxel_scale: list[float] = field(default_factory=lambda: [2.0, 4.0])  # voxel size x factor (fewer Gaussians)
    kernel_p: list[int] = field(default_factory=lambda: [2])
    train_transmittance: list[float] = field(default_factory=lambda: [0.05])
    spp: list[int] = field(default_factory=lambda: [1, 4, 16, 64, 128])
    render_k: list[int] = field(default_factory=lambda: [4, 8, 32])
    render_transmittance: list[float] = field(default_factory=lambda: [0.001, 0.05, 0.1])
    antialias: list[int] = field(default_factory=lambda: [1, 16])  # primary rays per pixel (render.antialias)
    test_views: int = 2  # test views scored per point (render time is per view)

    @classmethod
    def quick(cls) -> "SweepGrid":
        """A smoke-test grid (CI): one value per knob."""
        return cls(path_length=[1], train_downsample=[2], voxel_scale=[2.0], kernel_p=[], train_transmittance=[],
                   spp=[1, 4], render_k=[8], render_transmittance=[0.05], antialias=[1], test_views=1)


def render_and_evaluate(capture: Capture, model: Path, render_cfg: RenderConfig, device: str, test_views: int | None,
                        work: Path, tracer_over: dict | None = None, regions: dict | None = None,
                        warm_up: bool = True) -> tuple[dict, list[float]]:
    """Render the first ``test_views`` (None: all) test views of the model folder ``model`` (its tracer / path
    settings, with ``tracer_over`` on top) into ``work`` and score them as ``evaluate`` does (``evaluate_renders``
    with ``regions``); returns (its scores, seconds per view; ``warm_up``: an untimed 1-spp render first)."""
    gaussians, settings = load_model(model)
    tracer = Tracer(settings.tracer_config(**(tracer_over or {})), device=device)
    views = capture.split("test")[:test_views]
    try:
        tracer.update(gaussians)
        generator = torch.Generator().manual_seed(render_cfg.seed)
        if warm_up:
            render_view(tracer.trace, views[0].camera, gaussians, RenderConfig(spp=1, antialias=1, denoise=False),
                        generator, settings.path)
        seconds = []
        for view in views:
            t0 = time.perf_counter()
            img = render_view(tracer.trace, view.camera, gaussians, render_cfg, generator, settings.path)
            seconds.append(time.perf_counter() - t0)
            write_layers(work, view.name, img)
    finally:
        tracer.close()
    return evaluate_renders(Capture(views, capture.meta), work, regions=regions), seconds


def score(capture: Capture, model: Path, render_cfg: RenderConfig, device: str, test_views: int, work: Path,
          tracer_over: dict | None = None) -> dict:
    """Render ``test_views`` test views of the model folder ``model`` (its tracer / path settings, with
    ``tracer_over`` on top) and compare with the ground truth: PSNR per layer and seconds per view."""
    scores, seconds = render_and_evaluate(capture, model, render_cfg, device, test_views, work, tracer_over)
    mean = scores["mean"]
    return {"render_s_per_view": float(np.mean(seconds)),
            **{f"psnr_{layer}": mean[f"psnr_{layer}"] for layer in ("diffuse", "specular", "final")}}


def train_model(capture: Capture, init_cfg: InitConfig, recon: ReconstructConfig, device: str, work: Path):
    """Dense init + reconstruction into the model folder ``work``; returns (model folder, Gaussians, seconds)."""
    t0 = time.perf_counter()
    init, _ = dense_init(capture, init_cfg)
    tracer = Tracer(recon.tracer, device=device)
    try:
        trainer = Trainer(capture, init, recon, tracer)
        train(trainer, work, progress=False)
        save_model(work, trainer.gaussians(), trainer.settings())
        count = len(trainer.params["means"])
    finally:
        tracer.close()
    return work, count, time.perf_counter() - t0


def training_points(grid: SweepGrid, base_recon: dict, base_init: dict) -> list[tuple[str, dict, dict, int]]:
    """(name, reconstruct overrides, init overrides, training downsample factor) of every training point."""
    recon = ReconstructConfig.from_dict(base_recon)
    points = [("base", {}, {}, 1)]
    # exactly n segments: the limit at n too (else the path-length decision may lengthen it where mirrors face)
    points += [(f"train path {n}", {"max_path_length": n, "max_path_length_limit": n}, {}, 1) for n in grid.path_length
               if n != recon.max_path_length]
    points += [(f"train res 1/{f}", {}, {}, f) for f in grid.train_downsample if f != 1]
    voxel = base_init.get("voxel_fraction", InitConfig.voxel_fraction)
    points += [(f"voxel x{s:g}", {}, {"voxel_fraction": voxel * s}, 1) for s in grid.voxel_scale if s != 1]
    points += [(f"kernel p {p}", {"tracer": {"kernel_p": p}}, {}, 1) for p in grid.kernel_p
               if p != recon.tracer.kernel_p]
    points += [(f"train T {t:g}", {"tracer": {"transmittance_threshold": t}}, {}, 1)
               for t in grid.train_transmittance if t != recon.tracer.transmittance_threshold]
    return points


def render_points(grid: SweepGrid) -> list[tuple[str, dict, dict]]:
    """(name, render overrides, tracer overrides) of every render point."""
    points = [(f"spp {spp}{' +dn' if dn else ''}", {"spp": spp, "denoise": dn}, {})
              for spp in grid.spp for dn in (True, False)]
    points += [(f"render path {n}", {"max_path_length": n}, {}) for n in grid.path_length]
    points += [(f"k {k}", {}, {"k": k}) for k in grid.render_k]
    points += [(f"render T {t:g}", {}, {"transmittance_threshold": t}) for t in grid.render_transmittance]
    points += [(f"antialias {a}", {"antialias": a}, {}) for a in grid.antialias]
    return points


def run_sweep(capture: Capture, config: dict, grid: SweepGrid, device: str = "cpu",
              progress: Callable[[str], None] = print, work_dir: Path | None = None) -> dict:
    """All points of ``grid`` around the scene's merged ``config`` (its init / reconstruct / render sections)."""
    base_init = dict(config.get("init", {}))
    base_recon = dict(config.get("reconstruct", {}))
    base_render = dict(config.get("render", {}))
    base_render.update(path_views=0, video=False)
    base_render.setdefault("spp", RenderConfig.spp)
    training = training_points(grid, base_recon, base_init)
    points = []
    tmp = tempfile.TemporaryDirectory(prefix="sweep_") if work_dir is None else None
    work = Path(tmp.name) if tmp else Path(work_dir)
    try:
        # untimed warm-up: Warp kernel compilation / cache load would otherwise be charged to the first point
        train_model(capture, InitConfig.from_dict(base_init),
                    ReconstructConfig.from_dict({**base_recon, "iterations": 2, "warmup": 1, "prune_from": 10**9}),
                    device, work / "warmup")
        base_model = base_count = None
        for i, (name, recon_over, init_over, factor) in enumerate(training):
            progress(f"[{i + 1}/{len(training)}] training: {name}")
            recon = ReconstructConfig.from_dict(deep_merge(base_recon, recon_over))
            train_capture = downsample_train(capture, factor) if factor > 1 else capture
            init_cfg = InitConfig.from_dict({**base_init, **init_over})
            model, count, seconds = train_model(train_capture, init_cfg, recon, device, work / f"train_{i}")
            if name == "base":
                base_model, base_count = model, count
            # the model's own path length and tracer settings (model.yaml), as the render stage renders it
            render_cfg = RenderConfig.from_dict({**base_render, "max_path_length": None, "sampler": None})
            result = score(capture, model, render_cfg, device, grid.test_views, work / f"eval_{i}")
            points.append({"name": name, "group": "training", "train_s": round(seconds, 2), "gaussians": count,
                           **result})
            progress(f"    {points[-1]['train_s']:.0f} s, final {result['psnr_final']:.2f} dB")
        renders = render_points(grid)
        for j, (name, render_over, tracer_over) in enumerate(renders):
            progress(f"[{j + 1}/{len(renders)}] rendering: {name}")
            render_cfg = RenderConfig.from_dict({**base_render, **render_over})
            result = score(capture, base_model, render_cfg, device, grid.test_views, work / f"r_{j}", tracer_over)
            points.append({"name": name, "group": "render", "gaussians": base_count, **result})
    finally:
        if tmp:
            tmp.cleanup()
    return {"points": points, "recommended": recommend(points), "base": {
        "init": base_init, "reconstruct": base_recon, "render": base_render}, "device": device,
        "test_views": grid.test_views}


def format_table(result: dict) -> str:
    rows = [f"{'point':<20} {'group':<9} {'train s':>8} {'render s/view':>13} {'Gaussians':>9} "
            f"{'PSNR diff':>9} {'PSNR spec':>9} {'PSNR final':>10}"]
    for p in result["points"]:
        train_s = f"{p['train_s']:.1f}" if "train_s" in p else "-"
        rows.append(f"{p['name']:<20} {p['group']:<9} {train_s:>8} {p['render_s_per_view']:>13.3f} "
                    f"{p['gaussians']:>9} {p['psnr_diffuse']:>9.2f} {p['psnr_specular']:>9.2f} "
                    f"{p['psnr_final']:>10.2f}")
    rows.append("recommended:")
    for r in result["recommended"]:
        cost = r.get("train_s", r.get("render_s_per_view"))
        rows.append(f"  {r['group']:<9} {r['role']:<9} {r['name']:<20} {cost:8.2f} s  final {r['psnr_final']:.2f} dB")
    return "\n".join(rows)


def config_for_sweep(config: dict, iterations: int | None) -> dict:
    """The scene config with the training schedule shortened to ``iterations`` (warm-up, pruning and
    checkpoints scaled by the same fraction)."""
    config = copy.deepcopy(config)
    if iterations:
        rec = config.setdefault("reconstruct", {})
        full = rec.get("iterations", ReconstructConfig.iterations)
        f = iterations / full
        rec["iterations"] = iterations
        for key, default in (("warmup", ReconstructConfig.warmup), ("prune_every", ReconstructConfig.prune_every),
                             ("prune_from", ReconstructConfig.prune_from)):
            rec[key] = max(1, int(round(rec.get(key, default) * f)))
        rec["checkpoint_every"] = iterations
    return config
