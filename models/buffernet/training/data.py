"""Training data of the buffer network: data sources -> readers, deterministic batches, network encoding.

A batch is drawn from (seed, step) alone (sample indices, crops, flips), so a run resumed from a checkpoint
sees exactly the batches the uninterrupted run would have seen.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from models.buffernet.codec import encode_rgb, encode_target, input_exposure
from models.buffernet.codec import BUFFERS
from models.buffernet.datasets import BufferDataset, CaptureReader, HypersimReader, InteriorVerseReader


class CachedReader:
    """Keeps a reader's samples in memory after the first read (small synthetic datasets: every step
    would otherwise re-read the EXRs)."""

    def __init__(self, reader, limit: int = 20000):
        self.reader, self.limit, self._cache = reader, limit, {}

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, i: int):
        if i in self._cache:
            return self._cache[i]
        s = self.reader[i]
        if len(self._cache) < self.limit:
            self._cache[i] = s
        return s


def capture_dirs(path: Path) -> list[Path]:
    """``path`` if it is a capture (has transforms.json / transforms_train.json / sparse/), else its
    sub-folders that are, sorted."""
    def is_capture(p: Path) -> bool:
        return (p / "transforms.json").is_file() or (p / "transforms_train.json").is_file() or (p / "sparse").is_dir()

    if is_capture(path):
        return [path]
    found = sorted(p for p in path.iterdir() if p.is_dir() and is_capture(p)) if path.is_dir() else []
    if not found:
        raise FileNotFoundError(f"{path}: neither a capture (transforms.json) nor a folder of captures")
    return found


def make_readers(sources: list[str], cache: bool = True) -> list:
    """``kind:DIR[:split]`` strings -> readers. Kinds: hypersim, interiorverse, captures."""
    readers = []
    for src in sources:
        kind, sep, rest = src.partition(":")
        if not sep or not rest:
            raise ValueError(f"data source {src!r}: expected KIND:DIR with KIND one of hypersim, interiorverse, captures")
        if kind == "hypersim":
            readers.append(HypersimReader(rest))
        elif kind == "interiorverse":
            root, _, split = rest.partition(":")
            readers.append(InteriorVerseReader(root, split or "train"))
        elif kind == "captures":
            readers += [CaptureReader(p) for p in capture_dirs(Path(rest))]
        else:
            raise ValueError(f"data source {src!r}: unknown kind {kind!r} (hypersim, interiorverse, captures)")
    return [CachedReader(r) for r in readers] if cache else readers


def draw_batch(dataset: BufferDataset, seed: int, step: int, micro: int, batch_size: int) -> list[dict]:
    """The ``micro``-th micro-batch of ``step``: indices and augmentation from (seed, step, micro) only."""
    rng = np.random.default_rng([seed, step, micro])
    indices = rng.integers(0, len(dataset), size=batch_size)
    state = torch.get_rng_state()
    torch.manual_seed(int(rng.integers(0, 2**62)))
    try:
        return [dataset[int(i)] for i in indices]
    finally:
        torch.set_rng_state(state)


def encode_items(items: list[dict]) -> dict:
    """Dataset items -> network inputs: ``rgb`` [N, 3, S, S] in [-1, 1]; ``rows`` list of (image index,
    buffer name); ``targets`` [R, 3, S, S] in [-1, 1]; ``masks`` [R, S, S] float (1 = valid pixel).

    The exposure is the input image's (``codec.input_exposure``), applied to its diffuse / specular targets
    as at inference."""
    rgb, rows, targets, masks = [], [], [], []
    for i, item in enumerate(items):
        image = item["rgb"].permute(1, 2, 0).numpy()
        exposure = input_exposure(image)
        rgb.append(encode_rgb(image, exposure))
        for b in BUFFERS:
            m = item["masks"][b].numpy()
            if not m.any():
                continue
            arr = item["buffers"][b].numpy()
            arr = arr[0] if arr.shape[0] == 1 else arr.transpose(1, 2, 0)
            rows.append((i, b))
            targets.append(encode_target(b, arr, exposure, m))
            masks.append(torch.from_numpy(m).float())
    if not rows:
        raise ValueError("a batch with no valid buffer pixels: check the data sources' masks")
    return {"rgb": torch.stack(rgb), "rows": rows, "targets": torch.stack(targets), "masks": torch.stack(masks)}


def latent_mask(mask: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``[R, S, S]`` pixel masks -> ``[R, 1, h, w]``: a latent pixel counts only if its whole footprint is valid."""
    cover = F.interpolate(mask[:, None], size=size, mode="area")
    return (cover > 1 - 1e-4).float()
