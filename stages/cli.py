"""What every stage CLI shares: where its config section comes from, and one-line errors."""

from __future__ import annotations

import argparse
import json

from stages.config import ConfigError, check_section, load_config, presets_section


def add_config_args(parser: argparse.ArgumentParser, section: str) -> None:
    """--config-json (what Snakemake passes) or --scene [--preset ...] (the merged config, by hand)."""
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--config-json", help=f"the '{section}' config section as JSON (what Snakemake passes)")
    src.add_argument("--scene", help=f"use the '{section}' section of configs/scenes/<scene>.yaml merged with "
                     "configs/default.yaml and the scene's presets")
    parser.add_argument("--preset", action="append", default=[],
                        help="preset(s) of configs/presets/ applied over the scene's (with --scene) or over "
                        "configs/default.yaml (without it); not with --config-json (that section is complete)")


def load_section(args: argparse.Namespace, section: str) -> dict:
    """The stage's config section from --config-json or --scene/--preset; {} (dataclass defaults) without either.
    Either way it is validated against the section's schema (ConfigError naming the key), as the workflow's is."""
    if args.config_json:
        if args.preset:
            raise ConfigError(f"--preset {' '.join(args.preset)} cannot be combined with --config-json (the JSON is "
                              f"the whole '{section}' section); use --scene/--preset, or put the values in the JSON")
        try:
            value = json.loads(args.config_json)
        except json.JSONDecodeError as e:
            raise ConfigError(f"--config-json: invalid JSON ({e})") from None
        if not isinstance(value, dict):
            raise ConfigError(f"--config-json must be a JSON object (the '{section}' section), "
                              f"got {type(value).__name__}")
        return check_section(section, value)
    if args.scene:
        return load_config(args.scene, presets=args.preset).get(section, {})
    if args.preset:  # no scene: the defaults with the presets over them
        return check_section(section, presets_section(args.preset, section))
    return {}


def single_threaded_torch() -> None:
    """Run torch's own ops on one thread. The tracer already splits rays over its own threads (one Warp
    launch per core); torch's OpenMP pool competing with them for 2 cores made a 62k-element op 100x
    slower (0.85 s instead of 8 ms, measured)."""
    import torch

    torch.set_num_threads(1)
