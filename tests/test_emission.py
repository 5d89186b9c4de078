"""Lights seen directly (the capture's ``emission`` layer) are view-independent radiance of the Gaussians: the
diffuse target is diffuse + emission; without emission (or with an all-zero layer) training is unchanged."""

import copy

import numpy as np
import torch

from models.capture.layers import diffuse_radiance
from models.initialisation import InitConfig, dense_init
from models.reconstruction import ReconstructConfig, Trainer
from models.reconstruction.data import build_rayset
from models.tracer import Tracer, TracerConfig
from tests.test_init import plane_capture


def _with_emission(cap, kind: str):
    cap = copy.deepcopy(cap)
    for v in cap.views:
        e = np.zeros_like(v.buffers["diffuse"])
        if kind == "lamp":
            e[:5, :7] = 12.0
        if kind != "absent":
            v.buffers["emission"] = e
    return cap


def test_diffuse_target_includes_emission():
    lamp = _with_emission(plane_capture(), "lamp")
    rays = build_rayset(lamp, "train")
    want = np.concatenate([(v.buffers["diffuse"] + v.buffers["emission"]).reshape(-1, 3) for v in rays.views])
    assert torch.equal(rays.targets["diffuse"], torch.tensor(want))
    assert float(rays.targets["diffuse"].max()) >= 12.0
    v = lamp.views[0]
    assert diffuse_radiance({"diffuse": v.buffers["diffuse"]}) is v.buffers["diffuse"]  # no layer: itself
    clamped = build_rayset(lamp, "train", radiance_clamp=5.0)  # the clamp applies to the sum
    assert float(clamped.targets["diffuse"].max()) == 5.0


def test_training_without_or_with_zero_emission_is_unchanged():
    cap = plane_capture()
    init, _ = dense_init(cap, InitConfig(resolution=40, voxel_fraction=1 / 40))
    config = ReconstructConfig.from_dict(dict(iterations=6, warmup=6, rays_per_step=256, prune_every=0,
                                              max_path_length=1, checkpoint_every=100))
    runs = {}
    for kind in ("absent", "zero", "lamp"):
        trainer = Trainer(_with_emission(cap, kind), init, config, Tracer(TracerConfig(num_threads=2)))
        runs[kind] = ([trainer.train_step() for _ in range(3)], trainer.params, trainer.decisions)
    (m0, p0, d0), (mz, pz, dz), (ml, _, dl) = runs["absent"], runs["zero"], runs["lamp"]
    assert m0 == mz and all(torch.equal(p0[k], pz[k]) for k in p0)
    # an all-zero emission layer (the demo's: its lamp is never seen directly) is not worth a decision line
    assert not any("emission" in d for d in d0) and not any("emission" in d for d in dz)
    assert any("max 12" in d for d in dl) and ml[0]["loss_diffuse"] > m0[0]["loss_diffuse"]


def test_dense_init_colours_include_emission():
    cap = plane_capture()
    config = InitConfig(resolution=40, voxel_fraction=1 / 40)
    dark, _ = dense_init(_with_emission(cap, "absent"), config)
    zero, _ = dense_init(_with_emission(cap, "zero"), config)
    lit, _ = dense_init(_with_emission(cap, "lamp"), config)
    assert torch.equal(dark.diffuse, zero.diffuse)
    assert float(lit.diffuse.max()) > float(dark.diffuse.max()) + 1  # voxels on the lamp (radiance 12)
