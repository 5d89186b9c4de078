"""Training rays and per-ray targets of a capture, flattened over views."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from models.capture import Capture, View
from models.capture.layers import SUPERVISED, diffuse_radiance


@dataclass
class RaySet:
    origins: torch.Tensor  # [R, 3]
    dirs: torch.Tensor  # [R, 3] unit
    mask: torch.Tensor  # [R] bool, valid pixels
    targets: dict[str, torch.Tensor]  # layer -> [R, C]
    view_of_ray: torch.Tensor  # [R] int64 index into ``views``
    views: list[View]

    def __len__(self) -> int:
        return self.origins.shape[0]

    def subset(self, index: torch.Tensor) -> "RaySet":
        return RaySet(self.origins[index], self.dirs[index], self.mask[index],
                      {k: v[index] for k, v in self.targets.items()}, self.view_of_ray[index], self.views)

    def view_rays(self, i: int) -> "RaySet":
        return self.subset(torch.nonzero(self.view_of_ray == i).reshape(-1))


def view_rays(view: View) -> tuple[np.ndarray, np.ndarray]:
    """World origins and unit directions of every pixel of ``view``, row-major. # [H*W, 3] each"""
    dirs = view.camera.ray_directions().reshape(-1, 3)
    return np.broadcast_to(view.camera.origin, dirs.shape), dirs


def build_rayset(capture: Capture, split: str, radiance_clamp: float = 0.0) -> RaySet:
    """All pixels of the ``split`` views with the target layers every view has. The ``diffuse`` target is the
    view's diffuse + emission where it has an ``emission`` layer (``diffuse_radiance``): lights seen directly are
    view-independent radiance of the Gaussians, which reflection rays then see as the path tracer does."""
    views = capture.split(split)
    if not views:
        raise ValueError(f"capture has no {split!r} views")
    capture.require_complete(split, SUPERVISED)  # a partial layer is an error, not a loss silently off
    layers = [l for l in SUPERVISED if all(l in v.buffers for v in views)]
    o, d, m, vid = [], [], [], []
    targets: dict[str, list] = {l: [] for l in layers}
    for i, v in enumerate(views):
        oi, di = view_rays(v)
        o.append(oi)
        d.append(di)
        n = len(di)
        mask = v.buffers["mask"].reshape(-1) > 0.5 if "mask" in v.buffers else np.ones(n, bool)
        if "depth" in v.buffers:
            mask &= v.buffers["depth"].reshape(-1) > 0
        m.append(mask)
        vid.append(np.full(n, i))
        for l in layers:
            t = (diffuse_radiance(v.buffers) if l == "diffuse" else v.buffers[l]).reshape(n, -1)
            if l == "normal":  # a target facing away from its camera (another tool's outward normals seen from
                # inside) is the same surface: supervised facing the camera, as every reflection vertex is turned
                t = np.where((t * di).sum(-1, keepdims=True) > 0, -t, t)
            if radiance_clamp > 0 and l in ("diffuse", "specular"):
                t = np.minimum(t, radiance_clamp)
            targets[l].append(t)
    f32 = torch.float32
    return RaySet(
        origins=torch.tensor(np.concatenate(o), dtype=f32),
        dirs=torch.tensor(np.concatenate(d), dtype=f32),
        mask=torch.tensor(np.concatenate(m)),
        targets={l: torch.tensor(np.concatenate(t), dtype=f32) for l, t in targets.items()},
        view_of_ray=torch.tensor(np.concatenate(vid)),
        views=views,
    )
