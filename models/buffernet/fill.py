"""Fill a capture's missing buffers with the buffer network's predictions, in the capture format.

Per view, every requested buffer is predicted in ONE batched network pass (``BufferNetPipeline.predict``)
and converted from the network's conventions to the capture's:
- diffuse / specular: linear radiance in the input's units; by default (``radiance: complement``) the diffuse
  is the image minus the predicted specular, so the two sum to the image (``codec.split_radiance``);
- normal: camera space -> world (the view's camera-to-world rotation);
- depth: relative z-depth, aligned per view to 3D points (``align_to_points``: RANSAC scale + shift), then
  z-depth -> distance along the ray. The points are the capture's SfM points, or, for a synthetic scene run
  on predicted buffers (``points: truth``), a sparse random sample of its own rendered depth standing in
  for SfM (recorded in capture.yaml);
- roughness ``[H, W, 1]``, f0 ``[H, W, 3]`` in [0, 1].
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from models.buffernet.codec import BUFFERS, RADIANCE_MODES
from models.capture import Capture
from models.capture.depth_align import align_to_points
from models.capture.points import read_sfm_points
from models.capture.types import View
from models.settings import from_dict, setting


@dataclass
class BuffersConfig:
    """Network-predicted buffers for training (the ``buffers`` config section)."""

    model: str = setting("small", "a bare name = results/buffernet/<name>/pipeline (trained by the workflow), "
                         "else the path of a saved buffer network")
    predict: list[str] = setting(default_factory=list, doc="buffers to predict (diffuse, specular, normal, depth, "
                                 "roughness, f0); [] = the stage does not run")
    replace: bool = setting(False, "predict them on the train views even where the capture has them (a synthetic "
                            "scene run on network buffers; its test views keep the truth)")
    resolution: int | None = setting(None, "network processing size (long side); null = the image's own size",
                                     minimum=1)
    points: str = setting("sfm", "depth alignment points: sfm (points3D.ply / sparse/) | truth (synthetic: "
                          "truth_points random pixels of each train view's rendered depth)", enum=["sfm", "truth"])
    truth_points: int = setting(300, "per train view, with points: truth", minimum=1)
    radiance: str = setting("complement", "complement: diffuse = image - predicted specular (they sum to the "
                            "image); heads: the diffuse prompt's own output", enum=list(RADIANCE_MODES))

    @classmethod
    def from_dict(cls, d: dict) -> "BuffersConfig":
        cfg = from_dict(cls, d, "buffers")
        bad = [b for b in cfg.predict if b not in BUFFERS]
        if bad:
            raise ValueError(f"buffers.predict: unknown buffer(s) {bad}; valid: {', '.join(BUFFERS)}")
        return cfg


def network_path(model: str, results: str | Path = "results") -> Path:
    """Where the buffer network ``model`` is: a bare name is one the workflow trains
    (``<results>/buffernet/<name>/pipeline``), anything with a ``/`` is a path."""
    return Path(results) / "buffernet" / model / "pipeline" if "/" not in str(model) else Path(model)


def alignment_points(capture: Capture, capture_dir: Path, cfg: BuffersConfig) -> tuple[np.ndarray, str]:
    """World points ``[N, 3]`` the relative depths are aligned to, and where they come from."""
    if cfg.points == "truth":
        rng = np.random.default_rng(0)
        pts = []
        for view in capture.split("train"):
            if "depth" not in view.buffers:
                raise ValueError(f"buffers.points: truth needs the capture's depth; view {view.name!r} has none")
            dist = view.buffers["depth"][..., 0]
            rows, cols = np.nonzero(dist > 0)
            pick = rng.choice(len(rows), size=min(cfg.truth_points, len(rows)), replace=False)
            rays = view.camera.ray_directions()[rows[pick], cols[pick]]
            pts.append(view.camera.origin + rays * dist[rows[pick], cols[pick], None])
        return np.concatenate(pts), f"truth: {cfg.truth_points} rendered-depth pixels per train view (stand-in for SfM)"
    sfm = read_sfm_points(capture_dir)
    if sfm is None:
        raise ValueError(f"{capture_dir}: predicting depth needs SfM points to fix its scale and shift "
                         "(points3D.ply or sparse/), and the capture has none")
    return sfm[0], f"sfm: {sfm[2]}"


def to_capture_buffers(view: View, pred: dict[str, np.ndarray], points: np.ndarray | None, seed: int) -> tuple[dict, dict]:
    """Network outputs of one view -> capture-format buffers (float32 ``[H, W, C]``), and per-view notes."""
    out, notes = {}, {}
    for b, arr in pred.items():
        if b in ("diffuse", "specular", "f0"):
            out[b] = arr.astype(np.float32)
        elif b == "roughness":
            out[b] = arr[..., None].astype(np.float32)
        elif b == "normal":
            n = arr.astype(np.float64) @ view.camera.rotation.T
            out[b] = (n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)).astype(np.float32)
        elif b == "depth":
            out[b], fit = align_to_points(arr, view.camera, points, seed=seed, where=f"view {view.name!r} depth")
            notes["depth_fit"] = {"scale": fit.scale, "shift": fit.shift, "inliers": fit.inliers,
                                  "samples": fit.samples}
    return out, notes


def fill_buffers(capture: Capture, capture_dir: Path, pipe, cfg: BuffersConfig, progress: bool = True) -> tuple[Capture, dict]:
    """``capture`` with the requested buffers predicted (see module docstring); and what was done."""
    points, points_from = None, None
    if "depth" in cfg.predict:
        points, points_from = alignment_points(capture, capture_dir, cfg)
    views, per_view, seconds = [], {}, []
    for i, view in enumerate(tqdm(capture.views, desc="buffers", disable=not progress)):
        if cfg.replace:
            wanted = list(cfg.predict) if view.split == "train" else []
        else:
            wanted = [b for b in cfg.predict if b not in view.buffers]
        if not wanted:
            views.append(view)
            continue
        if "rgb" not in view.buffers:
            raise ValueError(f"view {view.name!r} has no R,G,B to predict buffers from")
        t = time.perf_counter()
        pred = pipe.predict(view.buffers["rgb"], wanted, resolution=cfg.resolution, radiance=cfg.radiance)
        seconds.append(time.perf_counter() - t)
        new, notes = to_capture_buffers(view, pred, points, seed=i)
        buffers = {**view.buffers, **new}
        if cfg.replace and "diffuse" in wanted:
            buffers.pop("emission", None)  # the network's diffuse includes lights seen directly, as in a photo
        views.append(View(view.name, view.camera, view.split, buffers))
        per_view[view.name] = {"predicted": wanted, **notes}
    info = {"model": str(cfg.model), "config": asdict(cfg), "points": points_from, "views": per_view,
            "seconds_per_view": float(np.mean(seconds)) if seconds else 0.0}
    meta = capture.meta
    meta.extra = {**meta.extra, "buffers": {k: v for k, v in info.items() if k != "views"}}
    return Capture(views, meta), info
