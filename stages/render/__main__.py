"""python -m stages.render: render a trained model for the capture's test cameras and a novel camera path."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

from models.capture import CaptureError, read_capture
from models.gaussians import read_ply
from models.tracer import Tracer, TracerConfig
from stages.cli import add_config_args, load_section, single_threaded_torch
from stages.config import ConfigError
from stages.provenance import write_stage_json
from stages.render.render import RenderConfig, camera_path, render_view, write_layers

log = logging.getLogger("stages.render")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.render",
        description="Render a trained Gaussian scene: primary segment (diffuse + G-buffer) once, N reflection "
        "samples per pixel, specular denoised with Open Image Denoise. Writes <out>/test/<view>.exr (+ png/) for "
        "the capture's test views and <out>/path/ for a novel camera path (+ video when possible).",
    )
    add_config_args(p, "render")
    p.add_argument("--model", required=True, type=Path, help="trained gaussians.ply")
    p.add_argument("--capture", required=True, type=Path, help="capture (its test cameras are rendered)")
    p.add_argument("--out", required=True, type=Path, help="output folder (renders/)")
    p.add_argument("--device", default="cpu", help="cpu | cuda")
    p.add_argument("--threads", type=int, default=2, help="CPU tracer threads")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    single_threaded_torch()
    try:
        section = load_section(args, "render")
        config = RenderConfig.from_dict(section)
        capture = read_capture(args.capture, layers=["mask"])
        gaussians = read_ply(args.model)
    except (CaptureError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    tracer = Tracer(TracerConfig(num_threads=args.threads), device=args.device)
    tracer.update(gaussians)
    generator = torch.Generator().manual_seed(config.seed)
    start = time.perf_counter()
    test_views = capture.split("test") or capture.split("train")
    timings = {}
    for view in tqdm(test_views, desc="render test", unit="view"):
        t0 = time.perf_counter()
        img = render_view(tracer.trace, view.camera, gaussians, config, generator)
        timings[view.name] = round(time.perf_counter() - t0, 3)
        write_layers(args.out / "test", view.name, img)
    frames = []
    for i, cam in enumerate(tqdm(camera_path([v.camera for v in test_views], config.path_views),
                                 desc="render path", unit="view")):
        img = render_view(tracer.trace, cam, gaussians, config, generator)
        write_layers(args.out / "path", f"path_{i:03d}", img)
        frames.append(args.out / "path" / "png" / f"path_{i:03d}_final.png")
    video = _video(frames, args.out / "path") if config.video and frames else None
    write_stage_json(args.out, "render", section, time.perf_counter() - start, device=args.device,
                     extra={"seconds_per_view": timings, "video": str(video) if video else None})
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
    sys.exit(main())
