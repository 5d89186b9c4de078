"""models.buffernet: tokenizer, codec, conv_in widening, the pipeline (save/load offline, batched == per
prompt, sizes), loading an SD-layout folder, training plumbing. Tiny random models only; never the hub."""

import copy
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from diffusers import AutoencoderKL, DDPMScheduler, EulerDiscreteScheduler, UNet2DConditionModel
from transformers import CLIPTextConfig, CLIPTextModel

from models.buffernet import (BUFFERS, PROMPTS, BufferNetPipeline, build_pipeline, clip_tokenizer, decode_output,
                              encode_rgb, encode_target, from_stable_diffusion, input_exposure, sd2_configs,
                              widen_conv_in)
from models.buffernet import tokenizer as tokenizer_module
from models.buffernet.build import _random_configs
from models.buffernet.codec import normalise_depth, split_radiance
from models.buffernet.pipeline import size_for

ALL = tuple(PROMPTS)  # BUFFERS + metalness


@pytest.fixture(scope="module")
def tokenizer(tmp_path_factory):
    return clip_tokenizer(tmp_path_factory.mktemp("clip_vocab"))


@pytest.fixture(scope="module")
def pipe(tokenizer):
    return build_pipeline("tiny", seed=0, tokenizer=tokenizer)


def hdr_image(h=50, w=37, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.random((h, w, 3)) ** 3 * 20.0).astype(np.float32)  # heavy-tailed HDR radiance


def unit_normals(h, w, seed=0):
    n = np.random.default_rng(seed).normal(size=(h, w, 3)).astype(np.float32)
    return n / np.linalg.norm(n, axis=2, keepdims=True)


# --- tokenizer ------------------------------------------------------------------------------------------------

def test_tokenizer_matches_clip_ids(tokenizer):
    assert tokenizer("a photo of a cat").input_ids == [49406, 320, 1125, 539, 320, 2368, 49407]
    assert len(tokenizer) == 49408
    ids = tokenizer(PROMPTS["normal"], padding="max_length", max_length=tokenizer.model_max_length).input_ids
    assert len(ids) == 77 and tokenizer.model_max_length == 77
    assert ids[-1] == tokenizer.pad_token_id == 0  # SD2 pads with "!"


def test_tokenizer_without_open_clip_names_the_package(monkeypatch, tmp_path):
    monkeypatch.setattr(tokenizer_module.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ModuleNotFoundError, match="open-clip-torch"):
        clip_tokenizer(tmp_path / "empty")


# --- codec ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("buffer", ALL)
def test_codec_round_trip(buffer):
    h, w = 24, 20
    rng = np.random.default_rng(1)
    exposure = input_exposure(hdr_image(h, w))
    x = {"diffuse": hdr_image(h, w, 2), "specular": hdr_image(h, w, 3), "normal": unit_normals(h, w),
         "depth": rng.uniform(1.0, 10.0, (h, w)).astype(np.float32),
         "roughness": rng.random((h, w), dtype=np.float32), "metalness": rng.random((h, w), dtype=np.float32),
         "f0": rng.random((h, w, 3), dtype=np.float32)}[buffer]
    enc = encode_target(buffer, x, exposure)
    assert enc.shape == (3, h, w) and enc.dtype == torch.float32
    assert enc.min() >= -1.0 and enc.max() <= 1.0
    dec = decode_output(buffer, enc, exposure)
    if buffer in ("diffuse", "specular"):
        np.testing.assert_allclose(dec, x, rtol=1e-4, atol=1e-6)  # float32 through the tonemap: worst ~1e-5
    elif buffer == "depth":  # relative depth: the percentile-normalised input
        np.testing.assert_allclose(dec, normalise_depth(x), atol=1e-6)
    else:
        np.testing.assert_allclose(dec, x, atol=1e-6)
    assert dec.shape == x.shape


def test_depth_is_affine_invariant_and_ignores_invalid_pixels():
    z = np.random.default_rng(0).uniform(1.0, 10.0, (16, 16)).astype(np.float32)
    torch.testing.assert_close(encode_target("depth", 3.0 * z + 7.0, 1.0), encode_target("depth", z, 1.0),
                               atol=1e-5, rtol=0)
    mask = np.ones_like(z, dtype=bool)
    mask[:4] = False
    z_bad = z.copy()
    z_bad[:4] = 1e6  # far outliers under the mask do not move the percentiles
    a, b = encode_target("depth", z_bad, 1.0, mask=mask), encode_target("depth", z, 1.0, mask=mask)
    torch.testing.assert_close(a, b)
    assert torch.all(a[:, :4] == 0)
    rel = decode_output("depth", encode_target("depth", z, 1.0), 1.0)
    assert rel[z.argmin() // 16, z.argmin() % 16] == 0.0 and rel.max() == 1.0  # near 0, far 1


def test_decode_clips_to_valid_ranges():
    t = torch.from_numpy(np.random.default_rng(0).uniform(-3, 3, (3, 8, 8)).astype(np.float32))
    t[:, 0, 0] = 0.0  # a zero normal
    for b in ("roughness", "metalness", "depth", "f0"):
        out = decode_output(b, t, 1.0)
        assert out.min() >= 0.0 and out.max() <= 1.0, b
    n = decode_output("normal", t, 1.0)
    np.testing.assert_allclose(np.linalg.norm(n, axis=2), 1.0, atol=1e-6)
    np.testing.assert_array_equal(n[0, 0], [0.0, 0.0, 1.0])
    for b in ("diffuse", "specular"):
        out = decode_output(b, t, 0.5)
        # TONEMAP_MAX caps exposed radiance at 999 (999.013 in float32)
        assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 999.1 / 0.5


def test_exposure_invariance():
    rgb = hdr_image()
    for k in (1e-3, 0.37, 250.0):
        torch.testing.assert_close(encode_rgb(k * rgb, input_exposure(k * rgb)),
                                   encode_rgb(rgb, input_exposure(rgb)), atol=2e-6, rtol=0)
        np.testing.assert_allclose(input_exposure(k * rgb), input_exposure(rgb) / k, rtol=1e-5)
        torch.testing.assert_close(encode_target("diffuse", k * rgb, input_exposure(k * rgb)),
                                   encode_target("diffuse", rgb, input_exposure(rgb)), atol=2e-6, rtol=0)
    assert input_exposure(np.zeros((4, 4, 3), np.float32)) == 1.0


def test_codec_errors_name_the_problem():
    with pytest.raises(ValueError, match=r"'albedo'.*diffuse, specular, normal, depth, roughness, f0"):
        encode_target("albedo", np.zeros((4, 4, 3)), 1.0)
    with pytest.raises(ValueError, match=r"roughness must be \[H, W\]"):
        encode_target("roughness", np.zeros((4, 4, 2)), 1.0)
    with pytest.raises(ValueError, match=r"\[H, W, 3\].*\(4, 4\)"):
        encode_rgb(np.zeros((4, 4)), 1.0)


# --- conv_in widening -----------------------------------------------------------------------------------------

def test_widen_conv_in_preserves_the_image_half():
    """Widened UNet on cat(z, z) == original UNet on z (weights cat(w, w) / 2, same bias)."""
    torch.manual_seed(0)
    cfg = _random_configs("tiny")
    original = UNet2DConditionModel(**cfg["unet"]).eval()
    widened = widen_conv_in(copy.deepcopy(original))
    assert widened.config.in_channels == 8 and widened.conv_in.weight.shape[1] == 8
    z = torch.randn(2, 4, 16, 16)
    text = torch.randn(2, 77, cfg["unet"]["cross_attention_dim"])
    t = torch.tensor([999, 999])
    with torch.no_grad():
        a = widened(torch.cat([z, z], dim=1), t, encoder_hidden_states=text).sample
        b = original(z, t, encoder_hidden_states=text).sample
    torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="4"):
        widen_conv_in(widened)


# --- pipeline -------------------------------------------------------------------------------------------------

def test_x0_is_v_turned_into_x0(pipe):
    abar = float(pipe.scheduler.alphas_cumprod[999])
    assert pipe.timestep == 999 and abs(abar - 0.0047) < 1e-4  # SD2 scaled-linear betas, no zero-SNR rescale
    lat, emb = torch.randn(2, 4, 8, 8), pipe.encode_prompts(("normal", "depth"))
    with torch.no_grad():
        x0 = pipe.x0_latents(lat, emb)
        v = pipe.unet(torch.cat([lat, torch.zeros_like(lat)], 1), 999, encoder_hidden_states=emb).sample
    torch.testing.assert_close(x0, -math.sqrt(1 - abar) * v)


def test_batched_prompts_equal_per_prompt(pipe):
    rgb = hdr_image(40, 48)
    batched, e1 = pipe.predict_images(rgb, BUFFERS)
    single, e2 = pipe.predict_images(rgb, BUFFERS, batched=False)
    assert batched.shape == (6, 3, 40, 48) and e1 == e2
    # float32 summation order differs with the batch size: worst seen 1.05e-5 at a value of 2.4
    torch.testing.assert_close(batched, single, atol=1e-5, rtol=1e-5)
    # prompts really differ: the buffers are not all the same image
    assert (batched[0] - batched[2]).abs().max() > 1e-3
    out, ref = pipe.predict(rgb), pipe.predict_per_prompt(rgb)
    for b in BUFFERS:  # diffuse / specular: HDR through the inverse tonemap, 1e-5 there grows to 1e-4 relative
        np.testing.assert_allclose(out[b], ref[b], atol=1e-4, rtol=1e-3)


def test_split_radiance_sums_to_the_image():
    rgb = hdr_image(12, 10)
    rgb[0, 0] = [-0.5, 0.2, np.nan]  # negative and non-finite pixels count as black
    spec = np.random.default_rng(1).normal(0.3, 1.0, rgb.shape).astype(np.float32)
    diffuse, specular = split_radiance(rgb, spec)
    image = np.clip(np.nan_to_num(rgb), 0, None)
    np.testing.assert_allclose(diffuse + specular, image, atol=1e-6)
    assert (specular >= 0).all() and (specular <= image).all() and (diffuse >= 0).all()
    inside = (spec >= 0) & (spec <= image)  # where the specular is feasible it is kept as predicted
    np.testing.assert_array_equal(specular[inside], spec[inside])
    with pytest.raises(ValueError, match=r"specular shape \(3, 3, 3\) does not match the image's \(12, 10, 3\)"):
        split_radiance(rgb, np.zeros((3, 3, 3)))


def test_predict_forms_the_diffuse_as_the_image_minus_the_specular(pipe):
    rgb = hdr_image(24, 24)
    heads = pipe.predict(rgb, ("diffuse", "specular"), radiance="heads")
    out = pipe.predict(rgb, ("diffuse", "specular"))
    expected_diffuse, expected_specular = split_radiance(rgb, heads["specular"])
    np.testing.assert_allclose(out["specular"], expected_specular, atol=1e-5)
    np.testing.assert_allclose(out["diffuse"], expected_diffuse, atol=1e-5)
    assert np.abs(out["diffuse"] - heads["diffuse"]).max() > 1e-2  # the diffuse prompt's output is not used
    # asking for the diffuse alone still runs the specular prompt (and returns only the diffuse)
    alone = pipe.predict(rgb, ("diffuse",))
    assert list(alone) == ["diffuse"]
    np.testing.assert_allclose(alone["diffuse"], out["diffuse"], atol=1e-5)
    with pytest.raises(ValueError, match="radiance must be one of complement, heads, got 'sum'"):
        pipe.predict(rgb, ("diffuse",), radiance="sum")


def test_predict_shapes_and_sizes(pipe):
    assert pipe.multiple == 8  # VAE 4x, UNet 2x
    assert size_for(50, 37, 8) == (48, 40) and size_for(50, 37, 64) == (64, 64)
    assert size_for(480, 640, 64, resolution=256) == (192, 256)
    out = pipe.predict(hdr_image(50, 37), ALL)
    assert list(out) == list(ALL)
    for b, a in out.items():
        want = (50, 37) if b in ("depth", "roughness", "metalness") else (50, 37, 3)
        assert a.shape == want and a.dtype == np.float32 and np.isfinite(a).all(), b
    np.testing.assert_allclose(np.linalg.norm(out["normal"], axis=2), 1.0, atol=1e-5)
    assert pipe.predict(hdr_image(50, 37), ("f0",), resolution=24)["f0"].shape == (50, 37, 3)


def test_scaling_the_input_scales_radiance_outputs(pipe):
    rgb = hdr_image(32, 32)
    a, ea = pipe.predict_images(rgb, ("diffuse",))
    b, eb = pipe.predict_images(4.0 * rgb, ("diffuse",))
    torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
    np.testing.assert_allclose(ea / eb, 4.0, rtol=1e-5)


def test_pipeline_errors(pipe):
    with pytest.raises(ValueError, match=r"unknown buffer 'albedo'; valid buffers: diffuse, specular"):
        pipe.predict(hdr_image(16, 16), ("normal", "albedo"))
    for bad in (np.zeros((16, 16)), np.zeros((16, 16, 4)), np.zeros((3, 16, 16))):
        with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
            pipe.predict(bad)
    cfg = _random_configs("tiny")
    with pytest.raises(ValueError, match="widen_conv_in"):
        BufferNetPipeline(UNet2DConditionModel(**cfg["unet"]), pipe.vae, pipe.text_encoder, pipe.tokenizer,
                          pipe.scheduler)


def test_save_and_reload_offline(pipe, tmp_path, monkeypatch):
    pipe.save_pretrained(tmp_path / "buffernet")
    index = json.loads((tmp_path / "buffernet" / "model_index.json").read_text())
    assert index["_class_name"] == "BufferNetPipeline" and index["unet"] == ["diffusers", "UNet2DConditionModel"]
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    loaded = BufferNetPipeline.from_pretrained(tmp_path / "buffernet")
    assert isinstance(loaded, BufferNetPipeline) and loaded.unet.config.in_channels == 8
    assert loaded.scheduler.config.prediction_type == "v_prediction"
    rgb = hdr_image(24, 40)
    a, _ = pipe.predict_images(rgb)
    b, _ = loaded.predict_images(rgb)
    torch.testing.assert_close(a, b, atol=0, rtol=0)


OFFLINE_LOAD = """
import socket, sys
import numpy as np

def no_network(*args, **kwargs):
    raise OSError("network access during an offline load")

socket.socket.connect = no_network
socket.create_connection = no_network
from models.buffernet import BufferNetPipeline
pipe = BufferNetPipeline.from_pretrained(sys.argv[1])
rgb = np.random.default_rng(0).random((24, 40, 3)).astype(np.float32)
np.save(sys.argv[2], pipe.predict_images(rgb)[0].numpy())
"""


def test_fresh_process_loads_offline_without_network(pipe, tmp_path):
    """HF_HUB_OFFLINE=1 set before huggingface_hub is imported, sockets disabled: the folder alone suffices."""
    pipe.save_pretrained(tmp_path / "buffernet")
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", OFFLINE_LOAD, str(tmp_path / "buffernet"), str(tmp_path / "out.npy")],
                          capture_output=True, text=True, env=env, cwd=Path(__file__).resolve().parents[1],
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rgb = np.random.default_rng(0).random((24, 40, 3)).astype(np.float32)
    np.testing.assert_allclose(np.load(tmp_path / "out.npy"), pipe.predict_images(rgb)[0].numpy(), atol=1e-6)


def test_from_stable_diffusion_folder(tokenizer, tmp_path, monkeypatch):
    from diffusers import StableDiffusionPipeline

    cfg = _random_configs("tiny")
    torch.manual_seed(1)
    sd = StableDiffusionPipeline(
        vae=AutoencoderKL(**cfg["vae"]), text_encoder=CLIPTextModel(CLIPTextConfig(**cfg["text_encoder"])),
        tokenizer=tokenizer, unet=UNet2DConditionModel(**cfg["unet"]),
        scheduler=EulerDiscreteScheduler(beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012,
                                         prediction_type="v_prediction", steps_offset=1),
        safety_checker=None, feature_extractor=None, requires_safety_checker=False)
    sd.save_pretrained(tmp_path / "sd2")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    pipe = from_stable_diffusion(tmp_path / "sd2")
    assert pipe.unet.config.in_channels == 8 and isinstance(pipe.scheduler, DDPMScheduler)
    assert pipe.scheduler.config.prediction_type == "v_prediction"
    w = sd.unet.conv_in.weight
    torch.testing.assert_close(pipe.unet.conv_in.weight, torch.cat([w, w], 1) / 2)
    torch.testing.assert_close(pipe.unet.conv_in.bias, sd.unet.conv_in.bias)
    torch.testing.assert_close(pipe.vae.encoder.conv_in.weight, sd.vae.encoder.conv_in.weight)
    assert pipe.predict(hdr_image(16, 16), ("depth",))["depth"].shape == (16, 16)
    with pytest.raises(FileNotFoundError, match="unet/config.json"):
        from_stable_diffusion(tmp_path)
    sd.scheduler = DDPMScheduler(prediction_type="epsilon")  # an epsilon model (e.g. SD2-base) warns
    sd.save_pretrained(tmp_path / "sd2_eps")
    with pytest.warns(UserWarning, match="epsilon"):
        from_stable_diffusion(tmp_path / "sd2_eps")


# --- training plumbing ----------------------------------------------------------------------------------------

def test_trainable_parameters_and_gradient_checkpointing(tokenizer):
    pipe = build_pipeline("tiny", seed=0, tokenizer=tokenizer)
    params = pipe.trainable_parameters()
    assert len(params) == len(list(pipe.unet.parameters()))
    assert not any(p.requires_grad for p in [*pipe.vae.parameters(), *pipe.text_encoder.parameters()])
    x = torch.from_numpy(np.random.default_rng(0).uniform(-1, 1, (2, 3, 32, 32)).astype(np.float32))
    with torch.no_grad():
        lat = pipe.image_latents(x)
    emb = pipe.encode_prompts(("diffuse", "normal"))
    pipe.unet.train()
    grads = []
    for checkpointing in (False, True):
        if checkpointing:
            pipe.unet.enable_gradient_checkpointing()
        pipe.unet.zero_grad(set_to_none=True)
        pipe.x0_latents(lat, emb).square().mean().backward()
        grads.append([p.grad.clone() for p in params])
    assert pipe.unet.is_gradient_checkpointing
    assert all(g.abs().sum() > 0 for g in grads[1][:3])
    for g0, g1 in zip(*grads):
        torch.testing.assert_close(g0, g1, atol=1e-6, rtol=1e-5)


def test_sd2_configs_have_sd2_sizes():
    from accelerate import init_empty_weights

    cfg = sd2_configs()
    with init_empty_weights():  # shapes only, no memory
        unet = UNet2DConditionModel(**cfg["unet"])
        vae = AutoencoderKL(**cfg["vae"])
        text = CLIPTextModel(CLIPTextConfig(**cfg["text_encoder"]))
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert (count(unet), count(vae), count(text)) == (865_910_724, 83_653_863, 340_387_840)
    assert cfg["unet"]["cross_attention_dim"] == cfg["text_encoder"]["hidden_size"]
    assert 2 ** (len(cfg["vae"]["block_out_channels"]) - 1) * 2 ** (len(cfg["unet"]["down_block_types"]) - 1) == 64
