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


def peak_memory(device: str = "cpu") -> dict[str, float]:
    """Peak resident memory of this process (MiB) and, on CUDA, peak torch allocation (MiB)."""
    import resource
    import sys

    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    out = {"peak_rss_mib": round(rss / (2**20 if sys.platform == "darwin" else 2**10), 1)}
    if str(device).startswith("cuda"):
        import torch

        if torch.cuda.is_available():
            out["peak_cuda_mib"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
    return out


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
