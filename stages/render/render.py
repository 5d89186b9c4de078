"""Render a trained scene: N samples per pixel of the reflection paths, denoised, every layer to EXR + PNG."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from models.capture import LAYER_CHANNELS, Camera
from models.capture.exr import write_exr_channels
from models.gaussians import Gaussians
from models.pathtrace.paths import PathConfig, trace_paths

from stages.config import reject_unknown

from .denoise import denoise


@dataclass
class RenderConfig:
    spp: int = 128  # reflection samples per pixel (the primary segment is deterministic: traced once)
    max_path_length: int = 3  # path segments (1 = no reflections)
    sampler: str = "vndf"  # vndf | ndf
    denoise: bool = True  # Intel Open Image Denoise on the specular layer (albedo = F0, normal guides)
    path_views: int = 24  # novel camera path: views interpolated through the test cameras (0 = none)
    video: bool = True  # also write the novel path as a video/GIF when imageio can
    batch_rays: int = 65536  # rays traced per call (memory bound)
    seed: int = 0

    @classmethod
    def from_dict(cls, d: dict) -> "RenderConfig":
        reject_unknown(cls, d, "render")
        return cls(**d)


@torch.no_grad()
def render_view(trace_fn, camera: Camera, gaussians: Gaussians, config: RenderConfig,
                generator: torch.Generator) -> dict[str, np.ndarray]:
    """Layers of one view as float32 [H, W, C]: final, diffuse, specular (denoised if on), specular_noisy,
    depth, normal, roughness, f0, transmittance, bounce<i> (mean contribution of reflection segment i)."""
    h, w = camera.height, camera.width
    dirs = torch.tensor(camera.ray_directions().reshape(-1, 3), dtype=torch.float32)
    origins = torch.tensor(camera.origin, dtype=torch.float32).expand_as(dirs).contiguous()
    path_cfg = PathConfig(max_path_length=config.max_path_length, sampler=config.sampler)
    layers: dict[str, list[np.ndarray]] = {}
    for start in range(0, len(dirs), config.batch_rays):
        o, d = origins[start:start + config.batch_rays], dirs[start:start + config.batch_rays]
        primary = trace_fn(o, d, gaussians)
        spec = torch.zeros((len(d), 3))
        bounces = [torch.zeros((len(d), 3)) for _ in range(config.max_path_length - 1)]
        for _ in range(config.spp if config.max_path_length > 1 else 0):
            out = trace_paths(trace_fn, o, d, gaussians, path_cfg, generator, primary=primary)
            spec += out.specular
            for i, b in enumerate(out.bounces):
                bounces[i] += b
        n = max(config.spp, 1)
        opacity = primary.opacity()
        chunk = {
            "diffuse": primary.diffuse,
            "specular_noisy": spec / n,
            "depth": primary.depth.reshape(-1, 1),
            "normal": torch.nn.functional.normalize(primary.normal, dim=-1),
            "roughness": (primary.roughness.reshape(-1, 1) / opacity).clamp(0, 1),
            "f0": (primary.f0 / opacity).clamp(0, 1),
            "transmittance": primary.transmittance.reshape(-1, 1),
            **{f"bounce{i + 1}": b / n for i, b in enumerate(bounces)},
        }
        for k, v in chunk.items():
            layers.setdefault(k, []).append(v.float().numpy())
    img = {k: np.concatenate(v).reshape(h, w, -1).astype(np.float32) for k, v in layers.items()}
    img["specular"] = img["specular_noisy"]
    if config.denoise and config.max_path_length > 1 and config.spp > 0:
        img["specular"] = np.maximum(denoise(img["specular_noisy"], albedo=img["f0"], normal=img["normal"]), 0)
    img["final"] = img["diffuse"] + img["specular"]
    return img


def write_layers(out_dir: Path, name: str, img: dict[str, np.ndarray]) -> None:
    """<out_dir>/<name>.exr with capture channel names (R,G,B = final) + <out_dir>/png/<name>_<layer>.png."""
    channels = {}
    names = {"final": "rgb"}
    for layer, arr in img.items():
        key = names.get(layer, layer)
        if key in LAYER_CHANNELS:
            chans = LAYER_CHANNELS[key]
        else:
            suffix = ("R", "G", "B") if arr.shape[-1] == 3 else ("Y",)
            chans = tuple(f"{layer}.{s}" for s in suffix)
        for i, c in enumerate(chans):
            channels[c] = arr[..., i]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_exr_channels(out_dir / f"{name}.exr", channels)
    png_dir = out_dir / "png"
    png_dir.mkdir(exist_ok=True)
    import imageio.v3 as iio

    for layer, arr in img.items():
        iio.imwrite(png_dir / f"{name}_{layer}.png", to_png(layer, arr))


def tonemap(x: np.ndarray) -> np.ndarray:
    """Linear radiance -> display [0, 1]: clamp then sRGB transfer curve (the PNGs and tonemapped metrics)."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def to_png(layer: str, arr: np.ndarray) -> np.ndarray:
    if layer == "normal":
        v = arr * 0.5 + 0.5
    elif layer == "depth":
        finite = arr[arr > 0]
        v = arr / (finite.max() if finite.size else 1.0)
    elif layer in ("roughness", "f0", "transmittance"):
        v = arr
    else:
        v = tonemap(arr)
    v = np.clip(v, 0, 1)
    if v.shape[-1] == 1:
        v = np.repeat(v, 3, axis=-1)
    return (v * 255 + 0.5).astype(np.uint8)


def camera_path(cameras: list[Camera], count: int) -> list[Camera]:
    """``count`` cameras interpolated through ``cameras`` (positions linearly, rotations by slerp), closed loop."""
    from scipy.spatial.transform import Rotation, Slerp

    if len(cameras) == 1 or count <= 0:
        return cameras[:max(count, 0)]
    keys = cameras + [cameras[0]]
    times = np.arange(len(keys), dtype=float)
    slerp = Slerp(times, Rotation.from_matrix(np.stack([c.c2w[:3, :3] for c in keys])))
    positions = np.stack([c.origin for c in keys])
    out = []
    for t in np.linspace(0, len(keys) - 1, count, endpoint=False):
        i = min(int(t), len(keys) - 2)
        c2w = np.eye(4)
        c2w[:3, :3] = slerp([t]).as_matrix()[0]
        c2w[:3, 3] = positions[i] + (t - i) * (positions[i + 1] - positions[i])
        ref = cameras[0]
        out.append(Camera(ref.width, ref.height, ref.fl_x, ref.fl_y, ref.cx, ref.cy, c2w))
    return out
