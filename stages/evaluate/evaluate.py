"""Compare renders with ground truth per layer (diffuse, specular, final) on the test split.

Ground truth "final" is diffuse + specular: the light sources seen directly
(the capture's ``emission`` layer) are not part of the reconstructed scene.
Metrics are reported in linear space (radiance clamped to [0, 1], peak 1) and
after the display tonemap of the PNGs (clamp + sRGB curve), which is what
image comparisons in papers use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.capture import Capture, read_view_buffers
from stages.render.render import tonemap

from .metrics import psnr, ssim

LAYERS = ("diffuse", "specular", "final")


def measure_fps(model_path: Path, camera, max_path_length: int, device: str = "cpu", threads: int = 2,
                repeats: int = 3) -> dict:
    """Frames per second rendering ``camera`` at 1 sample per pixel without the denoiser: the whole path
    (primary + ``max_path_length`` - 1 reflection segments) and the primary segment alone. Median of
    ``repeats`` timed frames after one warm-up frame (kernel compilation, BVH build)."""
    import time

    import torch

    from models.gaussians import read_ply
    from models.tracer import Tracer, TracerConfig
    from stages.render.render import RenderConfig, render_view

    gaussians = read_ply(model_path)
    tracer = Tracer(TracerConfig(num_threads=threads), device=device)
    try:
        tracer.update(gaussians)
        out = {"fps_resolution": [camera.width, camera.height]}
        for key, length in (("fps_1spp", max_path_length), ("fps_primary", 1)):
            cfg = RenderConfig(spp=1, max_path_length=length, denoise=False, path_views=0, video=False)
            generator = torch.Generator().manual_seed(0)
            times = []
            for _ in range(repeats + 1):
                t0 = time.perf_counter()
                render_view(tracer.trace, camera, gaussians, cfg, generator)
                times.append(time.perf_counter() - t0)
            out[key] = round(1.0 / float(np.median(times[1:])), 3)
        return out
    finally:
        tracer.close()


def region_mask(view, box_min, box_max) -> np.ndarray:
    """[H, W] bool: pixels whose ground-truth surface point (camera + ray x depth) lies in the world box."""
    points = view.camera.origin + view.camera.ray_directions() * view.buffers["depth"].astype(np.float64)
    inside = np.all((points >= np.asarray(box_min)) & (points <= np.asarray(box_max)), axis=-1)
    if "mask" in view.buffers:
        inside &= view.buffers["mask"][..., 0] > 0.5
    return inside


def evaluate_renders(capture: Capture, renders: Path, regions: dict | None = None) -> dict:
    """Per-view and mean metrics; ``regions``: name -> {min: [x, y, z], max: [x, y, z]} world boxes, each
    scored (PSNR per layer, linear) on the pixels whose ground-truth surface lies inside it."""
    per_view = {}
    for view in capture.split("test"):
        exr = renders / f"{view.name}.exr"
        if not exr.is_file():
            raise FileNotFoundError(f"render of test view {view.name!r} missing: {exr}")
        pred = read_view_buffers(exr, view.camera.height, view.camera.width)
        gt = {"diffuse": view.buffers["diffuse"], "specular": view.buffers["specular"]}
        gt["final"] = gt["diffuse"] + gt["specular"]
        pred = {"diffuse": pred["diffuse"], "specular": pred["specular"], "final": pred["rgb"]}
        row = {}
        for layer in LAYERS:
            p, t = np.clip(pred[layer], 0, 1), np.clip(gt[layer], 0, 1)
            row[f"psnr_{layer}"] = psnr(p, t)
            row[f"ssim_{layer}"] = ssim(p, t)
            row[f"psnr_{layer}_tonemapped"] = psnr(tonemap(pred[layer]), tonemap(gt[layer]))
            row[f"ssim_{layer}_tonemapped"] = ssim(tonemap(pred[layer]), tonemap(gt[layer]))
        for name, box in (regions or {}).items():
            m = region_mask(view, box["min"], box["max"])
            row[f"{name}_pixels"] = int(m.sum())
            for layer in LAYERS:
                if m.any():
                    row[f"{name}_psnr_{layer}"] = psnr(np.clip(pred[layer], 0, 1), np.clip(gt[layer], 0, 1), m)
        per_view[view.name] = row
    keys = dict.fromkeys(k for r in per_view.values() for k in r)
    mean = {k: float(np.mean([r[k] for r in per_view.values() if k in r])) for k in keys}
    return {"mean": mean, "views": per_view, "lpips": "not computed: LPIPS needs network weights that cannot be fetched here"}
