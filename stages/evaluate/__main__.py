"""python -m stages.evaluate: metrics.json from renders vs the capture's test split."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from models.capture import CaptureError, read_capture
from models.metrics import evaluate_renders
from models.rendering import measure_fps
from models.trained import GAUSSIANS_FILE, read_settings
from stages.cli import single_threaded_torch


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.evaluate",
        description="PSNR and SSIM per layer (diffuse, specular, final) of <renders>/test/*.exr against the "
        "capture's test views, linear and tonemapped (clamp to [0, 1] + sRGB curve, as the PNGs); adds training "
        "time, Gaussian count, peak memory and the training decisions from the model's stage.json, render time "
        "from the renders' stage.json, and render FPS at 1 spp (no denoiser). Writes <out> (metrics.json).",
    )
    p.add_argument("--capture", required=True, type=Path)
    p.add_argument("--renders", required=True, type=Path, help="render stage output folder")
    p.add_argument("--model", type=Path, help="model folder (reconstruct output: training time, and the FPS "
                   "measurement renders it with its own settings, model.yaml)")
    p.add_argument("--out", required=True, type=Path, help="metrics.json path")
    p.add_argument("--fps-repeats", type=int, default=3,
                   help="timed frames for render FPS at 1 spp (needs --model; 0 = skip)")
    p.add_argument("--device", default="cpu", help="cpu | cuda (FPS measurement)")
    p.add_argument("--threads", type=int, default=2, help="CPU tracer threads (FPS measurement)")
    p.add_argument("--config-json", default="{}", help="the 'evaluate' section as JSON: {regions: {name: {min, max}}}")
    args = p.parse_args(argv)
    single_threaded_torch()
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
        metrics["train_peak_rss_mib"] = stage.get("peak_rss_mib")
        if stage.get("peak_cuda_mib") is not None:
            metrics["train_peak_cuda_mib"] = stage["peak_cuda_mib"]
        metrics["decisions"] = stage.get("decisions", [])
    render_stage = {}
    if (args.renders / "stage.json").is_file():
        render_stage = json.loads((args.renders / "stage.json").read_text())
    if args.model and (args.model / GAUSSIANS_FILE).is_file():
        metrics["model"] = read_settings(args.model).to_dict()
        if args.fps_repeats > 0:  # at the render stage's path length (its override, else the model's)
            length = render_stage.get("path", {}).get("max_path_length")
            metrics.update(measure_fps(args.model, capture.split("test")[0].camera, length, args.device,
                                       args.threads, args.fps_repeats))
    if render_stage:
        metrics["render_seconds_per_view"] = render_stage.get("seconds_per_view", {})
        metrics["render_spp"] = render_stage.get("config", {}).get("spp")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(metrics, indent=1))
    tmp.replace(args.out)
    print(json.dumps(metrics["mean"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
