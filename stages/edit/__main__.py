"""python -m stages.edit {apply,evaluate}: edit a trained scene and score it against its ground truth.

  apply     model folder + named edit -> <out>/model/ (gaussians.ply + model.yaml), <out>/renders/test/*.exr
            (+ png/), <out>/stage.json
  evaluate  edited renders vs the edited ground truth, next to the unedited renders -> metrics.json

The edit comes from ``--edit NAME`` with ``--edit-json`` (its mapping, what Snakemake passes), ``--edit-file``
(a YAML with edits:, e.g. saved by the viewer) or from the ``edits:`` of ``--scene`` (the merged config).
The ground truth of a synthetic scene's edit is rendered by the synth stage from the edit's ground_truth list:
``python -m stages.synth --scene demo --edits move_ball --splits test --out results/demo/edits/move_ball/truth``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from stages.cli import add_config_args, load_section, single_threaded_torch
from stages.config import ConfigError, load_config
from stages.output import run_stage, staged_folder
from stages.provenance import write_stage_json

if TYPE_CHECKING:
    from models.editing import EditSpec

log = logging.getLogger("stages.edit")


def _edit_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--edit", required=True, help="the edit's name (a key of the scene config's edits:)")
    p.add_argument("--edit-json", help="the edit's mapping as JSON (what Snakemake passes); else from --scene")
    p.add_argument("--edit-file", type=Path, help="YAML with an edits: mapping (e.g. saved by the viewer, "
                   "python -m stages.view); else from --scene")


def _load_edit(args: argparse.Namespace) -> tuple[EditSpec, dict]:
    from models.editing import EditSpecError, parse_edit

    if args.edit_json:
        try:
            raw = json.loads(args.edit_json)
        except json.JSONDecodeError as e:
            raise ValueError(f"--edit-json: invalid JSON ({e})") from None
    elif args.edit_file:
        from models.settings import read_yaml_mapping

        if not args.edit_file.is_file():
            raise ValueError(f"--edit-file {args.edit_file}: no such file")
        edits = read_yaml_mapping(args.edit_file).get("edits") or {}
        if not isinstance(edits, dict):
            raise ValueError(f"{args.edit_file}: 'edits' must be a mapping of named edits, got "
                             f"{type(edits).__name__} {edits!r}")
        if args.edit not in edits:
            raise ValueError(f"{args.edit_file}: no edit {args.edit!r} under edits: (found: {', '.join(map(str, edits)) or 'none'})")
        try:
            return parse_edit(args.edit, edits[args.edit]), edits[args.edit]
        except EditSpecError as e:
            raise ValueError(f"{args.edit_file}: {e}") from None
    elif args.scene:
        edits = load_config(args.scene, presets=args.preset).get("edits") or {}
        if args.edit not in edits:
            raise ValueError(f"scene {args.scene!r}: unknown edit {args.edit!r} (known: {', '.join(edits) or 'none'})")
        raw = edits[args.edit]
    else:
        raise ValueError("give --edit-json, --edit-file or --scene (to read the edit from the scene config)")
    return parse_edit(args.edit, raw), raw


def _apply(args: argparse.Namespace) -> int:
    import dataclasses

    from models.capture import read_capture
    from models.editing import apply_edit
    from models.rendering import RenderConfig, render_views
    from models.tracer import Tracer
    from models.trained import load_model, save_model

    single_threaded_torch()
    start = time.perf_counter()
    spec, raw = _load_edit(args)
    section = load_section(args, "render")
    config = RenderConfig.from_dict(section)
    capture = read_capture(args.capture, layers=["mask"])
    gaussians, settings = load_model(args.model)
    tracer = Tracer(settings.tracer_config(args.threads), device=args.device)
    # set_albedo traces the model with the paths this stage renders
    edited, report = apply_edit(gaussians, spec, trace_fn=tracer.trace, path=config.path(settings.path))
    # the edited model renders like the model it was edited from (same model.yaml, plus the edit's name)
    settings = dataclasses.replace(settings, training={**settings.training, "edit": spec.name})
    # model/ and renders/ each complete or absent; stage.json (written last) says both belong to this run
    (args.out / "stage.json").unlink(missing_ok=True)
    with staged_folder(args.out / "model") as out:
        save_model(out, edited, settings)
    edited, _ = load_model(args.out / "model")  # render the model as written (the PLY's colour encoding rounds)
    tracer.update(edited, rebuild=True)
    views = capture.split("test") or capture.split("train")
    with staged_folder(args.out / "renders") as out:
        timings = render_views(tracer, views, edited, config, settings.path, out / "test", desc="render edit")
    write_stage_json(args.out, "edit", {"edit": raw, "render": section}, time.perf_counter() - start,
                     device=args.device, extra={"edit": spec.name, "ops": report, "render_spp": config.spp,
                                                "seconds_per_view": timings, "model": settings.to_dict()})
    print(json.dumps({"edit": spec.name, "ops": [{k: r[k] for k in ("op", "selected", "gaussians_after", "relit",
                                                                     "changed") if k in r} for r in report]}))
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from models.capture import read_capture
    from models.metrics import evaluate_edit

    layers = ["diffuse", "specular", "emission", "depth", "mask"]  # final = diffuse + specular + emission
    capture = read_capture(args.capture, layers=layers)
    truth = read_capture(args.truth, layers=layers)
    metrics = evaluate_edit(capture, truth, args.renders, args.baseline_renders)
    metrics = {"edit": args.edit, **metrics}
    stage = args.renders.parent.parent / "stage.json"
    if stage.is_file():
        rec = json.loads(stage.read_text())
        metrics["render_spp"] = rec.get("render_spp")
        metrics["ops"] = rec.get("ops")
    base = args.baseline_renders.parent / "stage.json"
    if base.is_file():
        metrics["baseline_render_spp"] = json.loads(base.read_text()).get("config", {}).get("spp")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(metrics, indent=1))
    tmp.replace(args.out)
    print(json.dumps({k: metrics[k] for k in ("edited_vs_truth", "unedited_vs_truth", "changed_region")}, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m stages.edit", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    a = sub.add_parser("apply", help="apply an edit to a model and render the capture's test views")
    _edit_args(a)
    add_config_args(a, "render")
    a.add_argument("--model", required=True, type=Path, help="trained model folder (gaussians.ply + model.yaml); "
                   "a gaussians.ply path means its folder")
    a.add_argument("--capture", required=True, type=Path, help="capture (its test cameras are rendered)")
    a.add_argument("--out", required=True, type=Path, help="output folder (edits/<name>/)")
    a.add_argument("--device", default="cpu", help="cpu | cuda")
    a.add_argument("--threads", type=int, default=2, help="CPU tracer threads")
    e = sub.add_parser("evaluate", help="edited renders vs ground truth, next to the unedited renders")
    e.add_argument("--edit", required=True, help="the edit's name (recorded in the metrics)")
    e.add_argument("--capture", required=True, type=Path, help="the unedited capture (test split)")
    e.add_argument("--truth", required=True, type=Path, help="the edited ground-truth capture (python -m stages.synth "
                   "... --edits NAME --splits test)")
    e.add_argument("--renders", required=True, type=Path, help="the edited renders (<edit>/renders/test)")
    e.add_argument("--baseline-renders", required=True, type=Path, help="the unedited renders (renders/test)")
    e.add_argument("--out", required=True, type=Path, help="metrics.json path")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    from models.capture import CaptureError  # after parsing: --help answers without torch / Warp

    try:
        return {"apply": _apply, "evaluate": _evaluate}[args.command](args)
    except (CaptureError, ConfigError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(run_stage(main))
