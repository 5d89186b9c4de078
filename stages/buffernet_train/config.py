"""``TrainConfig``: everything one buffer-network training run depends on (saved beside its checkpoints)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from stages.config import reject_unknown


@dataclass
class TrainConfig:
    """Defaults follow REFERENCE.md's recipe (AdamW 3e-5, exponential decay, fp32, gradient checkpointing)
    except where a CPU run needs otherwise (the command line / preset sets them)."""

    data: list[str] = field(default_factory=list)  # sources, each "hypersim:DIR", "interiorverse:DIR[:split]"
                                                   # or "captures:DIR" (a capture, or a folder of captures)
    init: str = "small"            # "tiny" | "small" (random weights, SD2 architecture) | a local folder: an SD2
                                   # checkpoint (diffusers layout, conv_in widened) or a saved buffer network
    out: str = "results/buffernet"  # output folder: pipeline/, checkpoints/, train_log.jsonl, stage.json
    iterations: int = 20000        # UNet optimiser steps
    batch_size: int = 8            # images per micro-batch (every buffer an image has is one UNet row)
    grad_accum: int = 4            # micro-batches per step: effective batch = batch_size x grad_accum (ref. 32)
    size: int = 128                # training crops are resized to size x size
    lr: float = 3e-5
    lr_final: float = 0.1          # exponential decay: lr x lr_final ** (step / iterations)
    weight_decay: float = 1e-2
    pixel_loss: float = 0.0        # weight of a masked pixel MSE after VAE decoding (0 = latent MSE only)
    vae_steps: int = 0             # first train the VAE as an autoencoder for this many steps (only for
                                   # random-weight models: SD2's own VAE stays frozen)
    vae_lr: float = 1e-3
    vae_lr_final: float = 0.02     # VAE phase: cosine decay from vae_lr to vae_lr x vae_lr_final (a constant lr
                                   # stalls the autoencoder at the noise floor of its steps; measured in README)
    checkpoint_every: int = 500    # steps between checkpoints (accelerate state: exact resume)
    keep_checkpoints: int = 2
    mixed_precision: str = "no"    # "no" | "fp16" | "bf16" (GPU); CPU trains in fp32
    gradient_checkpointing: bool = True
    seed: int = 0
    log_every: int = 10
    num_workers: int = 0           # DataLoader-free: batches are drawn deterministically per step (exact resume)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        reject_unknown(cls, d, "buffernet-train")
        cfg = cls(**d)
        cfg.check()
        return cfg

    def check(self) -> None:
        if not self.data:
            raise ValueError("no training data: give at least one source (hypersim:DIR, interiorverse:DIR, captures:DIR)")
        for name in ("iterations", "batch_size", "grad_accum", "size", "checkpoint_every", "keep_checkpoints", "log_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.vae_steps < 0:
            raise ValueError(f"vae_steps must be >= 0, got {self.vae_steps}")
        for name in ("lr_final", "vae_lr_final"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)}")
        if self.mixed_precision not in ("no", "fp16", "bf16"):
            raise ValueError(f"mixed_precision must be no, fp16 or bf16, got {self.mixed_precision!r}")

    def to_dict(self) -> dict:
        return asdict(self)
