"""Buffer network (ARCHITECTURE.md, "Buffer network"): one linear RGB image -> G-buffers in one batched step.

A Stable Diffusion 2 UNet, conv_in widened 4 -> 8 (image latent + zero latent), run once at timestep 999 with
one text prompt per buffer; its v prediction is turned into x0 and decoded by the VAE.

- ``codec``: buffer names, prompts, and the encodings of images / buffers into [-1, 1] and back.
- ``tokenizer``: CLIP's tokenizer built offline from the vocabulary in the open-clip-torch wheel.
- ``pipeline``: ``BufferNetPipeline`` (a diffusers pipeline: save_pretrained / from_pretrained(local_dir)).
- ``build``: random tiny / small models, the real SD2 configs, ``widen_conv_in``, ``from_stable_diffusion``.
"""

from .build import build_pipeline, from_stable_diffusion, sd2_configs, widen_conv_in
from .codec import BUFFERS, PROMPTS, decode_output, encode_rgb, encode_target, input_exposure
from .pipeline import BufferNetPipeline
from .tokenizer import clip_tokenizer

__all__ = [
    "BUFFERS", "PROMPTS", "BufferNetPipeline", "build_pipeline", "clip_tokenizer", "decode_output", "encode_rgb",
    "encode_target", "from_stable_diffusion", "input_exposure", "sd2_configs", "widen_conv_in",
]
