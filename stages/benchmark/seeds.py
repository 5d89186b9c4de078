"""Paired seeds: does a settings change beat the run-to-run spread?

One training run per room moves its tonemapped final PSNR by 0.5-1.5 dB with the seed alone (zoo_mirror_metal's
`test_001` shows a floater in some draws and not in others: 25.2 or 28.7 dB), so a change measured on one run
per room is a coin toss. This trains every (scene, seed) twice, with the scene's config ("base") and with the
changed one ("variant"), from the scene's capture (the dense initialisation and the schedule of its config, as
the workflow runs them), renders its test views (the render config's spp and denoiser, the model's own path
settings) and scores them (``evaluate``'s tonemapped PSNR per layer and per view). Same seed, same capture: the
pair differs by the change and by the chaos a changed setting starts; the table gives each pair's difference,
their mean and their range. Runs are independent processes (``jobs``): on a GPU several fit at once (the
training step is host-bound), on a 2-core CPU one or two.
"""

from __future__ import annotations

import concurrent.futures
import hashlib
import json
import multiprocessing
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from stages.config import deep_merge

LAYERS = ("final", "specular", "diffuse")
ROOT = Path(__file__).resolve().parents[2]
# what a point is made of besides its settings, capture and the libraries: bump when _point computes it otherwise
POINT_VERSION = 1
# the orchestration only (which points, in which processes, the table): left out of the code digest
ORCHESTRATION = ("stages/benchmark/seeds.py", "stages/benchmark/__main__.py")


def code_digest(root: Path = ROOT) -> str:
    """sha1 of the code a point runs: every .py under models/ and stages/ (but ORCHESTRATION) and every .yaml under
    configs/ (paths and contents), with POINT_VERSION."""
    h = hashlib.sha1(f"point {POINT_VERSION}".encode())
    files = sorted(f for pattern, top in (("*.py", "models"), ("*.py", "stages"), ("*.yaml", "configs"))
                   for f in (root / top).rglob(pattern) if f.relative_to(root).as_posix() not in ORCHESTRATION)
    for f in files:
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


def capture_digest(capture: Path) -> str:
    """sha1 of a capture's cameras and metadata (transforms.json, capture.yaml) and its images' names and sizes."""
    capture = Path(capture)
    h = hashlib.sha1()
    for name in ("transforms.json", "capture.yaml"):
        f = capture / name
        h.update(name.encode() + b"\0" + (f.read_bytes() if f.is_file() else b"") + b"\0")
    for f in sorted((capture / "images").glob("*")):
        h.update(f"{f.name} {f.stat().st_size}\0".encode())
    return h.hexdigest()


def run_key(scene: str, seed: int, config: dict, device: str, code: str, capture: str) -> str:
    """What makes a point the same point: runs reproduce exactly (same inputs, same numbers), so a point with this
    key can be taken from an earlier result instead of trained again (``reuse``)."""
    text = json.dumps({"scene": scene, "seed": seed, "config": config, "device": device, "code": code,
                       "capture": capture}, sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()


def parse_setting(text: str) -> dict:
    """``section.key[.sub]=value`` (value read as YAML: numbers, booleans, lists) -> a nested overrides dict."""
    import yaml

    key, sep, value = text.partition("=")
    parts = [k for k in key.strip().split(".") if k]
    if not sep or len(parts) < 2:
        raise ValueError(f"expected section.key=value (e.g. reconstruct.fill_anchor=0), got {text!r}")
    out: dict = {parts[-1]: yaml.safe_load(value)}
    for k in reversed(parts[:-1]):
        out = {k: out}
    return out


def _point(task: dict) -> dict:
    """One training + render + score (in a worker process, or in this one): the sweep's base point, all test views
    scored, tonemapped."""
    from stages.cli import single_threaded_torch

    single_threaded_torch()
    from models.capture import read_capture
    from models.initialisation import InitConfig
    from models.reconstruction import ReconstructConfig
    from models.rendering import RenderConfig
    from stages.benchmark.sweep import render_and_evaluate, train_model

    config, device, work = task["config"], task["device"], Path(task["work"])
    capture = read_capture(Path(task["capture"]))
    model, count, train_s = train_model(capture, InitConfig.from_dict(config.get("init", {})),
                                   ReconstructConfig.from_dict(config.get("reconstruct", {})), device, work / "model")
    render = {**config.get("render", {}), "path_views": 0, "video": False, "max_path_length": None, "sampler": None}
    scores, _ = render_and_evaluate(capture, model, RenderConfig.from_dict(render), device, None, work / "renders",
                                    regions=config.get("evaluate", {}).get("regions"), warm_up=False)
    mean = scores["mean"]
    return {**{k: task[k] for k in ("scene", "seed", "variant")}, "train_s": round(train_s, 1), "gaussians": count,
            **{f"psnr_{layer}_tonemapped": float(mean[f"psnr_{layer}_tonemapped"]) for layer in LAYERS},
            "views": {name: float(v["psnr_final_tonemapped"]) for name, v in scores["views"].items()},
            "regions": {k: float(v) for k, v in mean.items() if k.endswith("_psnr_final_tonemapped")}}


def run_seeds(scenes: dict[str, tuple[Path, dict]], variant: dict, seeds: list[int], device: str = "cpu",
              jobs: int = 1, work_dir: Path | None = None, progress: Callable[[str], None] = print,
              reuse: list[dict] | None = None) -> dict:
    """``scenes``: name -> (capture folder, merged config); ``variant``: overrides on top of each config. Trains
    every (scene, seed) with the base config and with the variant; returns every point and the paired table.
    ``reuse``: points of earlier results; one whose ``key`` (run_key: scene, seed, config, device, code, capture)
    is a task's is taken instead of training it again (marked ``reused``)."""
    tmp = tempfile.TemporaryDirectory(prefix="seeds_") if work_dir is None else None
    work = Path(tmp.name) if tmp else Path(work_dir)
    code = code_digest()
    known = {p["key"]: p for p in (reuse or []) if "key" in p}
    tasks, points = [], []
    for name, (capture, config) in scenes.items():
        cap = capture_digest(capture)
        for seed in seeds:
            for label, over in (("base", {}), ("variant", variant)):
                cfg = deep_merge(deep_merge(config, over), {"reconstruct": {"seed": seed}})
                key = run_key(name, seed, cfg, device, code, cap)
                if key in known:
                    points.append({**known[key], "variant": label, "reused": True})
                    progress(f"[reused] {_describe(points[-1])}")
                    continue
                tasks.append({"scene": name, "seed": seed, "variant": label, "config": cfg, "device": device,
                              "capture": str(capture), "work": str(work / f"{name}_{seed}_{label}"), "key": key})
    try:
        if jobs <= 1:
            for i, task in enumerate(tasks):
                points.append({**_point(task), "key": task["key"]})
                progress(f"[{i + 1}/{len(tasks)}] {_describe(points[-1])}")
        else:
            context = multiprocessing.get_context("spawn")  # torch / Warp state is not fork-safe
            with concurrent.futures.ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
                futures = {pool.submit(_point, t): t for t in tasks}
                for i, future in enumerate(concurrent.futures.as_completed(futures)):
                    points.append({**future.result(), "key": futures[future]["key"]})
                    progress(f"[{i + 1}/{len(tasks)}] {_describe(points[-1])}")
    finally:
        if tmp:
            tmp.cleanup()
    return {"points": sorted(points, key=lambda p: (p["scene"], p["seed"], p["variant"])),
            "pairs": pairs(points), "variant": variant, "seeds": list(seeds), "device": device}


def _describe(p: dict) -> str:
    return (f"{p['scene']} seed {p['seed']} {p['variant']}: final {p['psnr_final_tonemapped']:.2f} dB, "
            f"specular {p['psnr_specular_tonemapped']:.2f}, {p['train_s']:.0f} s")


def pairs(points: list[dict]) -> dict:
    """Per scene: each seed's (base, variant, difference) in final tonemapped PSNR, and the differences' mean,
    min and max (and the same for specular)."""
    by = {(p["scene"], p["seed"], p["variant"]): p for p in points}
    out: dict = {}
    for scene in sorted({p["scene"] for p in points}):
        seeds = sorted({p["seed"] for p in points if p["scene"] == scene})
        rows = []
        for seed in seeds:
            b, v = by.get((scene, seed, "base")), by.get((scene, seed, "variant"))
            if b is None or v is None:
                continue
            rows.append({"seed": seed, **{f"{layer}_{k}": x for layer in ("final", "specular")
                                          for k, x in (("base", b[f"psnr_{layer}_tonemapped"]),
                                                       ("variant", v[f"psnr_{layer}_tonemapped"]),
                                                       ("diff", v[f"psnr_{layer}_tonemapped"]
                                                        - b[f"psnr_{layer}_tonemapped"]))}})
        if rows:
            d = np.array([r["final_diff"] for r in rows])
            s = np.array([r["specular_diff"] for r in rows])
            out[scene] = {"seeds": rows, "final_diff_mean": float(d.mean()), "final_diff_min": float(d.min()),
                          "final_diff_max": float(d.max()), "specular_diff_mean": float(s.mean())}
    return out


def format_table(result: dict) -> str:
    rows = [f"{'scene':<22} {'seed':>4} {'base final':>10} {'variant':>8} {'diff':>6} | {'base spec':>9} "
            f"{'variant':>8} {'diff':>6}"]
    for scene, s in result["pairs"].items():
        for r in s["seeds"]:
            rows.append(f"{scene:<22} {r['seed']:>4} {r['final_base']:>10.2f} {r['final_variant']:>8.2f} "
                        f"{r['final_diff']:>+6.2f} | {r['specular_base']:>9.2f} {r['specular_variant']:>8.2f} "
                        f"{r['specular_diff']:>+6.2f}")
        rows.append(f"{scene:<22} {'mean':>4} {'':>10} {'':>8} {s['final_diff_mean']:>+6.2f} | {'':>9} {'':>8} "
                    f"{s['specular_diff_mean']:>+6.2f}   (final diff {s['final_diff_min']:+.2f} .. "
                    f"{s['final_diff_max']:+.2f})")
    return "\n".join(rows)
