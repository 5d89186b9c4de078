"""Anti-aliased renders (``render.antialias``): each pixel traces n x n primaries at the centres of a stratified
sub-pixel grid, the reflection samples are dealt out among them, and every layer is their mean. Checked exactly
against renders of cameras whose principal point is moved so that their pixel centres are those sub-pixel points."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from models.capture import Camera
from models.gaussians import Gaussians
from models.pathtrace.paths import PathConfig
from models.rendering import RenderConfig, render_view
from models.rendering.render import subpixel_offsets
from models.tracer import Tracer, TracerConfig


@pytest.fixture(scope="module")
def tracer():
    t = Tracer(TracerConfig(num_threads=2), "cpu")
    yield t
    t.close()


def _scene() -> Gaussians:
    """A mirror-ish floor of discs under a few coloured blobs with sharp edges: every layer varies within pixels."""
    rng = np.random.default_rng(3)
    xs = np.arange(-1.0, 1.0, 0.05)
    floor = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
    n_f = len(floor)
    blobs = rng.uniform([-0.5, 0.05, -0.5], [0.5, 0.6, 0.5], (30, 3))
    means = np.concatenate([np.c_[floor[:, 0], np.zeros(n_f), floor[:, 1]], blobs])
    n = len(means)
    scales = np.concatenate([np.tile([0.04, 0.04, 0.004], (n_f, 1)), rng.uniform(0.03, 0.08, (30, 3))])
    quats = np.concatenate([np.tile([math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0], (n_f, 1)),
                            rng.normal(size=(30, 4))])
    normals = np.concatenate([np.tile([0.0, 1.0, 0.0], (n_f, 1)), rng.normal(size=(30, 3))])
    f = dict(dtype=torch.float32)
    return Gaussians(
        means=torch.tensor(means, **f), quats=torch.tensor(quats, **f), log_scales=torch.tensor(np.log(scales), **f),
        opacity_logits=torch.full((n,), 4.0), diffuse=torch.tensor(rng.uniform(0, 1, (n, 3)), **f),
        normals=torch.tensor(normals, **f),
        roughness=torch.tensor(np.r_[np.full(n_f, 0.05), rng.uniform(0.2, 1, 30)], **f),
        f0=torch.tensor(np.r_[np.full((n_f, 3), 0.9), rng.uniform(0, 0.2, (30, 3))], **f))


def _camera(shift=(0.0, 0.0)) -> Camera:
    c2w = np.eye(4)
    look = np.array([0.0, -0.5, -1.0]) / math.sqrt(1.25)
    right = np.array([1.0, 0.0, 0.0])
    up = np.cross(right, look)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -look, [0.0, 1.0, 1.6]
    return Camera(width=24, height=18, fl_x=20.0, fl_y=20.0, cx=12.0 + shift[0], cy=9.0 + shift[1], c2w=c2w)


def test_subpixel_offsets_are_a_stratified_grid_and_refuse_other_counts():
    assert subpixel_offsets(1) == [(0.5, 0.5)]
    assert subpixel_offsets(4) == [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)]
    assert len(set(subpixel_offsets(9))) == 9
    with pytest.raises(ValueError, match="render.antialias=3"):
        subpixel_offsets(3)
    # the config refuses it before any work, naming the key and the values it takes
    with pytest.raises(ValueError, match=r"render.antialias must be one of 1, 4, 9, 16, .* got 3"):
        RenderConfig.from_dict({"antialias": 3})


@pytest.mark.parametrize("length", [1, 3])
def test_every_layer_is_the_mean_over_the_sub_pixel_primaries(tracer, length):
    g = _scene()
    path = dataclasses.replace(PathConfig(), max_path_length=length)
    aa = RenderConfig(spp=8, antialias=4, denoise=False)
    img = render_view(tracer.trace, _camera(), g, aa, torch.Generator().manual_seed(5), path)
    # the same sub-pixel rays as pixel centres of shifted cameras, in the same order with one generator: each
    # primary gets 2 of the 8 reflection samples
    gen = torch.Generator().manual_seed(5)
    one = RenderConfig(spp=2, antialias=1, denoise=False)
    parts = [render_view(tracer.trace, _camera((0.5 - ox, 0.5 - oy)), g, one, gen, path)
             for ox, oy in subpixel_offsets(4)]
    for key in ("diffuse", "depth", "roughness", "f0", "transmittance"):
        want = sum(p[key] for p in parts) / 4
        assert np.allclose(img[key], want, atol=1e-6), key
    spec = sum(p["specular_noisy"] * 2 for p in parts) / 8
    assert np.allclose(img["specular_noisy"], spec, atol=1e-6)
    assert np.allclose(img["final"], img["diffuse"] + img["specular"])
    normal = sum(p["normal"] for p in parts)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-8)
    assert np.allclose(img["normal"], normal, atol=1e-5)
    # and the edges are really softened: some pixels lie strictly between their sub-pixel extremes
    stack = np.stack([p["diffuse"] for p in parts])
    between = (img["diffuse"] > stack.min(0) + 1e-3) & (img["diffuse"] < stack.max(0) - 1e-3)
    assert between.any()

