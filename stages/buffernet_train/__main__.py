"""python -m stages.buffernet_train (train | evaluate | cost): the buffer network's training, its per-buffer
accuracy against trivial baselines, and the cost of batched vs per-prompt inference."""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from dataclasses import fields
from pathlib import Path

from stages.cli import single_threaded_torch
from stages.provenance import write_stage_json


def _train(args: argparse.Namespace) -> int:
    from models.buffernet.training.config import TrainConfig
    from models.buffernet.training.train import train

    overrides = {f.name: getattr(args, f.name) for f in fields(TrainConfig)
                 if getattr(args, f.name, None) is not None}
    start = time.perf_counter()
    try:
        cfg = TrainConfig.from_dict(overrides)
        final = train(cfg, resume=not args.fresh, progress=not args.no_progress)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    write_stage_json(cfg.out, "buffernet-train", cfg.to_dict(), time.perf_counter() - start)
    print(f"saved {final}  (load with BufferNetPipeline.from_pretrained('{final}'))")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from models.buffernet import BufferNetPipeline
    from models.buffernet.training.data import make_readers
    from models.buffernet.training.evaluate import evaluate_network, format_rows, vae_roundtrip

    try:
        if not (Path(args.model) / "model_index.json").is_file():
            raise FileNotFoundError(f"{args.model}: not a saved buffer network (no model_index.json)")
        pipe = BufferNetPipeline.from_pretrained(args.model)
        readers = make_readers(args.data, cache=False)
    except (ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    samples = list(itertools.islice((r[i] for r in readers for i in range(len(r))), args.limit))
    rows = evaluate_network(pipe, samples, resolution=args.resolution, progress=not args.no_progress)
    for b, value in vae_roundtrip(pipe, samples, resolution=args.resolution, progress=not args.no_progress).items():
        if b in rows:  # the truth through the VAE alone: the best any UNet on this VAE can score
            rows[b]["vae_roundtrip"] = value
    print(format_rows(rows))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"model": str(args.model), "data": args.data, "buffers": rows},
                                             indent=1))
    return 0


def _cost(args: argparse.Namespace) -> int:
    """Seconds per image, all buffers batched vs one run per buffer (median of ``repeat``)."""
    import numpy as np
    import torch

    from models.buffernet import BufferNetPipeline
    from models.buffernet.build import RANDOM_INITS, build_pipeline

    pipe = build_pipeline(args.model) if args.model in RANDOM_INITS else BufferNetPipeline.from_pretrained(args.model)
    pipe = pipe.to(args.device)
    rgb = np.random.default_rng(0).random((args.size, args.size, 3), dtype=np.float32)
    table = []
    for batched in (True, False):
        pipe.predict(rgb, batched=batched)  # warm-up
        times, cpu = [], []
        for _ in range(args.repeat):
            if args.device == "cuda":
                torch.cuda.synchronize()
            t, c = time.perf_counter(), time.process_time()
            pipe.predict(rgb, batched=batched)
            if args.device == "cuda":
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
        table.append({"mode": "batched (1 forward)" if batched else "per prompt (6 forwards)",
                      "seconds": float(np.median(times)), "cpu_seconds": float(np.median(cpu))})
    ratio = table[1]["seconds"] / table[0]["seconds"]
    cpu_ratio = table[1]["cpu_seconds"] / table[0]["cpu_seconds"]
    # CPU time (torch runs on one thread) stays meaningful when other jobs share the cores; wall time does not
    print(f"{'mode':<26} {'s / image':>10} {'CPU s':>8}   ({args.model}, {args.size}x{args.size}, {args.device})")
    for r in table:
        print(f"{r['mode']:<26} {r['seconds']:>10.4f} {r['cpu_seconds']:>8.4f}")
    print(f"per-prompt / batched = {ratio:.2f}x wall, {cpu_ratio:.2f}x CPU time")
    if args.out:
        Path(args.out).write_text(json.dumps({"model": args.model, "size": args.size, "device": args.device,
                                              "rows": table, "speedup": ratio,
                                              "speedup_cpu_time": cpu_ratio}, indent=1))
    return 0


def _train_config_flags(p: argparse.ArgumentParser) -> None:
    """One flag per TrainConfig field not added above (--name-with-dashes; booleans --x / --no-x), its help the
    field's doc: every option of a training run can be given on the command line (the workflow passes its
    buffernet.train section this way)."""
    import typing

    from models.buffernet.training.config import TrainConfig

    hints = typing.get_type_hints(TrainConfig)
    for f in fields(TrainConfig):
        if f.name in ("data", "init", "out"):
            continue
        flag = f"--{f.name.replace('_', '-')}"
        doc = (f.metadata.get("doc") or "").replace("%", "%%")
        if hints[f.name] is bool:
            p.add_argument(flag, dest=f.name, action="store_const", const=True, help=f"{doc} (default {f.default})")
            p.add_argument(f"--no-{f.name.replace('_', '-')}", dest=f.name, action="store_const", const=False)
        else:
            choices = f.metadata.get("constraints", {}).get("enum")
            p.add_argument(flag, dest=f.name, type=hints[f.name], choices=choices,
                           help=f"{doc} (default {f.default})")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m stages.buffernet_train", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="train (or resume) a buffer network; saves <out>/pipeline",
                       description="Masked latent MSE, AdamW, exponential decay, gradient checkpointing; "
                       "checkpoints every --checkpoint-every steps and resumes from the latest unless --fresh. "
                       "Multi-GPU: launch with `accelerate launch -m stages.buffernet_train train ...`.")
    t.add_argument("--data", action="append", help="KIND:DIR, repeatable: hypersim:DIR, interiorverse:DIR[:split], "
                   "captures:DIR (one capture or a folder of captures, e.g. from `python -m stages.synth procedural`)")
    t.add_argument("--init", help="tiny | small (random weights, SD2 architecture; default small) | sd2 (random "
                   "weights, SD2's exact configs, no download) or a local folder: stable-diffusion-2 (diffusers "
                   "layout) or a saved buffer network")
    t.add_argument("--out", help="output folder (default results/buffernet)")
    _train_config_flags(t)
    t.add_argument("--fresh", action="store_true", help="ignore existing checkpoints in --out")
    t.add_argument("--no-progress", action="store_true")
    e = sub.add_parser("evaluate", help="per-buffer accuracy vs trivial baselines on held-out data")
    e.add_argument("--model", required=True, help="a saved buffer network folder (<out>/pipeline)")
    e.add_argument("--data", action="append", required=True, help="KIND:DIR as for train (held-out data)")
    e.add_argument("--resolution", type=int, help="process at this long side (default: the image's own)")
    e.add_argument("--limit", type=int, help="at most this many images")
    e.add_argument("--out", help="write the table as JSON here")
    e.add_argument("--no-progress", action="store_true")
    c = sub.add_parser("cost", help="inference seconds per image: all buffers batched vs one pass per buffer")
    c.add_argument("--model", default="small", help="tiny | small | sd2 | a saved buffer network folder")
    c.add_argument("--size", type=int, default=128)
    c.add_argument("--repeat", type=int, default=5)
    c.add_argument("--device", default="cpu")
    c.add_argument("--out")
    args = p.parse_args(argv)
    single_threaded_torch()
    return {"train": _train, "evaluate": _evaluate, "cost": _cost}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
