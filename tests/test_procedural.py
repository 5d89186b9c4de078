"""Procedural training rooms: valid, deterministic, varied configs; one tiny render; resumable CLI."""

from __future__ import annotations

import json

import jsonschema
import numpy as np
import pytest
import yaml

from stages.config import SCHEMAS
from models.synth.procedural import random_scene_config
from stages.synth.procedural import render_procedural
from models.synth.spec import parse_spec

SEEDS = range(50)


def specs():
    return [parse_spec(random_scene_config(s)) for s in SEEDS]


def test_configs_are_valid():
    schema = yaml.safe_load((SCHEMAS / "synth.schema.yaml").read_text())
    for seed in SEEDS:
        cfg = random_scene_config(seed, resolution=(48, 32), views=5, spp=16)
        spec = parse_spec(cfg)  # raises ValueError naming the bad key
        jsonschema.validate(cfg, schema)
        assert json.loads(json.dumps(cfg)) == cfg  # plain JSON / YAML data
        assert spec.resolution == (48, 32) and spec.spp == 16 and spec.train.count == 5 and spec.test.count == 0
    with pytest.raises(ValueError, match="seed"):
        random_scene_config(-1)


def test_deterministic_per_seed_and_different_across_seeds():
    assert random_scene_config(7) == random_scene_config(7)
    configs = [json.dumps(random_scene_config(s)) for s in SEEDS]
    assert len(set(configs)) == len(configs)


def test_materials_and_layout_vary():
    all_specs = specs()
    counts, lights, roughness, kinds = set(), set(), [], set()
    for spec in all_specs:
        objs = [o for o in spec.objects if not o.name.startswith(("floor", "ceiling", "wall", "light"))]
        counts.add(len(objs))
        lights.add(sum(o.emitter is not None for o in spec.objects))
        metal = [o.material.type == "conductor" or o.material.metallic == 1.0 for o in objs]
        assert any(metal) and not all(metal), "every room has a metallic and a dielectric object"
        for o in objs:
            m = o.material
            kinds.add((m.type, m.metallic, m.texture is not None, o.shape))
            if m.type != "diffuse":
                roughness.append(m.roughness)
        assert {o.name for o in spec.objects} >= {"floor", "ceiling", "wall_back", "wall_front", "wall_left",
                                                  "wall_right"}
    assert counts >= {2, 6} and lights == {1, 2}
    assert min(roughness) == 0.0 and max(roughness) > 0.9  # mirrors .. rough
    assert np.mean([0.0 < r < 0.2 for r in roughness]) > 0.05  # glossy, not just mirror or matte
    types = {(t, metallic) for t, metallic, _, _ in kinds}
    assert types >= {("diffuse", 0.0), ("principled", 0.0), ("principled", 1.0), ("conductor", 0.0)}
    assert {shape for *_, shape in kinds} == {"sphere", "cube", "rectangle"}
    assert any(textured for _, _, textured, _ in kinds)


def test_render_one_tiny_scene_and_resume(tmp_path, capsys):
    pytest.importorskip("mitsuba")
    from models.capture import read_capture
    from stages.synth.__main__ import main

    out = tmp_path / "proc"
    report = render_procedural(out, 1, seed=3, resolution=(16, 16), views=2, spp=4, progress=False)
    assert report["rendered"] == ["scene_0000"] and report["skipped"] == []
    cap = read_capture(out / "scene_0000")
    assert [v.name for v in cap.views] == ["train_000", "train_001"]
    rough, f0 = [], []
    for v in cap.views:
        b = v.buffers
        total = b["diffuse"] + b["specular"] + b["emission"]
        np.testing.assert_allclose(b["rgb"], total, rtol=1e-4, atol=1e-5)
        rough.append(b["roughness"])
        f0.append(b["f0"])
    rough, f0 = np.concatenate(rough), np.concatenate(f0)
    assert rough.max() - rough.min() > 0.5 and f0.max() - f0.min() > 0.5  # metals next to dielectrics
    # resumable: the finished scene is skipped, the new one rendered
    args = ["procedural", "--count", "2", "--seed", "3", "--out", str(out), "--resolution", "16", "16",
            "--views", "2", "--spp", "4", "--no-progress"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "rendered 1 scene(s)" in printed and "skipped 1 already complete" in printed
    stage = json.loads((out / "scene_0001" / "stage.json").read_text())
    assert stage["config"]["synth"] == random_scene_config(4, resolution=(16, 16), views=2, spp=4)
    assert main([*args[:2], "-1", *args[3:]]) == 1
    assert "count must be >= 0" in capsys.readouterr().err


def test_denoised_room_is_closer_to_the_converged_render(tmp_path):
    """``denoise`` (the default for training rooms): OIDN brings a 4-spp room's diffuse / specular closer to
    the 256-spp render than the raw 4 spp, keeps R,G,B = diffuse + specular + emission and the G-buffers."""
    pytest.importorskip("mitsuba")
    from models.capture import read_capture

    caps = {}
    for name, spp, denoise in (("raw", 4, False), ("denoised", 4, True), ("reference", 256, False)):
        render_procedural(tmp_path / name, 1, seed=11, resolution=(32, 32), views=1, spp=spp, denoise=denoise,
                          progress=False)
        caps[name] = read_capture(tmp_path / name / "scene_0000").views[0].buffers
    ref, raw, den = caps["reference"], caps["raw"], caps["denoised"]
    for layer in ("diffuse", "specular"):
        err = {k: float(np.mean((np.minimum(b[layer], 4) - np.minimum(ref[layer], 4)) ** 2)) for k, b in caps.items()
               if k != "reference"}
        assert err["denoised"] < 0.7 * err["raw"], (layer, err)
    np.testing.assert_allclose(den["rgb"], den["diffuse"] + den["specular"] + den["emission"], rtol=1e-5, atol=1e-6)
    for layer in ("normal", "depth", "roughness", "f0", "mask", "emission"):
        np.testing.assert_array_equal(den[layer], raw[layer])
    with pytest.raises(ValueError, match="synth.denoise: must be true or false"):
        parse_spec({**random_scene_config(11), "denoise": "yes"})


def test_probe_rooms_look_where_the_training_orbit_does_not(tmp_path, capsys):
    """``python -m stages.synth probe``: held-out probe scenes (README, "Held-out probes"). Their test views sit
    between the training azimuths, lower than every training camera and inside the walls; --find picks rooms with
    two mirror-like objects and a glossy dielectric; an existing config is not overwritten."""
    from models.synth.cameras import path_poses
    from models.synth.procedural import probe_scene, probe_worthy
    from stages.config import load_config
    from stages.synth.__main__ import main

    schema = yaml.safe_load((SCHEMAS / "synth.schema.yaml").read_text())
    assert [s for s in range(300, 400) if probe_worthy(random_scene_config(s))] == [338, 339, 375, 376]
    for seed in (338, 376, 3, 17):
        doc = probe_scene(seed)
        jsonschema.validate(doc["synth"], schema)
        spec = parse_spec(doc["synth"])
        train = np.stack([p[:3, 3] for p in path_poses(spec.train)])
        test = np.stack([p[:3, 3] for p in path_poses(spec.test)])
        floor = next(o for o in doc["synth"]["objects"] if o["name"] == "floor")
        hx, hz = floor["transform"]["scale"][:2]
        assert len(test) == 3 and test[:, 1].max() < train[:, 1].min(), seed
        assert (np.abs(test[:, 0]) < hx - 0.25).all() and (np.abs(test[:, 2]) < hz - 0.25).all(), seed
        # no test camera where a training camera stands
        assert np.linalg.norm(test[:, None] - train[None], axis=-1).min() > 0.2, seed
    assert main(["probe", "338", "--find", "2", "--out-dir", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["probe_338.yaml", "probe_339.yaml"]
    cfg = yaml.safe_load((tmp_path / "probe_338.yaml").read_text())
    assert cfg == probe_scene(338) and "stages.synth probe 338" in (tmp_path / "probe_338.yaml").read_text()
    committed = load_config("probe_338")  # the one in configs/scenes: what the README's numbers ran
    assert committed["synth"] == probe_scene(338)["synth"]
    capsys.readouterr()
    assert main(["probe", "376", "338", "--out-dir", str(tmp_path)]) == 1  # one exists: none is written
    assert "probe_338.yaml exist(s) (--force overwrites)" in capsys.readouterr().err
    assert not (tmp_path / "probe_376.yaml").exists()
    blocked = tmp_path / "file"
    blocked.write_text("")
    assert main(["probe", "338", "--out-dir", str(blocked / "sub")]) == 1
    assert "error: cannot write" in capsys.readouterr().err


def test_mirror_probes_hide_what_the_training_cameras_see_only_in_the_mirror(tmp_path):
    """``python -m stages.synth probe --mirror``: the random room with a wall mirror the training cameras face.
    The floor objects named in ``evaluate.regions`` stand behind every training camera's image plane (no training
    pixel sees them directly), the test cameras face them, and the room keeps random_scene_config's objects but
    the panels on the mirror's wall; --find wants such an object and another shiny metal the cameras face."""
    from models.synth.cameras import path_poses
    from models.synth.procedural import mirror_probe_scene, mirror_probe_worthy
    from stages.config import load_config
    from stages.synth.__main__ import main

    schema = yaml.safe_load((SCHEMAS / "synth.schema.yaml").read_text())
    assert [s for s in range(30) if mirror_probe_worthy(mirror_probe_scene(s))] == [1, 21, 28]
    for seed in (1, 21, 28, 5):
        doc = mirror_probe_scene(seed)
        jsonschema.validate(doc["synth"], schema)
        spec = parse_spec(doc["synth"])
        room = {o["name"] for o in random_scene_config(seed)["objects"]}
        names = {o["name"] for o in doc["synth"]["objects"]}
        assert names - room == {"mirror"} and all(not n.startswith(("sphere", "cube")) for n in room - names)
        mirror = next(o for o in doc["synth"]["objects"] if o["name"] == "mirror")
        train, test = path_poses(spec.train), path_poses(spec.test)
        # OpenGL cameras look down -z: every training camera faces the mirror's wall
        assert all(-p[2, 2] < -0.7 for p in train), seed
        for name, box in doc["evaluate"]["regions"].items():
            lo, hi = np.array(box["min"]), np.array(box["max"])
            corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            for p in train:  # behind the image plane of every training camera
                assert ((corners - p[:3, 3]) @ -p[:3, 2] < 0).all(), (seed, name)
            for p in test:  # in front of every test camera
                assert ((lo + hi) / 2 - p[:3, 3]) @ -p[:3, 2] > 0.5, (seed, name)
        assert bool(doc["evaluate"]["regions"]) or not mirror_probe_worthy(doc), seed
        assert mirror["transform"]["translate"][2] > -doc["synth"]["objects"][0]["transform"]["scale"][1]
    assert main(["probe", "--mirror", "0", "--find", "2", "--out-dir", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["probe_mirror_1.yaml", "probe_mirror_21.yaml"]
    cfg = yaml.safe_load((tmp_path / "probe_mirror_21.yaml").read_text())
    assert cfg == mirror_probe_scene(21) and "probe --mirror 21" in (tmp_path / "probe_mirror_21.yaml").read_text()
    committed = load_config("probe_mirror_21")
    assert committed["synth"] == cfg["synth"] and committed["evaluate"]["regions"] == cfg["evaluate"]["regions"]


def test_lights_probes_put_a_window_in_view_beside_brushed_metal(tmp_path, capsys):
    """``python -m stages.synth probe --lights``: probe_scene's room with a window (an emitter) on the wall the most
    training cameras look at, inside three training frames at least (``lights_probe_worthy``), its wall's panels
    removed, and the largest floor object brushed metal (metallic, roughness 0.15-0.28); the rest of the room, its
    cameras and its test views are probe_scene's. --mirror and --lights do not go together."""
    from models.synth.cameras import path_poses
    from models.synth.procedural import lights_probe_scene, lights_probe_worthy, probe_scene
    from stages.config import load_config
    from stages.synth.__main__ import main

    schema = yaml.safe_load((SCHEMAS / "synth.schema.yaml").read_text())
    assert [s for s in range(40) if lights_probe_worthy(lights_probe_scene(s))] == [0, 23, 28]
    for seed in (0, 23, 5):
        doc = lights_probe_scene(seed)
        jsonschema.validate(doc["synth"], schema)
        plain = probe_scene(seed)["synth"]
        assert doc["scene"] == f"probe_lights_{seed}" and doc["synth"]["cameras"] == plain["cameras"]
        window = next(o for o in doc["synth"]["objects"] if o["name"] == "window")
        assert max(window["emitter"]["radiance"]) >= 6.0 and window["material"]["base_color"] == [0.0, 0.0, 0.0]
        floor = next(o for o in doc["synth"]["objects"] if o["name"] == "floor")
        hx, hz = floor["transform"]["scale"][:2]
        c = np.array(window["transform"]["translate"])
        gap = min(hx - abs(c[0]), hz - abs(c[2]))
        assert 0.0 < gap < 0.01, seed  # on a wall, just inside the room
        brushed = [o for o in doc["synth"]["objects"] if o["material"].get("metallic") == 1.0
                   and 0.15 <= o["material"]["roughness"] <= 0.28 and o["shape"] in ("sphere", "cube")]
        assert len(brushed) >= 1, seed
        names = {o["name"] for o in doc["synth"]["objects"]}
        gone = {o["name"] for o in plain["objects"]} - names
        assert names - {o["name"] for o in plain["objects"]} == {"window"}
        assert all(o["shape"] == "rectangle" for o in plain["objects"] if o["name"] in gone)
    assert lights_probe_worthy(lights_probe_scene(0)) and not lights_probe_worthy(lights_probe_scene(5))
    assert main(["probe", "--lights", "0", "--find", "2", "--out-dir", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["probe_lights_0.yaml", "probe_lights_23.yaml"]
    cfg = yaml.safe_load((tmp_path / "probe_lights_23.yaml").read_text())
    assert cfg == lights_probe_scene(23) and "probe --lights" in (tmp_path / "probe_lights_23.yaml").read_text()
    assert load_config("probe_lights_23")["synth"] == cfg["synth"]  # what the README's numbers ran
    with pytest.raises(SystemExit):
        main(["probe", "--lights", "--mirror", "0"])
    assert "not allowed with" in capsys.readouterr().err
