"""python -m stages.render: render a trained model for the capture's test cameras and a novel camera path."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from stages.cli import add_config_args, load_section, single_threaded_torch
from stages.config import ConfigError
from stages.output import run_stage, staged_folder
from stages.provenance import write_stage_json

log = logging.getLogger("stages.render")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.render",
        description="Render a trained Gaussian scene: primary segment (diffuse + G-buffer) once, N reflection "
        "samples per pixel, specular denoised with Open Image Denoise. Writes <out>/test/<view>.exr (+ png/) for "
        "the capture's test views and <out>/path/ for a novel camera path (+ video when possible).",
    )
    add_config_args(p, "render")
    p.add_argument("--model", required=True, type=Path, help="trained model folder (gaussians.ply + model.yaml: "
                   "the tracer / path settings it was trained with); a gaussians.ply path means its folder")
    p.add_argument("--capture", required=True, type=Path, help="capture (its test cameras are rendered)")
    p.add_argument("--out", required=True, type=Path, help="output folder (renders/)")
    p.add_argument("--device", default="cpu", help="cpu | cuda")
    p.add_argument("--threads", type=int, default=2, help="CPU tracer threads")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    single_threaded_torch()
    import torch  # after parsing: --help answers without loading torch / Warp
    from tqdm import tqdm

    from models.capture import CaptureError, read_capture
    from models.rendering import RenderConfig, camera_path, render_view, render_views, write_layers
    from models.tracer import Tracer
    from models.trained import load_model

    try:
        section = load_section(args, "render")
        config = RenderConfig.from_dict(section)
        capture = read_capture(args.capture, layers=["mask"])
        gaussians, settings = load_model(args.model)
    except (CaptureError, ConfigError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    path = config.path(settings.path)
    tracer = Tracer(settings.tracer_config(args.threads), device=args.device)
    tracer.update(gaussians)
    log.info("rendering with the model's settings (%s): kernel_p %d, max path length %d, sampler %s",
             settings.source, tracer.config.kernel_p, path.max_path_length, path.sampler)
    warnings = []
    if config.spp == 0 and path.max_path_length > 1:
        warnings.append("render.spp 0: no reflection samples, the specular layer is black and final = diffuse")
    if not capture.split("test"):
        warnings.append(f"{args.capture} has no test views: its training views are rendered into test/ "
                        "(the evaluate stage needs test views to score)")
    for w in warnings:
        log.warning(w)
    generator = torch.Generator().manual_seed(config.seed)
    start = time.perf_counter()
    test_views = capture.split("test") or capture.split("train")
    with staged_folder(args.out) as out:  # complete or absent: a killed run leaves no mix of old and new files
        timings = render_views(tracer, test_views, gaussians, config, settings.path, out / "test", generator,
                               desc="render test")
        frames = []
        for i, cam in enumerate(tqdm(camera_path([v.camera for v in test_views], config.path_views),
                                     desc="render path", unit="view")):
            img = render_view(tracer.trace, cam, gaussians, config, generator, settings.path)
            write_layers(out / "path", f"path_{i:03d}", img)
            frames.append(out / "path" / "png" / f"path_{i:03d}_final.png")
        video = _video(frames, out / "path") if config.video and frames else None
        write_stage_json(out, "render", section, time.perf_counter() - start, device=args.device,
                         extra={"seconds_per_view": timings,
                                "video": str(args.out / video.relative_to(out)) if video else None,
                                "warnings": warnings,
                                "model": settings.to_dict(), "path": {"max_path_length": path.max_path_length,
                                                                      "sampler": path.sampler}})
    return 0


def _video(frames: list[Path], out_dir: Path) -> Path | None:
    """An MP4 if an ffmpeg plugin is present, else an animated GIF; None (logged) if neither works."""
    import imageio.v3 as iio

    images = [iio.imread(f) for f in frames]
    for name, kwargs in (("path.mp4", {"fps": 12}), ("path.gif", {"duration": 80, "loop": 0})):
        try:
            iio.imwrite(out_dir / name, images, **kwargs)
            return out_dir / name
        except Exception as e:  # plugin missing: try the next format
            log.info("video %s not written (%s)", name, e)
    return None


if __name__ == "__main__":
    sys.exit(run_stage(main))
