"""A capture at lower resolution: buffers box-filtered, intrinsics scaled (training-resolution trade-offs)."""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .types import Capture, View


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
