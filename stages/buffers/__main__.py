"""python -m stages.buffers: fill a capture's missing buffers with the buffer network's predictions."""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from models.capture import CaptureError, read_capture, write_capture
from stages.cli import add_config_args, load_section, single_threaded_torch
from stages.config import ConfigError
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
    from models.buffernet import BufferNetPipeline
    from models.buffernet.fill import BuffersConfig, fill_buffers, network_path

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
    except (CaptureError, ConfigError, ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    write_capture(result, args.out)
    for extra in ("points3D.ply", "sparse"):  # SfM points stay with the capture (init falls back on them)
        src = args.capture / extra
        if src.is_file():
            shutil.copy2(src, args.out / extra)
        elif src.is_dir():
            shutil.copytree(src, args.out / extra, dirs_exist_ok=True)
    (args.out / "buffers.json").write_text(json.dumps(info, indent=1))
    write_stage_json(args.out, "buffers", section, time.perf_counter() - start, device=args.device,
                     extra={"seconds_per_view": info["seconds_per_view"], "points": info["points"]})
    print(f"predicted {sorted({b for v in info['views'].values() for b in v['predicted']})} for "
          f"{len(info['views'])} view(s) in {time.perf_counter() - start:.1f} s -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
