"""``TrainConfig``: everything one buffer-network training run depends on (saved beside its checkpoints)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from models.settings import from_dict, setting


@dataclass
class TrainConfig:
    """Buffer-network training settings. Defaults follow REFERENCE.md's recipe (AdamW 3e-5, exponential decay,
    fp32, gradient checkpointing) except where a CPU run needs otherwise (the command line / preset sets them)."""

    data: list[str] = setting(default_factory=list, doc="sources, each hypersim:DIR, interiorverse:DIR[:split] or "
                              "captures:DIR (a capture, or a folder of captures)")
    init: str = setting("small", "tiny | small (random weights, SD2 architecture) | sd2 (random weights, SD2's exact "
                        "sizes) | a local folder: an SD2 checkpoint "
                        "(diffusers layout, conv_in widened) or a saved buffer network")
    out: str = setting("results/buffernet", "output folder: pipeline/, checkpoints/, train_log.jsonl, stage.json")
    iterations: int = setting(20000, "UNet optimiser steps", minimum=1)
    batch_size: int = setting(8, "images per micro-batch (every buffer an image has is one UNet row)", minimum=1)
    grad_accum: int = setting(4, "micro-batches per step: effective batch = batch_size x grad_accum (ref. 32)",
                              minimum=1)
    size: int = setting(128, "training crops are resized to size x size", minimum=1)
    lr: float = setting(3e-5, "UNet learning rate", exclusiveMinimum=0)
    lr_final: float = setting(0.1, "exponential decay: lr x lr_final ** (step / iterations)", exclusiveMinimum=0,
                              maximum=1)
    weight_decay: float = setting(1e-2, "AdamW weight decay", minimum=0)
    pixel_loss: float = setting(0.0, "weight of a masked pixel MSE after VAE decoding (0 = latent MSE only)",
                                minimum=0)
    vae_steps: int = setting(0, "first train the VAE as an autoencoder for this many steps (only for random-weight "
                             "models: SD2's own VAE stays frozen)", minimum=0)
    vae_lr: float = setting(1e-3, "VAE phase learning rate", exclusiveMinimum=0)
    vae_lr_final: float = setting(0.02, "VAE phase: cosine decay from vae_lr to vae_lr x vae_lr_final (a constant "
                                  "lr stalls the autoencoder at the noise floor of its steps)", exclusiveMinimum=0,
                                  maximum=1)
    checkpoint_every: int = setting(500, "steps between checkpoints (accelerate state: exact resume)", minimum=1)
    keep_checkpoints: int = setting(2, "checkpoints kept", minimum=1)
    mixed_precision: str = setting("no", "no | fp16 | bf16 (GPU); CPU trains in fp32", enum=["no", "fp16", "bf16"])
    gradient_checkpointing: bool = setting(True, "recompute activations in the backward pass (less memory, ~30% "
                                           "slower)")
    seed: int = setting(0, "random seed")
    log_every: int = setting(10, "steps between log lines", minimum=1)
    num_workers: int = setting(0, "DataLoader-free: batches are drawn deterministically per step (exact resume)",
                               minimum=0)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        cfg = from_dict(cls, d, "buffernet-train")
        cfg.check()
        return cfg

    def check(self) -> None:
        if not self.data:
            raise ValueError("no training data: give at least one source (hypersim:DIR, interiorverse:DIR, captures:DIR)")

    def to_dict(self) -> dict:
        return asdict(self)
