"""torch <-> warp transfers that work whether or not torch sees the Warp device."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import torch
import warp as wp


@lru_cache(maxsize=None)
def torch_device_for(device: str) -> torch.device | None:
    """The torch device aliasing Warp `device`, or None when torch cannot reach it
    (e.g. a CPU-only torch build with a CUDA Warp device): then data is copied."""
    dev = wp.get_device(device)
    if dev.is_cpu:
        return torch.device("cpu")
    if torch.cuda.is_available():
        return torch.device(f"cuda:{dev.ordinal}")
    return None


def to_warp(t: torch.Tensor, dtype, device: str) -> wp.array:
    """Float32/int32 contiguous copy or alias of `t` as a Warp array of `dtype` on `device`."""
    if dtype is float:
        dtype = wp.float32
    target = torch.int32 if dtype is wp.int32 else torch.float32
    t = t.detach().to(target).contiguous()
    if t.numel() == 0:
        return wp.zeros(t.shape[0], dtype=dtype, device=device)
    if getattr(dtype, "_length_", 0) == 16:  # packed records: from_torch wants the inner shape (16,)
        t = t.reshape(-1, 16)
    tdev = torch_device_for(device)
    if tdev is not None:
        return wp.from_torch(t.to(tdev), dtype=dtype, requires_grad=False)
    return wp.array(t.cpu().numpy(), dtype=dtype, device=device)


def is_alias(a: wp.array, t: torch.Tensor) -> bool:
    """Whether ``a`` (from ``to_warp(t, ...)``) shares ``t``'s memory rather than holding a copy."""
    return t.numel() > 0 and a.ptr == t.data_ptr()


def to_torch(a: wp.array, device: torch.device) -> torch.Tensor:
    """Warp array -> torch tensor on `device` (alias when possible)."""
    if torch_device_for(str(a.device)) is not None:
        return wp.to_torch(a, requires_grad=False).to(device)
    return torch.from_numpy(np.ascontiguousarray(a.numpy())).to(device)
