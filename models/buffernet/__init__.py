"""Buffer network (ARCHITECTURE.md, "Buffer network"): one linear RGB image -> G-buffers in one batched step.

A Stable Diffusion 2 UNet, conv_in widened 4 -> 8 (image latent + zero latent), run once at timestep 999 with
one text prompt per buffer; its v prediction is turned into x0 and decoded by the VAE.

- ``codec``: buffer names, prompts, and the encodings of images / buffers into [-1, 1] and back.
- ``tokenizer``: CLIP's tokenizer built offline from the vocabulary in the open-clip-torch wheel.
- ``pipeline``: ``BufferNetPipeline`` (a diffusers pipeline: save_pretrained / from_pretrained(local_dir)).
- ``build``: random tiny / small models, the real SD2 configs, ``widen_conv_in``, ``from_stable_diffusion``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from models.lazy import lazy_getattr

# name -> submodule; imported on first use (PEP 562), so that importing models.buffernet.training.config or
# models.buffernet.fill (the settings, what a stage's --help and the workflow need) does not load torch / diffusers
_EXPORTS = {
    "build_pipeline": "build", "from_stable_diffusion": "build", "sd2_configs": "build", "widen_conv_in": "build",
    "BUFFERS": "codec", "PROMPTS": "codec", "decode_output": "codec", "encode_rgb": "codec", "encode_target": "codec",
    "input_exposure": "codec", "BufferNetPipeline": "pipeline", "clip_tokenizer": "tokenizer",
}
__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:
    from .build import build_pipeline, from_stable_diffusion, sd2_configs, widen_conv_in
    from .codec import BUFFERS, PROMPTS, decode_output, encode_rgb, encode_target, input_exposure
    from .pipeline import BufferNetPipeline
    from .tokenizer import clip_tokenizer


__getattr__ = lazy_getattr(__name__, _EXPORTS, globals())
