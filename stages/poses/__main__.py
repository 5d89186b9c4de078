"""python -m stages.poses: photos -> COLMAP poses (pycolmap, CPU) -> a capture with SfM points."""

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

log = logging.getLogger("stages.poses")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.poses",
        description="Structure from motion on a folder of photos (one camera, one resolution): SIFT features, "
        "exhaustive / sequential / vocabulary-tree matching, incremental mapping, the largest model undistorted "
        "to PINHOLE, the scene centred and scaled. Writes a capture (transforms.json + linear EXR per view + "
        "capture.yaml recording the normalisation) with points3D.ply and the COLMAP model in sparse/. A folder "
        "that already has a COLMAP model (images/ + sparse/ [+ priors/], the paper's released real scenes) "
        "skips SfM.",
    )
    add_config_args(p, "poses")
    p.add_argument("--images", type=Path, help="folder of photos, or a COLMAP folder with images/ + sparse/ "
                   "(default: the config's poses.images)")
    p.add_argument("--work", required=True, type=Path, help="COLMAP work folder: database.db, sparse/<k>/, undistorted/")
    p.add_argument("--out", required=True, type=Path, help="capture folder to write")
    p.add_argument("--threads", type=int, default=2, help="CPU threads for SIFT, matching and mapping (default 2)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    single_threaded_torch()
    from models.capture import CaptureError  # after parsing: --help answers at once
    from models.poses import run_poses
    from models.poses.config import PosesConfig

    start = time.perf_counter()
    try:
        section = load_section(args, "poses")
        config = PosesConfig.from_dict(section)
        images = args.images or (Path(config.images) if config.images else None)
        if images is None:
            raise ValueError("no photos given: pass --images DIR or set poses.images in the scene config")
        if args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        with staged_folder(args.out) as out:  # the capture complete or absent
            capture = run_poses(images, args.work, out, config, threads=args.threads,
                                progress=not args.no_progress)
    except (CaptureError, ConfigError, ValueError) as e:  # PosesError is a ValueError
        print(f"error: {e}", file=sys.stderr)
        return 1
    args.work.mkdir(parents=True, exist_ok=True)
    write_stage_json(args.work, "poses", section, time.perf_counter() - start,
                     extra={"poses": capture.meta.extra.get("poses"),
                            "normalisation": capture.meta.extra.get("normalisation")})
    return 0


if __name__ == "__main__":
    sys.exit(run_stage(main))
