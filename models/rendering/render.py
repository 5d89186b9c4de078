"""Render a trained scene: N samples per pixel of the reflection paths, denoised, every layer as float32 images.

The path settings (max path length, sampler) are the model's (``models/trained.py``); ``RenderConfig`` may
override them for one render (the sweep's render-time knobs, the viewer's path-length switch).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from models.capture import Camera
from models.gaussians import Gaussians
from models.pathtrace.brdf import DIFFUSE_LOBES, FRESNEL_MODES
from models.pathtrace.paths import BACK_NORMALS, REFLECTION_ORIGINS, PathConfig, shade_diffuse, trace_paths
from models.settings import from_dict, setting

from .denoise import denoise
from .images import write_layers


@dataclass
class RenderConfig:
    """Rendering settings (the ``render`` config section)."""

    spp: int = setting(128, "reflection samples per pixel (the primary segment is deterministic: traced once)",
                       minimum=0)
    max_path_length: int | None = setting(None, "path segments (1 = no reflections); null = the model's "
                                          "(model.yaml)", minimum=1, maximum=16)
    sampler: str | None = setting(None, "vndf | ndf; null = the model's (model.yaml)", enum=["vndf", "ndf", None])
    fresnel: str | None = setting(None, "schlick_f90 | schlick | dielectric; null = the model's (model.yaml)",
                                  enum=[*FRESNEL_MODES, None])
    reflection_origin: str | None = setting(None, "front | expected (where a reflection starts: "
                                            "reconstruct.reflection_origin); null = the model's (model.yaml)",
                                            enum=[*REFLECTION_ORIGINS, None])
    diffuse_lobe: str | None = setting(None, "lambert | disney (reconstruct.diffuse_lobe); null = the model's "
                                       "(model.yaml)", enum=[*DIFFUSE_LOBES, None])
    origin_grazing: float | None = setting(None, "the reflection start offset is divided by max(|cos|, this) "
                                           "(reconstruct.origin_grazing; 1 = fixed); null = the model's "
                                           "(model.yaml)", exclusiveMinimum=0, maximum=1)
    hole_fill: bool | None = setting(None, "true | false: a ray's blended diffuse divided by its opacity (the "
                                     "transmittance left at its end takes the colour it blended: "
                                     "reconstruct.hole_fill); null = the model's (model.yaml)")
    back_normal: str | None = setting(None, "flip | mirror: the normal a reflection takes where a ray meets the "
                                      "back of what was reconstructed (reconstruct.back_normal); null = the "
                                      "model's (model.yaml)", enum=[*BACK_NORMALS, None])
    antialias: int = setting(4, "primary rays per pixel, on a stratified n x n grid of sub-pixel points (1 = the "
                             "pixel centre; 4 = 2 x 2, ...: a perfect square); the reflection samples are shared "
                             "out among them and every layer is their mean, as the ground truth's box filter",
                             enum=[n * n for n in range(1, 9)])
    denoise: bool = setting(True, "Intel Open Image Denoise on the specular layer (albedo = F0, normal guides)")
    path_views: int = setting(24, "novel camera path: views interpolated through the test cameras (0 = none)",
                              minimum=0)
    video: bool = setting(True, "also write the novel path as a video/GIF when imageio can")
    batch_rays: int = setting(65536, "rays traced per call (memory bound)", minimum=1)
    seed: int = setting(0, "sampler seed")

    @classmethod
    def from_dict(cls, d: dict) -> "RenderConfig":
        return from_dict(cls, d, "render")

    def path(self, model: PathConfig) -> PathConfig:
        """The model's path settings with this render's overrides."""
        over = {k: getattr(self, k) for k in ("max_path_length", "sampler", "fresnel", "reflection_origin",
                                               "diffuse_lobe", "hole_fill", "origin_grazing",
                                               "back_normal")
                if getattr(self, k) is not None}
        return dataclasses.replace(model, **over)


def subpixel_offsets(count: int) -> list[tuple[float, float]]:
    """The centres of a stratified n x n grid of sub-pixel points (n = sqrt(count)), as (column, row) offsets in
    the pixel; [(0.5, 0.5)] for 1."""
    n = math.isqrt(count)
    if n * n != count:
        raise ValueError(f"render.antialias={count}: expected a perfect square (1, 4, 9, 16, ...)")
    return [((i + 0.5) / n, (j + 0.5) / n) for j in range(n) for i in range(n)]


@torch.no_grad()
def render_view(trace_fn, camera: Camera, gaussians: Gaussians, config: RenderConfig, generator: torch.Generator,
                path: PathConfig) -> dict[str, np.ndarray]:
    """Layers of one view as float32 [H, W, C]: final, diffuse, specular (denoised if on), specular_noisy,
    depth, normal, roughness, f0, transmittance, bounce<i> (mean contribution of reflection segment i).
    ``path``: the model's path settings (``config`` may override them). With ``config.antialias`` > 1 each pixel
    traces that many primary rays (``subpixel_offsets``), the ``spp`` reflection samples are dealt out among them
    in turn, and each layer is the mean over the pixel's primaries (the specular: over all its samples)."""
    h, w = camera.height, camera.width
    offsets = subpixel_offsets(config.antialias)
    path_cfg = config.path(path)
    length = path_cfg.max_path_length
    spp = config.spp if length > 1 else 0
    layers: dict[str, torch.Tensor] = {}
    for k, offset in enumerate(offsets):
        share = spp // len(offsets) + (1 if k < spp % len(offsets) else 0)  # this primary's reflection samples
        dirs = torch.tensor(camera.ray_directions(offset).reshape(-1, 3), dtype=torch.float32)
        origins = torch.tensor(camera.origin, dtype=torch.float32).expand_as(dirs).contiguous()
        parts: dict[str, list[torch.Tensor]] = {}
        for start in range(0, len(dirs), config.batch_rays):
            o, d = origins[start:start + config.batch_rays], dirs[start:start + config.batch_rays]
            primary = trace_fn(o, d, gaussians)
            spec = torch.zeros((len(d), 3))
            bounces = [torch.zeros((len(d), 3)) for _ in range(length - 1)]
            for _ in range(share):
                out = trace_paths(trace_fn, o, d, gaussians, path_cfg, generator, primary=primary)
                spec += out.specular
                for i, b in enumerate(out.bounces):
                    bounces[i] += b
            opacity = primary.opacity()
            chunk = {
                "diffuse": shade_diffuse(primary, d, path_cfg).diffuse,
                "specular_sum": spec,
                "depth": primary.depth.reshape(-1, 1),
                "normal": torch.nn.functional.normalize(primary.normal, dim=-1),
                "roughness": (primary.roughness.reshape(-1, 1) / opacity).clamp(0, 1),
                "f0": (primary.f0 / opacity).clamp(0, 1),
                "transmittance": primary.transmittance.reshape(-1, 1),
                **{f"bounce_sum{i + 1}": b for i, b in enumerate(bounces)},
            }
            for key, v in chunk.items():
                parts.setdefault(key, []).append(v.float())
        for key, v in parts.items():
            v = torch.cat(v)
            layers[key] = v if key not in layers else layers[key] + v
    n, m = max(spp, 1), len(offsets)
    img = {}
    for key, v in layers.items():
        if key == "specular_sum":
            key, v = "specular_noisy", v / n
        elif key.startswith("bounce_sum"):
            key, v = "bounce" + key[len("bounce_sum"):], v / n
        else:
            v = v / m
        img[key] = v.numpy().reshape(h, w, -1).astype(np.float32)
    if m > 1:  # the mean of unit normals is shorter where they disagree: the layer stays unit length
        norm = np.linalg.norm(img["normal"], axis=-1, keepdims=True)
        img["normal"] = np.where(norm > 1e-8, img["normal"] / np.maximum(norm, 1e-8), 0.0).astype(np.float32)
    img["specular"] = img["specular_noisy"]
    if config.denoise and length > 1 and config.spp > 0:
        img["specular"] = np.maximum(denoise(img["specular_noisy"], albedo=img["f0"], normal=img["normal"]), 0)
    img["final"] = img["diffuse"] + img["specular"]
    return img


def render_views(tracer, views, gaussians: Gaussians, config: RenderConfig, path: PathConfig, out_dir: Path,
                 generator: torch.Generator | None = None, desc: str = "render",
                 progress: bool = True) -> dict[str, float]:
    """Render ``views`` (objects with ``.name`` and ``.camera``) into ``out_dir`` (EXR + png/) with one
    ``generator`` for the whole sequence (default: seeded with ``config.seed``); returns seconds per view."""
    if generator is None:
        generator = torch.Generator().manual_seed(config.seed)
    timings = {}
    for view in tqdm(views, desc=desc, unit="view", disable=not progress):
        t0 = time.perf_counter()
        img = render_view(tracer.trace, view.camera, gaussians, config, generator, path)
        timings[view.name] = round(time.perf_counter() - t0, 3)
        write_layers(out_dir, view.name, img)
    return timings
