"""Training data of the buffer network: dataset readers with one sample type, and a torch Dataset of
fixed-size, augmented crops.

Readers (indexable, iterable, ``len``; each item a ``BufferSample``, conventions in ``_sample.py``):

* ``HypersimReader(root, scenes=None)``: diffuse, specular, normal, depth (``_hypersim.py``).
* ``InteriorVerseReader(root, split="train")``: normal, depth, roughness, f0 (``_interiorverse.py``).
* ``CaptureReader(capture_dir, split=None)``: the project's captures, e.g. ``python -m stages.synth
  procedural`` output (``_capture_reader.py``): every buffer.

``BufferDataset(readers, size)`` crops, resizes and flips samples into float32 tensors; it knows nothing
of the network's latent encoding (the training code encodes).
"""

from __future__ import annotations

import bisect
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ._capture_reader import CaptureReader
from ._hypersim import HypersimReader
from ._interiorverse import InteriorVerseReader
from ._sample import BUFFER_CHANNELS, BufferSample, DatasetError

__all__ = [
    "BUFFER_CHANNELS", "BufferDataset", "BufferSample", "CaptureReader", "DatasetError", "HypersimReader",
    "InteriorVerseReader", "resize_sample",
]

# How each buffer is resampled: masked area average, area average renormalised, or nearest.
_AREA = ("diffuse", "specular", "roughness", "f0")
_NEAREST = ("depth",)  # averaging depth across an edge invents floating surfaces


def _to_chw(arr: np.ndarray) -> torch.Tensor:
    t = torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32))
    return t.permute(2, 0, 1) if t.ndim == 3 else t[None]


def resize_sample(sample: BufferSample, box: tuple[int, int, int, int], size: int, flip: bool = False) -> dict:
    """Crop ``box = (top, left, height, width)`` of ``sample``, resize it to ``size x size`` and optionally
    flip it horizontally. Colour-like buffers are area-averaged over valid pixels, normals area-averaged
    and renormalised, depth taken at the nearest pixel; an output pixel is valid only if its whole
    footprint is (masks AND-ed). A horizontal flip negates the camera-space normal's x.

    Returns ``rgb`` [3, S, S], ``buffers`` name -> [C, S, S], ``masks`` name -> [S, S] bool (present
    buffers only)."""
    top, left, hh, ww = box
    sl = (slice(top, top + hh), slice(left, left + ww))
    out_size = (size, size)
    rgb = F.interpolate(_to_chw(sample.rgb[sl])[None], size=out_size, mode="area")[0]
    buffers, masks = {}, {}
    for key, arr in sample.buffers.items():
        x = _to_chw(arr[sl])[None]  # [1, C, h, w]
        m = torch.from_numpy(np.ascontiguousarray(sample.masks[key][sl])).float()[None, None]
        cover = F.interpolate(m, size=out_size, mode="area")[0, 0]
        valid = cover > 1 - 1e-4
        if key in _NEAREST:
            y = F.interpolate(x, size=out_size, mode="nearest-exact")[0]
        else:
            y = F.interpolate(x * m, size=out_size, mode="area")[0] / cover.clamp_min(1e-8)
            if key == "normal":
                y = y / y.norm(dim=0, keepdim=True).clamp_min(1e-8)
        buffers[key] = torch.where(valid, y, torch.zeros(()))
        masks[key] = valid
    if flip:
        rgb = rgb.flip(-1)
        buffers = {k: v.flip(-1) for k, v in buffers.items()}
        masks = {k: v.flip(-1) for k, v in masks.items()}
        if "normal" in buffers:
            buffers["normal"] = buffers["normal"] * torch.tensor([-1.0, 1.0, 1.0])[:, None, None]
    return {"rgb": rgb, "buffers": buffers, "masks": masks}


class BufferDataset(torch.utils.data.Dataset):
    """Fixed-size square samples from a list of readers, for training.

    Training (``augment=True``): a random square crop with side ``U(min_crop, 1) * min(H, W)`` at a random
    place, resized to ``size``, and a horizontal flip with probability 0.5, drawn from torch's global RNG
    (seeded per DataLoader worker). ``augment=False``: the centred largest square, no flip.

    An item is a dict that the default collate batches: ``rgb`` [3, S, S] float32 (linear HDR);
    ``buffers`` name -> [C, S, S] float32 and ``masks`` name -> [S, S] bool for every name in ``BUFFER_CHANNELS``
    (zeros / all False where the source lacks the buffer); ``present`` [len(BUFFERS)] bool in ``BUFFER_CHANNELS``
    order; ``name`` str.
    """

    def __init__(self, readers: Sequence, size: int = 128, *, augment: bool = True, min_crop: float = 0.5):
        if not readers:
            raise ValueError("BufferDataset needs at least one reader")
        if size < 1:
            raise ValueError(f"size must be >= 1, got {size}")
        if not 0 < min_crop <= 1:
            raise ValueError(f"min_crop must be in (0, 1], got {min_crop}")
        self.readers = list(readers)
        self.size, self.augment, self.min_crop = int(size), augment, float(min_crop)
        self._offsets = np.cumsum([0] + [len(r) for r in self.readers]).tolist()

    def __len__(self) -> int:
        return self._offsets[-1]

    def sample(self, index: int) -> BufferSample:
        """The reader's sample behind ``index`` (no crop / resize)."""
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range ({len(self)} samples)")
        r = bisect.bisect_right(self._offsets, index) - 1
        return self.readers[r][index - self._offsets[r]]

    def __getitem__(self, index: int) -> dict:
        s = self.sample(index)
        h, w = s.rgb.shape[:2]
        side = min(h, w)
        if self.augment:
            frac = self.min_crop + (1 - self.min_crop) * torch.rand(()).item()
            side = max(1, round(frac * side))
            top = int(torch.randint(0, h - side + 1, ()).item())
            left = int(torch.randint(0, w - side + 1, ()).item())
            flip = bool(torch.rand(()).item() < 0.5)
        else:
            top, left, flip = (h - side) // 2, (w - side) // 2, False
        out = resize_sample(s, (top, left, side, side), self.size, flip=flip)
        full_b, full_m = {}, {}
        for key, c in BUFFER_CHANNELS.items():
            if key in out["buffers"]:
                full_b[key], full_m[key] = out["buffers"][key], out["masks"][key]
            else:
                full_b[key] = torch.zeros(c, self.size, self.size)
                full_m[key] = torch.zeros(self.size, self.size, dtype=torch.bool)
        present = torch.tensor([k in out["buffers"] for k in BUFFER_CHANNELS], dtype=torch.bool)
        return {"rgb": out["rgb"], "buffers": full_b, "masks": full_m, "present": present, "name": s.name}
