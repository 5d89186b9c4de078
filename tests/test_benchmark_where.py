"""stages/benchmark/where.py: each pixel's path through the scene's true mirrors, and the error shares per path."""

from __future__ import annotations

import numpy as np
import pytest

from models.synth.spec import parse_spec
from stages.benchmark.__main__ import main
from stages.benchmark.where import error_by_label, mirror_objects, path_labels


def _corridor_spec():
    """Two facing mirrors (x = -1 a perfect conductor, x = +1 roughness 0.1), a floor (y = 0), an end wall
    (z = -3), a rough conductor ball (roughness 0.5: not a mirror) at (0, 1, 1) and a light above (y = 3)."""
    quad = {"shape": "rectangle", "material": {"type": "diffuse", "base_color": [0.5, 0.5, 0.5]}}
    mirror = {"shape": "rectangle", "material": {"type": "conductor", "roughness": 0.0}}
    return parse_spec({
        "resolution": [8, 6], "spp": 1,
        "objects": [
            {"name": "floor", **quad, "transform": {"rotate": [{"axis": [1, 0, 0], "angle": -90}], "scale": [1, 3, 1]}},
            {"name": "end", **quad, "transform": {"translate": [0, 1, -3], "scale": [1, 1, 1]}},
            {"name": "left", **mirror,
             "transform": {"translate": [-1, 1, 0], "rotate": [{"axis": [0, 1, 0], "angle": 90}], "scale": [3, 1, 1]}},
            {"name": "right", "shape": "rectangle", "material": {"type": "conductor", "roughness": 0.1},
             "transform": {"translate": [1, 1, 0], "rotate": [{"axis": [0, 1, 0], "angle": -90}], "scale": [3, 1, 1]}},
            {"name": "ball", "shape": "sphere", "material": {"type": "conductor", "roughness": 0.5},
             "transform": {"translate": [0, 1, 1], "scale": [0.2, 0.2, 0.2]}},
            {"name": "light", **quad, "emitter": {"radiance": [5, 5, 5]},
             "transform": {"translate": [0, 3, 0], "rotate": [{"axis": [1, 0, 0], "angle": 90}]}},
        ],
        "cameras": {"train": {"type": "list", "count": 1, "fov_y": 50, "views": [{"position": [0, 1, 2], "target": [0, 1, 0]}]},
                    "test": {"type": "list", "count": 1, "fov_y": 50, "views": [{"position": [0, 1, 2], "target": [0, 1, 0]}]}},
    })


def test_mirror_objects_are_the_smooth_conductors():
    assert mirror_objects(_corridor_spec()) == {"left", "right"}


def test_paths_follow_the_true_mirrors_and_stop_at_the_bounce_limit():
    o = np.array([[0, 1, 0.0], [0, 1, 0.0], [0, 1, 0.0], [0, 1, 0.0], [0, 1, 0.0]])
    d = np.array([[0, -1, 0.0],          # straight down: the floor
                  [0, 0, -1.0],          # down the corridor: the end wall
                  [-0.8, 0, -0.6],       # to the left mirror (z -0.75), across to the right one (z -2.25), the end
                  [-1, 0, 0.0],          # head-on: back and forth between the two mirrors until the limit
                  [0, 0, 1.0]])          # the rough ball (not a mirror), nothing after it
    labels = path_labels(_corridor_spec(), o, d, bounces=3)
    assert labels[:2] == ["floor", "end"]
    assert labels[2] == "left>right>end"
    assert labels[3] == "left>right>left>right"
    assert labels[4] == "ball"
    assert path_labels(_corridor_spec(), o[3:4], d[3:4], bounces=0) == ["left"]


def test_error_by_label_shares_add_up_and_rank_the_worst_path_first():
    err = np.array([0.01, 0.01, 0.04, 0.0, 0.0, 0.0])
    labels = ["a", "a", "b>c", "d", "d", "d"]
    truth = np.array([1.0, 1.0, 2.0, 0.5, 0.5, 0.5])
    ours = np.array([0.5, 0.5, 1.0, 0.5, 0.5, 0.5])
    rows = error_by_label(err, labels, truth, ours)
    assert [r["path"] for r in rows][:2] == ["b>c", "a"]
    assert sum(r["error_share"] for r in rows) == pytest.approx(1.0)
    assert sum(r["pixel_share"] for r in rows) == pytest.approx(1.0)
    b = rows[0]
    assert b["pixels"] == 1 and b["error_share"] == pytest.approx(2 / 3) and b["psnr"] == pytest.approx(10 * np.log10(25))
    assert (b["truth_mean"], b["ours_mean"]) == (2.0, 1.0)


def test_where_cli_names_what_is_missing(tmp_path, capsys):
    assert main(["where", "--scene", "no_such_scene", "--results", str(tmp_path)]) == 1
    assert "no_such_scene" in capsys.readouterr().err
    assert main(["where", "--scene", "zoo_corridor", "--results", str(tmp_path)]) == 1
    assert str(tmp_path / "zoo_corridor" / "capture") in capsys.readouterr().err
    assert main(["where", "--scene", "zoo_corridor", "--bounces", "-1"]) == 1
    assert "--bounces" in capsys.readouterr().err
