"""benchmark ceiling: the ground truth's noise and surfaces at their mean colour (stages/benchmark/ceiling.py).
Tiny renders (24 x 18, 8 spp): a few seconds."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from models.synth.render import render_spec  # noqa: E402
from models.synth.spec import parse_spec  # noqa: E402
from models.synth.textures import make_texture  # noqa: E402
from stages.benchmark.ceiling import NOISE_TO_NOISE_DB, flat_spec, run_ceiling, unseen_objects  # noqa: E402

ROOM = {
    "seed": 5, "resolution": [24, 18], "spp": 8, "max_depth": 3,
    "textures": {"tex": {"type": "noise", "seed": 1, "size": 32, "scale": 4},
                 "poster": {"type": "checker", "seed": 2, "size": 32, "scale": 4,
                            "colors": [[0.1, 0.2, 0.6], [0.9, 0.6, 0.1]]}},
    "objects": [
        {"name": "floor", "shape": "rectangle", "material": {"type": "diffuse", "texture": "tex"},
         "transform": {"rotate": [{"axis": [1, 0, 0], "angle": -90}], "scale": [3, 3, 1]}},
        {"name": "wall", "shape": "rectangle", "material": {"type": "diffuse", "texture": "tex"},
         "transform": {"translate": [0, 1.2, -1.5], "scale": [3, 1.2, 1]}},
        # behind the training cameras (they stand at z ~ 2.3 and look at the origin): only the ball shows it
        {"name": "back", "shape": "rectangle", "material": {"type": "diffuse", "texture": "poster"},
         "transform": {"translate": [0, 1.2, 3.0], "rotate": [{"axis": [0, 1, 0], "angle": 180}], "scale": [3, 1.2, 1]}},
        {"name": "ball", "shape": "sphere", "material": {"type": "conductor", "roughness": 0.0},
         "transform": {"translate": [0, 0.4, 0], "scale": 0.4}},
        {"name": "light", "shape": "rectangle", "material": {"type": "diffuse", "base_color": [0, 0, 0]},
         "transform": {"translate": [0, 2.4, 0], "rotate": [{"axis": [1, 0, 0], "angle": 90}], "scale": 0.6},
         "emitter": {"radiance": [8, 8, 8]}},
    ],
    "cameras": {"train": {"type": "orbit", "count": 3, "fov_y": 50, "target": [0, 0.5, 0], "radius": 2.3,
                          "height": [1.2, 1.6], "azimuth": [-20, 20]},
                "test": {"type": "list", "count": 2, "fov_y": 60,
                         "views": [{"position": [0, 1.0, -1.0], "target": [0, 1.0, 3.0]},
                                   {"position": [1.0, 1.2, 1.5], "target": [0, 0.4, 0]}]}},
}


@pytest.fixture(scope="module")
def room():
    spec = parse_spec(ROOM)
    return spec, render_spec(spec, progress=False)


def test_unseen_objects_are_the_textured_ones_no_training_pixel_hits(room):
    spec, capture = room
    assert unseen_objects(spec, [v.camera for v in capture.split("train")]) == ["back"]


def test_flat_spec_gives_the_named_objects_their_textures_mean_colour_only(room):
    spec, _ = room
    flat = flat_spec(spec, ["back", "ball"])  # the ball has no texture: unchanged
    back = flat.object("back").material
    assert back.texture is None
    assert np.allclose(back.base_color, make_texture(spec.textures["poster"]).reshape(-1, 3).mean(0), atol=1e-6)
    for name in ("floor", "wall", "ball", "light"):
        assert flat.object(name) == spec.object(name)
    with pytest.raises(ValueError, match="no object named 'sofa'.*floor, wall, back"):
        flat_spec(spec, ["sofa"])


def test_ceilings_noise_is_finite_and_flat_with_nothing_to_flatten_is_the_truth_itself(room):
    spec, capture = room
    same = run_ceiling(spec, capture, flat=["light"])  # untextured: the same scene, the same sampler seed
    assert sorted(same["noise_views"]) == ["test_000", "test_001"]
    assert 5 < same["noise"] < 60  # 8 spp: noisy, not identical
    assert same["noise_free_estimate"] == pytest.approx(same["noise"] + NOISE_TO_NOISE_DB)
    assert NOISE_TO_NOISE_DB == pytest.approx(3.0103, abs=1e-4)
    assert min(same["flat_views"].values()) >= 100  # bit-identical render: the noise cancels exactly
    flat = run_ceiling(spec, capture, flat=["back"])
    # test_000 looks straight at the back wall: its texture is what a mean colour misses; test_001 sees it only in
    # the ball (a few pixels), and loses far less
    views = flat["flat_views"]
    assert views["test_000"] < 40 and views["test_001"] > views["test_000"] + 10
    assert flat["noise"] == same["noise"]  # the noise render does not depend on --flat


def test_a_ground_truth_of_another_size_is_named(room):
    import dataclasses

    spec, capture = room
    with pytest.raises(ValueError, match="test view 'test_000': the ground truth is 24 x 18, the scene renders 12 x 9"):
        run_ceiling(dataclasses.replace(spec, resolution=(12, 9)), capture)


def test_cli_names_a_missing_capture(tmp_path, capsys):
    from stages.benchmark.__main__ import main

    assert main(["ceiling", "--scene", "zoo_spheres", "--capture", str(tmp_path / "nowhere"),
                 "--out", str(tmp_path / "c.json")]) == 1
    assert "nowhere" in capsys.readouterr().err
