"""Typed in-memory form of a capture: views (camera + buffers + split) and provenance."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterable

import numpy as np

from .camera import Camera
from .errors import CaptureError
from .layers import LAYERS

SPLITS = ("train", "test")


@dataclass
class View:
    """One image of a capture. ``buffers``: layer name -> float32 ``[H, W, C]`` (see ``LAYERS``)."""

    name: str
    camera: Camera
    split: str
    buffers: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def check(self, where: str | None = None) -> None:
        """Raise CaptureError unless split, camera and every buffer are valid."""
        where = where or f"view {self.name!r}"
        if self.split not in SPLITS:
            raise CaptureError(f"{where}: unknown split {self.split!r} (expected one of {', '.join(SPLITS)})")
        self.camera.check(where)
        for layer, arr in self.buffers.items():
            check_buffer(where, layer, arr, self.camera.height, self.camera.width)


def check_buffer(where: str, layer: str, arr: np.ndarray, height: int, width: int) -> None:
    """Raise CaptureError unless ``arr`` is a finite float32 ``[height, width, C]`` buffer of ``layer``."""
    if layer not in LAYERS:
        raise CaptureError(f"{where}: unknown layer {layer!r} (known: {', '.join(LAYERS)})")
    want = LAYERS[layer]
    if arr.ndim != 3 or arr.shape[2] != want:
        raise CaptureError(f"{where}: layer {layer!r} must have {want} channel(s), got array of shape {arr.shape}")
    if arr.shape[:2] != (height, width):
        raise CaptureError(
            f"{where}: layer {layer!r} is {arr.shape[1]}x{arr.shape[0]} but transforms.json says {width}x{height}"
        )
    if arr.dtype != np.float32:
        raise CaptureError(f"{where}: layer {layer!r} must be float32, got {arr.dtype}")
    bad = ~np.isfinite(arr)
    if bad.any():
        y, x, c = np.argwhere(bad)[0]
        raise CaptureError(
            f"{where}: layer {layer!r} has {int(bad.any(axis=2).sum())} pixel(s) with NaN/Inf "
            f"(first at x={x}, y={y}, value {arr[y, x, c]})"
        )


@dataclass
class CaptureMeta:
    """Provenance (``capture.yaml``): where the buffers come from and the scene's scale."""

    source: str = "synthetic"  # synthetic | colmap | network | paper | ...
    color_space: str = "linear"  # linear radiance (HDR)
    extent: float | None = None  # radius of the sphere bounding the cameras, scene units
    units: str = "meters"
    extra: dict[str, Any] = field(default_factory=dict)  # free-form provenance (spp, timings, ...)


@dataclass
class Capture:
    views: list[View]
    meta: CaptureMeta = field(default_factory=CaptureMeta)

    @property
    def layers(self) -> list[str]:
        """Layers present in every view, in canonical order."""
        return [l for l in LAYERS if self.views and all(l in v.buffers for v in self.views)]

    def split(self, name: str) -> list[View]:
        if name not in SPLITS:
            raise ValueError(f"unknown split {name!r} (expected one of {', '.join(SPLITS)})")
        return [v for v in self.views if v.split == name]

    def require_complete(self, split: str, layers: Iterable[str]) -> None:
        """Raise CaptureError naming the ``split`` views that lack one of ``layers`` while other views of the split
        have it: a layer in some views only is a broken capture, not a capture without that layer."""
        views = self.split(split)
        for layer in layers:
            lacking = [v.name for v in views if layer not in v.buffers]
            if lacking and len(lacking) < len(views):
                shown = ", ".join(lacking[:8]) + (f", ... ({len(lacking)} in all)" if len(lacking) > 8 else "")
                raise CaptureError(f"the {layer!r} buffer is missing from {len(lacking)} of {len(views)} {split} "
                                   f"view(s) ({shown}) but present in the others: give it to every {split} view "
                                   "or to none")

    def camera_extent(self) -> float:
        """Radius of the sphere around the camera centres' mean that bounds them (3DGS scene extent), x1.1."""
        centres = np.stack([v.camera.origin for v in self.views])
        return float(1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max())

    def check(self) -> None:
        names = [v.name for v in self.views]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise CaptureError(f"capture has duplicate view names: {sorted(dup)}")
        for v in self.views:
            v.check()
