"""Render speed of a model: frames per second at 1 sample per pixel, whole path and primary segment alone."""

from __future__ import annotations

import time

import numpy as np
import torch

from models.capture import Camera
from models.tracer import Tracer
from models.trained import load_model

from .render import RenderConfig, render_view


def measure_fps(model: str, camera: Camera, max_path_length: int | None = None, device: str = "cpu",
                threads: int = 2, repeats: int = 3) -> dict:
    """Frames per second rendering ``camera`` at 1 sample per pixel without the denoiser: the whole path
    (primary + reflection segments; ``max_path_length`` None = the model's) and the primary segment alone.
    Median of ``repeats`` timed frames after one warm-up frame (kernel compilation, BVH build)."""
    gaussians, settings = load_model(model)
    tracer = Tracer(settings.tracer_config(threads), device=device)
    try:
        tracer.update(gaussians)
        out = {"fps_resolution": [camera.width, camera.height]}
        for key, length in (("fps_1spp", max_path_length), ("fps_primary", 1)):
            cfg = RenderConfig(spp=1, antialias=1, max_path_length=length, denoise=False, path_views=0, video=False)
            generator = torch.Generator().manual_seed(0)
            times = []
            for _ in range(repeats + 1):
                t0 = time.perf_counter()
                render_view(tracer.trace, camera, gaussians, cfg, generator, settings.path)
                times.append(time.perf_counter() - t0)
            out[key] = round(1.0 / float(np.median(times[1:])), 3)
        return out
    finally:
        tracer.close()
