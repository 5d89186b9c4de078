"""python -m stages.edit {apply,truth,evaluate}: edit a trained scene, render its ground truth, score it.

  apply     model + named edit -> <out>/model/gaussians.ply, <out>/renders/test/*.exr (+ png/), <out>/stage.json
  truth     synthetic scenes: the capture's test views rendered (Mitsuba) with the edit's ``ground_truth``
  evaluate  edited renders vs truth, next to the unedited renders vs the capture -> metrics.json

The edit comes from ``--edit NAME`` with ``--edit-json`` (its mapping, what Snakemake passes) or from the
``edits:`` of ``--scene`` (the merged config).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from models.capture import CaptureError, read_capture
from stages.cli import add_config_args, load_section, single_threaded_torch
from stages.config import ConfigError, load_config
from stages.provenance import write_stage_json

from .spec import EditSpec, parse_edit

log = logging.getLogger("stages.edit")


def _edit_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--edit", required=True, help="the edit's name (a key of the scene config's edits:)")
    p.add_argument("--edit-json", help="the edit's mapping as JSON (what Snakemake passes); else from --scene")
    p.add_argument("--edit-file", type=Path, help="YAML with an edits: mapping (e.g. saved by the viewer, "
                   "python -m stages.view); else from --scene")


def _load_edit(args: argparse.Namespace) -> tuple[EditSpec, dict]:
    if args.edit_json:
        try:
            raw = json.loads(args.edit_json)
        except json.JSONDecodeError as e:
            raise ValueError(f"--edit-json: invalid JSON ({e})") from None
    elif args.edit_file:
        import yaml

        edits = (yaml.safe_load(args.edit_file.read_text()) or {}).get("edits") or {}
        if args.edit not in edits:
            raise ValueError(f"{args.edit_file}: no edit {args.edit!r} under edits: (found: {', '.join(edits) or 'none'})")
        raw = edits[args.edit]
    elif args.scene:
        edits = load_config(args.scene, presets=args.preset).get("edits") or {}
        if args.edit not in edits:
            raise ValueError(f"scene {args.scene!r}: unknown edit {args.edit!r} (known: {', '.join(edits) or 'none'})")
        raw = edits[args.edit]
    else:
        raise ValueError("give --edit-json, --edit-file or --scene (to read the edit from the scene config)")
    return parse_edit(args.edit, raw), raw


def _apply(args: argparse.Namespace) -> int:
    from models.gaussians import read_ply, write_ply
    from models.tracer import Tracer, TracerConfig
    from stages.render.render import RenderConfig

    from .edit import apply_edit, render_test_views

    single_threaded_torch()
    start = time.perf_counter()
    spec, raw = _load_edit(args)
    section = load_section(args, "render")
    config = RenderConfig.from_dict(section)
    capture = read_capture(args.capture, layers=["mask"])
    gaussians = read_ply(args.model)
    edited, report = apply_edit(gaussians, spec)
    write_ply(args.out / "model" / "gaussians.ply", edited)
    tracer = Tracer(TracerConfig(num_threads=args.threads), device=args.device)
    timings = render_test_views(tracer, capture, edited.to(device=args.device), config, args.out / "renders" / "test")
    write_stage_json(args.out, "edit", {"edit": raw, "render": section}, time.perf_counter() - start,
                     device=args.device, extra={"edit": spec.name, "ops": report, "render_spp": config.spp,
                                                "seconds_per_view": timings})
    print(json.dumps({"edit": spec.name, "ops": [{k: r[k] for k in ("op", "selected", "gaussians_after")}
                                                  for r in report]}))
    return 0


def _truth(args: argparse.Namespace) -> int:
    from .truth import render_truth

    start = time.perf_counter()
    spec, raw = _load_edit(args)
    if args.synth_json:
        synth = json.loads(args.synth_json)
    elif args.scene:
        synth = load_config(args.scene, presets=args.preset).get("synth")
    else:
        raise ValueError("give --synth-json or --scene (the synth: section to re-render)")
    if not synth:
        raise ValueError(f"edit {spec.name!r}: no synth: section, a ground truth needs a synthetic scene")
    capture = render_truth(synth, spec, args.out)
    write_stage_json(args.out, "edit_truth", {"synth": synth, "ground_truth": list(spec.ground_truth or [])},
                     time.perf_counter() - start, extra={"edit": spec.name, "views": len(capture.views)})
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from .edit import evaluate_edit

    layers = ["diffuse", "specular", "depth", "mask"]
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
    a.add_argument("--model", required=True, type=Path, help="trained gaussians.ply")
    a.add_argument("--capture", required=True, type=Path, help="capture (its test cameras are rendered)")
    a.add_argument("--out", required=True, type=Path, help="output folder (edits/<name>/)")
    a.add_argument("--device", default="cpu", help="cpu | cuda")
    a.add_argument("--threads", type=int, default=2, help="CPU tracer threads")
    t = sub.add_parser("truth", help="render the capture's test views of the synthetic scene with the edit's "
                       "ground_truth applied (Mitsuba)")
    _edit_args(t)
    t.add_argument("--scene", help="read the edit and the synth: section from this scene's merged config")
    t.add_argument("--preset", action="append", default=[], help="extra preset(s) applied with --scene")
    t.add_argument("--synth-json", help="the synth: section as JSON (what Snakemake passes)")
    t.add_argument("--out", required=True, type=Path, help="output capture folder")
    e = sub.add_parser("evaluate", help="edited renders vs ground truth, next to the unedited renders")
    e.add_argument("--edit", required=True, help="the edit's name (recorded in the metrics)")
    e.add_argument("--capture", required=True, type=Path, help="the unedited capture (test split)")
    e.add_argument("--truth", required=True, type=Path, help="the edited ground-truth capture ('truth' output)")
    e.add_argument("--renders", required=True, type=Path, help="the edited renders (<edit>/renders/test)")
    e.add_argument("--baseline-renders", required=True, type=Path, help="the unedited renders (renders/test)")
    e.add_argument("--out", required=True, type=Path, help="metrics.json path")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        return {"apply": _apply, "truth": _truth, "evaluate": _evaluate}[args.command](args)
    except (CaptureError, ConfigError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
