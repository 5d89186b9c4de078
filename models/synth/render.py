"""Render every train / test view of a synthetic scene and write the capture."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from models.capture import Capture, CaptureMeta, View, write_capture

from .cameras import path_cameras
from .edits import apply_edits
from .integrator import render_view
from .mitsuba_scene import VARIANT, load_scene
from .spec import SynthSpec, parse_spec


def scene_views(spec: SynthSpec) -> list[tuple[str, str, object]]:
    """(name, split, Camera) of every view: train_000.., test_000.."""
    out = []
    for split, path in (("train", spec.train), ("test", spec.test)):
        for i, cam in enumerate(path_cameras(path, spec.resolution)):
            out.append((f"{split}_{i:03d}", split, cam))
    return out


def denoise_view(buffers: dict[str, np.ndarray], albedo: np.ndarray) -> dict[str, np.ndarray]:
    """Monte Carlo noise out of a rendered view (training data wants the noiseless image's buffers): Intel
    Open Image Denoise on ``diffuse`` with the first-hit colour and normal as guides, on ``specular`` without
    guides (what it shows is not the surface's colour), then ``rgb = diffuse + specular + emission`` so the
    capture's identity still holds. G-buffers are untouched."""
    from models.rendering.denoise import denoise

    out = dict(buffers)
    out["diffuse"] = np.maximum(denoise(buffers["diffuse"], albedo, buffers["normal"]), 0.0)
    out["specular"] = np.maximum(denoise(buffers["specular"]), 0.0)
    out["rgb"] = (out["diffuse"] + out["specular"] + buffers["emission"]).astype(np.float32)
    return out


def render_spec(spec: SynthSpec, *, progress: bool = True, scene_name: str | None = None,
                splits: tuple[str, ...] | None = None) -> Capture:
    """Render the views of ``spec`` (only those of ``splits`` if given) into an in-memory Capture. A view's
    sampler seed depends on its place among all views, so a subset renders exactly as in the full capture."""
    import drjit
    import mitsuba

    scene, materials = load_scene(spec)
    views, timings = [], {}
    t_all = time.perf_counter()
    todo = [(i, v) for i, v in enumerate(scene_views(spec)) if splits is None or v[1] in splits]
    for i, (name, split, cam) in tqdm(todo, desc="synth", unit="view", disable=not progress):
        t0 = time.perf_counter()
        buffers = render_view(scene, materials, cam, spec.spp, seed=spec.seed * 100_003 + i,
                              max_depth=spec.max_depth, spp_chunk=spec.spp_chunk)
        albedo = buffers.pop("albedo")  # a denoiser guide, not a capture layer
        if spec.denoise:
            buffers = denoise_view(buffers, albedo)
        timings[name] = round(time.perf_counter() - t0, 4)
        views.append(View(name=name, camera=cam, split=split, buffers=buffers))
    capture = Capture(views=views, meta=CaptureMeta(source="synthetic", color_space="linear", units="meters"))
    capture.meta.extent = capture.camera_extent() if views else None
    capture.meta.extra = {
        "scene": scene_name,
        "renderer": f"mitsuba {mitsuba.__version__} ({VARIANT}), drjit {drjit.__version__}, split path tracer",
        "spp": spec.spp,
        "max_depth": spec.max_depth,
        "resolution": list(spec.resolution),
        "seed": spec.seed,
        "emission_layer": "light seen directly by the camera; R,G,B = diffuse + specular + emission",
        "denoised": ("OIDN 'RT' on diffuse (albedo + normal guides) and specular (no guide); "
                     "rgb = their sum + emission") if spec.denoise else False,
        "gbuffer_filter": "box; depth/normal/roughness/f0 averaged over the pixel's hit samples, mask = hit fraction",
        "seconds_per_view": timings,
        "seconds_total": round(time.perf_counter() - t_all, 3),
        "mean_seconds_per_view": round(float(np.mean(list(timings.values()))), 4) if timings else None,
    }
    return capture


def render_capture(synth_cfg: dict, out_dir: Path, *, edits: list[dict] | None = None, progress: bool = True,
                   scene_name: str | None = None, splits: tuple[str, ...] | None = None) -> Capture:
    """Parse the ``synth:`` section, apply ``edits`` (a list of edit ops), render every view with a
    progress bar and write the capture to ``out_dir`` (atomically). Returns the Capture."""
    spec = apply_edits(parse_spec(synth_cfg), edits)
    capture = render_spec(spec, progress=progress, scene_name=scene_name, splits=splits)
    if edits:
        capture.meta.extra["edits"] = edits
    write_capture(capture, Path(out_dir))
    return capture
