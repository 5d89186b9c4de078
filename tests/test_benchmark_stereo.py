"""stages/benchmark/stereo.py: Mitsuba's true hits along reflected rays, and the accuracy table built from them."""

from __future__ import annotations

import numpy as np
import pytest

from models.synth.spec import parse_spec
from stages.benchmark.stereo import accuracy_table, format_table, true_hits


def _room_spec():
    """A floor (y = 0), a back wall (z = -2) and a ball of radius 0.5 at (0, 1, 0); an area light."""
    quad = {"shape": "rectangle", "material": {"type": "diffuse", "base_color": [0.5, 0.5, 0.5]}}
    return parse_spec({
        "resolution": [8, 6], "spp": 1,
        "objects": [
            {"name": "floor", **quad, "transform": {"rotate": [{"axis": [1, 0, 0], "angle": -90}], "scale": [3, 3, 1]}},
            {"name": "wall", **quad, "transform": {"translate": [0, 1.5, -2], "scale": [3, 1.5, 1]}},
            {"name": "ball", "shape": "sphere", "material": {"type": "diffuse", "base_color": [0.8, 0.2, 0.2]},
             "transform": {"translate": [0, 1, 0], "scale": [0.5, 0.5, 0.5]}},
            {"name": "light", **quad, "emitter": {"radiance": [5, 5, 5]},
             "transform": {"translate": [0, 3, 0], "rotate": [{"axis": [1, 0, 0], "angle": 90}]}},
        ],
        "cameras": {"train": {"type": "list", "count": 1, "fov_y": 50, "views": [{"position": [0, 1, 2], "target": [0, 1, 0]}]},
                    "test": {"type": "list", "count": 1, "fov_y": 50, "views": [{"position": [0, 1, 2], "target": [0, 1, 0]}]}},
    })


def test_true_hits_name_the_first_surface_and_its_distance():
    o = np.array([[0, 1, 2.0], [2, 1, 0.0], [0, 1, 2.0], [0, 1, 0.8], [0, 1, 2.0]])
    d = np.array([[0, 0, -1.0], [0, 0, -1.0], [0, -1, 0.0], [0, 1, 0.0], [0, 0, 1.0]])
    t, names = true_hits(_room_spec(), o, d)
    assert names == ["ball", "wall", "floor", "light", "none"]
    assert t[:4] == pytest.approx([1.5, 2.0, 1.0, 2.0], abs=1e-3) and np.isinf(t[4])


def test_accuracy_table_tells_floaters_from_hidden_points():
    """Errors of 2 cm, 10 cm, 40 cm in front (near) and 40 cm behind (deep) on one object: each lands in its
    column, per kind of match, and "all" adds the objects up."""
    t_true = np.full(8, 3.0)
    t = t_true + np.array([0.02, -0.10, -0.40, 0.40, 0.02, 0.02, -0.4, 0.0])
    names = ["wall"] * 4 + ["ball"] * 4
    own = np.array([True] * 4 + [False] * 4)
    placed = np.array([True, False, True, False, True, True, False, False])
    table = accuracy_table(t, t_true, names, own, placed)
    wall = table["own/all"]["wall"]
    assert wall["n"] == 4 and wall["within_5cm"] == 0.25 and wall["within_15cm"] == 0.5
    assert wall["near"] == 0.25 and wall["deep"] == 0.25
    assert table["own/placed"]["wall"]["n"] == 2 and table["own/placed"]["wall"]["near"] == 0.5
    assert table["completed/all"]["ball"]["near"] == 0.25 and table["completed/all"]["all"]["n"] == 4
    assert "ball" not in table["own/all"]
    text = format_table({"accuracy": table, "stereo": {"planes": 2, "planar_views": 2, "kept": 8, "completed": 4,
                                                       "inconsistent": 0, "added": 4}})
    assert "own/placed" in text and "wall" in text
