"""python -m stages.evaluate: metrics.json from renders vs the capture's test split."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from stages.cli import single_threaded_torch


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.evaluate",
        description="PSNR and SSIM per layer (diffuse, specular, final) of <renders>/test/*.exr against the "
        "capture's test views (ground truth final = diffuse + specular + emission, diffuse = diffuse + emission, "
        "when the capture has an emission layer): linear at the view's peak (its ground-truth final image's maximum, "
        "the same for every layer), mu-law "
        "tonemapped (the headline), and, blind above 1, clamped and clamp + sRGB curve (as the PNGs); SSIM as 3DGS; "
        "'saturated' lists scores that stopped measuring (models/metrics/scoring.py DEFINITIONS); where the training "
        "views have depth, the tonemapped scores split into the pixels a training camera sees directly and the rest "
        "(seen_fraction, <seen|unseen>_psnr_<layer>_tonemapped, unseen_error_share_<layer>); with normal buffers, "
        "the angle between our normals and the truth's (normal_angle_deg, shiny_normal_angle_deg on F0 > 0.3); the "
        "share of the diffuse / specular error where that layer of the truth is dark (dark_error_share_<layer>: "
        "light where there is none). Adds training "
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
    p.add_argument("--device", default="cpu", help="cpu | cuda (FPS measurement, LPIPS)")
    p.add_argument("--threads", type=int, default=2, help="CPU tracer threads (FPS measurement)")
    p.add_argument("--config-json", default="{}", help="the 'evaluate' section as JSON: {regions: {name: {min, max}}, "
                   "lpips: {backbone: <torchvision alexnet-owt-7be5be79.pth>, lin: <lpips weights/v0.1/alex.pth>}} "
                   "(lpips: LPIPS v0.1 AlexNet from these local files, lpips_<layer> on the clamped sRGB images; "
                   "default off)")
    args = p.parse_args(argv)
    single_threaded_torch()
    from models.capture import CaptureError, read_capture  # after parsing: --help answers without torch / Warp
    from models.metrics import evaluate_renders
    from models.metrics.lpips import load_lpips
    from models.rendering import measure_fps
    from models.trained import GAUSSIANS_FILE, read_settings

    try:
        section = json.loads(args.config_json)
        unknown = set(section) - {"regions", "lpips"}
        if unknown:
            raise ValueError(f"unknown evaluate option(s) {sorted(unknown)}; known: ['lpips', 'regions']")
        lpips = None
        if section.get("lpips") is not None:
            lpips = load_lpips(**lpips_files(section["lpips"])).to(args.device)
        capture = read_capture(args.capture, layers=["diffuse", "specular", "emission", "depth", "mask", "normal",
                                                      "f0"])
        if not capture.split("test"):
            raise CaptureError(f"{args.capture}: the capture has no test views, nothing to score the renders "
                               "against; mark some frames \"split\": \"test\" in its transforms.json (photos: "
                               "poses.test_every > 0; synthetic: synth.cameras.test.count > 0)")
        check_renders(args.renders, args.model)
        metrics = evaluate_renders(capture, args.renders / "test", section.get("regions"), lpips)
    except (CaptureError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if capture.meta.extra.get("photos_path"):  # a photos run scored against a rendered truth: what limits it
        record = capture.meta.extra["photos_path"]
        metrics["photos_path"] = {"similarity": record.get("similarity"), "truth_scene": record.get("truth_scene"),
                                  "poses": {k: v for k, v in record.get("poses", {}).items() if k != "per_view"},
                                  "network": {"mean": (record.get("network") or {}).get("mean")}}
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
        try:
            metrics["model"] = read_settings(args.model).to_dict()
            if args.fps_repeats > 0:  # at the render stage's path length (its override, else the model's)
                length = render_stage.get("path", {}).get("max_path_length")
                metrics.update(measure_fps(args.model, capture.split("test")[0].camera, length, args.device,
                                           args.threads, args.fps_repeats))
        except (FileNotFoundError, ValueError) as e:  # a bad model.yaml, a truncated gaussians.ply
            print(f"error: {e}", file=sys.stderr)
            return 1
    if render_stage:
        metrics["render_seconds_per_view"] = render_stage.get("seconds_per_view", {})
        metrics["render_spp"] = render_stage.get("config", {}).get("spp")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_text(json.dumps(metrics, indent=1))
    tmp.replace(args.out)
    print(json.dumps(metrics["mean"], indent=1))
    for s in metrics["saturated"]:
        print(f"warning: saturated score, view {s['view']} {s['layer']}: {'; '.join(s['reasons'])}", file=sys.stderr)
    return 0


def lpips_files(option) -> dict[str, str]:
    """evaluate.lpips checked: {backbone: path, lin: path}, both and nothing else."""
    if not isinstance(option, dict) or set(option) != {"backbone", "lin"} or \
            not all(isinstance(v, str) and v for v in option.values()):
        raise ValueError(f"evaluate.lpips must be {{backbone: <path>, lin: <path>}} (two local files), got {option!r}")
    return option


def check_renders(renders: Path, model: Path | None) -> None:
    """Refuse renders that are not one finished run of the render stage (its stage.json is written last) or
    that were made from another model than ``model``."""
    from models.trained import GAUSSIANS_FILE, read_settings

    stage = renders / "stage.json"
    if not stage.is_file():
        raise ValueError(f"{renders}: no stage.json, so not a finished render (interrupted, or not written by "
                         "stages.render); render again")
    made_from = json.loads(stage.read_text()).get("model", {}).get("training")
    if model is not None and (model / GAUSSIANS_FILE).is_file() and made_from is not None:
        current = read_settings(model).training
        if made_from != current:
            raise ValueError(f"{renders} was rendered from another model than {model} (model.yaml training "
                             f"{made_from} vs {current}); render again")


if __name__ == "__main__":
    sys.exit(main())
