import os

# Keep the Warp kernel cache inside the checkout (CI starts from a clean clone).
os.environ.setdefault("WARP_CACHE_PATH", os.path.join(os.path.dirname(os.path.dirname(__file__)), ".warp_cache"))

import torch

# As the stage CLIs do (stages.cli.single_threaded_torch): the tracer owns the cores.
torch.set_num_threads(1)


import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# Snakemake's note that it reads the workflow profile (profiles/default), printed by every run
PROFILE_NOTE = re.compile(r"Using (profiles? .* and )?workflow specific profile .* for setting default command line")
SNAKEMAKE = [sys.executable, "-m", "snakemake", "--snakefile", str(ROOT / "Snakefile"), "--cores", "2"]


def snakemake(workdir, *args, timeout=600):
    """Run the workflow in ``workdir`` (its .snakemake/ state stays there)."""
    return subprocess.run([*SNAKEMAKE, "--directory", str(workdir), *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="session")
def tiny_demo(tmp_path_factory):
    """The whole pipeline on demo at CI size (preset ci, ~1 min with a warm Warp cache), run once per session:
    (workdir, results folder, the snakemake arguments used, the first run's process)."""
    workdir = tmp_path_factory.mktemp("tiny_demo")
    results = workdir / "results"
    args = ("--config", "scene=demo", "preset=ci", f"results={results}")
    proc = snakemake(workdir, *args)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return workdir, results, args, proc
