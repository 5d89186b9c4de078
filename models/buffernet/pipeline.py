"""``BufferNetPipeline``: a Stable Diffusion 2 UNet used as a one-step buffer predictor (ARCHITECTURE.md).

One forward per image and per buffer, all buffers batched: the image latent (VAE mean x scaling factor) is
concatenated with a zero latent (conv_in has 8 input channels: image first), the UNet runs at the fixed
timestep 999 with the buffer's prompt, and its v prediction becomes x0:

    x0 = sqrt(abar_999) z_t - sqrt(1 - abar_999) v,   z_t = 0 (the zero latent)

``abar_999`` is the scheduler's ``alphas_cumprod[999]``; with SD2's scaled-linear betas (no zero-terminal-SNR
rescaling, the schedule the pretrained weights were trained with) it is 0.0047, so x0 = -0.998 v. A scheduler
configured with ``rescale_betas_zero_snr=True`` gives abar = 0 and x0 = -v exactly; nothing else of the
scheduler is used. ``x0_latents`` is the one function both training (latent loss) and inference call.

Saved and loaded as a diffusers pipeline folder (``save_pretrained`` / ``from_pretrained(local_dir)``, works
with ``HF_HUB_OFFLINE=1``); every component is a stock diffusers / transformers class.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from diffusers import AutoencoderKL, DDPMScheduler, DiffusionPipeline, UNet2DConditionModel
from transformers import CLIPTextModel, CLIPTokenizer

from .codec import (BUFFERS, PROMPTS, RADIANCE_MODES, check_buffer, check_rgb, decode_output, encode_rgb,
                    input_exposure, split_radiance)

IN_CHANNELS = 8  # image latent (4) + zero latent (4)


def resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """``[B, C, H, W]`` -> ``[B, C, *size]``: bilinear, antialiased (area-like) where it shrinks; identity if
    the size already matches."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)


def size_for(height: int, width: int, multiple: int, resolution: int | None = None) -> tuple[int, int]:
    """Processing size: (optionally) scale so the longer side is ``resolution``, then round each side to the
    nearest multiple of ``multiple`` (at least one multiple)."""
    scale = 1.0 if resolution is None else resolution / max(height, width)
    return tuple(max(multiple, int(round(s * scale / multiple)) * multiple) for s in (height, width))


class BufferNetPipeline(DiffusionPipeline):
    """Image -> buffers (``codec.BUFFERS``) in one batched UNet step. Components: ``unet``
    (UNet2DConditionModel, in_channels 8, v prediction), ``vae`` (AutoencoderKL), ``text_encoder``
    (CLIPTextModel), ``tokenizer`` (CLIPTokenizer), ``scheduler`` (DDPMScheduler, v_prediction; only
    ``alphas_cumprod[999]`` is used)."""

    model_cpu_offload_seq = "text_encoder->unet->vae"

    def __init__(self, unet: UNet2DConditionModel, vae: AutoencoderKL, text_encoder: CLIPTextModel,
                 tokenizer: CLIPTokenizer, scheduler: DDPMScheduler):
        super().__init__()
        if unet.config.in_channels != IN_CHANNELS:
            raise ValueError(f"the UNet takes {unet.config.in_channels} input channels; a buffer network needs "
                             f"{IN_CHANNELS} (image latent + zero latent): widen it with build.widen_conv_in")
        if scheduler.config.prediction_type != "v_prediction":
            raise ValueError(f"scheduler prediction_type is {scheduler.config.prediction_type!r}; the buffer "
                             "network predicts v ('v_prediction')")
        self.register_modules(unet=unet, vae=vae, text_encoder=text_encoder, tokenizer=tokenizer,
                              scheduler=scheduler)
        self._prompt_cache: dict[tuple, torch.Tensor] = {}

    # --- sizes and schedule ------------------------------------------------------------------------------

    @property
    def multiple(self) -> int:
        """Image sides must be multiples of this: VAE downsampling x UNet downsampling (64 for SD2)."""
        vae = 2 ** (len(self.vae.config.block_out_channels) - 1)
        unet = 2 ** (len(self.unet.config.down_block_types) - 1)
        return vae * unet

    @property
    def timestep(self) -> int:
        """The fixed timestep: the last training step (999)."""
        return self.scheduler.config.num_train_timesteps - 1

    # --- the three stages ---------------------------------------------------------------------------------

    def encode_prompts(self, buffers: Sequence[str]) -> torch.Tensor:
        """``[B, 77, D]`` text embeddings (last hidden state), one per buffer; cached per buffer, text encoder,
        device and dtype (the text encoder is frozen)."""
        for b in buffers:
            check_buffer(b)
        device, dtype = self.text_encoder.device, self.unet.dtype
        key = (id(self.text_encoder), device, dtype)
        missing = [b for b in dict.fromkeys(buffers) if (b, *key) not in self._prompt_cache]
        if missing:
            ids = self.tokenizer([PROMPTS[b] for b in missing], padding="max_length", truncation=True,
                                 max_length=self.tokenizer.model_max_length, return_tensors="pt").input_ids
            with torch.no_grad():
                emb = self.text_encoder(ids.to(device))[0].to(dtype)
            for b, e in zip(missing, emb):
                self._prompt_cache[(b, *key)] = e
        return torch.stack([self._prompt_cache[(b, *key)] for b in buffers])

    def image_latents(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` ``[B, 3, H, W]`` in [-1, 1] (``codec.encode_rgb`` / ``encode_target``) -> ``[B, 4, h, w]``:
        the VAE posterior mean x scaling factor. Also the latent training targets."""
        x = x.to(self.vae.device, self.vae.dtype)
        return self.vae.encode(x).latent_dist.mean * self.vae.config.scaling_factor

    def x0_latents(self, image_latents: torch.Tensor, prompt_embeds: torch.Tensor,
                   unet: torch.nn.Module | None = None) -> torch.Tensor:
        """``[B, 4, h, w]`` image latents + ``[B, 77, D]`` prompts -> ``[B, 4, h, w]`` predicted buffer latents
        (module docstring). Differentiable w.r.t. the UNet; used by training and inference alike. ``unet``:
        the same UNet wrapped for training (accelerate / DDP), default ``self.unet``."""
        if image_latents.shape[0] != prompt_embeds.shape[0]:
            raise ValueError(f"{image_latents.shape[0]} image latents but {prompt_embeds.shape[0]} prompts")
        z_t = torch.zeros_like(image_latents)
        t = torch.full((image_latents.shape[0],), self.timestep, dtype=torch.long, device=image_latents.device)
        v = (unet or self.unet)(torch.cat([image_latents, z_t], dim=1), t, encoder_hidden_states=prompt_embeds).sample
        abar = float(self.scheduler.alphas_cumprod[self.timestep])
        return math.sqrt(abar) * z_t - math.sqrt(1.0 - abar) * v

    def decode_latents(self, latents: torch.Tensor) -> torch.Tensor:
        """``[B, 4, h, w]`` -> ``[B, 3, H, W]`` images (nominally [-1, 1], not clipped)."""
        return self.vae.decode(latents / self.vae.config.scaling_factor).sample

    # --- inference ----------------------------------------------------------------------------------------

    @torch.no_grad()
    def predict(self, rgb_linear: np.ndarray, buffers: Sequence[str] = BUFFERS, *, batched: bool = True,
                resolution: int | None = None, radiance: str = "complement") -> dict[str, np.ndarray]:
        """Linear RGB ``[H, W, 3]`` -> ``{buffer: array}`` in capture conventions (``codec``), at ``H x W``:
        ``predict_images`` then ``codec.decode_output`` per buffer.

        ``radiance``: how the diffuse is formed. ``"complement"`` (default): the image minus the specular
        prediction (``codec.split_radiance``; diffuse + specular = the image exactly, the specular clipped to
        [0, image]); the specular prompt runs, in the same batch, even when only the diffuse is asked for.
        ``"heads"``: each prompt's own output (the diffuse prompt's, and the specular unclipped)."""
        if radiance not in RADIANCE_MODES:
            raise ValueError(f"radiance must be one of {', '.join(RADIANCE_MODES)}, got {radiance!r}")
        buffers = tuple(buffers)
        complement = radiance == "complement" and "diffuse" in buffers
        run = buffers + ("specular",) if complement and "specular" not in buffers else buffers
        images, exposure = self.predict_images(rgb_linear, run, batched=batched, resolution=resolution)
        out = {b: decode_output(b, images[i], exposure) for i, b in enumerate(run)}
        if complement:
            out["diffuse"], out["specular"] = split_radiance(rgb_linear, out["specular"])
        return {b: out[b] for b in buffers}

    @torch.no_grad()
    def predict_images(self, rgb_linear: np.ndarray, buffers: Sequence[str] = BUFFERS, *, batched: bool = True,
                       resolution: int | None = None) -> tuple[torch.Tensor, float]:
        """Linear RGB ``[H, W, 3]`` -> (``[B, 3, H, W]`` float32 CPU network outputs in the codec's [-1, 1]
        space, one per buffer, not yet decoded; the input's exposure).

        The image is exposed + tonemapped (``codec``), resized (bilinear, antialiased) to ``size_for(H, W,
        multiple, resolution)``, encoded once, and all requested buffers run as ONE UNet batch (image latent
        repeated, prompts batched) and one VAE decode; outputs are resized back to ``H x W``.
        ``batched=False`` runs the whole chain once per buffer instead (same numbers; the naive baseline)."""
        rgb = check_rgb(rgb_linear)
        buffers = tuple(buffers)
        if not buffers:
            raise ValueError("no buffers requested; valid buffers: " + ", ".join(PROMPTS))
        for b in buffers:
            check_buffer(b)
        if not batched:
            runs = [self.predict_images(rgb, (b,), resolution=resolution) for b in buffers]
            return torch.cat([images for images, _ in runs]), runs[0][1]
        height, width = rgb.shape[:2]
        exposure = input_exposure(rgb)
        x = resize(encode_rgb(rgb, exposure)[None], size_for(height, width, self.multiple, resolution))
        latents = self.image_latents(x.to(self.device))
        embeds = self.encode_prompts(buffers)
        x0 = self.x0_latents(latents.expand(len(buffers), -1, -1, -1), embeds.to(latents.device))
        return resize(self.decode_latents(x0).float().cpu(), (height, width)), exposure

    def predict_per_prompt(self, rgb_linear: np.ndarray, buffers: Sequence[str] = BUFFERS,
                           resolution: int | None = None, radiance: str = "complement") -> dict[str, np.ndarray]:
        """``predict`` with one full run per buffer (for the batched-vs-per-prompt comparison and benchmark)."""
        return self.predict(rgb_linear, buffers, batched=False, resolution=resolution, radiance=radiance)

    # --- training -----------------------------------------------------------------------------------------

    def freeze(self) -> None:
        """What training updates: the UNet. The VAE and text encoder are frozen (no grad, eval mode)."""
        for module in (self.vae, self.text_encoder):
            module.requires_grad_(False)
            module.eval()
        self.unet.requires_grad_(True)

    def trainable_parameters(self) -> list[torch.nn.Parameter]:
        """``freeze()`` then the UNet's parameters (what the optimiser gets)."""
        self.freeze()
        return [p for p in self.unet.parameters() if p.requires_grad]
