"""Stage outputs are complete or absent: a killed run leaves the previous output as it was, a failing run and a
full disk leave nothing half-written, and evaluate refuses renders that are unfinished or of another model."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stages.output import partial_path, replace_file, staged_folder
from tests.conftest import ROOT


def _tree(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_staged_folder_replaces_only_on_success(tmp_path):
    out = tmp_path / "renders"
    with staged_folder(out) as tmp:
        (tmp / "a.txt").write_text("first")
    assert _tree(out) == {"a.txt": hashlib.sha256(b"first").hexdigest()}
    with pytest.raises(RuntimeError):
        with staged_folder(out) as tmp:
            (tmp / "b.txt").write_text("second")
            raise RuntimeError("killed half-way")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["renders"]  # no partial folder left
    assert (out / "a.txt").read_text() == "first" and not (out / "b.txt").exists()
    with staged_folder(out) as tmp:
        (tmp / "b.txt").write_text("second")
    assert sorted(p.name for p in out.iterdir()) == ["b.txt"]  # the new output, not a mix
    with pytest.raises(OSError):
        replace_file(tmp_path / "m.json", lambda p: (p.write_text("{"), (_ for _ in ()).throw(OSError(28, "full"))))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["renders"]


def _render(capture, model, out, *extra):
    return [sys.executable, "-m", "stages.render", "--scene", "demo", "--preset", "ci", "--capture", str(capture),
            "--model", str(model), "--out", str(out), *extra]


def _evaluate(capture, renders, model, out):
    return subprocess.run([sys.executable, "-m", "stages.evaluate", "--capture", str(capture), "--renders",
                           str(renders), "--model", str(model), "--out", str(out), "--fps-repeats", "0"],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)


def test_killed_render_keeps_the_previous_output(tiny_demo, tmp_path):
    _, results, _, _ = tiny_demo
    capture, model = results / "demo" / "capture", results / "demo" / "model"
    out = tmp_path / "renders"
    done = subprocess.run(_render(capture, model, out), capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    before = _tree(out)
    job = subprocess.Popen(_render(capture, model, out), cwd=ROOT, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not list((partial_path(out) / "test").glob("*.exr")):  # killed once it has written something
        assert job.poll() is None and time.monotonic() < deadline, "the render ended before it could be killed"
        time.sleep(0.02)
    job.kill()
    job.wait()
    assert _tree(out) == before  # the finished output, untouched
    # evaluate scores the finished folder and refuses the killed run's partial one
    ok = _evaluate(capture, out, model, tmp_path / "metrics.json")
    assert ok.returncode == 0, ok.stderr[-2000:]
    partial = _evaluate(capture, partial_path(out), model, tmp_path / "partial.json")
    assert partial.returncode == 1 and "no stage.json, so not a finished render" in partial.stderr
    assert not (tmp_path / "partial.json").exists()
    # a new run starts clean from the stale partial folder and replaces the output
    again = subprocess.run(_render(capture, model, out), capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert again.returncode == 0 and not partial_path(out).exists()
    assert set(_tree(out)) == set(before)


def test_evaluate_refuses_renders_of_another_model(tiny_demo, tmp_path):
    _, results, _, _ = tiny_demo
    capture = results / "demo" / "capture"
    model = tmp_path / "model"
    shutil.copytree(results / "demo" / "model", model, ignore=shutil.ignore_patterns("checkpoints"))
    text = (model / "model.yaml").read_text()
    assert "steps: 120" in text
    (model / "model.yaml").write_text(text.replace("steps: 120", "steps: 119"))
    proc = _evaluate(capture, results / "demo" / "renders", model, tmp_path / "metrics.json")
    assert proc.returncode == 1 and "was rendered from another model" in proc.stderr, proc.stderr[-2000:]
    assert not (tmp_path / "metrics.json").exists()


def _tiny_filesystem_runner() -> list[str] | None:
    """A command prefix that runs a shell with a 256 KiB tmpfs mounted at /mnt/full (root, or an unprivileged
    user + mount namespace), or None where neither is allowed."""
    for prefix in (["unshare", "--mount"], ["unshare", "--user", "--map-root-user", "--mount"]):
        if shutil.which(prefix[0]) is None:
            return None
        probe = subprocess.run([*prefix, "sh", "-c", "mount -t tmpfs -o size=256k tmpfs /mnt && echo ok"],
                               capture_output=True, text=True)
        if probe.stdout.strip() == "ok":
            return prefix
    return None


def test_full_disk_is_one_line_and_leaves_nothing(tiny_demo, tmp_path):
    prefix = _tiny_filesystem_runner()
    if prefix is None:
        pytest.skip("cannot mount a small tmpfs here (needs root or unprivileged user namespaces)")
    _, results, _, _ = tiny_demo
    command = " ".join(_render(results / "demo" / "capture", results / "demo" / "model", "/mnt/renders"))
    proc = subprocess.run([*prefix, "sh", "-c", f"mount -t tmpfs -o size=256k tmpfs /mnt && cd {ROOT} && "
                           f"{command}; echo rc=$?; ls -A /mnt"], capture_output=True, text=True, timeout=300)
    lines = proc.stdout.strip().splitlines()
    assert lines[-1] == "rc=1", proc.stdout[-2000:] + proc.stderr[-3000:]  # nothing listed after it: empty
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "no space left on the device while writing" in errors[0], proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    json.dumps(errors)
