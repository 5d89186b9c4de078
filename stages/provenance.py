"""``stage.json`` provenance written next to every stage's outputs."""

from __future__ import annotations

import json
import os
import platform
import time
from importlib import metadata
from pathlib import Path
from typing import Any

from .config import config_hash

PACKAGES = ("torch", "numpy", "warp-lang", "mitsuba", "drjit", "pycolmap", "snakemake", "OpenImageIO",
            "diffusers", "transformers")


def package_versions() -> dict[str, str]:
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return versions


def peak_memory(device: str = "cpu") -> dict[str, float | None]:
    """Peak resident memory of this process (MiB) and, on CUDA, the GPU memory of both allocators (MiB):

    - ``peak_cuda_torch_mib``: torch's peak allocated tensors (``torch.cuda.max_memory_allocated``);
      ``peak_cuda_torch_reserved_mib``: what its caching allocator held from the driver at most;
    - ``peak_cuda_warp_mib``: Warp's peak in its CUDA memory pool (``wp.get_mempool_used_mem_high``: the tracer's
      arrays, BVH, replay buffers; arrays Warp borrows from torch count under torch); None when Warp was not used
      or allocates outside a pool (then untracked);
    - ``peak_cuda_mib``: torch + Warp peaks added: the process's peak, from above (the two may peak apart);
    - ``cuda_device_used_mib``: the device's used memory at the end (``torch.cuda.mem_get_info``: every process,
      CUDA contexts and both allocators' caches included)."""
    import resource
    import sys

    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    out: dict[str, float | None] = {"peak_rss_mib": round(rss / (2**20 if sys.platform == "darwin" else 2**10), 1)}
    if str(device).startswith("cuda"):
        import torch

        if torch.cuda.is_available():
            mib = lambda b: round(b / 2**20, 1)  # noqa: E731
            torch_peak = torch.cuda.max_memory_allocated()
            warp_peak = _warp_mempool_peak(device)
            free, total = torch.cuda.mem_get_info()
            out.update(peak_cuda_torch_mib=mib(torch_peak), peak_cuda_torch_reserved_mib=mib(
                torch.cuda.max_memory_reserved()), peak_cuda_warp_mib=None if warp_peak is None else mib(warp_peak),
                peak_cuda_mib=mib(torch_peak + (warp_peak or 0)), cuda_device_used_mib=mib(total - free))
    return out


def _warp_mempool_peak(device: str) -> int | None:
    """Bytes at the high-water mark of Warp's memory pool on ``device``; None if this process never imported
    Warp (nothing to count; importing it here would only start it) or the device allocates outside a pool."""
    import sys

    wp = sys.modules.get("warp")
    if wp is None:
        return None
    try:
        if not wp.is_mempool_enabled(device):
            return None
        return int(wp.get_mempool_used_mem_high(device))
    except (RuntimeError, ValueError):  # not a CUDA device / no pool support
        return None


def write_stage_json(out_dir: str | Path, stage: str, config: Any, wall_time_s: float, device: str = "cpu",
                     extra: dict | None = None) -> Path:
    """Write ``<out_dir>/stage.json`` atomically: stage, config hash, package versions, device, wall time,
    peak memory."""
    out_dir = Path(out_dir)
    record = {
        "stage": stage,
        "config_hash": config_hash(config),
        "config": config,
        "packages": package_versions(),
        "python": platform.python_version(),
        "device": device,
        "wall_time_s": round(wall_time_s, 3),
        **peak_memory(device),
        "finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **(extra or {}),
    }
    path = out_dir / "stage.json"
    tmp = path.with_name(f".stage.json.tmp{os.getpid()}")
    tmp.write_text(json.dumps(record, indent=1, default=str))
    os.replace(tmp, path)
    return path
