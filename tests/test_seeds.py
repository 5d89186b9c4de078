"""Paired-seed benchmark (stages/benchmark/seeds.py): settings parsed as the CLI takes them, a base / variant pair
per seed trained, rendered and scored as the workflow would, the pair table's differences, clear CLI errors."""

import math
import re

import pytest

from models.capture import read_capture
from stages.benchmark.__main__ import main as benchmark_main
from stages.benchmark.seeds import format_table, pairs, parse_setting, run_seeds
from stages.benchmark.sweep import config_for_sweep
from stages.config import load_config
from tests.conftest import snakemake


def test_parse_setting_nests_keys_and_reads_yaml_values():
    assert parse_setting("reconstruct.fill_anchor=3") == {"reconstruct": {"fill_anchor": 3}}
    assert parse_setting("reconstruct.tracer.kernel_p=2") == {"reconstruct": {"tracer": {"kernel_p": 2}}}
    assert parse_setting("render.denoise=false") == {"render": {"denoise": False}}
    assert parse_setting("reconstruct.loss=[a, b]") == {"reconstruct": {"loss": ["a", "b"]}}
    for bad in ("fill_anchor=3", "reconstruct.fill_anchor", "=3"):
        with pytest.raises(ValueError, match="section.key=value"):
            parse_setting(bad)


def test_pairs_are_variant_minus_base_per_seed():
    pts = [{"scene": "s", "seed": seed, "variant": v, "psnr_final_tonemapped": f, "psnr_specular_tonemapped": 20.0}
           for seed, v, f in ((0, "base", 28.0), (0, "variant", 29.0), (1, "base", 27.0), (1, "variant", 26.5))]
    p = pairs(pts)["s"]
    assert [r["final_diff"] for r in p["seeds"]] == [1.0, -0.5]
    assert (p["final_diff_mean"], p["final_diff_min"], p["final_diff_max"]) == (0.25, -0.5, 1.0)
    assert "+0.25" in format_table({"pairs": {"s": p}})


def test_seeds_trains_base_and_variant_per_seed_and_scores_them(tiny_demo, tmp_path):
    _, results, _, _ = tiny_demo
    config = config_for_sweep(load_config("demo", presets=["ci"]), 40)
    config["render"]["spp"] = 2
    result = run_seeds({"demo": (results / "demo" / "capture", config)}, {"reconstruct": {"back_fill": False}},
                       [3], jobs=2, work_dir=tmp_path / "work", progress=lambda m: None)
    assert [(p["seed"], p["variant"]) for p in result["points"]] == [(3, "base"), (3, "variant")]
    for p in result["points"]:
        assert p["gaussians"] > 100 and p["train_s"] > 0
        for layer in ("final", "specular", "diffuse"):
            assert math.isfinite(p[f"psnr_{layer}_tonemapped"]) and p[f"psnr_{layer}_tonemapped"] > 5
        assert set(p["views"]) == {v.name for v in read_capture(results / "demo" / "capture").split("test")}
    base, variant = result["points"]
    row = result["pairs"]["demo"]["seeds"][0]
    assert row["final_diff"] == pytest.approx(variant["psnr_final_tonemapped"] - base["psnr_final_tonemapped"])
    # each run trained, saved and rendered its own model
    assert (tmp_path / "work" / "demo_3_base" / "model" / "gaussians.ply").is_file()
    assert (tmp_path / "work" / "demo_3_variant" / "renders").is_dir()


def test_seeds_cli_says_what_is_missing(tmp_path, capsys):
    assert benchmark_main(["seeds", "--scenes", "demo", "--results", str(tmp_path)]) == 1
    assert "nothing to compare" in capsys.readouterr().err
    assert benchmark_main(["seeds", "--scenes", "demo", "--set", "reconstruct.fill_anchor=3",
                           "--results", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "no capture for scene 'demo'" in err and str(tmp_path / "demo" / "capture") in err
    # the command it gives is one the workflow runs (it named capture/transforms.json once: no rule makes that)
    command = re.search(r"`snakemake --cores 2 (\S+) --config (\S+)`", err)
    assert command, err
    proc = snakemake(tmp_path / "wd", "-n", "--cores", "1", command.group(1), "--config", command.group(2))
    assert proc.returncode == 0 and "rule synth" in proc.stdout + proc.stderr, proc.stdout + proc.stderr
    (tmp_path / "bad.json").write_text("[1, 2]")
    assert benchmark_main(["seeds", "--scenes", "demo", "--set", "reconstruct.fill_anchor=3",
                           "--reuse", str(tmp_path / "bad.json"), "--results", str(tmp_path)]) == 1
    assert f"--reuse {tmp_path / 'bad.json'}: not a seeds result" in capsys.readouterr().err
    assert benchmark_main(["seeds", "--scenes", "demo", "--set", "reconstruct.fill_anchor=-1",
                           "--results", str(tmp_path)]) == 1
    assert "reconstruct.fill_anchor must be >= 0" in capsys.readouterr().err
    assert benchmark_main(["seeds", "--scenes", "demo", "--set", "reconstruct.fill_anchor=1", "--seeds", ""]) == 1
    assert "no seeds" in capsys.readouterr().err
    assert benchmark_main(["seeds", "--scenes", "nope", "--set", "reconstruct.fill_anchor=1"]) == 1
    assert "unknown scene 'nope'" in capsys.readouterr().err
    (tmp_path / "a_file").write_text("x")
    assert benchmark_main(["seeds", "--scenes", "demo", "--set", "reconstruct.fill_anchor=1",
                           "--keep", str(tmp_path / "a_file")]) == 1
    assert f"--keep {tmp_path / 'a_file'}: exists and is not a folder" in capsys.readouterr().err


def test_seeds_reuses_points_of_the_same_code_settings_seed_and_capture(tmp_path, monkeypatch):
    """--reuse: a point made by the same code, settings, seed, device and capture is taken from the earlier result,
    not trained again (runs reproduce exactly); a changed variant or capture trains again."""
    import stages.benchmark.seeds as seeds

    capture = tmp_path / "capture"
    (capture / "images").mkdir(parents=True)
    (capture / "transforms.json").write_text("{}")
    (capture / "images" / "train_000.exr").write_bytes(b"x" * 10)
    trained = []

    def fake_point(task):
        trained.append((task["seed"], task["variant"]))
        score = 20.0 + task["seed"] + (1.0 if task["config"]["reconstruct"].get("back_fill") is False else 0.0)
        return {"scene": task["scene"], "seed": task["seed"], "variant": task["variant"], "train_s": 1.0,
                "gaussians": 1, "views": {}, "regions": {},
                **{f"psnr_{layer}_tonemapped": score for layer in ("final", "specular", "diffuse")}}

    monkeypatch.setattr(seeds, "_point", fake_point)
    scenes = {"demo": (capture, {"reconstruct": {"iterations": 10}})}
    off = {"reconstruct": {"back_fill": False}}
    first = run_seeds(scenes, off, [0, 1], progress=lambda m: None)
    assert sorted(trained) == [(0, "base"), (0, "variant"), (1, "base"), (1, "variant")]
    assert all(len(p["key"]) == 40 for p in first["points"])
    trained.clear()
    again = run_seeds(scenes, off, [0, 1], progress=lambda m: None, reuse=first["points"])
    assert trained == [] and all(p["reused"] for p in again["points"])
    assert again["pairs"] == first["pairs"]
    # another variant: its base runs are the first result's
    other = run_seeds(scenes, {"reconstruct": {"back_fill": True}}, [0, 1], progress=lambda m: None,
                      reuse=first["points"])
    assert sorted(trained) == [(0, "variant"), (1, "variant")]
    assert [p.get("reused", False) for p in other["points"]] == [True, False, True, False]
    # another capture (an image re-rendered to another size): everything again
    trained.clear()
    (capture / "images" / "train_000.exr").write_bytes(b"x" * 11)
    run_seeds(scenes, off, [0], progress=lambda m: None, reuse=first["points"])
    assert sorted(trained) == [(0, "base"), (0, "variant")]


def test_code_digest_follows_the_code_a_point_runs_not_the_orchestration(tmp_path):
    from stages.benchmark.seeds import code_digest

    for rel in ("models/a.py", "stages/benchmark/seeds.py", "stages/benchmark/sweep.py", "configs/scenes/x.yaml"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("v1")
    base = code_digest(tmp_path)
    (tmp_path / "stages/benchmark/seeds.py").write_text("v2")  # orchestration: the same points
    assert code_digest(tmp_path) == base
    for rel in ("models/a.py", "stages/benchmark/sweep.py", "configs/scenes/x.yaml"):
        (tmp_path / rel).write_text("v2")
        assert code_digest(tmp_path) != base, rel
        (tmp_path / rel).write_text("v1")
    assert code_digest(tmp_path) == base
