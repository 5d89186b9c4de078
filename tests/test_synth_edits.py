"""Scene spec parsing errors and edit ops of the synth stage (no rendering)."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from stages.config import ConfigError, load_config
from models.synth.edits import apply_edits
from models.synth.mitsuba_scene import conductor_f0, material_entry, to_world_matrix
from models.synth.spec import parse_spec


@pytest.fixture(scope="module")
def demo_cfg():
    return load_config("demo")["synth"]


@pytest.fixture(scope="module")
def demo(demo_cfg):
    return parse_spec(demo_cfg)


def test_translate_rotate_scale(demo):
    e = apply_edits(demo, [
        {"op": "translate", "object": "mirror_ball", "offset": [0.1, 0.0, -0.2]},
        {"op": "rotate", "object": "gold_cube", "axis": [0, 1, 0], "angle": 15},
        {"op": "scale", "object": "box_a", "factor": 2.0},
    ])
    np.testing.assert_allclose(e.object("mirror_ball").transform.translate,
                               np.add(demo.object("mirror_ball").transform.translate, [0.1, 0.0, -0.2]))
    # 30 + 15 degrees about y, about the object's own origin (translation unchanged)
    m = to_world_matrix(e.object("gold_cube").transform)
    c, s = np.cos(np.radians(45)), np.sin(np.radians(45))
    np.testing.assert_allclose(m[:3, :3] / 0.25, [[c, 0, s], [0, 1, 0], [-s, 0, c]], atol=1e-12)
    np.testing.assert_allclose(m[:3, 3], demo.object("gold_cube").transform.translate)
    np.testing.assert_allclose(e.object("box_a").transform.scale, np.multiply(demo.object("box_a").transform.scale, 2))
    # the input spec is untouched
    assert demo.object("box_a").transform.scale == (0.2, 0.2, 0.2)


def test_duplicate_and_delete(demo):
    e = apply_edits(demo, [{"op": "duplicate", "object": "mirror_ball", "new_name": "mirror_ball2",
                            "offset": [1.0, 0.0, 0.0]}])
    a, b = e.object("mirror_ball"), e.object("mirror_ball2")
    assert a.material == b.material and a.transform.scale == b.transform.scale
    np.testing.assert_allclose(np.subtract(b.transform.translate, a.transform.translate), [1, 0, 0])
    e2 = apply_edits(e, [{"op": "delete", "object": "mirror_ball"}])
    assert "mirror_ball" not in [o.name for o in e2.objects] and len(e2.objects) == len(demo.objects)
    with pytest.raises(ValueError, match="already exists"):
        apply_edits(e, [{"op": "duplicate", "object": "box_a", "new_name": "mirror_ball2", "offset": [0, 0, 0]}])
    with pytest.raises(ValueError, match="only light"):
        apply_edits(demo, [{"op": "delete", "object": "light"}])


def test_set_roughness(demo):
    e = apply_edits(demo, [{"op": "set_roughness", "object": "floor", "value": 0.05},
                           {"op": "set_roughness", "object": "mirror_ball", "value": 0.3}])
    assert e.object("floor").material.roughness == 0.05
    assert material_entry(e.object("mirror_ball"), None).roughness == 0.3
    with pytest.raises(ValueError, match="diffuse and has no roughness"):
        apply_edits(demo, [{"op": "set_roughness", "object": "box_a", "value": 0.1}])
    with pytest.raises(ValueError, match=r"edits\[0\]\.value: must be in \[0.0, 1.0\], got 2.0"):
        apply_edits(demo, [{"op": "set_roughness", "object": "floor", "value": 2.0}])


def test_set_f0_per_material(demo):
    e = apply_edits(demo, [
        {"op": "set_f0", "object": "gold_cube", "value": [0.95, 0.64, 0.54]},   # metallic=1 -> base_color
        {"op": "set_f0", "object": "floor", "value": 0.02},                      # dielectric -> specular
        {"op": "set_f0", "object": "mirror_ball", "value": [0.5, 0.6, 0.7]},     # conductor -> reflectance
    ])
    for name, want in [("gold_cube", [0.95, 0.64, 0.54]), ("floor", [0.02] * 3), ("mirror_ball", [0.5, 0.6, 0.7])]:
        np.testing.assert_allclose(material_entry(e.object(name), None).f0_const, want, rtol=1e-12)
    assert e.object("floor").material.specular == pytest.approx(0.25)
    with pytest.raises(ValueError, match="must be grey and <= 0.08"):
        apply_edits(demo, [{"op": "set_f0", "object": "floor", "value": 0.5}])
    with pytest.raises(ValueError, match="set_f0 needs a conductor or a principled"):
        apply_edits(demo, [{"op": "set_f0", "object": "box_a", "value": 0.04}])


def test_set_f0_conductor_with_complex_ior():
    cfg = {"type": "conductor", "roughness": 0.1, "eta": [0.2, 0.9, 1.1], "k": [3.9, 2.4, 2.1]}
    from models.synth.spec import parse_material
    m = parse_material(cfg, "m", {})
    assert np.all(np.asarray(conductor_f0(m)) < 1)


def test_edit_errors_name_the_problem(demo):
    with pytest.raises(ValueError, match=r"edits\[0\]\.op: must be one of"):
        apply_edits(demo, [{"op": "explode", "object": "floor"}])
    with pytest.raises(ValueError, match=r"edits\[0\]\.object: no object named 'nope'"):
        apply_edits(demo, [{"op": "delete", "object": "nope"}])
    with pytest.raises(ValueError, match=r"edits\[0\]: missing required key\(s\) 'offset'"):
        apply_edits(demo, [{"op": "translate", "object": "floor"}])


def test_spec_errors_name_key_and_value(demo_cfg):
    bad = copy.deepcopy(demo_cfg)
    bad["objects"][1]["material"]["base_color"] = [0.5, 1.5, 0.5]
    with pytest.raises(ValueError, match=r"synth\.objects\[1\]\.material\.base_color\[1\]: must be in \[0.0, 1.0\], got 1.5"):
        parse_spec(bad)
    bad = copy.deepcopy(demo_cfg)
    bad["objects"][0]["material"]["texture"] = "nope"
    with pytest.raises(ValueError, match=r"synth\.objects\[0\]\.material\.texture: unknown texture 'nope'"):
        parse_spec(bad)
    bad = copy.deepcopy(demo_cfg)
    bad["objects"][7]["shape"] = "teapot"
    with pytest.raises(ValueError, match=r"synth\.objects\[7\]\.shape: must be one of .* got 'teapot'"):
        parse_spec(bad)
    bad = copy.deepcopy(demo_cfg)
    bad["cameras"]["train"]["radus"] = 2
    with pytest.raises(ValueError, match=r"synth\.cameras\.train: unknown key\(s\) 'radus'"):
        parse_spec(bad)
    bad = copy.deepcopy(demo_cfg)
    bad["objects"][0]["material"]["metallic"] = 0.5
    bad["objects"][0]["material"]["type"] = "diffuse"
    with pytest.raises(ValueError, match=r"'metallic'.* not valid for a diffuse material"):
        parse_spec(bad)
    bad = copy.deepcopy(demo_cfg)
    bad["objects"][8]["material"]["specular"] = 0.0  # gold_cube, metallic 1
    with pytest.raises(ValueError, match=r"synth\.objects\[8\]\.material: .*metallic > 0 needs specular > 0"):
        parse_spec(bad)


def test_schema_rejects_bad_yaml_values():
    with pytest.raises(ConfigError, match=r"config synth\.spp must be >= 1, got 0 \(schema synth\.schema\.yaml\)"):
        load_config("demo", overrides={"synth": {"spp": 0}})
    with pytest.raises(ConfigError, match=r"synth\.objects\.0\.material\.roughness"):
        cfg = yaml.safe_load((Path(__file__).parents[1] / "configs/scenes/demo.yaml").read_text())
        cfg["synth"]["objects"][0]["material"]["roughness"] = 3
        load_config("demo", overrides={"synth": {"objects": cfg["synth"]["objects"]}})
