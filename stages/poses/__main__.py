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


def align_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.poses align",
        description="Score a photos run against a rendered truth: move the test views of a synthetic capture "
        "(exact buffers) into the frame the photos were posed in, by the similarity that maps the true train "
        "camera centres (the capture the photos were rendered from) onto the posed ones (Umeyama). Writes a "
        "capture of those test views (render and evaluate read it) whose capture.yaml records, under photos_path, "
        "the similarity, the pose errors of every registered photo and, with --predicted, the network's buffer "
        "errors on the train views: what limits the run (poses, network, or the reconstruction).",
    )
    p.add_argument("--truth", required=True, type=Path, help="synthetic capture whose test views are the truth")
    p.add_argument("--reference", required=True, type=Path,
                   help="the capture the photos were rendered from (true train cameras; synth --photos)")
    p.add_argument("--posed", required=True, type=Path, help="the poses stage's capture of those photos")
    p.add_argument("--predicted", type=Path, help="the buffers stage's capture (network buffers), to report its "
                   "errors against the reference's exact buffers")
    p.add_argument("--truth-scene", help="the truth's scene name, recorded (the batch report sets the photos run "
                   "beside that scene's row)")
    p.add_argument("--out", required=True, type=Path, help="capture folder to write (test views only)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    from models.capture import CaptureError, read_capture, write_capture
    from models.poses.truth import photos_truth

    start = time.perf_counter()
    try:
        truth = read_capture(args.truth)
        reference = read_capture(args.reference)
        posed = read_capture(args.posed, layers=["rgb"])
        predicted = read_capture(args.predicted) if args.predicted else None
        capture, record = photos_truth(truth, reference, posed, predicted, truth_scene=args.truth_scene)
        with staged_folder(args.out) as out:
            write_capture(capture, out)
            write_stage_json(out, "poses align", {"truth": str(args.truth), "reference": str(args.reference),
                                                  "posed": str(args.posed)}, time.perf_counter() - start,
                             extra={"photos_path": {k: v for k, v in record.items() if k != "network"}
                                    | {"network": (record.get("network") or {}).get("mean")}})
    except (CaptureError, ValueError) as e:  # PosesError is a ValueError
        print(f"error: {e}", file=sys.stderr)
        return 1
    poses = record["poses"]
    print(f"{len(capture.views)} test views moved into {args.posed}'s frame (scale {record['similarity']['scale']:.4g}); "
          f"{poses['registered']}/{poses['photos']} photos registered, rotation error mean "
          f"{poses['rotation_deg_mean']:.3f} deg (max {poses['rotation_deg_max']:.3f}), position error mean "
          f"{100 * poses['position_frac_mean']:.3f}% of the camera extent (max {100 * poses['position_frac_max']:.3f}%)")
    if "network" in record and record["network"].get("mean"):
        print("network buffers vs exact, train views: " + ", ".join(
            f"{k} {v:.3g}" for k, v in record["network"]["mean"].items()))
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "align":
        return align_main(argv[1:])
    p = argparse.ArgumentParser(
        prog="python -m stages.poses",
        description="Structure from motion on a folder of photos (one camera, one resolution): SIFT features, "
        "exhaustive / sequential / vocabulary-tree matching, incremental mapping, the largest model undistorted "
        "to PINHOLE, the scene centred and scaled. Writes a capture (transforms.json + linear EXR per view + "
        "capture.yaml recording the normalisation) with points3D.ply and the COLMAP model in sparse/. A folder "
        "that already has a COLMAP model (images/ + sparse/ [+ priors/], the paper's released real scenes) "
        "skips SfM. 'python -m stages.poses align --help': score such a run against a rendered truth.",
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
