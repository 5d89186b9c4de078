"""Snakemake workflow: dry run, a real tiny run, caching, config errors, lint."""

import subprocess
import sys

import pytest

from models.capture import read_capture
from tests.conftest import ROOT, snakemake


def test_unknown_scene_is_one_line_listing_known(tmp_path):
    proc = snakemake(tmp_path, "-n", "--config", "scene=nope")
    assert proc.returncode != 0
    lines = [l for l in (proc.stdout + proc.stderr).splitlines() if l.strip()]
    assert lines == [lines[0]] and lines[0].startswith("error: unknown scene 'nope'; known scenes: ")
    assert "demo" in lines[0] and "mirror_book" in lines[0] and "chromeballs" in lines[0]


def test_bad_config_value_names_key(tmp_path):
    proc = snakemake(tmp_path, "-n", "--config", "scene=demo", "device=tpu")
    assert proc.returncode != 0
    assert "config device must be one of cpu, cuda, got 'tpu' (schema config.schema.yaml)" in proc.stdout + proc.stderr


def test_config_typo_and_string_numbers(tmp_path):
    """A misspelt top-level key is an error naming it (it used to plan a full-size run); nested numbers given on
    the command line arrive as strings and take the schema's types."""
    proc = snakemake(tmp_path, "-n", "--config", "scene=demo", "presset=ci")
    assert proc.returncode != 0
    assert "unknown top-level option(s) ['presset']" in proc.stderr and "did you mean 'presets'" in proc.stderr
    proc = snakemake(tmp_path, "-n", "-p", "--config", "scene=demo", 'reconstruct={"iterations": 200}')
    assert proc.returncode == 0, proc.stderr
    assert '"iterations": 200' in proc.stdout


def test_dry_run_plans_synth(tmp_path):
    proc = snakemake(tmp_path, "-n", "--config", "scene=demo")
    assert proc.returncode == 0, proc.stderr
    for rule in ("synth", "init", "reconstruct", "render", "evaluate"):
        assert rule in proc.stdout, rule


def test_dry_run_network_buffers(tmp_path):
    """A scene asking for network buffers plans the training data, the network and the buffers stage, and
    trains on capture_net; the demo scene plans none of them."""
    proc = snakemake(tmp_path, "-n", "--config", "scene=demo_network")
    assert proc.returncode == 0, proc.stderr
    for rule in ("buffernet_rooms", "buffernet_train", "buffers", "init", "reconstruct"):
        assert f"rule {rule}:" in proc.stdout, rule
    assert "demo_network/capture_net" in proc.stdout
    proc = snakemake(tmp_path, "-n", "--config", "scene=demo")
    assert "rule buffers:" not in proc.stdout and "buffernet" not in proc.stdout


def test_lint():
    """Snakemake's linter finds nothing but its advice to use conda/containers (this project pins a venv)."""
    proc = subprocess.run([sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), "--lint"],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    text = proc.stdout + proc.stderr
    lints = [l.strip() for l in text.splitlines() if l.startswith("    * ")]
    assert lints, text  # the linter ran
    assert all(l.startswith("* Specify a conda environment or container") for l in lints), lints


def test_tiny_run_then_cached(tiny_demo):
    tmp_path, results, args, _ = tiny_demo
    capture = read_capture(results / "demo" / "capture")
    assert len(capture.split("train")) == 4 and len(capture.split("test")) == 2
    assert capture.views[0].camera.width == 32 and capture.views[0].camera.height == 24
    assert {"rgb", "diffuse", "specular", "depth", "normal", "roughness", "f0", "mask"} <= set(capture.layers)
    assert (results / "demo" / "logs" / "synth.log").is_file()
    from models.gaussians import read_ply

    assert len(read_ply(results / "demo" / "init" / "points.ply")) > 10
    import json

    metrics = json.loads((results / "demo" / "metrics.json").read_text())["mean"]
    assert metrics["psnr_diffuse"] > 15  # a trained (if tiny) scene, not an empty one
    assert (results / "demo" / "renders" / "test" / "png").is_dir()
    for stage in ("synth", "init", "reconstruct", "render", "evaluate", "report"):
        assert (results / "demo" / "logs" / f"{stage}.log").is_file(), stage
    second = snakemake(tmp_path, *args)
    assert second.returncode == 0, second.stderr
    assert "Nothing to be done" in second.stdout + second.stderr
    # a changed parameter reruns the stage
    (tmp_path / "more.yaml").write_text("synth: {spp: 4}\n")
    third = snakemake(tmp_path, "-n", "--configfile", str(tmp_path / "more.yaml"), *args)
    assert third.returncode == 0 and "synth" in third.stdout
