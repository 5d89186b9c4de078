"""Camera paths of a synthetic scene -> ``models.capture.Camera`` (OpenGL / nerfstudio c2w)."""

from __future__ import annotations

import math

import numpy as np

from models.capture import Camera

from .spec import CameraPathSpec

WORLD_UP = np.array([0.0, 1.0, 0.0])


def look_at(position, target, up=WORLD_UP) -> np.ndarray:
    """Camera-to-world, OpenGL convention (camera looks down -Z, +Y up, +X right). # [4, 4] float64"""
    pos = np.asarray(position, dtype=np.float64)
    z = pos - np.asarray(target, dtype=np.float64)  # -Z points at the target
    if np.linalg.norm(z) == 0:
        raise ValueError(f"camera position {pos.tolist()} equals its target")
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-8:  # looking straight up/down: pick another up
        x = np.cross(np.array([0.0, 0.0, -1.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, pos
    return c2w


def intrinsics(width: int, height: int, fov_y_deg: float) -> dict:
    """Square pixels, principal point at the image centre."""
    fl = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return {"width": width, "height": height, "fl_x": fl, "fl_y": fl, "cx": width / 2, "cy": height / 2}


def path_poses(path: CameraPathSpec) -> list[np.ndarray]:
    """``path.count`` camera-to-world matrices along the path. # list of [4, 4]"""
    n = path.count
    if n == 0:
        return []
    if path.type == "list":
        idx = np.round(np.linspace(0, len(path.views) - 1, n)).astype(int) if n < len(path.views) else range(n)
        return [look_at(*path.views[i]) for i in idx]
    # orbit: evenly spaced azimuths; a closed 360-degree orbit does not repeat its first view
    a0, a1 = path.azimuth
    closed = abs(abs(a1 - a0) - 360.0) < 1e-9
    t = np.arange(n) / n if closed else (np.linspace(0, 1, n) if n > 1 else np.array([0.5]))
    target = np.asarray(path.target)
    poses = []
    for ti in t:
        a = math.radians(a0 + (a1 - a0) * ti)
        h = path.height[0] + (path.height[1] - path.height[0]) * ti
        pos = target + np.array([path.radius * math.sin(a), 0.0, path.radius * math.cos(a)])
        pos[1] = h
        poses.append(look_at(pos, target))
    return poses


def path_cameras(path: CameraPathSpec, resolution: tuple[int, int]) -> list[Camera]:
    k = intrinsics(resolution[0], resolution[1], path.fov_y)
    return [Camera(c2w=c2w, **k) for c2w in path_poses(path)]
