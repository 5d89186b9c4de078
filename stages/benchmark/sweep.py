"""Speed / accuracy sweep: what each knob costs in time and buys in PSNR, on one captured scene.

Two kinds of points:

* training points retrain the scene from its dense init with one knob changed from the base schedule
  (max path length, training resolution, voxel size = number of Gaussians, kernel p, transmittance
  threshold) and are scored by rendering the test views at the base render settings;
* render points reuse the base model and change only render-time knobs (samples per pixel with and
  without the denoiser, max path length, replay k, transmittance threshold).

Every point records wall time (training; rendering per test view), PSNR per layer on the test views
(linear, as ``evaluate``), and the Gaussian count. The Pareto front (no other point both faster and
better in final PSNR) gives the recommended settings.
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

from models.capture import Capture, View
from models.capture.camera import Camera
from models.tracer import Tracer, TracerConfig
from stages.evaluate.evaluate import evaluate_renders
from stages.init.dense import InitConfig, dense_init
from stages.reconstruct.config import ReconstructConfig
from stages.reconstruct.trainer import Trainer, train
from stages.render.render import RenderConfig, render_view, write_layers


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
    test_views: int = 2  # test views scored per point (render time is per view)

    @classmethod
    def quick(cls) -> "SweepGrid":
        """A smoke-test grid (CI): one value per knob."""
        return cls(path_length=[1], train_downsample=[2], voxel_scale=[2.0], kernel_p=[], train_transmittance=[],
                   spp=[1, 4], render_k=[8], render_transmittance=[0.05], test_views=1)


def downsample_view(view: View, factor: int) -> View:
    """The view at 1/``factor`` resolution: buffers box-filtered over factor x factor pixels (normals
    renormalised, the mask kept only where all pixels were valid, depth averaged over valid pixels), the
    camera's intrinsics scaled so every low-resolution pixel sees the centre of its block."""
    if factor == 1:
        return view
    cam = view.camera
    h, w = cam.height // factor, cam.width // factor
    if h < 1 or w < 1:
        raise ValueError(f"view {view.name!r}: {cam.width}x{cam.height} is too small to downsample by {factor}")

    def pool(a: np.ndarray) -> np.ndarray:
        a = a[:h * factor, :w * factor]
        return a.reshape(h, factor, w, factor, -1).mean(axis=(1, 3))

    bufs = {}
    valid = np.ones((cam.height, cam.width, 1), np.float32)
    if "mask" in view.buffers:
        valid = valid * (view.buffers["mask"] > 0.5)
    if "depth" in view.buffers:
        valid = valid * (view.buffers["depth"] > 0)
    cover = pool(valid)
    for layer, arr in view.buffers.items():
        if layer == "mask":
            bufs[layer] = (cover > 0.999).astype(np.float32)
        elif layer == "depth":
            bufs[layer] = (pool(arr * valid) / np.maximum(cover, 1e-8)).astype(np.float32)
        elif layer == "normal":
            n = pool(arr)
            bufs[layer] = (n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)).astype(np.float32)
        else:
            bufs[layer] = pool(arr).astype(np.float32)
    if "depth" in bufs and "mask" not in bufs:
        bufs["mask"] = (cover > 0.999).astype(np.float32)
    camera = Camera(w, h, cam.fl_x / factor, cam.fl_y / factor, cam.cx / factor, cam.cy / factor, cam.c2w)
    return View(view.name, camera, view.split, bufs)


def downsample_train(capture: Capture, factor: int) -> Capture:
    """``capture`` with its training views at 1/``factor`` resolution (test views unchanged)."""
    views = [downsample_view(v, factor) if v.split == "train" else v for v in capture.views]
    return Capture(views, capture.meta)


def score(capture: Capture, gaussians, render_cfg: RenderConfig, tracer_cfg: TracerConfig, device: str,
          test_views: int, work: Path) -> dict:
    """Render ``test_views`` test views and compare with the ground truth: PSNR per layer and seconds per view."""
    tracer = Tracer(tracer_cfg, device=device)
    try:
        tracer.update(gaussians)
        views = capture.split("test")[:test_views]
        generator = torch.Generator().manual_seed(render_cfg.seed)
        render_view(tracer.trace, views[0].camera, gaussians, RenderConfig(spp=1, denoise=False), generator)  # warm
        seconds = []
        for view in views:
            t0 = time.perf_counter()
            img = render_view(tracer.trace, view.camera, gaussians, render_cfg, generator)
            seconds.append(time.perf_counter() - t0)
            write_layers(work, view.name, img)
    finally:
        tracer.close()
    sub = Capture(views, capture.meta)
    mean = evaluate_renders(sub, work)["mean"]
    return {"render_s_per_view": float(np.mean(seconds)),
            **{f"psnr_{layer}": mean[f"psnr_{layer}"] for layer in ("diffuse", "specular", "final")}}


def _train(capture: Capture, init_cfg: InitConfig, recon: ReconstructConfig, device: str, work: Path):
    t0 = time.perf_counter()
    init, _ = dense_init(capture, init_cfg)
    tracer = Tracer(TracerConfig(kernel_p=recon.kernel_p, transmittance_threshold=recon.transmittance_threshold,
                                 num_threads=recon.threads), device=device)
    try:
        trainer = Trainer(capture, init, recon, tracer)
        train(trainer, work, progress=False)
        gaussians = trainer.gaussians().to()
    finally:
        tracer.close()
    return gaussians, time.perf_counter() - t0


def run_sweep(capture: Capture, config: dict, grid: SweepGrid, device: str = "cpu",
              progress: Callable[[str], None] = print, work_dir: Path | None = None) -> dict:
    """All points of ``grid`` around the scene's merged ``config`` (its init / reconstruct / render sections)."""
    base_init = dict(config.get("init", {}))
    base_recon = dict(config.get("reconstruct", {}))
    base_render = dict(config.get("render", {}))
    base_render.update(path_views=0, video=False)
    base_render.setdefault("spp", RenderConfig.spp)
    recon_base = ReconstructConfig.from_dict(base_recon)
    training = [("base", {}, {}, 1)]
    training += [(f"train path {n}", {"max_path_length": n}, {}, 1) for n in grid.path_length
                 if n != recon_base.max_path_length]
    training += [(f"train res 1/{f}", {}, {}, f) for f in grid.train_downsample if f != 1]
    voxel = base_init.get("voxel_fraction", InitConfig.voxel_fraction)
    training += [(f"voxel x{s:g}", {}, {"voxel_fraction": voxel * s}, 1) for s in grid.voxel_scale if s != 1]
    training += [(f"kernel p {p}", {"kernel_p": p}, {}, 1) for p in grid.kernel_p if p != recon_base.kernel_p]
    training += [(f"train T {t:g}", {"transmittance_threshold": t}, {}, 1) for t in grid.train_transmittance
                 if t != recon_base.transmittance_threshold]
    points = []
    tmp = tempfile.TemporaryDirectory(prefix="sweep_") if work_dir is None else None
    work = Path(tmp.name) if tmp else Path(work_dir)
    try:
        # untimed warm-up: Warp kernel compilation / cache load would otherwise be charged to the first point
        _train(capture, InitConfig.from_dict(base_init),
               ReconstructConfig.from_dict({**base_recon, "iterations": 2, "warmup": 1, "prune_from": 10**9}),
               device, work / "warmup")
        base_model = None
        for i, (name, recon_over, init_over, factor) in enumerate(training):
            progress(f"[{i + 1}/{len(training)}] training: {name}")
            recon = ReconstructConfig.from_dict({**base_recon, **recon_over})
            train_capture = downsample_train(capture, factor) if factor > 1 else capture
            gaussians, seconds = _train(train_capture, InitConfig.from_dict({**base_init, **init_over}), recon,
                                        device, work / f"train_{i}")
            if name == "base":
                base_model = gaussians
            render_cfg = RenderConfig.from_dict({**base_render, "max_path_length": recon.max_path_length})
            tracer_cfg = TracerConfig(kernel_p=recon.kernel_p, transmittance_threshold=recon.transmittance_threshold,
                                      num_threads=recon.threads)
            result = score(capture, gaussians, render_cfg, tracer_cfg, device, grid.test_views, work / f"eval_{i}")
            points.append({"name": name, "group": "training", "train_s": round(seconds, 2),
                           "gaussians": len(gaussians), **result})
            progress(f"    {points[-1]['train_s']:.0f} s, final {result['psnr_final']:.2f} dB")
        renders = []
        for spp in grid.spp:
            for dn in (True, False):
                renders.append((f"spp {spp}{' +dn' if dn else ''}", {"spp": spp, "denoise": dn}, {}))
        renders += [(f"render path {n}", {"max_path_length": n}, {}) for n in grid.path_length]
        renders += [(f"k {k}", {}, {"k": k}) for k in grid.render_k]
        renders += [(f"render T {t:g}", {}, {"transmittance_threshold": t}) for t in grid.render_transmittance]
        for j, (name, render_over, tracer_over) in enumerate(renders):
            progress(f"[{j + 1}/{len(renders)}] rendering: {name}")
            render_cfg = RenderConfig.from_dict({**base_render, **render_over})
            tracer_cfg = TracerConfig(**{"kernel_p": recon_base.kernel_p, "num_threads": recon_base.threads,
                                         "transmittance_threshold": recon_base.transmittance_threshold,
                                         **tracer_over})
            result = score(capture, base_model, render_cfg, tracer_cfg, device, grid.test_views, work / f"r_{j}")
            points.append({"name": name, "group": "render", "gaussians": len(base_model), **result})
    finally:
        if tmp:
            tmp.cleanup()
    return {"points": points, "recommended": recommend(points), "base": {
        "init": base_init, "reconstruct": base_recon, "render": base_render}, "device": device,
        "test_views": grid.test_views}


def recommend(points: list[dict], tolerance_db: float = 0.5) -> list[dict]:
    """Settings derived from the Pareto fronts: per group, the fastest point within ``tolerance_db`` of the
    best final PSNR ("balanced"), the best ("quality"), and the fastest on the front ("fastest")."""
    from stages.report.figures import pareto_front

    out = []
    for group, cost in (("training", "train_s"), ("render", "render_s_per_view")):
        pts = [p for p in points if p["group"] == group and p.get(cost) is not None]
        if not pts:
            continue
        front = pareto_front(pts, cost, "psnr_final")
        best = max(pts, key=lambda p: p["psnr_final"])
        balanced = next(p for p in front if p["psnr_final"] >= best["psnr_final"] - tolerance_db)
        for role, p in (("fastest", front[0]), ("balanced", balanced), ("quality", best)):
            out.append({"group": group, "role": role, "name": p["name"], cost: p[cost],
                        "psnr_final": p["psnr_final"]})
    return out


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


def sweep_report(result: dict, title: str) -> str:
    """HTML: the Pareto plots (time vs PSNR per layer), the table, the recommended settings."""
    from stages.report.figures import pareto_plot
    from stages.report.html import esc, page, table

    parts = [f"<h1>{esc(title)}</h1>", "<p class=\"note\">Each training point retrains the scene with one knob "
             "changed from the base schedule; each render point re-renders the base model. Dashed: the Pareto "
             "front (no other point both faster and better). Test views scored: "
             f"{result['test_views']}; device: {esc(result['device'])}.</p>"]
    for group, cost in (("training", "train_s"), ("render", "render_s_per_view")):
        pts = [p for p in result["points"] if p["group"] == group]
        if pts:
            uri = pareto_plot(pts, cost, ["psnr_diffuse", "psnr_specular", "psnr_final"])
            parts.append(f"<h2>{group}: {cost} vs PSNR</h2><img class=\"plot\" src=\"{uri}\" alt=\"{group} pareto\">")
    parts.append("<h2>Points</h2>" + table(
        ["point", "group", "train s", "render s/view", "Gaussians", "PSNR diffuse", "PSNR specular", "PSNR final"],
        [[p["name"], p["group"], p.get("train_s"), p["render_s_per_view"], p["gaussians"], p["psnr_diffuse"],
          p["psnr_specular"], p["psnr_final"]] for p in result["points"]], left=2))
    parts.append("<h2>Recommended settings</h2>" + table(
        ["group", "role", "point", "seconds", "PSNR final"],
        [[r["group"], r["role"], r["name"], r.get("train_s", r.get("render_s_per_view")), r["psnr_final"]]
         for r in result["recommended"]], left=3))
    return page(title, "\n".join(parts))


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

