"""Buffer-network training with accelerate: masked latent MSE (+ optional pixel MSE), AdamW, exponential
decay, gradient checkpointing, mixed precision on GPU, checkpoints with exact resume, a diffusers pipeline
folder at the end.

Phases: an optional VAE phase (``vae_steps``) trains a random-weight model's VAE as an autoencoder of the
encoded images and buffers (SD2's pretrained VAE is never trained), then the UNet phase (``iterations``).
Batches depend on (seed, step) only (``data.draw_batch``), and the accelerate state holds the weights,
optimisers, schedulers and RNGs, so resuming from a checkpoint continues exactly.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

import torch
from tqdm import tqdm

from models.buffernet import BufferNetPipeline
from models.buffernet.build import RANDOM_INITS, build_pipeline, from_stable_diffusion
from models.buffernet.codec import BUFFERS
from models.buffernet.datasets import BufferDataset

from .config import TrainConfig
from .data import draw_batch, encode_items, latent_mask, make_readers

KL_WEIGHT = 1e-6  # VAE phase: keeps latents near the prior (SD's VAE used a similarly small weight)


def load_initial(init: str, seed: int = 0) -> BufferNetPipeline:
    """``tiny`` / ``small`` / ``sd2`` (random weights), a saved buffer network, or a local SD2 folder (widened)."""
    if init in RANDOM_INITS:
        return build_pipeline(init, seed=seed)
    path = Path(init)
    index = path / "model_index.json"
    if not index.is_file():
        raise FileNotFoundError(f"init {init!r}: not {'/'.join(RANDOM_INITS)} and no model_index.json in {path} "
                                "(give a local stable-diffusion-2 folder or a saved buffer network)")
    if json.loads(index.read_text()).get("_class_name") == "BufferNetPipeline":
        return BufferNetPipeline.from_pretrained(path)
    return from_stable_diffusion(path)


def latest_checkpoint(out: Path) -> Path | None:
    ckpts = sorted((out / "checkpoints").glob("step_*")) if (out / "checkpoints").is_dir() else []
    ckpts = [c for c in ckpts if (c / "meta.json").is_file()]
    return ckpts[-1] if ckpts else None


RESUMABLE_CHANGES = {"iterations", "checkpoint_every", "keep_checkpoints", "log_every", "num_workers"}


def _changed_since_checkpoints(out: Path, cfg: TrainConfig) -> bool:
    """Whether the checkpoints in ``out`` come from a run with other options (anything but the schedule's length and
    logging): resuming them would continue a different training, or fail on other weight shapes."""
    saved = out / "config.json"
    if not saved.is_file():
        return False
    old, new = json.loads(saved.read_text()), cfg.to_dict()
    return any(old.get(k) != v for k, v in new.items() if k not in RESUMABLE_CHANGES)


def vae_lr_factor(step: int, cfg: TrainConfig) -> float:
    """VAE-phase learning rate / ``vae_lr``: cosine from 1 at step 0 to ``vae_lr_final`` at ``vae_steps``."""
    t = min(step / max(cfg.vae_steps, 1), 1.0)
    return cfg.vae_lr_final + (1.0 - cfg.vae_lr_final) * 0.5 * (1.0 + math.cos(math.pi * t))


def masked_mse(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the valid entries (``mask`` broadcast over channels)."""
    mask = mask.expand_as(pred)
    return ((pred - target) ** 2 * mask).sum() / mask.sum().clamp_min(1.0)


def train(cfg: TrainConfig, resume: bool = True, progress: bool = True) -> Path:
    """Run (or continue) the training described by ``cfg``; returns the saved pipeline folder."""
    from accelerate import Accelerator
    from accelerate.utils import set_seed

    cfg.check()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    acc = Accelerator(mixed_precision=cfg.mixed_precision)
    set_seed(cfg.seed)
    pipe = load_initial(cfg.init, cfg.seed).to(acc.device)
    pipe.freeze()
    dataset = BufferDataset(make_readers(cfg.data), cfg.size)
    train_vae = cfg.vae_steps > 0
    if train_vae and cfg.init not in RANDOM_INITS:
        raise ValueError("vae_steps > 0 trains the VAE, which only a random-weight model (init tiny/small/sd2) needs")
    prompts = {b: e for b, e in zip(BUFFERS, pipe.encode_prompts(BUFFERS))}
    if cfg.gradient_checkpointing:
        pipe.unet.enable_gradient_checkpointing()

    unet_opt = torch.optim.AdamW(pipe.unet.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    unet_sched = torch.optim.lr_scheduler.LambdaLR(unet_opt, lambda s: cfg.lr_final ** (s / cfg.iterations))
    unet, unet_opt, unet_sched = acc.prepare(pipe.unet, unet_opt, unet_sched)
    if train_vae:
        pipe.vae.requires_grad_(True)
        vae_opt = torch.optim.AdamW(pipe.vae.parameters(), lr=cfg.vae_lr, weight_decay=0.0)
        vae_sched = torch.optim.lr_scheduler.LambdaLR(vae_opt, lambda s: vae_lr_factor(s, cfg))
        vae, vae_opt, vae_sched = acc.prepare(pipe.vae, vae_opt, vae_sched)

    start = 0
    ckpt = latest_checkpoint(out) if resume else None
    if ckpt is not None and _changed_since_checkpoints(out, cfg):
        # nothing lost: the other run's checkpoints, log and options move aside
        kept = out / "replaced" / time.strftime("%Y%m%dT%H%M%S", time.gmtime())
        kept.mkdir(parents=True, exist_ok=True)
        for name in ("checkpoints", "train_log.jsonl", "config.json"):
            if (out / name).exists():
                shutil.move(str(out / name), str(kept / name))
        acc.print(f"{out}: the training options changed since its checkpoints were written; starting afresh "
                  f"(the previous run's checkpoints, log and options are in {kept})")
        ckpt = None
    if ckpt is None:  # a fresh run (or --fresh): forget any previous run's checkpoints and log
        shutil.rmtree(out / "checkpoints", ignore_errors=True)
        (out / "train_log.jsonl").unlink(missing_ok=True)
    if ckpt is not None:
        acc.load_state(str(ckpt))
        meta = json.loads((ckpt / "meta.json").read_text())
        start = meta["step"]
        pipe.vae.register_to_config(scaling_factor=meta["scaling_factor"])
        acc.print(f"resumed from {ckpt} (step {start})")
    (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))

    total = cfg.vae_steps + cfg.iterations
    log = (out / "train_log.jsonl").open("a")
    bar = tqdm(range(start, total), initial=start, total=total, desc="buffernet", disable=not progress,
               dynamic_ncols=True)
    t0, running = time.perf_counter(), []
    for step in bar:
        if step == cfg.vae_steps and train_vae:
            _set_scaling_factor(pipe, dataset, cfg)
            pipe.vae.requires_grad_(False)
            pipe.vae.eval()
        if step < cfg.vae_steps:
            phase, loss = "vae", _vae_step(pipe, vae, vae_opt, dataset, cfg, step, acc)
            vae_sched.step()
        else:
            phase, loss = "unet", _unet_step(pipe, unet, unet_opt, unet_sched, dataset, prompts, cfg, step, acc)
        running.append(loss)
        if (step + 1) % cfg.log_every == 0 or step + 1 == total:
            mean = sum(running) / len(running)
            running = []
            lr = (vae_sched if phase == "vae" else unet_sched).get_last_lr()[0]
            bar.set_postfix(phase=phase, loss=f"{mean:.4f}")
            log.write(json.dumps({"step": step + 1, "phase": phase, "loss": mean, "lr": lr,
                                  "seconds": round(time.perf_counter() - t0, 2)}) + "\n")
            log.flush()
        if (step + 1) % cfg.checkpoint_every == 0 and step + 1 < total:
            _save_checkpoint(acc, pipe, out, step + 1, cfg.keep_checkpoints)
    log.close()
    if start < total:
        _save_checkpoint(acc, pipe, out, total, cfg.keep_checkpoints)
    final = out / "pipeline"
    acc.wait_for_everyone()
    if acc.is_main_process:
        pipe.unet.disable_gradient_checkpointing()
        tmp = out / ".pipeline.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        pipe.save_pretrained(tmp)
        shutil.rmtree(final, ignore_errors=True)
        tmp.rename(final)
    return final


def _unet_step(pipe, unet, opt, sched, dataset, prompts, cfg: TrainConfig, step: int, acc) -> float:
    unet.train()
    total = 0.0
    for micro in range(cfg.grad_accum):
        enc = encode_items(draw_batch(dataset, cfg.seed, step, micro, cfg.batch_size))
        with torch.no_grad():
            image_lat = pipe.image_latents(enc["rgb"].to(acc.device))
            target_lat = pipe.image_latents(enc["targets"].to(acc.device))
        index = torch.tensor([i for i, _ in enc["rows"]], device=acc.device)
        embeds = torch.stack([prompts[b] for _, b in enc["rows"]]).to(acc.device)
        masks = enc["masks"].to(acc.device)
        with acc.autocast():
            x0 = pipe.x0_latents(image_lat[index], embeds, unet=unet)
        loss = masked_mse(x0.float(), target_lat.float(), latent_mask(masks, tuple(x0.shape[-2:])))
        if cfg.pixel_loss > 0:
            decoded = pipe.decode_latents(x0.to(pipe.vae.dtype)).float()
            loss = loss + cfg.pixel_loss * masked_mse(decoded, enc["targets"].to(acc.device), masks[:, None])
        acc.backward(loss / cfg.grad_accum)
        total += float(loss.detach()) / cfg.grad_accum
    opt.step()
    sched.step()
    opt.zero_grad(set_to_none=True)
    return total


def _vae_step(pipe, vae, opt, dataset, cfg: TrainConfig, step: int, acc) -> float:
    vae.train()
    total = 0.0
    for micro in range(cfg.grad_accum):
        enc = encode_items(draw_batch(dataset, cfg.seed, step, micro, cfg.batch_size))
        # the images and as many of their buffers (drawn from (seed, step)): an autoencoder of both kinds
        n = len(enc["rgb"])
        pick = torch.randperm(len(enc["targets"]), generator=torch.Generator().manual_seed(cfg.seed * 100003 + step))[:n]
        x = torch.cat([enc["rgb"], enc["targets"][pick]]).to(acc.device)
        mask = torch.cat([torch.ones(n, 1, *x.shape[-2:]), enc["masks"][pick][:, None]]).to(acc.device)
        with acc.autocast():
            posterior = vae.encode(x).latent_dist
            recon = vae.decode(posterior.mean).sample
        loss = masked_mse(recon.float(), x, mask) + KL_WEIGHT * posterior.kl().mean()
        acc.backward(loss / cfg.grad_accum)
        total += float(loss.detach()) / cfg.grad_accum
    opt.step()
    opt.zero_grad(set_to_none=True)
    return total


@torch.no_grad()
def _set_scaling_factor(pipe, dataset, cfg: TrainConfig) -> None:
    """SD's rule for a newly trained VAE: scaling factor = 1 / std of the latents (on a fixed batch)."""
    enc = encode_items(draw_batch(dataset, cfg.seed, 2**31, 0, max(cfg.batch_size, 16)))  # step 2**31: no run reaches it
    x = torch.cat([enc["rgb"], enc["targets"]]).to(pipe.vae.device)
    std = float(pipe.vae.encode(x).latent_dist.mean.std())
    pipe.vae.register_to_config(scaling_factor=1.0 / max(std, 1e-6))


def _save_checkpoint(acc, pipe, out: Path, step: int, keep: int) -> None:
    ckpt = out / "checkpoints" / f"step_{step:07d}"
    acc.save_state(str(ckpt))
    if acc.is_main_process:
        (ckpt / "meta.json").write_text(json.dumps({"step": step,
                                                    "scaling_factor": pipe.vae.config.scaling_factor}))
        for old in sorted((out / "checkpoints").glob("step_*"))[:-keep]:
            shutil.rmtree(old, ignore_errors=True)
