"""Interrupted training under Snakemake resumes from its last checkpoint and ends with the model an uninterrupted
run writes; a checkpoint written under another config is kept aside, not resumed."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time

import pytest
import torch
import yaml

from tests.conftest import SNAKEMAKE


def _workdir(tiny_demo, path, **reconstruct):
    """A workflow folder whose results hold the tiny demo's capture and init (copied with their times), and a
    config file training ``reconstruct`` on them."""
    _, results, _, _ = tiny_demo
    res = path / "results"
    for part in ("capture", "init"):
        shutil.copytree(results / "demo" / part, res / "demo" / part)
    config = {"scene": "demo", "preset": "ci", "results": str(res),
              "reconstruct": {"iterations": 200, "checkpoint_every": 50, **reconstruct}}
    (path / "config.yaml").write_text(yaml.safe_dump(config))
    return res


def _command(path, res):
    return [*SNAKEMAKE, str(res / "demo" / "model" / "model.yaml"), "--directory", str(path),
            "--configfile", str(path / "config.yaml")]


def _logged_step(log_path) -> int:
    if not log_path.exists():
        return 0
    steps = [json.loads(line)["step"] for line in log_path.read_text().splitlines() if line.strip()]
    return max(steps, default=0)


def _kill_training(res) -> None:
    """SIGKILL the stages.reconstruct process writing into ``res`` (not Snakemake)."""
    out = subprocess.run(["pgrep", "-f", f"stages.reconstruct .*{res}"], capture_output=True, text=True).stdout
    pids = [int(p) for p in out.split()]
    assert pids, "the training process was not found"
    for pid in pids:
        os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(shutil.which("pgrep") is None, reason="needs pgrep to find the training process")
def test_sigkill_mid_training_resumes_to_the_same_model(tiny_demo, tmp_path):
    straight = _workdir(tiny_demo, tmp_path / "straight")
    proc = subprocess.run(_command(tmp_path / "straight", straight), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]

    killed = _workdir(tiny_demo, tmp_path / "killed")
    model = killed / "demo" / "model"
    job = subprocess.Popen(_command(tmp_path / "killed", killed), stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    while _logged_step(model / "train_log.jsonl") < 120:  # past the checkpoint at step 100, before the end
        assert job.poll() is None and time.monotonic() < deadline, "training ended before it could be killed"
        time.sleep(0.05)
    _kill_training(killed)
    assert job.wait(timeout=120) != 0
    assert not (model / "gaussians.ply").exists()
    checkpoint_step = torch.load(model / "checkpoints" / "last.pt", weights_only=False)["step"]
    assert 100 <= checkpoint_step < 200

    proc = subprocess.run(_command(tmp_path / "killed", killed), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = (killed / "demo" / "logs" / "reconstruct.log").read_text()
    assert f"resumed from {model / 'checkpoints' / 'last.pt'} at step {checkpoint_step}" in log
    # at most one checkpoint interval redone, the log continues where the checkpoint was
    steps = [json.loads(line)["step"] for line in (model / "train_log.jsonl").read_text().splitlines()]
    assert steps == sorted(set(steps)) and steps[-1] == 200
    stage = json.loads((model / "stage.json").read_text())
    assert stage["resumed_from_step"] == checkpoint_step
    assert (model / "gaussians.ply").read_bytes() == (straight / "demo" / "model" / "gaussians.ply").read_bytes()


def test_checkpoint_of_another_config_is_kept_aside(tiny_demo, tmp_path):
    res = _workdir(tiny_demo, tmp_path, iterations=100)
    proc = subprocess.run(_command(tmp_path, res), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    model = res / "demo" / "model"
    first = (model / "gaussians.ply").read_bytes()

    config = yaml.safe_load((tmp_path / "config.yaml").read_text())
    config["reconstruct"]["lr"] = {"opacity": 0.02}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    proc = subprocess.run(_command(tmp_path, res), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = (res / "demo" / "logs" / "reconstruct.log").read_text()
    assert "not resuming from" in log and "another config: lr.opacity:" in log and "Starting afresh" in log
    assert "resumed from" not in log
    aside = list((model / "checkpoints").glob("replaced-*-step100.pt"))
    assert len(aside) == 1, list((model / "checkpoints").iterdir())
    assert torch.load(model / "checkpoints" / "last.pt", weights_only=False)["step"] == 100
    assert (model / "gaussians.ply").read_bytes() != first
    assert json.loads((model / "stage.json").read_text())["resumed_from_step"] is None
