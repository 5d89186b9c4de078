"""Training batches on the trainer's device: every ray's data packed once, a batch gathered in one launch.

A ``RaySet`` lives on the CPU (the fills and the decisions read it there). ``RayBatcher`` copies it once to the
device as one [R, C] float32 table (origins, dirs, mask, each target layer), so a random batch is ONE
``index_select`` into a buffer kept between steps, and a whole view is a slice (views are contiguous row ranges):
no per-step host-to-device copies of rays or targets, no scan for a view's rays.
"""

from __future__ import annotations

import torch

from .data import RaySet


class RayBatcher:
    def __init__(self, rays: RaySet, device: torch.device):
        self.rays = rays
        self.device = torch.device(device)
        columns = {"origins": rays.origins, "dirs": rays.dirs, "mask": rays.mask.reshape(-1, 1).float(),
                   **{f"target:{k}": v for k, v in rays.targets.items()}}  # targets: [R, C]
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

    def _unpack(self, rows: torch.Tensor, view_of_ray: torch.Tensor) -> RaySet:
        s = self.slices
        targets = {name.split(":", 1)[1]: rows[:, sl] for name, sl in s.items() if name.startswith("target:")}
        return RaySet(rows[:, s["origins"]], rows[:, s["dirs"]], rows[:, s["mask"]].reshape(-1) > 0.5, targets,
                      view_of_ray, self.rays.views)

    def sample(self, index: torch.Tensor) -> RaySet:
        """The rays ``index`` ([n] int64, CPU): gathered into the reused buffer (valid until the next sample)."""
        n = index.shape[0]
        if self._buffer is None or self._buffer.shape[0] != n:
            self._buffer = torch.empty((n, self.table.shape[1]), dtype=self.table.dtype, device=self.device)
        torch.index_select(self.table, 0, index.to(self.device, non_blocking=True), out=self._buffer)
        return self._unpack(self._buffer, self.rays.view_of_ray[index])

    def view(self, i: int) -> RaySet:
        """Every ray of view ``i``, in pixel order (a slice of the table when views are contiguous)."""
        if not self.views_contiguous:
            return self.sample(torch.nonzero(self.rays.view_of_ray == i).reshape(-1))
        a, b = self.view_start[i], self.view_start[i + 1]
        return self._unpack(self.table[a:b], self.rays.view_of_ray[a:b])
