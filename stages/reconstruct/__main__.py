"""python -m stages.reconstruct: train the Gaussian scene of a capture from its dense init."""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import sys
import time
from pathlib import Path

from models.settings import file_sha256
from stages.cli import add_config_args, load_section, single_threaded_torch
from stages.config import ConfigError
from stages.output import run_stage
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
    p.add_argument("--resume", action="store_true",
                   help="continue from <out>/checkpoints/last.pt when it was written under the same config and inputs "
                   "(otherwise it is kept aside as checkpoints/replaced-*.pt and training starts afresh)")
    p.add_argument("--threads", type=int, help="CPU tracer threads (what Snakemake gives the job; default: the "
                   "config's reconstruct.tracer.num_threads)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    single_threaded_torch()
    import dataclasses  # the models after parsing: --help answers without loading torch / Warp

    from models.capture import CaptureError, read_capture
    from models.gaussians import read_ply
    from models.reconstruction import ReconstructConfig, Trainer, train
    from models.tracer import Tracer
    from models.trained import save_model

    try:
        section = load_section(args, "reconstruct")
        config = ReconstructConfig.from_dict(section)
        if args.threads is not None:  # not part of the resume fingerprint (a runtime setting)
            config = dataclasses.replace(config, tracer=dataclasses.replace(config.tracer, num_threads=args.threads))
        capture = read_capture(args.capture)
        init = read_ply(args.init)
        trainer = Trainer(capture, init, config, Tracer(config.tracer, device=args.device))
    except (CaptureError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    trainer.inputs = {"init": file_sha256(args.init), "capture": capture_digest(args.capture)}
    # the model files of an earlier run go first: until this run ends, the folder holds no model (only the
    # checkpoints it may resume from), never an old model beside new checkpoints
    for name in ("gaussians.ply", "model.yaml", "stage.json"):
        (args.out / name).unlink(missing_ok=True)
    resumed = resume(trainer, args.out, args.resume)
    start = time.perf_counter()
    metrics = train(trainer, args.out, progress=not args.no_progress)
    save_model(args.out, trainer.gaussians(), trainer.settings())
    log.info("final: %s", json.dumps(metrics))
    write_stage_json(args.out, "reconstruct", section, time.perf_counter() - start, device=args.device,
                     extra={"decisions": trainer.decisions, "final": metrics, "resumed_from_step": resumed})
    return 0


def capture_digest(folder: Path) -> str:
    """SHA-256 over a capture's capture.yaml and its files' names, sizes and modification times (reading every
    EXR would cost more than a resume saves)."""
    digest = hashlib.sha256((folder / "capture.yaml").read_bytes() if (folder / "capture.yaml").is_file() else b"")
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        st = path.stat()
        digest.update(f"{path.relative_to(folder)}:{st.st_size}:{st.st_mtime_ns}".encode())
    return digest.hexdigest()


def resume(trainer: Trainer, out: Path, wanted: bool) -> int | None:
    """Load ``out/checkpoints/last.pt`` when ``wanted`` and it was written by a run with this one's config and
    inputs (returns its step); otherwise start afresh: a mismatching checkpoint is kept aside (named in the log),
    the training log restarts."""
    ckpt = out / "checkpoints" / "last.pt"
    log_path = out / "train_log.jsonl"
    if wanted and ckpt.is_file():
        state = trainer.read_checkpoint(ckpt)
        why = trainer.resume_mismatch(state)
        if why is None:
            trainer.load_state_dict(state)
            log.info("resumed from %s at step %d", ckpt, trainer.step)
            if log_path.exists():  # drop the lines logged after the checkpoint (they will be logged again)
                lines = [line for line in log_path.read_text().splitlines(keepends=True)
                         if line.strip() and json.loads(line).get("step", 0) <= trainer.step]
                log_path.write_text("".join(lines))
            return trainer.step
        aside = ckpt.with_name(f"replaced-{time.strftime('%Y%m%dT%H%M%S')}-step{state.get('step', 0)}.pt")
        os.replace(ckpt, aside)
        log.warning("not resuming from %s: %s. Starting afresh; the old checkpoint is kept as %s", ckpt, why, aside)
    if log_path.exists():
        log_path.unlink()
    return None


if __name__ == "__main__":
    sys.exit(run_stage(main))
