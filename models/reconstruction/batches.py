"""Training batches on the trainer's device: every ray's data packed once, a batch gathered in one launch.

A ``RaySet`` lives on the CPU (the fills and the decisions read it there). ``RayBatcher`` copies it once to the
device as one [R, C] float32 table (origins, dirs, mask, each target layer), so a random batch is ONE
``index_select`` into a buffer kept between steps, and a whole view is a slice (views are contiguous row ranges):
no per-step host-to-device copies of rays or targets, no scan for a view's rays.

With ``jitter`` each ray also carries its pixel's footprint (the unnormalised direction through the pixel centre,
camera-space depth 1, and the world steps of one pixel across and down), and a batch drawn with a generator goes
through a uniform random point of each pixel instead of its centre: the ground truth's pixel is the mean over its
area (a box filter), which a model trained at the centres alone can meet only by blurring its edges. Measured worse
on four zoo rooms (``reconstruct.jitter``, off: README, thirty-eighth session); the renders average 2 x 2 primaries
instead (``render.antialias``).
"""

from __future__ import annotations

import torch

from .data import RaySet


def pixel_footprints(rays: RaySet) -> dict[str, torch.Tensor]:
    """Per ray [R, 3] each: "centre", the unnormalised world direction through its pixel's centre (camera-space
    depth 1), and "across" / "down", the world direction steps of one pixel along the image's columns / rows: the
    ray through the point (u, v) of its pixel (offsets from the centre, in pixels) is centre + u across + v down."""
    out = {k: torch.zeros_like(rays.dirs, dtype=torch.float64) for k in ("centre", "across", "down")}
    for i, view in enumerate(rays.views):
        rows = torch.nonzero(rays.view_of_ray == i).reshape(-1)
        if not len(rows):
            continue
        cam = view.camera
        rot = torch.tensor(cam.rotation, dtype=torch.float64)  # camera -> world; columns: right, up, back
        local = rays.dirs[rows].double() @ rot
        out["centre"][rows] = (local / (-local[:, 2:3])) @ rot.T
        out["across"][rows] = rot[:, 0] / cam.fl_x
        out["down"][rows] = -rot[:, 1] / cam.fl_y
    return {k: v.float() for k, v in out.items()}


class RayBatcher:
    def __init__(self, rays: RaySet, device: torch.device, jitter: bool = False):
        self.rays = rays
        self.device = torch.device(device)
        self.jitter = jitter
        columns = {"origins": rays.origins, "dirs": rays.dirs, "mask": rays.mask.reshape(-1, 1).float(),
                   **{f"target:{k}": v for k, v in rays.targets.items()}}  # targets: [R, C]
        if jitter:
            columns.update({f"pixel:{k}": v for k, v in pixel_footprints(rays).items()})
        self.slices: dict[str, slice] = {}
        start = 0
        for name, value in columns.items():
            self.slices[name] = slice(start, start + value.shape[1])
            start += value.shape[1]
        self.table = torch.cat([v.float() for v in columns.values()], dim=1).to(self.device)  # [R, C]
        self._buffer: torch.Tensor | None = None  # [n, C], reused while the batch size stays
        vid = rays.view_of_ray
        counts = torch.bincount(vid, minlength=len(rays.views))
        self.view_start = torch.cat([torch.zeros(1, dtype=torch.long), counts.cumsum(0)]).tolist()
        self.views_contiguous = bool((vid[1:] >= vid[:-1]).all()) if len(vid) > 1 else True

    def _unpack(self, rows: torch.Tensor, view_of_ray: torch.Tensor,
                generator: torch.Generator | None = None) -> RaySet:
        s = self.slices
        targets = {name.split(":", 1)[1]: rows[:, sl] for name, sl in s.items() if name.startswith("target:")}
        dirs = rows[:, s["dirs"]]
        if self.jitter and generator is not None:  # a uniform random point of each ray's pixel
            u, v = (torch.rand((len(rows), 2), generator=generator) - 0.5).to(rows.device).unbind(1)
            dirs = torch.nn.functional.normalize(rows[:, s["pixel:centre"]] + u[:, None] * rows[:, s["pixel:across"]]
                                                 + v[:, None] * rows[:, s["pixel:down"]], dim=-1)
        return RaySet(rows[:, s["origins"]], dirs, rows[:, s["mask"]].reshape(-1) > 0.5, targets,
                      view_of_ray, self.rays.views)

    def sample(self, index: torch.Tensor, generator: torch.Generator | None = None) -> RaySet:
        """The rays ``index`` ([n] int64, CPU): gathered into the reused buffer (valid until the next sample). With
        ``jitter`` and a ``generator``: through random points of their pixels (``pixel_footprints``)."""
        n = index.shape[0]
        if self._buffer is None or self._buffer.shape[0] != n:
            self._buffer = torch.empty((n, self.table.shape[1]), dtype=self.table.dtype, device=self.device)
        torch.index_select(self.table, 0, index.to(self.device, non_blocking=True), out=self._buffer)
        return self._unpack(self._buffer, self.rays.view_of_ray[index], generator)

    def view(self, i: int, generator: torch.Generator | None = None) -> RaySet:
        """Every ray of view ``i``, in pixel order (a slice of the table when views are contiguous); ``generator``
        as for ``sample``."""
        if not self.views_contiguous:
            return self.sample(torch.nonzero(self.rays.view_of_ray == i).reshape(-1), generator)
        a, b = self.view_start[i], self.view_start[i + 1]
        return self._unpack(self.table[a:b], self.rays.view_of_ray[a:b], generator)
