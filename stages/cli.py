"""What every stage CLI shares: where its config section comes from, and one-line errors."""

from __future__ import annotations

import argparse
import json

from stages.config import load_config


def add_config_args(parser: argparse.ArgumentParser, section: str) -> None:
    """--config-json (what Snakemake passes) or --scene [--preset ...] (the merged config, by hand)."""
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--config-json", help=f"the '{section}' config section as JSON (what Snakemake passes)")
    src.add_argument("--scene", help=f"use the '{section}' section of configs/scenes/<scene>.yaml merged with "
                     "configs/default.yaml and the scene's presets")
    parser.add_argument("--preset", action="append", default=[], help="extra preset(s) applied with --scene")


def load_section(args: argparse.Namespace, section: str) -> dict:
    """The stage's config section from --config-json or --scene/--preset; {} (dataclass defaults) without either."""
    if args.config_json:
        value = json.loads(args.config_json)
        if not isinstance(value, dict):
            raise ValueError(f"--config-json must be a JSON object, got {type(value).__name__}")
        return value
    if args.scene:
        return load_config(args.scene, presets=args.preset).get(section, {})
    return {}


def single_threaded_torch() -> None:
    """Run torch's own ops on one thread. The tracer already splits rays over its own threads (one Warp
    launch per core); torch's OpenMP pool competing with them for 2 cores made a 62k-element op 100x
    slower (0.85 s instead of 8 ms, measured)."""
    import torch

    torch.set_num_threads(1)
