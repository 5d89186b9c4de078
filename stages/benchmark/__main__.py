"""CLI: python -m stages.benchmark tracer [--sizes 50000,200000] [--res 128,256] [--threads 1,2]
[--repeats 3] [--device cpu] [--torch-threads 1] [--out FILE.json] [--quick]
     python -m stages.benchmark sweep --capture results/demo/capture --scene demo --out results/sweep/demo
[--iterations N] [--quick] (speed/accuracy sweep -> sweep.json; python -m stages.report sweep draws it)
     python -m stages.benchmark train-step [--rays 64,1024,4096] [--views 128x96] [--large] [--device cpu,cuda]
[--gaussians 50000] [--steps 5] [--out FILE.json] [--quick] (ms per training step by section; see train-step --help)
     python -m stages.benchmark buffernet-step [--init sd2] [--size 512] [--dtype bf16] [--device cuda]
(one buffer-network training step; see buffernet-step --help)
     python -m stages.benchmark seeds --scenes zoo_mirror_metal,zoo_mirror_only --set reconstruct.fill_anchor=0
[--seeds 0,1] [--jobs 2] [--device cuda] (a settings change against the seed-to-seed spread; see seeds --help)
     python -m stages.benchmark ceiling --scene zoo_spheres [--flat wall_front] [--capture DIR] [--out FILE.json]
(what a synthetic scene's test views allow at best: its ground truth's noise, surfaces at their mean colour)
     python -m stages.benchmark stereo --scene probe_mirror_21 [--results results] [--out FILE.json]
(mirror stereo's depths against the scene's true surfaces, per object; see stereo --help)
     python -m stages.benchmark where --scene zoo_corridor [--results results] [--layer specular] [--out FILE.json]
(a rendered synthetic scene's test-view error by what each pixel sees: first object, then its mirror reflections)"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from stages.benchmark.tracer import TracerBenchmarkConfig


def _ints(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def parse_args(argv=None) -> tuple[str, TracerBenchmarkConfig, Path | None]:
    p = argparse.ArgumentParser(prog="python -m stages.benchmark", description=__doc__)
    p.add_argument("what", choices=["tracer", "sweep"], help="which benchmark (sweep: see sweep --help)")
    p.add_argument("--sizes", type=_ints, help="numbers of Gaussians, e.g. 50000,200000")
    p.add_argument("--res", type=_ints, help="square resolutions, e.g. 128,256")
    p.add_argument("--threads", type=_ints, help="CPU thread counts to compare, e.g. 1,2")
    p.add_argument("--repeats", type=int, help="timed runs per measurement (best kept)")
    p.add_argument("--device", default=None, help="Warp device (cpu, cuda)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--torch-threads", type=int, default=None, help="torch intra-op threads (default 1)")
    p.add_argument("--out", type=Path, default=None, help="write the JSON result here")
    p.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test, not a measurement)")
    p.add_argument("--scenes", help="scene types of the second table, comma-separated (room, deep, dense_room, "
                   "million; default all; 'none' skips the table)")
    p.add_argument("--scene-res", type=int, help="scene types: res x res rays (default 128)")
    p.add_argument("--scene-n", type=int, help="scene types: number of Gaussians (default: each type's full size)")
    p.add_argument("--no-mitsuba", action="store_true", help="scene types: skip the Mitsuba 3 column")
    p.add_argument("--bvh", choices=["auto", "sah", "lbvh", "median"], help="BVH constructor of our tracers "
                   "(TracerConfig.bvh_constructor; auto: sah on a CPU, lbvh on a GPU)")
    p.add_argument("--octants", choices=["always", "never", "auto"], help="scene types: our tracer's octant trees "
                   "(TracerConfig.octant_bvh; default always, as a render uses them: refreshed once per update, and "
                   "the timed traces do not update)")
    p.add_argument("--binary-bvh", action="store_true", help="scene types: our tracer queries Warp's binary tree "
                   "(with --octants) instead of the 8-wide one (TracerConfig.wide_bvh false; the CPU default is the "
                   "wide tree, CUDA always uses Warp's)")
    p.add_argument("--no-floor", action="store_true", help="scene types: skip the exact-order floor column "
                   "(boxes an exact t*-order traversal must examine per blended hit; stages/benchmark/floor.py)")
    a = p.parse_args(argv)
    from stages.benchmark.tracer import TracerBenchmarkConfig  # after parsing: --help without torch / Warp

    cfg = TracerBenchmarkConfig.quick() if a.quick else TracerBenchmarkConfig()
    for arg, name in (("sizes", "sizes"), ("res", "resolutions"), ("threads", "threads"), ("repeats", "repeats"),
                      ("device", "device"), ("seed", "seed"), ("torch_threads", "torch_threads")):
        if getattr(a, arg) is not None:
            setattr(cfg, name, getattr(a, arg))
    if a.scenes is not None:
        cfg.scene_types = [] if a.scenes == "none" else [v for v in a.scenes.split(",") if v]
    if a.scene_res is not None:
        cfg.scene_res = a.scene_res
    if a.scene_n is not None:
        cfg.scene_n = a.scene_n
    if a.no_mitsuba:
        cfg.mitsuba = False
    if a.no_floor:
        cfg.floor = False
    if a.bvh is not None:
        cfg.bvh = a.bvh
    if a.octants is not None:
        cfg.octants = a.octants
    if a.binary_bvh:
        cfg.wide_bvh = False
    cfg.__post_init__()
    return a.what, cfg, a.out


def write_json_atomic(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def sweep_main(argv) -> int:

    p = argparse.ArgumentParser(
        prog="python -m stages.benchmark sweep",
        description="Speed/accuracy sweep on one scene: retrain with one knob changed at a time (max path length, "
        "training resolution, voxel size, kernel p, transmittance threshold) and re-render the base model with "
        "render-time knobs (spp with/without denoiser, path length, replay k, transmittance threshold). Prints a "
        "table and writes <out>/sweep.json; `python -m stages.report sweep <out>/sweep.json` draws the Pareto "
        "plots and recommended settings.",
    )
    p.add_argument("--capture", required=True, type=Path, help="the scene's capture (results/<scene>/capture)")
    p.add_argument("--scene", required=True, help="scene whose merged config is the base point")
    p.add_argument("--preset", action="append", default=[], help="extra preset(s) on top of the scene's")
    p.add_argument("--config-json", help="the scene's merged config as JSON (what Snakemake passes; "
                   "overrides --scene/--preset)")
    p.add_argument("--iterations", type=int, default=None,
                   help="shorten every training run to this many steps (warm-up and pruning scaled alike)")
    p.add_argument("--quick", action="store_true", help="one value per knob (smoke test, not a measurement)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    a = p.parse_args(argv)
    from stages.benchmark.sweep import SweepGrid, config_for_sweep, format_table, run_sweep
    from stages.cli import single_threaded_torch
    from stages.config import ConfigError, load_config

    single_threaded_torch()
    from models.capture import CaptureError, read_capture

    try:
        config = json.loads(a.config_json) if a.config_json else load_config(a.scene, presets=a.preset)
        capture = read_capture(a.capture)
    except (CaptureError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    config = config_for_sweep(config, a.iterations)
    grid = SweepGrid.quick() if a.quick else SweepGrid()
    result = run_sweep(capture, config, grid, a.device, progress=lambda m: print(m, file=sys.stderr, flush=True))
    result["scene"] = a.scene
    result["iterations"] = config["reconstruct"].get("iterations")
    print(format_table(result))
    write_json_atomic(a.out / "sweep.json", result)
    print(f"wrote {a.out / 'sweep.json'} (HTML: python -m stages.report sweep {a.out / 'sweep.json'})")
    return 0


def seeds_main(argv) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.benchmark seeds",
        description="A settings change against the run-to-run spread: every scene is trained, rendered and scored "
        "(tonemapped PSNR, as evaluate) at each seed twice, with its own config (base) and with the --set changes "
        "(variant), from <results>/<scene>/capture (make it with `snakemake --cores 2 <results>/<scene>/capture/"
        "transforms.json`). Prints each pair's difference, their mean and range per scene, and writes the JSON.",
    )
    p.add_argument("--scenes", required=True, help="comma-separated scene names (configs/scenes/)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="the variant: a config value changed (repeatable; VALUE read as YAML), e.g. "
                   "reconstruct.fill_anchor=0 (free, against the default's anchored surfels: configs/default.yaml)")
    p.add_argument("--both", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="a change made to base and variant alike, e.g. render.denoise=false where pyoidn is missing")
    p.add_argument("--seeds", type=_ints, default=[0, 1], help="reconstruct seeds (default 0,1)")
    p.add_argument("--preset", action="append", default=[], help="extra preset(s) on top of each scene's")
    p.add_argument("--iterations", type=int, default=None,
                   help="shorten every training run to this many steps (warm-up and pruning scaled alike)")
    p.add_argument("--results", type=Path, default=Path("results"), help="where <scene>/capture lies")
    p.add_argument("--jobs", type=int, default=1, help="runs at once, each its own process (a GPU holds several)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", type=Path, default=Path("results/benchmark/seeds.json"))
    p.add_argument("--keep", type=Path, default=None, metavar="DIR",
                   help="keep every run's model and renders in DIR/<scene>_<seed>_<base|variant>/ (to compare them "
                   "pixel by pixel); default: a temporary folder, deleted at the end")
    p.add_argument("--reuse", type=Path, action="append", default=[], metavar="SEEDS.JSON",
                   help="an earlier result (repeatable): its points made by the same code (models/, stages/, "
                   "configs/), settings, seed, device and capture are taken instead of trained again (runs "
                   "reproduce exactly), e.g. the base runs of a second variant")
    a = p.parse_args(argv)
    from stages.benchmark.seeds import format_table, parse_setting, run_seeds
    from stages.benchmark.sweep import config_for_sweep
    from stages.config import ConfigError, deep_merge, load_config

    try:
        variant, both = {}, {}
        for text in a.sets:
            variant = deep_merge(variant, parse_setting(text))
        for text in a.both:
            both = deep_merge(both, parse_setting(text))
        if not variant:
            raise ValueError("nothing to compare: give the variant's change with --set SECTION.KEY=VALUE")
        if not a.seeds:
            raise ValueError("no seeds: give --seeds, e.g. 0,1")
        if a.keep is not None and a.keep.exists() and not a.keep.is_dir():
            raise ValueError(f"--keep {a.keep}: exists and is not a folder")
        reuse = []
        for f in a.reuse:
            try:
                reuse += json.loads(f.read_text())["points"]
            except (OSError, ValueError, KeyError, TypeError) as e:
                raise ValueError(f"--reuse {f}: not a seeds result ({type(e).__name__}: {e})") from None
        scenes = {}
        for name in [s for s in a.scenes.split(",") if s]:
            config = config_for_sweep(deep_merge(load_config(name, presets=a.preset), both), a.iterations)
            load_config(name, presets=a.preset, overrides=deep_merge(both, variant))  # the variant validated
            capture = a.results / name / "capture"
            if not (capture / "transforms.json").is_file():
                raise ValueError(f"no capture for scene {name!r}: {capture}/transforms.json missing (make it with "
                                 f"`snakemake --cores 2 {capture} --config results={a.results}`: the folder is "
                                 f"what the synth rule makes)")
            scenes[name] = (capture, config)
    except (ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    result = run_seeds(scenes, variant, a.seeds, a.device, a.jobs, work_dir=a.keep,
                       progress=lambda m: print(m, file=sys.stderr, flush=True), reuse=reuse)
    result.update(both=both, iterations=a.iterations, presets=a.preset)
    print(format_table(result))
    write_json_atomic(a.out, result)
    print(f"wrote {a.out}")
    return 0


def ceiling_main(argv) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.benchmark ceiling",
        description="What a synthetic scene's test views allow any reconstruction at best (stages/benchmark/"
        "ceiling.py): the test views rendered again with another sampler seed and scored against the ground truth "
        "as evaluate scores a render (tonemapped final; a noise-free exact render scores ~3 dB above it), and, with "
        "--flat, rendered with the named objects' textures at their mean colour (everything else exact). Prints a "
        "table and writes the JSON.",
    )
    p.add_argument("--scene", required=True, help="a synthetic scene of configs/scenes/ (its synth: section)")
    p.add_argument("--capture", type=Path, default=None,
                   help="its rendered ground truth (default results/<scene>/capture)")
    p.add_argument("--flat", default="", help="comma-separated object names whose textures become their mean "
                   "colour, e.g. the walls no training view sees; 'unseen': every textured object no training "
                   "view's pixel centre hits first")
    p.add_argument("--out", type=Path, default=None, help="JSON path (default results/benchmark/ceiling_<scene>.json)")
    a = p.parse_args(argv)
    from models.capture import CaptureError, read_capture
    from models.synth.spec import parse_spec
    from stages.benchmark.ceiling import format_table, run_ceiling, unseen_objects
    from stages.config import ConfigError, load_config

    capture = a.capture or Path("results") / a.scene / "capture"
    out = a.out or Path("results/benchmark") / f"ceiling_{a.scene}.json"
    flat = [n for n in a.flat.split(",") if n]
    try:
        config = load_config(a.scene)
        if "synth" not in config:
            raise ValueError(f"scene {a.scene!r} has no synth: section (the ceilings need the scene's own renderer)")
        spec = parse_spec(config["synth"])
        truth = read_capture(capture)
        if flat == ["unseen"]:
            flat = unseen_objects(spec, [v.camera for v in truth.split("train")])
            print(f"textured objects no training view sees directly: {', '.join(flat) or 'none'}", file=sys.stderr)
        for name in flat:
            spec.object(name)
        print(f"rendering {len(truth.split('test'))} test views {1 + bool(flat)} times at {spec.spp} spp ...",
              file=sys.stderr, flush=True)
        result = run_ceiling(spec, truth, flat)
    except (CaptureError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    result.update(scene=a.scene, capture=str(capture))
    print(format_table(result))
    write_json_atomic(out, result)
    print(f"wrote {out}")
    return 0


def _sizes(text: str) -> list[tuple[int, int]]:
    if text == "none":
        return []
    try:
        return [tuple(int(x) for x in v.lower().split("x")) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated WxH sizes, got {text!r}") from None


def train_step_main(argv) -> int:
    p = argparse.ArgumentParser(prog="python -m stages.benchmark train-step",
                                description="Milliseconds per reconstruction training step (the real Trainer on a "
                                "synthetic room capture built in memory), split into tracer kernels, path sampling, "
                                "losses, autograd, optimizer and host overhead; prints a table, --out writes JSON.")
    p.add_argument("--rays", type=_ints, help="random rays per step, one row each (default 64,1024,4096)")
    p.add_argument("--views", type=_sizes, help="whole views per step, WxH (default 128x96; 'none' for no row)")
    p.add_argument("--large", action=argparse.BooleanOptionalAction, default=None,
                   help="also a whole 768x576 view (default: on CUDA only)")
    p.add_argument("--device", help="comma-separated: cpu, cuda (default cpu, and cuda when available)")
    p.add_argument("--gaussians", type=int, help="Gaussians in the room (default 50000)")
    p.add_argument("--n-views", type=int, help="training views of the synthetic capture (default 4)")
    p.add_argument("--steps", type=int, help="timed steps per row (default 5)")
    p.add_argument("--threads", type=int, help="tracer CPU threads (default 2)")
    p.add_argument("--seed", type=int)
    p.add_argument("--sync-checks", action="store_true",
                   help="read the tracer's checks back at every trace, as before deferred checks (the A/B of the "
                   "GPU's host syncs; the CPU always does)")
    p.add_argument("--checkpoint", help="time a real run instead of the random room: its checkpoint "
                   "(<model>/checkpoints/last.pt), with --scene, --capture and --init; the scene's own reconstruct "
                   "config, one row at the checkpoint's step")
    p.add_argument("--scene", help="with --checkpoint: the scene (configs/scenes/<scene>.yaml)")
    p.add_argument("--capture", help="with --checkpoint: the scene's capture folder")
    p.add_argument("--init", help="with --checkpoint: the run's init/points.ply")
    p.add_argument("--out", type=Path, help="write the JSON result here")
    p.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test, not a measurement)")
    a = p.parse_args(argv)
    from stages.benchmark.train_step import TrainStepBenchmarkConfig, format_table, run_train_step_benchmark

    cfg = TrainStepBenchmarkConfig.quick() if a.quick else TrainStepBenchmarkConfig()
    for arg, name in (("rays", "rays"), ("views", "views"), ("large", "large_view"), ("gaussians", "n_gaussians"),
                      ("n_views", "n_views"), ("steps", "steps"), ("threads", "threads"), ("seed", "seed"),
                      ("checkpoint", "checkpoint"), ("scene", "scene"), ("capture", "capture"), ("init", "init")):
        if getattr(a, arg) is not None:
            setattr(cfg, name, getattr(a, arg))
    if a.device:
        cfg.devices = [d for d in a.device.split(",") if d]
    cfg.sync_checks = a.sync_checks
    try:
        cfg.__post_init__()
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    from models.capture import CaptureError
    from stages.config import ConfigError

    try:
        result = run_train_step_benchmark(cfg, progress=lambda m: print(m, file=sys.stderr, flush=True))
    except (ConfigError, CaptureError, OSError) as e:  # --checkpoint's scene, capture or init
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(format_table(result))
    if a.out is not None:
        write_json_atomic(a.out, result)
        print(f"wrote {a.out}")
    return 0


def stereo_main(argv) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.benchmark stereo",
        description="How close mirror stereo puts what the mirrors show to the true surface, per object of a "
        "synthetic scene: the sweep runs on <results>/<scene>/capture with its init (as the trainer calls it at "
        "the end of the warm-up) and Mitsuba casts every match's reflected ray into the scene's geometry. Prints "
        "a table per kind of match (own texture / completed; all / placed) and writes the JSON. Takes ~4 min on "
        "2 CPU cores for a 20-view 128 x 96 room (stages/benchmark/stereo.py).",
    )
    p.add_argument("--scene", required=True, help="a synthetic scene (configs/scenes/<scene>.yaml)")
    p.add_argument("--preset", action="append", default=[], help="extra preset(s) on top of the scene's")
    p.add_argument("--results", type=Path, default=Path("results"),
                   help="where <scene>/capture and <scene>/init/points.ply lie (make them with `snakemake --cores 2 "
                   "<results>/<scene>/init/points.ply`)")
    p.add_argument("--out", type=Path, default=None, help="write the JSON here")
    a = p.parse_args(argv)
    from stages.cli import single_threaded_torch
    from stages.config import ConfigError, load_config

    single_threaded_torch()
    from models.capture import CaptureError, read_capture
    from models.gaussians import read_ply
    from models.reconstruction import ReconstructConfig
    from models.synth.spec import parse_spec
    from stages.benchmark.stereo import format_table, run_stereo_benchmark

    try:
        config = load_config(a.scene, presets=a.preset)
        if "synth" not in config:
            raise ValueError(f"scene {a.scene!r} has no synth section: the check needs the scene's true geometry")
        spec = parse_spec(config["synth"])
        capture = read_capture(a.results / a.scene / "capture")
        init_path = a.results / a.scene / "init" / "points.ply"
        if not init_path.exists():
            raise ValueError(f"{init_path}: no init (make it with `snakemake --cores 2 {init_path}`)")
        init = read_ply(init_path)
        recon = ReconstructConfig.from_dict(config.get("reconstruct", {}))
    except (CaptureError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    result = run_stereo_benchmark(spec, capture, init, recon)
    result["scene"] = a.scene
    print(format_table(result))
    if a.out is not None:
        write_json_atomic(a.out, result)
        print(f"wrote {a.out}")
    return 0


def where_main(argv) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.benchmark where",
        description="Where a rendered synthetic scene's test-view error lies: Mitsuba casts every test pixel's ray "
        "into the scene's true geometry and follows it through up to --bounces mirror reflections (conductors "
        "smoother than roughness 0.3); each path (\"metal_left>ceiling\") gets its share of the view's pixels and "
        "of its tonemapped squared error (mu-law at the view's peak, as evaluate), the PSNR there and the mean true "
        "and rendered luminance. Reads <results>/<scene>/capture, renders/test and metrics.json (run the scene's "
        "workflow first); prints a table per view and writes the JSON (stages/benchmark/where.py).",
    )
    p.add_argument("--scene", required=True, help="a synthetic scene (configs/scenes/<scene>.yaml)")
    p.add_argument("--results", type=Path, default=Path("results"),
                   help="where <scene>/capture, <scene>/renders and <scene>/metrics.json lie")
    p.add_argument("--layer", choices=["final", "specular", "diffuse"], default="final", help="the layer scored")
    p.add_argument("--bounces", type=int, default=3, help="mirror reflections followed (default 3)")
    p.add_argument("--top", type=int, default=8, help="paths per view in the table (the JSON has all)")
    p.add_argument("--out", type=Path, default=None, help="write the JSON here")
    a = p.parse_args(argv)
    if a.bounces < 0 or a.top < 1:
        print("error: --bounces must be >= 0 and --top >= 1", file=sys.stderr)
        return 1
    from stages.config import ConfigError, load_config

    from models.capture import CaptureError, read_capture
    from models.synth.spec import parse_spec
    from stages.benchmark.where import format_table, run_where

    root = a.results / a.scene
    try:
        config = load_config(a.scene)
        if "synth" not in config:
            raise ValueError(f"scene {a.scene!r} has no synth section: the paths need the scene's true geometry")
        spec = parse_spec(config["synth"])
        capture = read_capture(root / "capture")
        metrics_path = root / "metrics.json"
        if not metrics_path.exists():
            raise ValueError(f"{metrics_path}: no metrics (run `snakemake --cores 2 {metrics_path}` first)")
        metrics = json.loads(metrics_path.read_text())
        result = run_where(spec, capture, root / "renders" / "test", metrics, layer=a.layer, bounces=a.bounces)
    except (CaptureError, ConfigError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    result["scene"] = a.scene
    print(format_table(result, top=a.top))
    if a.out is not None:
        write_json_atomic(a.out, result)
        print(f"wrote {a.out}")
    return 0


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["where"]:
        return where_main(argv[1:])
    if argv[:1] == ["stereo"]:
        return stereo_main(argv[1:])
    if argv[:1] == ["sweep"]:
        return sweep_main(argv[1:])
    if argv[:1] == ["train-step"]:
        return train_step_main(argv[1:])
    if argv[:1] == ["seeds"]:
        return seeds_main(argv[1:])
    if argv[:1] == ["ceiling"]:
        return ceiling_main(argv[1:])
    if argv[:1] == ["buffernet-step"]:
        from stages.benchmark.buffernet_step import buffernet_step_main

        return buffernet_step_main(argv[1:], write_json_atomic)
    _, cfg, out = parse_args(argv)
    from stages.benchmark.tracer import format_table, run_tracer_benchmark

    result = run_tracer_benchmark(cfg, progress=lambda m: print(m, file=sys.stderr, flush=True))
    print(format_table(result))
    if out is not None:
        write_json_atomic(out, result)
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
