"""Snakemake workflow: dry run, a real tiny run, caching, config errors, lint."""

import re
import subprocess
import sys

import pytest

from models.capture import read_capture
from tests.conftest import PROFILE_NOTE, ROOT, snakemake



def test_unknown_scene_is_one_line_listing_known(tmp_path):
    proc = snakemake(tmp_path, "-n", "--config", "scene=nope")
    assert proc.returncode != 0
    # besides Snakemake's note that it reads the workflow profile (profiles/default), one line
    lines = [l for l in (proc.stdout + proc.stderr).splitlines() if l.strip() and not PROFILE_NOTE.match(l)]
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


def test_console_shows_stage_progress_and_the_report(tiny_demo):
    """Besides Snakemake's job blocks, the console has one line when each stage starts and ends (elapsed time;
    progress lines between them when a stage runs long), and at the end where the report is."""
    _, results, _, proc = tiny_demo
    for stage in ("synth", "init", "reconstruct", "render", "evaluate", "report"):
        assert f"[{stage} scene=demo] started (log: {results}/demo/logs/{stage}.log)" in proc.stderr, stage
        # "12.3 s", or "1:05 min" past a minute (a loaded machine: reconstruct took over 60 s)
        assert re.search(rf"\[{stage} scene=demo\] done in ([0-9.]+ s|[0-9]+:[0-9]{{2}} min)", proc.stderr), stage
    assert f"open {results}/demo/report.html" in proc.stderr.splitlines()


def test_report_states_command_and_presets(tiny_demo):
    _, results, args, _ = tiny_demo
    html = (results / "demo" / "report.html").read_text()
    assert f"--config {' '.join(args[1:])}</code> (presets: fast, ci)" in html  # the demo scene names fast itself


def test_snakemake_report_has_scene_report_metrics_and_pictures(tiny_demo):
    """`snakemake --report` (the catalog's report) of the tiny run: the scene's own HTML report, its metrics.json
    and the final / diffuse / specular PNG of each test view."""
    import zipfile

    workdir, _, args, _ = tiny_demo
    proc = snakemake(workdir, *args, "--report", str(workdir / "report.zip"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    names = {n.rsplit("/", 1)[-1] for n in zipfile.ZipFile(workdir / "report.zip").namelist()}
    assert {"report.html", "metrics.json", "test_000_final.png", "test_001_specular.png"} <= names, names


def test_default_profile_gives_threads_and_memory(tmp_path):
    """profiles/default (the workflow profile) sets each rule's threads and mem_mb; the stage gets {threads}."""
    proc = snakemake(tmp_path, "-n", "-p", "--config", "scene=demo")
    assert proc.returncode == 0, proc.stderr
    block = proc.stdout[proc.stdout.index("rule reconstruct:"):].split("\n\n")[0]
    assert "threads: 2" in block and "mem_mb=16000" in block and "gpu=0" in block, block
    assert "-m stages.reconstruct" in block and "--threads 2" in block, block


def test_slurm_profile_dry_run(tmp_path):
    """The cluster profile plans the demo without a cluster (a dry run calls no sbatch)."""
    pytest.importorskip("snakemake_executor_plugin_slurm")
    proc = subprocess.run([sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"),
                           "--directory", str(tmp_path), "--profile", str(ROOT / "profiles" / "slurm"), "-n",
                           "--config", "scene=demo", f"results={tmp_path / 'results'}"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "profiles/slurm" in proc.stderr and "workflow specific profile" in proc.stderr
    for rule in ("synth", "init", "reconstruct", "render", "evaluate", "report"):
        assert f"rule {rule}:" in proc.stdout, rule
    assert "runtime=720" in proc.stdout and "mem_mb=16000" in proc.stdout


def test_own_capture_with_buffers(tmp_path, tiny_demo):
    """kind: capture (configs/scenes/my_buffers.yaml): without its folder, one line saying where it goes; with
    it, the workflow plans init -> reconstruct -> render -> evaluate -> report and nothing that makes a capture."""
    import shutil

    results = tmp_path / "results"
    args = ("-n", "--config", "scene=my_buffers", f"results={results}")
    proc = snakemake(tmp_path, *args)
    assert proc.returncode != 0
    assert (f"error: scene 'my_buffers' is kind: capture, so its capture must already exist: put the folder "
            f"(transforms.json + images/, the format of README 'The capture format') at {results}/my_buffers/capture/"
            ) in proc.stderr + proc.stdout
    shutil.copytree(tiny_demo[1] / "demo" / "capture", results / "my_buffers" / "capture")
    proc = snakemake(tmp_path, *args)
    assert proc.returncode == 0, proc.stderr[-2000:]
    jobs = proc.stdout.split("Job stats:")[1].split("total")[0]
    assert all(rule in jobs for rule in ("init", "reconstruct", "render", "evaluate", "report"))
    assert "synth" not in jobs and "poses" not in jobs


def test_edit_scored_against_a_truth_folder(tmp_path):
    """An edit's `truth: <capture folder>` replaces the synth re-render as its ground truth (the way to score
    edits of a capture made elsewhere); a truth that is not a capture folder is named."""
    import yaml

    truth = tmp_path / "mytruth"
    config = {"scene": "demo", "preset": "ci", "results": str(tmp_path / "results"),
              "edits": {"mine": {"select": {"box": {"min": [0, 0, 0], "max": [1, 1, 1]}},
                                 "ops": [{"op": "set_roughness", "value": 0.5}], "truth": str(truth)}}}
    (tmp_path / "cfg.yaml").write_text(yaml.safe_dump(config))
    target = str(tmp_path / "results" / "demo" / "edits" / "mine" / "metrics.json")
    proc = snakemake(tmp_path, target, "-n", "--configfile", str(tmp_path / "cfg.yaml"))
    assert proc.returncode != 0
    assert f"edit 'mine': truth '{truth}' is not a capture folder (no transforms.json)" in proc.stdout + proc.stderr
    truth.mkdir()
    (truth / "transforms.json").write_text("{}")
    proc = snakemake(tmp_path, target, "-n", "--configfile", str(tmp_path / "cfg.yaml"))
    assert proc.returncode == 0, proc.stderr[-2000:]
    jobs = proc.stdout.split("Job stats:")[1].split("total")[0]
    assert "edit_metrics" in jobs and "edit_truth" not in jobs
