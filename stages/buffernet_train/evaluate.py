"""Per-buffer accuracy of a buffer network on held-out images, next to trivial baselines.

Metrics (valid pixels of each buffer only):
- diffuse, specular: PSNR of the exposure-normalised linear values (both multiplied by the input image's
  exposure, ``codec.input_exposure``: its 95th-percentile luminance becomes 1), clipped to [0, 1];
- roughness, f0: PSNR in [0, 1];
- normal: mean angular error in degrees (camera space);
- depth: AbsRel |z' - z| / z after the least-squares scale and shift fit of the prediction to the truth.

Baselines, the predictions a network that learned nothing could make: diffuse = the input RGB, specular = 0,
normal = facing the camera (0, 0, 1), depth = constant, roughness = 0.5, f0 = 0.04.
"""

from __future__ import annotations

import numpy as np
import torch
from tqdm import tqdm

from models.buffernet.codec import BUFFERS, decode_output, encode_target, input_exposure
from models.buffernet.pipeline import resize, size_for

LOWER_IS_BETTER = {"normal": "mean angular error (deg)", "depth": "AbsRel"}


def psnr(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    pred, truth = np.clip(pred, 0, 1), np.clip(truth, 0, 1)
    mse = float(((pred - truth) ** 2)[mask].mean())
    return float(10 * np.log10(1.0 / max(mse, 1e-10)))


def angular_error(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    cos = np.clip((pred * truth).sum(-1) / np.maximum(np.linalg.norm(pred, axis=-1) * np.linalg.norm(truth, axis=-1),
                                                      1e-8), -1, 1)
    return float(np.degrees(np.arccos(cos))[mask].mean())


def abs_rel_aligned(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """AbsRel after fitting ``a pred + b`` to ``truth`` by least squares on the valid pixels."""
    p, t = pred[mask].astype(np.float64), truth[mask].astype(np.float64)
    A = np.stack([p, np.ones_like(p)], 1)
    (a, b), *_ = np.linalg.lstsq(A, t, rcond=None)
    return float((np.abs(a * p + b - t) / np.maximum(t, 1e-6)).mean())


def score(buffer: str, pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, exposure: float) -> float:
    if buffer in ("diffuse", "specular"):
        return psnr(pred * exposure, truth * exposure, mask)
    if buffer in ("roughness", "f0"):
        return psnr(pred, truth, mask)
    if buffer == "normal":
        return angular_error(pred, truth, mask)
    return abs_rel_aligned(pred, truth, mask)


def baseline(buffer: str, rgb: np.ndarray) -> np.ndarray:
    h, w = rgb.shape[:2]
    return {"diffuse": lambda: rgb, "specular": lambda: np.zeros_like(rgb),
            "normal": lambda: np.broadcast_to(np.array([0, 0, 1], np.float32), (h, w, 3)),
            "depth": lambda: np.ones((h, w), np.float32), "roughness": lambda: np.full((h, w), 0.5, np.float32),
            "f0": lambda: np.full((h, w, 3), 0.04, np.float32)}[buffer]()


def evaluate_network(pipe, samples, resolution: int | None = None, progress: bool = True) -> dict:
    """Mean per-buffer metric of ``pipe`` and of the baselines over ``samples`` (``BufferSample``s)."""
    ours = {b: [] for b in BUFFERS}
    base = {b: [] for b in BUFFERS}
    for s in tqdm(samples, desc="evaluate", disable=not progress):
        wanted = [b for b in BUFFERS if b in s.buffers and s.masks[b].any()]
        if not wanted:
            continue
        pred = pipe.predict(s.rgb, wanted, resolution=resolution)
        exposure = input_exposure(s.rgb)
        for b in wanted:
            mask = s.masks[b]
            ours[b].append(score(b, pred[b], s.buffers[b], mask, exposure))
            base[b].append(score(b, baseline(b, s.rgb), s.buffers[b], mask, exposure))
    rows = {}
    for b in BUFFERS:
        if not ours[b]:
            continue
        metric = LOWER_IS_BETTER.get(b, "PSNR (dB)")
        o, bl = float(np.mean(ours[b])), float(np.mean(base[b]))
        better = o < bl if b in LOWER_IS_BETTER else o > bl
        rows[b] = {"metric": metric, "network": round(o, 4), "baseline": round(bl, 4), "images": len(ours[b]),
                   "beats_baseline": bool(better)}
    return rows


@torch.no_grad()
def vae_roundtrip(pipe, samples, resolution: int | None = None, progress: bool = True) -> dict:
    """Mean per-buffer metric of the TRUE buffers after the VAE round trip (encode, decode), exactly as the
    network's outputs pass through it: the best any UNet on this VAE can score (the ceiling)."""
    scores = {b: [] for b in BUFFERS}
    for s in tqdm(samples, desc="vae round trip", disable=not progress):
        exposure = input_exposure(s.rgb)
        h, w = s.rgb.shape[:2]
        size = size_for(h, w, pipe.multiple, resolution)
        for b in BUFFERS:
            if b not in s.buffers or not s.masks[b].any():
                continue
            x = resize(encode_target(b, s.buffers[b], exposure, s.masks[b])[None], size)
            y = resize(pipe.decode_latents(pipe.image_latents(x.to(pipe.device))).float().cpu(), (h, w))[0]
            scores[b].append(score(b, decode_output(b, y, exposure), s.buffers[b], s.masks[b], exposure))
    return {b: round(float(np.mean(v)), 4) for b, v in scores.items() if v}


def format_rows(rows: dict) -> str:
    """The table: network, baseline, whether it beats it, and (when measured) the VAE round trip of the truth."""
    ceiling = any("vae_roundtrip" in r for r in rows.values())
    head = f"{'buffer':<10} {'metric':<26} {'network':>9} {'baseline':>9}  beats"
    lines = [head + ("  VAE ceiling" if ceiling else ""), "-" * (64 + 13 * ceiling)]
    for b, r in rows.items():
        line = (f"{b:<10} {r['metric']:<26} {r['network']:>9.3f} {r['baseline']:>9.3f}  "
                f"{'yes' if r['beats_baseline'] else 'NO ':<5}")
        if "vae_roundtrip" in r:
            line += f"  {r['vae_roundtrip']:>11.3f}"
        lines.append(line.rstrip())
    return "\n".join(lines)
