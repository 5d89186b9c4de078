"""python -m stages.reconstruct: train the Gaussian scene of a capture from its dense init."""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

from models.capture import CaptureError, read_capture
from models.gaussians import read_ply
from models.reconstruction import ReconstructConfig, Trainer, train
from models.tracer import Tracer
from models.trained import save_model
from stages.cli import add_config_args, load_section, single_threaded_torch
from stages.config import ConfigError
from stages.provenance import write_stage_json

log = logging.getLogger("stages.reconstruct")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.reconstruct",
        description="Optimise ONE Gaussian scene: diffuse + G-buffer losses on primary rays, path-traced specular "
        "after warm-up (paper Eq. 4-7). Writes the model folder <out>/ (gaussians.ply + model.yaml: the tracer and "
        "path settings every consumer renders it with), <out>/checkpoints/last.pt (exact resume), "
        "<out>/train_log.jsonl (metrics, JSON lines) and <out>/stage.json.",
    )
    add_config_args(p, "reconstruct")
    p.add_argument("--capture", required=True, type=Path, help="capture folder")
    p.add_argument("--init", required=True, type=Path, help="initial Gaussians (init/points.ply)")
    p.add_argument("--out", required=True, type=Path, help="output folder (model/)")
    p.add_argument("--device", default="cpu", help="cpu | cuda")
    p.add_argument("--resume", action="store_true", help="continue from <out>/checkpoints/last.pt if present")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    single_threaded_torch()
    try:
        section = load_section(args, "reconstruct")
        config = ReconstructConfig.from_dict(section)
        capture = read_capture(args.capture)
        init = read_ply(args.init)
        trainer = Trainer(capture, init, config, Tracer(config.tracer, device=args.device))
    except (CaptureError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    ckpt = args.out / "checkpoints" / "last.pt"
    if args.resume and ckpt.is_file():
        trainer.load_checkpoint(ckpt)
        log.info("resumed from %s at step %d", ckpt, trainer.step)
    elif (args.out / "train_log.jsonl").exists():
        (args.out / "train_log.jsonl").unlink()
    start = time.perf_counter()
    metrics = train(trainer, args.out, progress=not args.no_progress)
    save_model(args.out, trainer.gaussians(), trainer.settings())
    log.info("final: %s", json.dumps(metrics))
    write_stage_json(args.out, "reconstruct", section, time.perf_counter() - start, device=args.device,
                     extra={"decisions": trainer.decisions, "final": metrics})
    return 0


if __name__ == "__main__":
    sys.exit(main())
