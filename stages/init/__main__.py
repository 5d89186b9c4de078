"""python -m stages.init: dense Gaussian initialisation of a capture -> <out>/points.ply."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from models.capture import CaptureError, read_capture
from models.gaussians import write_ply
from stages.config import ConfigError, load_config
from stages.init.dense import InitConfig, dense_init
from stages.provenance import write_stage_json

log = logging.getLogger("stages.init")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.init",
        description="Dense initialisation: unproject the training views' depth at low resolution, colour from the "
        "diffuse buffer, voxelise, one Gaussian per voxel with >= min_samples samples. Writes <out>/points.ply "
        "(3DGS field names + extra fields) and <out>/stage.json.",
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument("--config-json", help="the 'init' config section as JSON (what Snakemake passes)")
    src.add_argument("--scene", help="load the init section of configs/scenes/<scene>.yaml (+ defaults)")
    p.add_argument("--preset", action="append", default=[], help="preset(s) applied with --scene")
    p.add_argument("--capture", required=True, type=Path, help="capture folder (transforms.json + images/)")
    p.add_argument("--out", required=True, type=Path, help="output folder; gets points.ply")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        if args.config_json:
            section = json.loads(args.config_json)
        elif args.scene:
            section = load_config(args.scene, presets=args.preset).get("init", {})
        else:
            section = {}
        config = InitConfig.from_dict(section)
        start = time.perf_counter()
        capture = read_capture(args.capture, layers=["depth", "diffuse", "mask"])
        gaussians, summary = dense_init(capture, config)
    except (CaptureError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    write_ply(args.out / "points.ply", gaussians)
    log.info("dense init: %s", ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in summary.items()))
    write_stage_json(args.out, "init", section, time.perf_counter() - start, extra={"summary": summary})
    return 0


if __name__ == "__main__":
    sys.exit(main())
