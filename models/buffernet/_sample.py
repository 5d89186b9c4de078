"""The common training sample of the buffer network's dataset readers, and the geometry helpers they share.

Conventions of every reader's output (``BufferSample``):

* ``rgb``: linear HDR radiance ``[H, W, 3]`` float32 (non-finite input pixels are zeroed and masked out).
* ``diffuse`` / ``specular``: linear radiance ``[H, W, 3]``, ``rgb ~= diffuse + specular``.
* ``normal``: unit ``[H, W, 3]`` in CAMERA space, OpenGL convention (x right, y up, z toward the
  viewer), oriented toward the camera (``n . to_camera >= 0``).
* ``depth``: planar z-depth ``[H, W]`` in metres (positive; the camera-space point is at z = -depth).
* ``roughness``: perceptual GGX roughness ``[H, W]`` in [0, 1]; ``f0``: ``[H, W, 3]`` in [0, 1].

A buffer a source does not provide is absent from ``buffers`` (and ``masks``). Invalid pixels of a
present buffer are 0 and False in its mask.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models.capture.layers import PREDICTED, channels

# Buffer names in the network's prompt order, and their channel counts (models/capture/layers.py).
BUFFER_CHANNELS: dict[str, int] = channels(PREDICTED)


class DatasetError(ValueError):
    """A dataset folder does not have the expected layout (the message names the file or folder)."""


@dataclass
class BufferSample:
    """One training image with its ground-truth buffers (see the module docstring for conventions)."""

    rgb: np.ndarray  # [H, W, 3] float32, linear HDR
    buffers: dict[str, np.ndarray] = field(default_factory=dict, repr=False)  # name -> [H, W, 3] or [H, W]
    masks: dict[str, np.ndarray] = field(default_factory=dict, repr=False)  # name -> [H, W] bool
    name: str = ""  # source/scene/frame

    def check(self) -> None:
        """Raise AssertionError unless shapes, dtypes and finiteness follow the conventions (internal)."""
        h, w = self.rgb.shape[:2]
        assert self.rgb.shape == (h, w, 3) and self.rgb.dtype == np.float32, self.name
        assert np.isfinite(self.rgb).all(), self.name
        assert set(self.buffers) == set(self.masks) and set(self.buffers) <= set(BUFFER_CHANNELS), self.name
        for key, arr in self.buffers.items():
            shape = (h, w, 3) if BUFFER_CHANNELS[key] == 3 else (h, w)
            assert arr.shape == shape and arr.dtype == np.float32, (self.name, key, arr.shape)
            assert self.masks[key].shape == (h, w) and self.masks[key].dtype == bool, (self.name, key)
            assert np.isfinite(arr).all(), (self.name, key)


def pinhole_directions(height: int, width: int, fl_x: float, fl_y: float, cx: float | None = None,
                       cy: float | None = None) -> np.ndarray:
    """Camera-space (OpenGL) directions through pixel centres, z = -1: the ray toward pixel (u, v) is
    ((u + 0.5 - cx) / fl_x, -(v + 0.5 - cy) / fl_y, -1). # [H, W, 3] float64"""
    cx = width / 2 if cx is None else cx
    cy = height / 2 if cy is None else cy
    u = (np.arange(width, dtype=np.float64) + 0.5 - cx) / fl_x
    v = -(np.arange(height, dtype=np.float64) + 0.5 - cy) / fl_y
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv, -np.ones_like(uu)], axis=-1)


def distance_to_planar(distance: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance along the ray ``[H, W]`` -> planar z-depth, given camera-space ray directions ``[H, W, 3]``
    (any length, looking down -z). # [H, W]"""
    cos = -directions[..., 2] / np.linalg.norm(directions, axis=-1)
    return distance * cos


def orient_normals(normal: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit camera-space normals flipped toward the camera (``n . ray <= 0``), and the mask of usable ones
    (finite and non-zero). Unusable normals come back as 0. # ([H, W, 3] float32, [H, W] bool)"""
    n = np.where(np.isfinite(normal), normal, 0.0).astype(np.float64)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    valid = length[..., 0] > 1e-6
    n = np.where(valid[..., None], n / np.maximum(length, 1e-12), 0.0)
    facing_away = (n * directions).sum(-1) > 0
    n = np.where(facing_away[..., None], -n, n)
    return n.astype(np.float32), valid & np.isfinite(normal).all(-1)


def finalize(name: str, rgb: np.ndarray, buffers: dict[str, np.ndarray], masks: dict[str, np.ndarray],
             base: np.ndarray | None = None) -> BufferSample:
    """Assemble a BufferSample: float32, masks AND-ed with finiteness, ``base`` (pixels valid for every
    buffer) and the finiteness of ``rgb``; invalid pixels zeroed."""
    rgb = np.asarray(rgb, dtype=np.float32)
    rgb_ok = np.isfinite(rgb).all(-1)
    base = rgb_ok if base is None else (base & rgb_ok)
    out_b, out_m = {}, {}
    for key in BUFFER_CHANNELS:
        if key not in buffers:
            continue
        arr = np.asarray(buffers[key], dtype=np.float32)
        ok = base & masks[key] & (np.isfinite(arr).all(-1) if arr.ndim == 3 else np.isfinite(arr))
        out_b[key] = np.where(ok[..., None] if arr.ndim == 3 else ok, arr, 0.0).astype(np.float32)
        out_m[key] = ok
    rgb = np.where(rgb_ok[..., None], rgb, 0.0).astype(np.float32)
    return BufferSample(rgb=rgb, buffers=out_b, masks=out_m, name=name)
