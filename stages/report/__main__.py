"""python -m stages.report: self-contained HTML reports (one scene, or a batch across scenes)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from stages.config import ConfigError, load_config


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.report",
        description="HTML reports with every picture embedded (one file to copy off a remote machine).\n"
        "  scene: ground truth vs ours per layer with error maps, metrics, cost, training curves, what the scene "
        "required and what was switched off, the novel camera path and the edits.\n"
        "  batch: the scenes side by side like the paper's Tables 1 (PSNR diffuse / specular / final) and 2 "
        "(training time), with links to each scene's report.\n"
        "  sweep: the speed / accuracy sweep (python -m stages.benchmark sweep): Pareto plots, table, recommended "
        "settings.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("scene", help="report of one scene's results folder")
    s.add_argument("results", type=Path, help="results/<scene> (capture/, model/, renders/, metrics.json)")
    s.add_argument("--out", type=Path, help="HTML path (default <results>/report.html)")
    s.add_argument("--config-json", help="the scene's merged config as JSON (what Snakemake passes); "
                   "default: configs/scenes/<folder name>.yaml merged with defaults and presets")
    s.add_argument("--command", dest="run_command", help="the command that ran the workflow, stated in the "
                   "report's header (Snakemake passes its own command line); default: the snakemake command for the "
                   "config's scene and presets")
    b = sub.add_parser("batch", help="one table across scenes")
    b.add_argument("results", type=Path, nargs="+", help="results/<scene> folders")
    b.add_argument("--out", type=Path, required=True, help="HTML path")
    b.add_argument("--title", default="batch report")
    b.add_argument("--command", dest="run_command", help="the command that ran the workflow, stated in the report's header")
    b.add_argument("--presets-json", default="{}", help="scene -> its presets, as JSON (what Snakemake passes); "
                   "shown in the table of each scene")
    w = sub.add_parser("sweep", help="the speed / accuracy sweep's sweep.json as HTML")
    w.add_argument("sweep", type=Path, help="sweep.json written by python -m stages.benchmark sweep")
    w.add_argument("--out", type=Path, help="HTML path (default: report.html beside sweep.json)")
    args = p.parse_args(argv)
    from .batch import batch_report  # after parsing: --help answers without torch / Warp
    from .scene import scene_report
    from .sweep import sweep_report

    try:
        if args.command == "scene":
            if not args.results.is_dir():
                raise FileNotFoundError(f"results folder {args.results} does not exist (run the pipeline first)")
            if args.config_json:
                config = json.loads(args.config_json)
            else:
                try:
                    config = load_config(args.results.name)
                except ConfigError:
                    config = {"scene": args.results.name}
            out = args.out or args.results / "report.html"
            _write(out, scene_report(args.results, config, command=args.run_command))
        elif args.command == "sweep":
            if not args.sweep.is_file():
                raise FileNotFoundError(f"{args.sweep} does not exist (run python -m stages.benchmark sweep first)")
            result = json.loads(args.sweep.read_text())
            out = args.out or args.sweep.with_name("report.html")
            _write(out, sweep_report(result, f"speed/accuracy sweep: {result.get('scene', args.sweep.parent.name)}"))
        else:
            missing = [str(d) for d in args.results if not (d / "metrics.json").is_file()]
            if missing:
                raise FileNotFoundError(f"no metrics.json in {', '.join(missing)} (run the scene(s) first)")
            out = args.out
            presets = json.loads(args.presets_json)
            if not isinstance(presets, dict):
                raise ValueError(f"--presets-json must map scene names to preset lists, got {args.presets_json!r}")
            _write(out, batch_report(args.results, out, args.title, command=args.run_command, presets=presets))
    except (FileNotFoundError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
