"""synth stage end to end: library entry point and CLI write a readable capture."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from models.capture import read_capture  # noqa: E402
from stages.config import load_config  # noqa: E402
from models.synth import render_capture  # noqa: E402
from stages.synth.__main__ import main  # noqa: E402


def tiny_demo() -> dict:
    cfg = copy.deepcopy(load_config("demo")["synth"])
    cfg.update(resolution=[16, 12], spp=2, max_depth=2)
    cfg["cameras"]["train"]["count"] = 2
    cfg["cameras"]["test"]["count"] = 1
    return cfg


def test_render_capture_writes_every_layer(tmp_path):
    edits = [{"op": "translate", "object": "mirror_ball", "offset": [0.2, 0, 0]}]
    cap = render_capture(tiny_demo(), tmp_path / "capture", edits=edits, progress=False, scene_name="demo")
    back = read_capture(tmp_path / "capture")
    assert [v.name for v in back.views] == ["train_000", "train_001", "test_000"]
    assert [v.split for v in back.views] == ["train", "train", "test"]
    assert set(back.layers) == {"rgb", "diffuse", "specular", "emission", "depth", "normal", "roughness", "f0", "mask"}
    for a, b in zip(cap.views, back.views):
        np.testing.assert_allclose(a.camera.c2w, b.camera.c2w)
        for layer in a.buffers:
            np.testing.assert_array_equal(a.buffers[layer], b.buffers[layer])
    extra = back.meta.extra
    assert extra["spp"] == 2 and set(extra["seconds_per_view"]) == {"train_000", "train_001", "test_000"}
    assert extra["edits"] == edits and back.meta.source == "synthetic"


def test_cli_config_json(tmp_path, capsys):
    rc = main(["--config-json", json.dumps(tiny_demo()), "--out", str(tmp_path / "c"), "--no-progress"])
    assert rc == 0
    assert "wrote 3 views" in capsys.readouterr().out
    assert (tmp_path / "c" / "transforms.json").is_file()
    assert json.loads((tmp_path / "c" / "stage.json").read_text())["stage"] == "synth"
    read_capture(tmp_path / "c")  # stage.json does not disturb readers


def test_cli_errors_are_one_line(tmp_path, capsys):
    cfg = tiny_demo()
    cfg["spp"] = "many"
    assert main(["--config-json", json.dumps(cfg), "--out", str(tmp_path / "c")]) == 1
    err = capsys.readouterr().err.strip()
    # the same schema check as the workflow's config (stages.config.check_section)
    assert err == "error: config synth.spp must be of type integer, got str 'many' (schema synth.schema.yaml)"
    assert main(["--scene", "demo", "--edits", "nope", "--out", str(tmp_path / "c")]) == 1
    assert "unknown edit list 'nope'" in capsys.readouterr().err
    assert main(["--scene", "no_such_scene", "--out", str(tmp_path / "c")]) == 1
    assert "unknown scene 'no_such_scene'" in capsys.readouterr().err
