"""Buffer-network training-step benchmark: milliseconds per UNet optimiser step at a given size, batch and dtype.

The step is the training's own (models.buffernet.training.train: VAE-encoded image and target latents, x0
prediction through the widened UNet with gradient checkpointing, masked latent MSE, backward, AdamW), on random
weights built in memory (``--init tiny | small | sd2``; sd2 = Stable Diffusion 2's exact configs: 866M-parameter
UNet, ~5 GB of fp32 weights, ~16 GB to train on a CPU) and random images, so it runs without a download. Split into
VAE encoding, UNet forward + backward, optimiser; peak memory alongside. bf16 / fp16 run the UNet under autocast (as
``mixed_precision`` in training); the CPU trains in fp32.
"""

from __future__ import annotations

import argparse
import platform
import resource
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


@dataclass
class BufferNetStepConfig:
    init: str = "sd2"          # tiny | small | sd2 (random weights)
    size: int | None = None    # image side (default 512 on CUDA, 64 on the CPU); a multiple of the model's
    batch: int = 1             # images per step; each gives one UNet row per buffer
    buffers: int = 6           # UNet rows per image (the six buffers of the paper)
    dtype: str = "fp32"        # fp32 | bf16 | fp16 (autocast of the UNet, CUDA)
    device: str = "cuda" if torch.cuda.is_available() else "cpu"
    steps: int = 3             # timed steps (after one warm-up)
    gradient_checkpointing: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        if self.dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, got {self.dtype!r}")
        if self.dtype != "fp32" and not self.device.startswith("cuda"):
            raise ValueError(f"dtype {self.dtype} is for CUDA (the CPU trains in fp32), got device {self.device!r}")
        if not 1 <= self.buffers <= 6:
            raise ValueError(f"buffers must be 1..6, got {self.buffers}")
        for name in ("batch", "steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.size is None:
            self.size = 512 if self.device.startswith("cuda") else 64


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def run_buffernet_step(cfg: BufferNetStepConfig, progress=print) -> dict:
    from models.buffernet.build import build_pipeline
    from models.buffernet.codec import BUFFERS
    from models.buffernet.training.data import latent_mask
    from models.buffernet.training.train import masked_mse

    progress(f"buffernet-step: building {cfg.init} (random weights) on {cfg.device} ...")
    start = time.perf_counter()
    pipe = build_pipeline(cfg.init, seed=cfg.seed).to(cfg.device)
    build_s = time.perf_counter() - start
    if cfg.size % pipe.multiple:
        raise ValueError(f"size {cfg.size} is not a multiple of {pipe.multiple} (the {cfg.init} model's)")
    pipe.freeze()
    if cfg.gradient_checkpointing:
        pipe.unet.enable_gradient_checkpointing()
    pipe.unet.train()
    opt = torch.optim.AdamW(pipe.unet.parameters(), lr=3e-5, weight_decay=1e-2)
    g = torch.Generator().manual_seed(cfg.seed)
    rows = cfg.batch * cfg.buffers
    rgb = (torch.rand(cfg.batch, 3, cfg.size, cfg.size, generator=g) * 2 - 1).to(cfg.device)
    targets = (torch.rand(rows, 3, cfg.size, cfg.size, generator=g) * 2 - 1).to(cfg.device)
    masks = torch.ones(rows, cfg.size, cfg.size, device=cfg.device)
    index = torch.arange(cfg.batch, device=cfg.device).repeat_interleave(cfg.buffers)
    embeds = pipe.encode_prompts(list(BUFFERS[:cfg.buffers]) * cfg.batch)
    autocast = torch.autocast("cuda", dtype=DTYPES[cfg.dtype], enabled=cfg.dtype != "fp32") \
        if cfg.device.startswith("cuda") else torch.autocast("cpu", enabled=False)

    def step() -> dict:
        times = {}
        _sync(cfg.device)
        t0 = time.perf_counter()
        with torch.no_grad():
            image_lat = pipe.image_latents(rgb)
            target_lat = pipe.image_latents(targets)
        _sync(cfg.device)
        t1 = time.perf_counter()
        with autocast:
            x0 = pipe.x0_latents(image_lat[index], embeds)
        loss = masked_mse(x0.float(), target_lat.float(), latent_mask(masks, tuple(x0.shape[-2:])))
        loss.backward()
        _sync(cfg.device)
        t2 = time.perf_counter()
        opt.step()
        opt.zero_grad(set_to_none=True)
        _sync(cfg.device)
        t3 = time.perf_counter()
        times.update(vae_encode_ms=(t1 - t0) * 1e3, unet_forward_backward_ms=(t2 - t1) * 1e3,
                     optimizer_ms=(t3 - t2) * 1e3, step_ms=(t3 - t0) * 1e3, loss=float(loss.detach()))
        return times

    progress(f"buffernet-step: warm-up step ({cfg.size}x{cfg.size}, {rows} UNet rows, {cfg.dtype}) ...")
    step()
    if cfg.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    runs = []
    for i in range(cfg.steps):
        progress(f"buffernet-step: step {i + 1}/{cfg.steps} ...")
        runs.append(step())
    row = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    row["images_per_s"] = cfg.batch / (row["step_ms"] / 1e3)
    row["unet_parameters"] = sum(p.numel() for p in pipe.unet.parameters())
    row["build_s"] = build_s
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    row["peak_rss_mib"] = rss / (2**20 if sys.platform == "darwin" else 2**10)
    if cfg.device.startswith("cuda"):
        row["peak_cuda_torch_mib"] = torch.cuda.max_memory_allocated() / 2**20
    return {"benchmark": "buffernet-step", "config": asdict(cfg), "result": row,
            "provenance": {"torch": torch.__version__, "python": platform.python_version(),
                           "cuda": torch.cuda.get_device_name() if cfg.device.startswith("cuda") else None}}


def format_result(result: dict) -> str:
    c, r = result["config"], result["result"]
    cuda = f", peak CUDA (torch) {r['peak_cuda_torch_mib']:.0f} MiB" if "peak_cuda_torch_mib" in r else ""
    lines = [f"buffer network {c['init']} ({r['unet_parameters'] / 1e6:.0f}M UNet parameters), "
             f"{c['size']}x{c['size']}, {c['batch']} image(s) x {c['buffers']} buffers, {c['dtype']} on "
             f"{c['device']}, median of {c['steps']}:",
             f"  step {r['step_ms']:.0f} ms = VAE encode {r['vae_encode_ms']:.0f} + UNet fwd+bwd "
             f"{r['unet_forward_backward_ms']:.0f} + AdamW {r['optimizer_ms']:.0f}; {r['images_per_s']:.2f} images/s",
             f"  peak RSS {r['peak_rss_mib']:.0f} MiB{cuda}"]
    return "\n".join(lines)


def buffernet_step_main(argv, write_json) -> int:
    """The ``buffernet-step`` command line; ``write_json(path, data)`` writes --out."""
    p = argparse.ArgumentParser(prog="python -m stages.benchmark buffernet-step", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--init", choices=["tiny", "small", "sd2"], help="random-weight model (default sd2)")
    p.add_argument("--size", type=int, help="image side (default 512 on CUDA, 64 on the CPU)")
    p.add_argument("--batch", type=int, help="images per step (default 1)")
    p.add_argument("--buffers", type=int, help="UNet rows per image (default 6)")
    p.add_argument("--dtype", choices=list(DTYPES), help="fp32 | bf16 | fp16 (UNet autocast; CUDA only)")
    p.add_argument("--device", help="cpu | cuda (default cuda when available)")
    p.add_argument("--steps", type=int, help="timed steps (default 3)")
    p.add_argument("--no-checkpointing", action="store_true", help="no gradient checkpointing")
    p.add_argument("--out", type=Path, help="write the JSON result here")
    a = p.parse_args(argv)
    kw = {k: getattr(a, k) for k in ("init", "size", "batch", "buffers", "dtype", "device", "steps")
          if getattr(a, k) is not None}
    try:
        cfg = BufferNetStepConfig(**kw, gradient_checkpointing=not a.no_checkpointing)
        result = run_buffernet_step(cfg, progress=lambda m: print(m, file=sys.stderr, flush=True))
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(format_result(result))
    if a.out is not None:
        write_json(a.out, result)
        print(f"wrote {a.out}")
    return 0
