"""python -m stages.evaluate: metrics.json from renders vs the capture's test split."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from models.capture import CaptureError, read_capture
from stages.evaluate.evaluate import evaluate_renders


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.evaluate",
        description="PSNR and SSIM per layer (diffuse, specular, final) of <renders>/test/*.exr against the "
        "capture's test views, linear and tonemapped; adds training time and Gaussian count from the model's "
        "stage.json and render time from the renders' stage.json. Writes <out> (metrics.json).",
    )
    p.add_argument("--capture", required=True, type=Path)
    p.add_argument("--renders", required=True, type=Path, help="render stage output folder")
    p.add_argument("--model", type=Path, help="reconstruct output folder (for training time)")
    p.add_argument("--out", required=True, type=Path, help="metrics.json path")
    p.add_argument("--config-json", default="{}", help="the 'evaluate' section as JSON: {regions: {name: {min, max}}}")
    args = p.parse_args(argv)
    try:
        section = json.loads(args.config_json)
        unknown = set(section) - {"regions"}
        if unknown:
            raise ValueError(f"unknown evaluate option(s) {sorted(unknown)}; known: ['regions']")
        capture = read_capture(args.capture, layers=["diffuse", "specular", "depth", "mask"])
        metrics = evaluate_renders(capture, args.renders / "test", section.get("regions"))
    except (CaptureError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if args.model and (args.model / "stage.json").is_file():
        stage = json.loads((args.model / "stage.json").read_text())
        metrics["train_time_s"] = stage.get("wall_time_s")
        metrics["gaussians"] = stage.get("final", {}).get("gaussians")
    if (args.renders / "stage.json").is_file():
        seconds = json.loads((args.renders / "stage.json").read_text()).get("seconds_per_view", {})
        metrics["render_seconds_per_view"] = seconds
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(metrics, indent=1))
    tmp.replace(args.out)
    print(json.dumps(metrics["mean"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
