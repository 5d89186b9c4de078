"""Every stage's ``--help`` answers at once: the CLIs parse their arguments before importing torch or Warp
(which cost 6-13 s, more on a busy machine, before the help was printed)."""

import subprocess
import sys

import pytest

from tests.conftest import ROOT

STAGES = sorted(p.parent.name for p in (ROOT / "stages").glob("*/__main__.py"))
SUBCOMMANDS = [("benchmark", "sweep"), ("benchmark", "train-step"), ("benchmark", "seeds"), ("benchmark", "stereo"),
               ("benchmark", "where"),
               ("buffernet_train", "train"), ("edit", "apply"), ("edit", "evaluate"), ("report", "scene"),
               ("report", "batch"), ("synth", "procedural")]
HEAVY = {"torch", "warp"}
TIMEOUT_S = 20  # a hang guard, not a benchmark: --help takes ~0.3 s on 2 idle cores (~1 s busy)


def imported_modules(stderr: str) -> set[str]:
    """Module names from ``python -X importtime`` lines (``import time: self | cumulative | name``)."""
    return {line.rsplit("|", 1)[1].strip() for line in stderr.splitlines() if line.startswith("import time:")}


@pytest.mark.parametrize("args", [(s,) for s in STAGES] + SUBCOMMANDS, ids=" ".join)
def test_help_parses_before_heavy_imports(args):
    stage, *sub = args
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", f"stages.{stage}", *sub, "--help"],
                          capture_output=True, text=True, timeout=TIMEOUT_S, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "usage:" in proc.stdout
    heavy = sorted(m for m in imported_modules(proc.stderr) if m.split(".")[0] in HEAVY)
    assert not heavy, f"python -m stages.{' '.join(args)} --help imported {heavy[:5]}"


def test_every_stage_is_checked():
    """The list above covers every stage CLI (a new stage is checked without editing this file)."""
    assert {"reconstruct", "render", "evaluate", "report", "synth", "view"} <= set(STAGES)
