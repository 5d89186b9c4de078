"""CLI: ``python -m stages.synth (--scene NAME | --config-json JSON) [--edits NAME...] [--splits test] --out DIR``
(a synthetic capture; with ``--edits``, the ground truth of named edits: the scene re-rendered with their
``ground_truth`` ops), and ``python -m stages.synth procedural --count N --seed S --out DIR [--resolution W H]
[--views V] [--spp P] [--no-denoise]`` (random training rooms, ``procedural.py``), and ``python -m stages.synth probe
SEED... [--find N]`` (held-out probe scene configs: such rooms with test views the training orbit lacks). The renderer
is ``models/synth``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from stages.config import check_section, load_config
from stages.output import run_stage, staged_folder


def procedural_main(argv: list[str]) -> int:
    """``python -m stages.synth procedural ...``: render random rooms (resumable)."""
    p = argparse.ArgumentParser(prog="python -m stages.synth procedural",
                                description="Render N random rooms into DIR/scene_0000, ... (skips finished ones).")
    p.add_argument("--count", type=int, required=True, help="number of scenes")
    p.add_argument("--seed", type=int, default=0, help="scene i uses seed S + i (default 0)")
    p.add_argument("--out", type=Path, required=True, help="output folder of the capture folders")
    p.add_argument("--resolution", type=int, nargs=2, default=(64, 64), metavar=("W", "H"))
    p.add_argument("--views", type=int, default=8, help="cameras per scene (default 8)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    p.add_argument("--no-denoise", dest="denoise", action="store_false",
                   help="keep the Monte Carlo noise (default: OIDN-denoised diffuse / specular, rgb = their sum)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    args = p.parse_args(argv)

    from stages.synth.procedural import render_procedural

    try:
        report = render_procedural(args.out, args.count, args.seed, resolution=tuple(args.resolution),
                                   views=args.views, spp=args.spp, denoise=args.denoise,
                                   progress=not args.no_progress)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    total = sum(report["seconds"].values())
    print(f"rendered {len(report['rendered'])} scene(s) in {total:.1f} s, skipped {len(report['skipped'])} "
          f"already complete, into {args.out}")
    return 0


PROBE_HEADER = """\
# Held-out probe (README, "Held-out probes"): the random room of models.synth.procedural seed {seed}, written by
# `python -m stages.synth probe {seed}`. Nobody tunes to it: its test views (between the training azimuths, nearer
# the walls, below every training camera) see sides of the objects the training orbit looks down on.
#   snakemake --cores 2 --config scene={scene}
"""

MIRROR_PROBE_HEADER = """\
# Held-out mirror probe (README, "Held-out probes"): the random room of models.synth.procedural seed {seed} with a
# wall mirror, written by `python -m stages.synth probe --mirror {seed}`. Nobody tunes to it: the training cameras
# face the mirror, so the floor objects behind them (evaluate.regions hidden_*) are seen only in it; the test
# cameras, by the mirror, turn round and look at them directly.
#   snakemake --cores 2 --config scene={scene}
"""


LIGHTS_PROBE_HEADER = """\
# Held-out lights probe (README, "Held-out probes"): the random room of models.synth.procedural seed {seed} with a
# window the training cameras see and a brushed-metal object, written by `python -m stages.synth probe --lights
# {seed}`. Nobody tunes to it: the fills that place lights from reflections must not misplace the ones in view.
#   snakemake --cores 2 --config scene={scene}
"""


def probe_main(argv: list[str]) -> int:
    """``python -m stages.synth probe SEED...``: held-out probe scene configs (``procedural.probe_scene``)."""
    p = argparse.ArgumentParser(
        prog="python -m stages.synth probe",
        description="Write configs/scenes/probe_<seed>.yaml for random rooms (the buffer network's generator) with "
        "test views the training orbit does not have; then `snakemake --config scene=probe_<seed>` runs it. With "
        "--find N: the first N seeds from SEED whose room holds two mirror-like objects and a glossy dielectric. With "
        "--mirror: probe_mirror_<seed>.yaml, the room with a wall mirror that the training cameras face, so what "
        "stands behind them is seen only in it (--find: at least one such floor object, and another shiny metal "
        "the cameras face). With --lights: probe_lights_<seed>.yaml, the room with a window the training cameras "
        "see and a brushed-metal object (--find: the window well inside at least three training frames).")
    p.add_argument("seeds", type=int, nargs="+", metavar="SEED", help="room seed(s) (models.synth.procedural)")
    p.add_argument("--find", type=int, metavar="N", help="instead: the first N probe-worthy seeds from SEED on")
    kind = p.add_mutually_exclusive_group()
    kind.add_argument("--mirror", action="store_true",
                      help="mirror probes (procedural.mirror_probe_scene): what the cameras see only in a wall mirror")
    kind.add_argument("--lights", action="store_true",
                      help="lights probes (procedural.lights_probe_scene): a window in view beside brushed metal")
    p.add_argument("--out-dir", type=Path, default=Path(__file__).resolve().parents[2] / "configs" / "scenes",
                   help="where the scene configs go (default: configs/scenes)")
    p.add_argument("--force", action="store_true", help="overwrite an existing config")
    args = p.parse_args(argv)
    import yaml

    from models.synth.procedural import (lights_probe_scene, lights_probe_worthy, mirror_probe_scene,
                                         mirror_probe_worthy, probe_scene, probe_worthy, random_scene_config)

    if args.mirror:
        make, header = mirror_probe_scene, MIRROR_PROBE_HEADER
        worthy = lambda s: mirror_probe_worthy(mirror_probe_scene(s))  # noqa: E731
    elif args.lights:
        make, header = lights_probe_scene, LIGHTS_PROBE_HEADER
        worthy = lambda s: lights_probe_worthy(lights_probe_scene(s))  # noqa: E731
    else:
        make, header = probe_scene, PROBE_HEADER
        worthy = lambda s: probe_worthy(random_scene_config(s))  # noqa: E731

    if any(s < 0 for s in args.seeds) or (args.find is not None and args.find < 1):
        print("error: seeds must be >= 0 and --find >= 1", file=sys.stderr)
        return 1
    seeds = args.seeds
    if args.find is not None:
        seeds, s = [], args.seeds[0]
        while len(seeds) < args.find:
            if worthy(s):
                seeds.append(s)
            s += 1
    docs = [make(seed) for seed in seeds]
    paths = [args.out_dir / f"{doc['scene']}.yaml" for doc in docs]
    taken = [str(path) for path in paths if path.exists()]
    if taken and not args.force:  # checked before writing any: nothing half done
        print(f"error: {', '.join(taken)} exist(s) (--force overwrites)", file=sys.stderr)
        return 1
    for seed, doc, path in zip(seeds, docs, paths):
        text = header.format(seed=seed, scene=doc["scene"]) + yaml.safe_dump(
            doc, sort_keys=False, default_flow_style=None, width=118)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        except OSError as e:
            print(f"error: cannot write {path}: {e.strerror or e}", file=sys.stderr)
            return 1
        print(f"wrote {path} (snakemake --cores 2 --config scene={doc['scene']})")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "procedural":
        return procedural_main(argv[1:])
    if argv and argv[0] == "probe":
        return probe_main(argv[1:])
    p = argparse.ArgumentParser(prog="python -m stages.synth", description=__doc__)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--scene", help="scene name: loads configs/scenes/NAME.yaml (merged config)")
    p.add_argument("--preset", action="append", default=[], help="extra preset(s) applied with --scene")
    src.add_argument("--config-json", help="the synth: section as JSON (as Snakemake passes it)")
    p.add_argument("--edits", nargs="*", default=[], metavar="NAME",
                   help="named edits of the scene config's 'edits:' mapping (their ground_truth lists), applied in order "
                   "(needs --scene)")
    p.add_argument("--edits-json", help="an edit list as JSON (works with --config-json too)")
    p.add_argument("--splits", nargs="+", choices=("train", "test"), help="render only these splits (default: "
                   "all); each view keeps the sampler seed it has in the full capture, so the pixels an edit does "
                   "not reach are the capture's own, noise included")
    p.add_argument("--name", help="name recorded in capture.yaml (default: the scene; 'edit:<names>' with --edits)")
    p.add_argument("--out", required=True, type=Path, help="capture output directory")
    p.add_argument("--photos", type=Path, help="also write each rendered view as a photo into this folder: "
                   "<view>.png, 8-bit sRGB of the final image clipped at 1 (what a camera keeps; no buffers, no "
                   "poses), for the photos path (poses -> buffers -> ...) on a room whose truth is known")
    p.add_argument("--threads", type=int, help="Mitsuba's (Dr.Jit's) CPU threads (what Snakemake gives the job; "
                   "default: one per core)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    args = p.parse_args(argv)

    import time

    from models.synth import render_capture

    if args.threads is not None:
        if args.threads < 1:
            print(f"error: --threads must be >= 1, got {args.threads}", file=sys.stderr)
            return 1
        import drjit as dr

        dr.set_thread_count(args.threads)

    t0 = time.perf_counter()
    try:
        edits: list = []
        if args.scene:
            config = load_config(args.scene, presets=args.preset)
            if "synth" not in config:
                raise ValueError(f"scene {args.scene!r}: config has no 'synth:' section (not a synthetic scene?)")
            synth_cfg, name = config["synth"], args.scene
            named = config.get("edits") or {}
            for e in args.edits:
                if e not in named:
                    raise ValueError(f"scene {args.scene!r}: unknown edit list {e!r} (known: {', '.join(named) or 'none'})")
                # a named edit (models/editing/spec.py): its synth side is 'ground_truth'
                gt = named[e].get("ground_truth") if isinstance(named[e], dict) else named[e]
                if not gt:
                    raise ValueError(f"scene {args.scene!r}: edit {e!r} has no ground_truth (synth edit list)")
                edits += list(gt)
        else:
            if args.edits:
                raise ValueError("--edits NAME needs --scene (with --config-json pass --edits-json)")
            try:
                synth_cfg = json.loads(args.config_json)
            except json.JSONDecodeError as e:
                raise ValueError(f"--config-json: invalid JSON ({e})") from None
            if not isinstance(synth_cfg, dict):
                raise ValueError(f"--config-json must be a JSON object (the 'synth' section), got "
                                 f"{type(synth_cfg).__name__}")
            synth_cfg = check_section("synth", synth_cfg)  # the schema the workflow's config is checked with
            name = None
        if args.edits_json:
            try:
                edits += json.loads(args.edits_json)
            except json.JSONDecodeError as e:
                raise ValueError(f"--edits-json: invalid JSON ({e})") from None
        if args.edits and args.name is None:
            name = f"edit:{','.join(args.edits)}"
        from stages.provenance import write_stage_json

        with staged_folder(args.out) as out:  # the capture complete or absent
            capture = render_capture(synth_cfg, out, edits=edits or None, progress=not args.no_progress,
                                     scene_name=args.name or name, splits=tuple(args.splits) if args.splits else None)
            extra = capture.meta.extra
            write_stage_json(out, "synth", {"synth": synth_cfg, "edits": edits}, time.perf_counter() - t0,
                             extra={"seconds_per_view": extra["seconds_per_view"], "spp": extra["spp"]})
        if args.photos:
            with staged_folder(args.photos) as folder:
                write_photos(capture, folder)
    except ValueError as e:  # includes ConfigError and CaptureError subclasses of ValueError
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"wrote {len(capture.views)} views to {args.out} ({extra['spp']} spp, "
          f"{extra['mean_seconds_per_view']} s/view, {extra['seconds_total']} s total)")
    return 0


def write_photos(capture, folder: Path) -> None:
    """<folder>/<view>.png per view: the final image (R,G,B) clipped to [0, 1], sRGB-encoded, 8 bits."""
    import imageio.v3 as iio
    import numpy as np

    from models.capture.color import linear_to_srgb

    for view in capture.views:
        srgb = linear_to_srgb(np.clip(view.buffers["rgb"], 0.0, 1.0))
        iio.imwrite(folder / f"{view.name}.png", (np.clip(srgb, 0, 1) * 255 + 0.5).astype(np.uint8))


if __name__ == "__main__":
    sys.exit(run_stage(main))
