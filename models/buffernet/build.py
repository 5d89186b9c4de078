"""Building a ``BufferNetPipeline``: from the real stable-diffusion-2 weights on disk, or random weights of the
same architecture family at test / CPU-training size, or at SD2's exact size.

``from_stable_diffusion(local_dir)`` loads a diffusers-layout SD2 folder (``unet/``, ``vae/``,
``text_encoder/``, ``tokenizer/``, ``scheduler/``) without the hub and widens conv_in 4 -> 8
(``widen_conv_in``). ``build_pipeline("tiny" | "small" | "sd2")`` gives random weights: "tiny" for unit tests,
"small" for training on CPU at 64..128 px, "sd2" SD2's exact configs (``sd2_configs()``: 866M-parameter UNet, 84M
VAE, 340M OpenCLIP ViT-H text tower; ~5 GB fp32) for timing and memory runs at the paper's scale without a download.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import torch
from diffusers import AutoencoderKL, DDPMScheduler, UNet2DConditionModel
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

from .pipeline import IN_CHANNELS, BufferNetPipeline
from .tokenizer import MAX_LENGTH, clip_tokenizer

VOCAB_SIZE = 49408  # CLIP's BPE vocabulary (tokenizer.py)
RANDOM_INITS = ("tiny", "small", "sd2")  # build_pipeline sizes (random weights)

# stabilityai/stable-diffusion-2 (768-v): scaled-linear betas, v prediction, no zero-terminal-SNR rescaling.
SCHEDULER_CONFIG = dict(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                        clip_sample=False, prediction_type="v_prediction", steps_offset=1,
                        rescale_betas_zero_snr=False)


def sd2_configs() -> dict[str, dict]:
    """Component configs of stabilityai/stable-diffusion-2 (768-v), as in its diffusers folder (documentation;
    instantiating the UNet allocates ~865M parameters). Note diffusers' ``attention_head_dim`` is SD2's number
    of heads per block (head size 64)."""
    unet = dict(sample_size=96, in_channels=4, out_channels=4, layers_per_block=2,
                block_out_channels=(320, 640, 1280, 1280),
                down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
                up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3,
                attention_head_dim=(5, 10, 20, 20), cross_attention_dim=1024, use_linear_projection=True,
                upcast_attention=True, norm_num_groups=32, flip_sin_to_cos=True, freq_shift=0)
    vae = dict(in_channels=3, out_channels=3, latent_channels=4, layers_per_block=2,
               block_out_channels=(128, 256, 512, 512), down_block_types=("DownEncoderBlock2D",) * 4,
               up_block_types=("UpDecoderBlock2D",) * 4, norm_num_groups=32, sample_size=768,
               scaling_factor=0.18215)
    # OpenCLIP ViT-H/14 text tower without its last layer (SD2 uses the penultimate layer's output).
    text = dict(vocab_size=VOCAB_SIZE, hidden_size=1024, intermediate_size=4096, num_hidden_layers=23,
                num_attention_heads=16, max_position_embeddings=MAX_LENGTH, hidden_act="gelu", projection_dim=512)
    return {"unet": unet, "vae": vae, "text_encoder": text, "scheduler": dict(SCHEDULER_CONFIG)}


def _random_configs(size: str) -> dict[str, dict]:
    """SD2's layout (cross-attention down blocks then a plain one, linear projections, text hidden size =
    cross-attention size, 49408 x 77 text embeddings) at reduced width. ``multiple``: tiny 8, small 8."""
    if size == "tiny":  # unit tests: well under a second per 6-buffer forward at 64 x 64
        width, text_width = (32, 64), 32
        unet = dict(block_out_channels=width, layers_per_block=1, attention_head_dim=(2, 4), norm_num_groups=8,
                    down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
                    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), sample_size=8)
        vae = dict(block_out_channels=(16, 32, 32), layers_per_block=1, norm_num_groups=8, sample_size=64)
        text = dict(hidden_size=text_width, intermediate_size=64, num_hidden_layers=2, num_attention_heads=4)
    elif size == "small":  # trainable on a 2-core CPU at 64..128 px
        width, text_width = (32, 64, 64), 64
        unet = dict(block_out_channels=width, layers_per_block=1, attention_head_dim=(2, 4, 4), norm_num_groups=8,
                    down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
                    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"), sample_size=32)
        # VAE downsampling x2 only (SD's is x8): a VAE trained from scratch on a CPU for minutes cannot squeeze
        # 64 x 64 textures through an x4 (16 x 16 x 4) latent; the x2 one reconstructs them (measured in the
        # README: the "VAE ceiling" column of `python -m stages.buffernet_train evaluate`)
        vae = dict(block_out_channels=(32, 64), layers_per_block=1, norm_num_groups=16, sample_size=128)
        text = dict(hidden_size=text_width, intermediate_size=256, num_hidden_layers=2, num_attention_heads=4)
    else:
        raise ValueError(f"unknown model size {size!r}; valid sizes: {', '.join(RANDOM_INITS)}")
    unet.update(in_channels=4, out_channels=4, cross_attention_dim=text_width, use_linear_projection=True)
    n = len(vae["block_out_channels"])
    vae.update(in_channels=3, out_channels=3, latent_channels=4, down_block_types=("DownEncoderBlock2D",) * n,
               up_block_types=("UpDecoderBlock2D",) * n)
    text.update(vocab_size=VOCAB_SIZE, max_position_embeddings=MAX_LENGTH, hidden_act="gelu")
    return {"unet": unet, "vae": vae, "text_encoder": text}


def widen_conv_in(unet: UNet2DConditionModel) -> UNet2DConditionModel:
    """conv_in 4 -> 8 input channels in place: weight ``cat(w, w) / 2``, same bias; config ``in_channels=8``.

    Hence the widened UNet on ``cat(z, z)`` equals the original on ``z`` (what "preserves the 4-channel output
    on the image half" means; tested). With the zero latent in the second half, as the buffer network feeds
    it, the first layer sees ``w z / 2 + b``: the image latent at half weight, which fine-tuning adapts."""
    old = unet.conv_in
    if old.in_channels != 4:
        raise ValueError(f"conv_in has {old.in_channels} input channels; widen_conv_in expects SD's 4")
    new = torch.nn.Conv2d(IN_CHANNELS, old.out_channels, old.kernel_size, old.stride, old.padding,
                          bias=old.bias is not None, device=old.weight.device, dtype=old.weight.dtype)
    with torch.no_grad():
        new.weight.copy_(torch.cat([old.weight, old.weight], dim=1) / 2.0)
        if old.bias is not None:
            new.bias.copy_(old.bias)
    unet.conv_in = new
    unet.register_to_config(in_channels=IN_CHANNELS)
    return unet


def build_pipeline(size: str = "tiny", seed: int = 0, tokenizer: CLIPTokenizer | None = None) -> BufferNetPipeline:
    """Random weights (``torch.manual_seed(seed)``) of SD2's architecture at ``size`` "tiny" or "small", or of
    SD2 itself ("sd2": ``sd2_configs()``), conv_in widened to 8. The tokenizer is CLIP's real one
    (``clip_tokenizer()``) unless given.

    Note: the VAE is random too, so a "small" model's decoded outputs mean nothing until its VAE has been
    trained as an autoencoder; the real model uses SD2's VAE (``from_stable_diffusion``)."""
    cfg = sd2_configs() if size == "sd2" else _random_configs(size)
    torch.manual_seed(seed)
    unet = widen_conv_in(UNet2DConditionModel(**cfg["unet"]))
    vae = AutoencoderKL(**cfg["vae"])
    text_encoder = CLIPTextModel(CLIPTextConfig(**cfg["text_encoder"]))
    pipe = BufferNetPipeline(unet=unet.eval(), vae=vae.eval(), text_encoder=text_encoder.eval(),
                             tokenizer=tokenizer if tokenizer is not None else clip_tokenizer(),
                             scheduler=DDPMScheduler(**SCHEDULER_CONFIG))
    return pipe


def from_stable_diffusion(local_dir: str | Path, torch_dtype: torch.dtype = torch.float32) -> BufferNetPipeline:
    """A buffer network initialised from a local stable-diffusion-2 folder (diffusers layout), never the hub:
    UNet (conv_in widened 4 -> 8), VAE, text encoder, tokenizer (``tokenizer/`` if present, else
    ``clip_tokenizer()``), and a DDPMScheduler from its ``scheduler/`` config with ``prediction_type`` set to
    ``v_prediction`` (a warning if the source was not a v model, e.g. stable-diffusion-2-base)."""
    root = Path(local_dir)
    if not (root / "unet" / "config.json").is_file():
        raise FileNotFoundError(f"{root} is not a diffusers Stable Diffusion folder (no unet/config.json); "
                                "download stabilityai/stable-diffusion-2 once and pass its local path")
    kw = dict(local_files_only=True)
    unet = UNet2DConditionModel.from_pretrained(root, subfolder="unet", torch_dtype=torch_dtype, **kw)
    vae = AutoencoderKL.from_pretrained(root, subfolder="vae", torch_dtype=torch_dtype, **kw)
    text_encoder = CLIPTextModel.from_pretrained(root, subfolder="text_encoder", dtype=torch_dtype, **kw)
    if (root / "tokenizer").is_dir():
        tokenizer = CLIPTokenizer.from_pretrained(root, subfolder="tokenizer", **kw)
    else:
        tokenizer = clip_tokenizer()
    if (root / "scheduler").is_dir():
        sched_cfg = DDPMScheduler.load_config(root, subfolder="scheduler", **kw)
    else:
        sched_cfg = dict(SCHEDULER_CONFIG)
    if sched_cfg.get("prediction_type", "epsilon") != "v_prediction":
        warnings.warn(f"{root}: the scheduler's prediction_type is {sched_cfg.get('prediction_type')!r}; the "
                      "buffer network predicts v (stabilityai/stable-diffusion-2 768-v is a v model)", stacklevel=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # other schedulers' config keys (Euler's sigmas, ...) are ignored
        scheduler = DDPMScheduler.from_config(sched_cfg, prediction_type="v_prediction")
    return BufferNetPipeline(unet=widen_conv_in(unet).eval(), vae=vae.eval(), text_encoder=text_encoder.eval(),
                             tokenizer=tokenizer, scheduler=scheduler)
