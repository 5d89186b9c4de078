"""A trained model folder describes itself (gaussians.ply + model.yaml). A model trained with tracer.kernel_p 2
is rendered with p = 2 by every consumer: render, evaluate, edit, view and the sweep (each compared with a
direct trace at p = 2, and shown to differ from p = 3)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch
import yaml

from models.capture import read_capture
from models.capture.exr import read_exr_channels
from models.tracer import Tracer, TracerConfig
from models.trained import MODEL_FILE, ModelSettings, load_model, read_settings, save_model

TRAIN = {"iterations": 24, "warmup": 12, "rays_per_step": 256, "far_field": "off", "prune_from": 10**6,
         "checkpoint_every": 24, "log_every": 12, "max_path_length": 2, "tracer": {"kernel_p": 2}}
# one primary per pixel: the renders are compared with a direct trace at the pixel centres
RENDER = {"spp": 1, "antialias": 1, "denoise": False, "path_views": 0, "video": False}


@pytest.fixture(scope="module")
def p2(tiny_demo, tmp_path_factory):
    """The CI demo capture and a model trained on it with kernel_p 2 and max path length 2 (by the stage CLI)."""
    from stages.reconstruct.__main__ import main as reconstruct

    _, results, _, _ = tiny_demo
    root = tmp_path_factory.mktemp("p2")
    capture = results / "demo" / "capture"
    assert reconstruct(["--config-json", json.dumps(TRAIN), "--capture", str(capture), "--init",
                        str(results / "demo" / "init" / "points.ply"), "--out", str(root / "model"),
                        "--no-progress"]) == 0
    return root, capture


def _diffuse(g, camera, kernel_p: int) -> np.ndarray:
    """The diffuse layer (primary segment: deterministic) of ``camera`` traced directly at ``kernel_p``, shaded as
    the default path settings' (``diffuse_lobe``) shade it."""
    from models.pathtrace.paths import PathConfig, shade_diffuse

    tracer = Tracer(TracerConfig(kernel_p=kernel_p, num_threads=1))
    tracer.update(g)
    dirs = torch.tensor(camera.ray_directions().reshape(-1, 3), dtype=torch.float32)
    out = tracer.trace(torch.tensor(camera.origin, dtype=torch.float32).expand_as(dirs).contiguous(), dirs, g)
    out = shade_diffuse(out, dirs, PathConfig())
    tracer.close()
    return out.diffuse.numpy().reshape(camera.height, camera.width, 3)


def _assert_rendered_with_p2(exr, g, camera):
    ch = read_exr_channels(exr)
    diffuse = np.stack([ch[f"diffuse.{c}"] for c in "RGB"], -1)
    np.testing.assert_array_equal(diffuse, _diffuse(g, camera, 2))
    assert np.abs(diffuse - _diffuse(g, camera, 3)).max() > 1e-4  # p matters on this model


def test_model_yaml_records_the_training_settings(p2):
    root, _ = p2
    text = (root / "model" / MODEL_FILE).read_text()
    data = yaml.safe_load(text)
    assert data["tracer"]["kernel_p"] == 2 and "num_threads" not in data["tracer"]  # a runtime setting
    assert data["path"]["max_path_length"] == 2 and data["path"]["sampler"] == "vndf"
    assert data["colour"] == "linear" and data["units"] == "meters" and data["training"]["steps"] == 24
    _, settings = load_model(root / "model")
    assert settings.tracer.kernel_p == 2 and settings.path.max_path_length == 2


def test_render_stage_uses_the_model_settings(p2):
    from stages.render.__main__ import main as render

    root, capture = p2
    assert render(["--config-json", json.dumps(RENDER), "--model", str(root / "model"), "--capture", str(capture),
                   "--out", str(root / "renders"), "--threads", "1"]) == 0
    g, _ = load_model(root / "model")
    view = read_capture(capture).split("test")[0]
    _assert_rendered_with_p2(root / "renders" / "test" / f"{view.name}.exr", g, view.camera)
    stage = json.loads((root / "renders" / "stage.json").read_text())
    assert stage["model"]["tracer"]["kernel_p"] == 2 and stage["path"]["max_path_length"] == 2
    assert stage["warnings"] == []


def test_render_without_reflection_samples_says_so(p2, caplog):
    from stages.render.__main__ import main as render

    root, capture = p2
    with caplog.at_level(logging.WARNING):
        assert render(["--config-json", json.dumps({**RENDER, "spp": 0}), "--model", str(root / "model"),
                       "--capture", str(capture), "--out", str(root / "renders0"), "--threads", "1"]) == 0
    stage = json.loads((root / "renders0" / "stage.json").read_text())
    assert stage["warnings"] == ["render.spp 0: no reflection samples, the specular layer is black and final = diffuse"]
    assert "render.spp 0" in caplog.text


def test_evaluate_stage_uses_the_model_settings(p2):
    from stages.evaluate.__main__ import main as evaluate

    root, capture = p2
    if not (root / "renders").is_dir():
        pytest.skip("needs test_render_stage_uses_the_model_settings")
    assert evaluate(["--capture", str(capture), "--renders", str(root / "renders"), "--model", str(root / "model"),
                     "--out", str(root / "metrics.json"), "--fps-repeats", "1", "--threads", "1"]) == 0
    metrics = json.loads((root / "metrics.json").read_text())
    assert metrics["model"]["tracer"]["kernel_p"] == 2 and metrics["fps_1spp"] > 0


def test_edit_stage_uses_and_keeps_the_model_settings(p2):
    from stages.edit.__main__ import main as edit

    root, capture = p2
    spec = {"select": {"all": True}, "ops": [{"op": "translate", "offset": [0.05, 0.0, 0.0]}]}
    out = root / "edits" / "shift"
    assert edit(["apply", "--edit", "shift", "--edit-json", json.dumps(spec), "--config-json", json.dumps(RENDER),
                 "--model", str(root / "model"), "--capture", str(capture), "--out", str(out), "--threads", "1"]) == 0
    edited, settings = load_model(out / "model")  # the edited model describes itself too
    assert settings.tracer.kernel_p == 2 and settings.path.max_path_length == 2
    assert settings.training["edit"] == "shift"
    view = read_capture(capture).split("test")[0]
    _assert_rendered_with_p2(out / "renders" / "test" / f"{view.name}.exr", edited, view.camera)


def test_viewer_uses_the_model_settings(p2):
    from stages.view.__main__ import open_session, parse_args

    root, capture = p2
    session, _, _, _ = open_session(parse_args([str(root / "model"), "--capture", str(capture), "--threads", "1"]))
    try:
        assert session.tracer.config.kernel_p == 2
        assert session.settings.max_path_length == 2 and session.view.path.max_path_length == 2
    finally:
        session.close()


def test_sweep_scores_with_the_model_settings(p2, tmp_path):
    from models.rendering import RenderConfig
    from stages.benchmark.sweep import score

    root, capture_dir = p2
    capture = read_capture(capture_dir)
    score(capture, root / "model", RenderConfig(**RENDER), "cpu", 1, tmp_path)
    g, _ = load_model(root / "model")
    view = capture.split("test")[0]
    _assert_rendered_with_p2(tmp_path / f"{view.name}.exr", g, view.camera)


def test_model_folder_errors(tmp_path, caplog):
    from models.gaussians import random_gaussians

    with pytest.raises(FileNotFoundError, match="gaussians.ply does not exist"):
        load_model(tmp_path / "nothing")
    g = random_gaussians(10, torch.Generator().manual_seed(0))
    save_model(tmp_path / "m", g, ModelSettings(tracer=TracerConfig(kernel_p=2)))
    (tmp_path / "m" / MODEL_FILE).write_text("tracer: {kernel: 2}\n")
    with pytest.raises(ValueError, match=r"model.yaml tracer: unknown key\(s\) \['kernel'\]"):
        load_model(tmp_path / "m")
    (tmp_path / "m" / MODEL_FILE).write_text("tracer: {kernel_p: 0}\n")
    with pytest.raises(ValueError, match="model.yaml tracer: kernel_p must be an int >= 1, got 0"):
        load_model(tmp_path / "m")
    (tmp_path / "m" / MODEL_FILE).unlink()  # a folder from before models described themselves: the defaults
    with caplog.at_level(logging.WARNING):
        settings = read_settings(tmp_path / "m" / "gaussians.ply")
    assert settings.tracer == TracerConfig() and "no model.yaml" in caplog.text


def test_model_yaml_from_before_the_traversal_option_still_loads(tmp_path):
    """A model.yaml written when the traversal was two booleans (repeated_kbuffer / ordered_traversal) and
    replay growth had a 4096 ceiling loads with the equivalent traversal and no ceiling."""
    from models.gaussians import random_gaussians

    g = random_gaussians(10, torch.Generator().manual_seed(0))
    save_model(tmp_path / "m", g, ModelSettings())
    old = {"kernel_p": 2, "replay_capacity": 64, "max_replay_capacity": 4096, "repeated_kbuffer": False,
           "ordered_traversal": False}
    for flags, traversal in (({}, "interval"), ({"repeated_kbuffer": True}, "kbuffer"),
                             ({"ordered_traversal": True}, "ordered")):
        (tmp_path / "m" / MODEL_FILE).write_text(yaml.safe_dump({"format": 1, "tracer": {**old, **flags}}))
        tracer = read_settings(tmp_path / "m").tracer
        assert (tracer.traversal, tracer.kernel_p, tracer.max_replay_capacity) == (traversal, 2, None)


def test_model_yaml_from_before_the_fresnel_option_keeps_the_papers_schlick(tmp_path):
    """Models trained before ``path.fresnel`` existed were trained with F90 = 1: they load as "schlick"; a new
    model writes its mode, and the default is "schlick_f90". Likewise ``path.reflection_origin``: older models
    started reflections at the expected depth and load as "expected"; new ones write theirs (default "front"); and
    ``path.diffuse_lobe``: older models' diffuse was the same from every side ("lambert"; default "disney"); and
    ``path.origin_grazing``: older models started every reflection a fixed distance past its surface (1); and
    ``path.back_normal``: older models flipped a normal met from behind ("flip"; default "mirror")."""
    from models.gaussians import random_gaussians
    from models.pathtrace.paths import PathConfig

    g = random_gaussians(10, torch.Generator().manual_seed(0))
    save_model(tmp_path / "m", g, ModelSettings())
    assert PathConfig().fresnel == "schlick_f90"
    assert yaml.safe_load((tmp_path / "m" / MODEL_FILE).read_text())["path"]["fresnel"] == "schlick_f90"
    assert read_settings(tmp_path / "m").path.fresnel == "schlick_f90"
    assert read_settings(tmp_path / "m").path.reflection_origin == PathConfig().reflection_origin == "front"
    assert read_settings(tmp_path / "m").path.diffuse_lobe == PathConfig().diffuse_lobe == "disney"
    assert read_settings(tmp_path / "m").path.origin_grazing == PathConfig().origin_grazing == 0.1
    assert read_settings(tmp_path / "m").path.back_normal == PathConfig().back_normal == "mirror"
    for path in ({"max_path_length": 3, "sampler": "vndf"}, None):
        (tmp_path / "m" / MODEL_FILE).write_text(yaml.safe_dump({"format": 1, **({"path": path} if path else {})}))
        assert read_settings(tmp_path / "m").path == PathConfig(fresnel="schlick", reflection_origin="expected", diffuse_lobe="lambert",
                                                                   origin_grazing=1.0, back_normal="flip")
    (tmp_path / "m" / MODEL_FILE).write_text(yaml.safe_dump({"format": 1, "path": {"fresnel": "fresnell"}}))
    with pytest.raises(ValueError, match="model.yaml path: fresnel must be one of"):
        read_settings(tmp_path / "m")
    (tmp_path / "m" / MODEL_FILE).write_text(yaml.safe_dump({"format": 1, "path": {"reflection_origin": "middle"}}))
    with pytest.raises(ValueError, match="model.yaml path: reflection_origin must be one of .*'middle'"):
        read_settings(tmp_path / "m")
    (tmp_path / "m" / MODEL_FILE).unlink()  # no model.yaml at all (older still): the defaults, that Fresnel and origin
    assert read_settings(tmp_path / "m").path == PathConfig(fresnel="schlick", reflection_origin="expected", diffuse_lobe="lambert",
                                                                   origin_grazing=1.0, back_normal="flip")
