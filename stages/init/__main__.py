"""python -m stages.init: Gaussian initialisation of a capture (dense from depth, else SfM points) -> <out>/points.ply."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from stages.cli import add_config_args, load_section
from stages.config import ConfigError
from stages.output import run_stage, staged_folder
from stages.provenance import write_stage_json

log = logging.getLogger("stages.init")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.init",
        description="Dense initialisation: unproject the training views' depth at low resolution, colour from the "
        "diffuse buffer, voxelise, one Gaussian per voxel with >= min_samples samples. Without a depth buffer (or "
        "with source: sfm): one Gaussian per SfM point of <capture>/points3D.ply or <capture>/sparse/. Writes "
        "<out>/points.ply (3DGS field names + extra fields) and <out>/stage.json.",
    )
    add_config_args(p, "init")
    p.add_argument("--capture", required=True, type=Path, help="capture folder (transforms.json + images/)")
    p.add_argument("--out", required=True, type=Path, help="output folder; gets points.ply")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    from models.capture import CaptureError, read_capture  # after parsing: --help answers without torch
    from models.gaussians import write_ply
    from models.initialisation import InitConfig, initialise

    try:
        section = load_section(args, "init")
        config = InitConfig.from_dict(section)
        start = time.perf_counter()
        layers = ["depth", "diffuse", "emission", "mask"] + (["normal"] if config.flatten < 1.0 else [])
        capture = read_capture(args.capture, layers=layers)
        gaussians, summary = initialise(capture, args.capture, config)
    except (CaptureError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    log.info("%s", summary.get("decision"))
    log.info("init: %s", ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                                   for k, v in summary.items() if k != "decision"))
    if config.flatten < 1.0 and not summary.get("discs"):
        if any("normal" in v.buffers for v in capture.views):  # normals, yet no disc: worth a look
            log.warning("init.flatten %g asked for discs, none made: no voxel's normals agree", config.flatten)
        else:  # photos / SfM captures without normals: the reference's spheres, as expected
            log.info("init.flatten %g asked for discs, none made: the capture has no normal buffer (spheres)",
                     config.flatten)
    with staged_folder(args.out) as out:
        write_ply(out / "points.ply", gaussians)
        write_stage_json(out, "init", section, time.perf_counter() - start, extra={"summary": summary})
    return 0


if __name__ == "__main__":
    sys.exit(run_stage(main))
