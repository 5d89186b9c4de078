"""A synthetic capture built in memory for training benchmarks (no Mitsuba, no files): cameras inside a random
room of Gaussians (``room_gaussians``), whose buffers are the room traced by the Warp tracer itself (diffuse, G-buffer
from the first segment, specular from a 3-segment path), so every loss of the trainer has a target."""

from __future__ import annotations

import math

import numpy as np
import torch

from models.capture import Camera, Capture, CaptureMeta, View
from models.gaussians import Gaussians, room_gaussians
from models.pathtrace.paths import PathConfig, trace_paths


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world, OpenGL convention (looks down -Z, +Y up). # [4, 4] float64"""
    back = eye - target
    back = back / np.linalg.norm(back)
    up = np.array([0.0, 1.0, 0.0]) if abs(back[1]) < 0.95 else np.array([0.0, 0.0, 1.0])
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, eye
    return c2w


def room_cameras(n_views: int, width: int, height: int, seed: int = 0, fov_y_deg: float = 60.0) -> list[Camera]:
    """``n_views`` pinhole cameras at random points of the room's middle, each looking at a random point of it."""
    rng = np.random.default_rng(seed)
    fl = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    cams = []
    for _ in range(n_views):
        eye = rng.uniform(-0.4, 0.4, 3)
        target = eye + rng.normal(size=3)
        cams.append(Camera(width, height, fl, fl, width / 2, height / 2, look_at(eye, target)))
    return cams


@torch.no_grad()
def render_view(tracer, truth: Gaussians, camera: Camera, generator: torch.Generator) -> dict[str, np.ndarray]:
    """The buffers of one view of ``truth``: float32 [H, W, C] per layer."""
    h, w = camera.height, camera.width
    dirs = torch.tensor(camera.ray_directions().reshape(-1, 3), dtype=torch.float32)
    origins = torch.tensor(camera.origin, dtype=torch.float32).expand_as(dirs).contiguous()
    out = trace_paths(tracer.trace, origins, dirs, truth, PathConfig(max_path_length=3), generator)
    p = out.primary
    opacity = p.opacity()
    layers = {
        "diffuse": p.diffuse, "specular": out.specular, "depth": p.depth.reshape(-1, 1) / opacity,
        "normal": torch.nn.functional.normalize(p.normal, dim=1), "roughness": p.roughness.reshape(-1, 1) / opacity,
        "f0": p.f0 / opacity, "mask": (1.0 - p.transmittance.reshape(-1, 1) > 0.5).float(),
    }
    return {k: v.reshape(h, w, -1).float().numpy().astype(np.float32) for k, v in layers.items()}


def room_capture(tracer, n_gaussians: int, n_views: int, width: int, height: int,
                 seed: int = 0) -> tuple[Capture, Gaussians]:
    """(capture of a random room's ``n_views`` train views, an initialisation: another random room of the same
    size, so training has something to fit). ``tracer``: a models.tracer.Tracer on the CPU."""
    truth = room_gaussians(n_gaussians, torch.Generator().manual_seed(seed))
    truth.roughness = truth.roughness * 0.5  # shinier than uniform: reflections worth tracing
    generator = torch.Generator().manual_seed(seed)
    views = [View(f"v{i:03d}", cam, "train", render_view(tracer, truth, cam, generator))
             for i, cam in enumerate(room_cameras(n_views, width, height, seed))]
    init = room_gaussians(n_gaussians, torch.Generator().manual_seed(seed + 1))
    return Capture(views, CaptureMeta(source="synthetic", extent=1.0, extra={"benchmark": "train-step"})), init
