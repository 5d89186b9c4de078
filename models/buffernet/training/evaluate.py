"""Per-buffer accuracy of a buffer network on held-out images, next to trivial baselines.

Metrics (valid pixels of each buffer only):
- diffuse, specular: PSNR of the exposure-normalised linear values (both multiplied by the input image's
  exposure, ``codec.input_exposure``: its 95th-percentile luminance becomes 1), clipped to [0, 1];
- roughness, f0: PSNR in [0, 1];
- normal: mean angular error in degrees (camera space);
- depth: AbsRel |z' - z| / z after the least-squares scale and shift fit of the prediction to the truth.

Aggregation over the held-out images: PSNRs are of the pooled squared error (every valid pixel of every image
weighs the same, as if the set were one image); angles and AbsRel are means over images. A mean of per-image
PSNRs is not used: an image whose truth a baseline matches exactly (a matte room: specular = 0, diffuse = RGB)
scores 100 dB there, and three such images out of 96 outweighed the other 93. ``wins`` counts the images where
the network scores better than the baseline (per-image metric).

The diffuse is scored as ``BufferNetPipeline.predict`` returns it (default ``radiance="complement"``: the image
minus the predicted specular); ``head`` holds the diffuse prompt's own output (``radiance="heads"``).

Baselines, the predictions a network that learned nothing could make: diffuse = the input RGB, specular = 0,
normal = facing the camera (0, 0, 1), depth = constant, roughness = 0.5, f0 = 0.04.
"""

from __future__ import annotations

import numpy as np
import torch
from tqdm import tqdm

from models.buffernet.codec import BUFFERS, RADIANCE, decode_output, encode_target, input_exposure
from models.buffernet.pipeline import resize, size_for
from models.metrics.image import mse_to_psnr, psnr

LOWER_IS_BETTER = {"normal": "mean angular error (deg)", "depth": "AbsRel"}


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


PSNR_BUFFERS = tuple(b for b in BUFFERS if b not in LOWER_IS_BETTER)  # diffuse, specular, roughness, f0


def _scaled(buffer: str, x: np.ndarray, exposure: float) -> np.ndarray:
    return x * exposure if buffer in RADIANCE else x


def _better(buffer: str, a: float, b: float) -> bool:
    """Whether score ``a`` is better than ``b`` for ``buffer``'s metric."""
    return a < b if buffer in LOWER_IS_BETTER else a > b


def score(buffer: str, pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, exposure: float) -> float:
    if buffer in PSNR_BUFFERS:
        return psnr(np.clip(_scaled(buffer, pred, exposure), 0, 1), np.clip(_scaled(buffer, truth, exposure), 0, 1),
                    mask)
    if buffer == "normal":
        return angular_error(pred, truth, mask)
    return abs_rel_aligned(pred, truth, mask)


class _Tally:
    """Per-image scores of one buffer and one predictor, plus the pooled squared error (PSNR buffers)."""

    def __init__(self, buffer: str):
        self.buffer, self.scores, self.sse, self.n = buffer, [], 0.0, 0

    def add(self, pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, exposure: float) -> None:
        if self.buffer not in PSNR_BUFFERS:
            self.scores.append(score(self.buffer, pred, truth, mask, exposure))
            return
        p = np.clip(_scaled(self.buffer, pred, exposure), 0, 1)
        t = np.clip(_scaled(self.buffer, truth, exposure), 0, 1)
        err = ((p - t) ** 2)[mask]
        self.scores.append(mse_to_psnr(float(err.mean())))  # = score(...), from the same errors
        self.sse, self.n = self.sse + float(err.sum()), self.n + err.size

    def value(self) -> float:
        if self.buffer in PSNR_BUFFERS:
            return mse_to_psnr(self.sse / max(self.n, 1))
        return float(np.mean(self.scores))

    def wins_over(self, other: "_Tally") -> int:
        return int(sum(_better(self.buffer, a, b) for a, b in zip(self.scores, other.scores)))


def baseline(buffer: str, rgb: np.ndarray) -> np.ndarray:
    h, w = rgb.shape[:2]
    return {"diffuse": lambda: rgb, "specular": lambda: np.zeros_like(rgb),
            "normal": lambda: np.broadcast_to(np.array([0, 0, 1], np.float32), (h, w, 3)),
            "depth": lambda: np.ones((h, w), np.float32), "roughness": lambda: np.full((h, w), 0.5, np.float32),
            "f0": lambda: np.full((h, w, 3), 0.04, np.float32)}[buffer]()


def evaluate_network(pipe, samples, resolution: int | None = None, progress: bool = True) -> dict:
    """Per-buffer metric of ``pipe`` and of the baselines over ``samples`` (``BufferSample``s), aggregated as
    the module docstring says, with the per-image wins."""
    ours = {b: _Tally(b) for b in BUFFERS}
    base = {b: _Tally(b) for b in BUFFERS}
    head = _Tally("diffuse")
    for s in tqdm(samples, desc="evaluate", disable=not progress):
        wanted = [b for b in BUFFERS if b in s.buffers and s.masks[b].any()]
        if not wanted:
            continue
        pred = pipe.predict(s.rgb, wanted, resolution=resolution)
        exposure = input_exposure(s.rgb)
        for b in wanted:
            ours[b].add(pred[b], s.buffers[b], s.masks[b], exposure)
            base[b].add(baseline(b, s.rgb), s.buffers[b], s.masks[b], exposure)
        if "diffuse" in wanted:
            own = pipe.predict(s.rgb, ["diffuse"], resolution=resolution, radiance="heads")["diffuse"]
            head.add(own, s.buffers["diffuse"], s.masks["diffuse"], exposure)
    rows = {}
    for b in BUFFERS:
        if not ours[b].scores:
            continue
        metric = LOWER_IS_BETTER.get(b, "PSNR (dB)")
        o, bl = ours[b].value(), base[b].value()
        rows[b] = {"metric": metric, "network": round(o, 4), "baseline": round(bl, 4), "images": len(ours[b].scores),
                   "wins": ours[b].wins_over(base[b]), "beats_baseline": _better(b, o, bl)}
        if b == "diffuse":
            rows[b]["head"] = {"network": round(head.value(), 4), "wins": head.wins_over(base[b]),
                               "beats_baseline": _better(b, head.value(), bl)}
    return rows


@torch.no_grad()
def vae_roundtrip(pipe, samples, resolution: int | None = None, progress: bool = True) -> dict:
    """Per-buffer metric of the TRUE buffers after the VAE round trip (encode, decode), exactly as the
    network's outputs pass through it: the best any UNet on this VAE can score (the ceiling)."""
    tallies = {b: _Tally(b) for b in BUFFERS}
    for s in tqdm(samples, desc="vae round trip", disable=not progress):
        exposure = input_exposure(s.rgb)
        h, w = s.rgb.shape[:2]
        size = size_for(h, w, pipe.multiple, resolution)
        for b in BUFFERS:
            if b not in s.buffers or not s.masks[b].any():
                continue
            x = resize(encode_target(b, s.buffers[b], exposure, s.masks[b])[None], size)
            y = resize(pipe.decode_latents(pipe.image_latents(x.to(pipe.device))).float().cpu(), (h, w))[0]
            tallies[b].add(decode_output(b, y, exposure), s.buffers[b], s.masks[b], exposure)
    return {b: round(t.value(), 4) for b, t in tallies.items() if t.scores}


def format_rows(rows: dict) -> str:
    """The table: network, baseline, images won, whether it beats it, and (when measured) the VAE round trip
    of the truth; the diffuse prompt's own output on a line of its own."""
    ceiling = any("vae_roundtrip" in r for r in rows.values())
    head = f"{'buffer':<16} {'metric':<26} {'network':>9} {'baseline':>9} {'wins':>7}  beats"
    lines = [head + ("  VAE ceiling" if ceiling else ""), "-" * (78 + 13 * ceiling)]

    def line(name, r, network, wins, beats, ceil):
        won = f"{wins}/{r['images']}"
        verdict = "yes" if beats else "NO"
        text = f"{name:<16} {r['metric']:<26} {network:>9.3f} {r['baseline']:>9.3f} {won:>7}  {verdict:<5}"
        return (text + (f"  {ceil:>11.3f}" if ceil is not None else "")).rstrip()

    for b, r in rows.items():
        lines.append(line(b, r, r["network"], r["wins"], r["beats_baseline"], r.get("vae_roundtrip")))
        if "head" in r:
            own = r["head"]
            lines.append(line(f"{b} (head)", r, own["network"], own["wins"], own["beats_baseline"], None))
    return "\n".join(lines)
