"""``python -m stages.synth procedural``: render random rooms (``models/synth/procedural.py``) into
``out_dir/scene_0000, scene_0001, ...`` (each a capture folder, with ``stage.json``); scenes whose folder already
holds a capture of the same config are skipped, so an interrupted run resumes."""

from __future__ import annotations

import time
from pathlib import Path

from tqdm import tqdm

from models.settings import config_hash
from models.synth import render_capture
from models.synth.procedural import random_scene_config
from stages.provenance import write_stage_json


def scene_dir(out_dir: str | Path, index: int) -> Path:
    return Path(out_dir) / f"scene_{index:04d}"


def is_complete(folder: Path, config: dict) -> bool:
    """Whether ``folder`` holds a finished capture rendered from ``config`` (its stage.json's hash)."""
    import json

    stage = folder / "stage.json"
    if not (folder / "transforms.json").is_file() or not stage.is_file():
        return False
    try:
        return json.loads(stage.read_text()).get("config_hash") == config_hash(config)
    except (json.JSONDecodeError, OSError):
        return False


def render_procedural(out_dir: str | Path, count: int, seed: int = 0, *, resolution: tuple[int, int] = (64, 64),
                      views: int = 8, spp: int = 64, denoise: bool = True, progress: bool = True) -> dict:
    """Render ``count`` random rooms (seeds ``seed .. seed + count - 1``) into ``out_dir/scene_NNNN``,
    skipping complete ones. Returns {"rendered": [...], "skipped": [...], "seconds": {name: s}}."""
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    report: dict = {"rendered": [], "skipped": [], "seconds": {}}
    bar = tqdm(range(count), desc="procedural", unit="scene", disable=not progress)
    for i in bar:
        folder = scene_dir(out_dir, i)
        cfg = random_scene_config(seed + i, resolution=resolution, views=views, spp=spp,
                                  denoise=denoise)
        record = {"synth": cfg, "procedural": {"seed": seed + i}}
        if is_complete(folder, record):
            report["skipped"].append(folder.name)
            continue
        bar.set_postfix_str(folder.name)
        t0 = time.perf_counter()
        capture = render_capture(cfg, folder, progress=False, scene_name=folder.name)
        seconds = time.perf_counter() - t0
        write_stage_json(folder, "synth", record, seconds,
                         extra={"seconds_per_view": capture.meta.extra["seconds_per_view"], "spp": spp})
        report["rendered"].append(folder.name)
        report["seconds"][folder.name] = round(seconds, 3)
    return report
