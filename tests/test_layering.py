"""The layering of ARCHITECTURE.md, checked by import-linter (the contracts in pyproject.toml): models/ never
imports stages/, no stage imports another stage. The contracts must list every stage, and must fail when a stage
imports another (shown on a copy of the packages with one such import added)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

from tests.conftest import ROOT

LINT = [sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"]


def _lint(cwd: Path, pythonpath: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return subprocess.run(LINT, cwd=cwd, capture_output=True, text=True, timeout=300, env=env)


def stage_packages() -> set[str]:
    return {f"stages.{p.parent.name}" for p in (ROOT / "stages").glob("*/__main__.py")}


def test_import_contracts_hold():
    proc = _lint(ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "models/ never imports stages/ KEPT" in proc.stdout
    assert "stages are leaves: no stage imports another stage KEPT" in proc.stdout


def test_contract_lists_every_stage():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    independent = next(c for c in config["contracts"] if c["type"] == "independence")
    assert set(independent["modules"]) == stage_packages()


def test_contract_fails_on_a_stage_importing_another(tmp_path):
    """A copy of the packages where the render stage imports the evaluate stage: the contract is BROKEN and the
    message names the import."""
    for name in ("models", "stages"):
        shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    cli = tmp_path / "stages" / "render" / "__main__.py"
    cli.write_text(cli.read_text().replace("from __future__ import annotations\n",
                                           "from __future__ import annotations\n\nimport stages.evaluate.__main__\n", 1))
    proc = _lint(tmp_path, pythonpath=tmp_path)
    assert proc.returncode != 0
    assert "stages are leaves: no stage imports another stage BROKEN" in proc.stdout
    assert "stages.render is not allowed to import stages.evaluate" in proc.stdout
    assert "stages.render.__main__ -> stages.evaluate.__main__" in proc.stdout


def test_workflow_imports_no_stage_internals():
    """The Snakefile and rules may use the shared config plumbing (stages.config) and models/, never a stage."""
    pattern = re.compile(r"^\s*(?:from|import)\s+(stages\.\w+)", re.M)
    offenders = []
    for smk in [ROOT / "Snakefile", *sorted((ROOT / "workflow" / "rules").glob("*.smk"))]:
        offenders += [f"{smk.name}: {m}" for m in pattern.findall(smk.read_text()) if m in stage_packages()]
    assert not offenders, offenders
