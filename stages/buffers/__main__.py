"""python -m stages.buffers: fill a capture's missing buffers with the buffer network's predictions."""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from stages.cli import add_config_args, load_section, single_threaded_torch
from stages.config import ConfigError
from stages.output import run_stage, staged_folder
from stages.provenance import write_stage_json


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.buffers",
        description="Predict the buffers listed in the config's buffers.predict (diffuse, specular, normal, depth, "
        "roughness, f0) with a saved buffer network, one batched pass per view, and write the capture with them "
        "(normals to world space, relative depth aligned to SfM points). Views that already have a buffer keep it "
        "unless buffers.replace is set.")
    add_config_args(p, "buffers")
    p.add_argument("--capture", required=True, type=Path, help="input capture folder")
    p.add_argument("--model", help="saved buffer network folder (default: the config's buffers.model)")
    p.add_argument("--out", required=True, type=Path, help="capture folder to write")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    single_threaded_torch()
    from models.buffernet import BufferNetPipeline  # after parsing: --help answers at once
    from models.buffernet.fill import BuffersConfig, fill_buffers, network_path
    from models.capture import POINTS_FILE, CaptureError, read_capture, write_capture, write_points_ply
    from models.capture.points import find_sfm_points

    start = time.perf_counter()
    try:
        section = load_section(args, "buffers")
        if args.model:
            section = {**section, "model": args.model}
        cfg = BuffersConfig.from_dict(section)
        if not cfg.predict:
            raise ValueError("buffers.predict is empty: nothing to predict")
        model = network_path(cfg.model)
        if not (model / "model_index.json").is_file():
            raise FileNotFoundError(f"buffer network {model} not found (no model_index.json): train one with "
                                    "`snakemake --cores 2 buffernet` or `python -m stages.buffernet_train train`")
        pipe = BufferNetPipeline.from_pretrained(model).to(args.device)
        capture = read_capture(args.capture)
        result, info = fill_buffers(capture, args.capture, pipe, cfg, progress=not args.no_progress)
        points = find_sfm_points(args.capture)  # also nerfstudio's ply_file_path / colmap/sparse/0
    except (CaptureError, ConfigError, ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    with staged_folder(args.out) as out:
        write_capture(result, out)
        for extra in ("points3D.ply", "sparse"):  # SfM points stay with the capture (init falls back on them)
            src = args.capture / extra
            if src.is_file():
                shutil.copy2(src, out / extra)
            elif src.is_dir():
                shutil.copytree(src, out / extra, dirs_exist_ok=True)
        if points is not None and points[2] != args.capture / POINTS_FILE:  # named elsewhere: keep as points3D.ply
            write_points_ply(out / POINTS_FILE, points[0], points[1])
        (out / "buffers.json").write_text(json.dumps(info, indent=1))
        write_stage_json(out, "buffers", section, time.perf_counter() - start, device=args.device,
                         extra={"seconds_per_view": info["seconds_per_view"], "points": info["points"]})
    print(f"predicted {sorted({b for v in info['views'].values() for b in v['predicted']})} for "
          f"{len(info['views'])} view(s) in {time.perf_counter() - start:.1f} s -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_stage(main))
