"""python -m stages.export: a trained model folder as a standard 3DGS PLY that common splat viewers display."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from stages.output import run_stage, staged_folder
from stages.provenance import write_stage_json

log = logging.getLogger("stages.export")

PLY_NAME = "scene_3dgs.ply"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m stages.export",
        description="Export a trained model folder as a standard 3DGS PLY (SuperSplat, Spark, PlayCanvas "
        "splat-transform, gaussian-splats-3d, ...). Writes <out>/" + PLY_NAME + " and <out>/stage.json. Our "
        "gaussians.ply stores LINEAR diffuse radiance in f_dc (emitters exceed 1) and a far-field shell far "
        "outside the scene, so a viewer shows it dark inside a grey sphere; the export writes f_dc as the "
        "sRGB-encoded diffuse colour clamped to [0, 1] (the PNG tonemap; specular reflections are not "
        "exported), f_rest_0..44 and nx,ny,nz as zeros, opacity as logit, scale_0..2 as log standard "
        "deviation, rot_0..3 as the unit quaternion w,x,y,z, and drops the far-field shell.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--model", required=True, type=Path,
                   help="trained model folder (gaussians.ply + model.yaml); a gaussians.ply path means its folder")
    p.add_argument("--out", required=True, type=Path, help="output folder (gets " + PLY_NAME + " + stage.json)")
    p.add_argument("--capture", type=Path, default=None,
                   help="the capture the model was trained on (its training cameras place the far-field shell: "
                   "outside the sphere of radius = camera extent around their mean centre). The far field "
                   "dropped is every Gaussian farther from the centre (the cameras' mean, or without --capture "
                   "the Gaussians' per-axis median) than --far-field-factor x R, R = the larger of the camera "
                   "extent (with --capture) and the Gaussians' median distance from the centre (robust while "
                   "the shell is under half of the Gaussians; the reconstruction adds ~10%%)")
    p.add_argument("--far-field-factor", type=float, default=2.0, help="radius of the kept sphere, in units of R")
    p.add_argument("--keep-far-field", action="store_true", help="keep the far-field shell (export every Gaussian)")
    p.add_argument("--no-emitters", action="store_true",
                   help="drop emitters (linear diffuse radiance > 1 in any channel); by default they are kept, "
                   "their colour clamped to white-ish like every other colour")
    p.add_argument("--scale-factor", default="kernel",
                   help="multiply every Gaussian's scale by this number; 'kernel': the factor that gives a plain "
                   "Gaussian (what viewers draw) the footprint integral of the model's tracer kernel "
                   "(model.yaml tracer.kernel_p, exp(-r^(2p)/(2p)): 0.90 for p = 3, 1 for p = 1)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    from models.capture import CaptureError, read_capture  # after parsing: --help answers without torch / Warp
    from models.gaussians.export import (emitter_mask, far_field_cut, far_field_mask, standard_3dgs_vertices,
                                         write_3dgs_ply)
    from models.trained import load_model, model_folder

    start = time.perf_counter()
    try:
        if args.out.resolve() == model_folder(args.model).resolve():
            raise ValueError(f"--out {args.out} is the model folder: export into a folder of its own")
        gaussians, settings = load_model(args.model)
        scale_factor = _scale_factor(args.scale_factor, settings.tracer.kernel_p)
        means = gaussians.means.detach().cpu().double().numpy()
        keep = np.ones(len(gaussians), dtype=bool)
        cut = None
        if not args.keep_far_field:
            origins = extent = None
            if args.capture is not None:
                capture = read_capture(args.capture, layers=[])
                views = capture.split("train") or capture.views  # the reconstruction centres the shell on these
                origins, extent = np.stack([v.camera.origin for v in views]), capture.camera_extent()
            cut = far_field_cut(means, args.far_field_factor, origins, extent)
            keep &= ~far_field_mask(means, cut)
        far = int(len(keep) - keep.sum())
        emitters = emitter_mask(gaussians.diffuse.detach().cpu().numpy())
        if args.no_emitters:
            keep &= ~emitters
        if not keep.any():
            raise ValueError(f"nothing left to export: all {len(keep)} Gaussians were dropped (far field: {far}; "
                             "try --keep-far-field or a larger --far-field-factor)")
        vertices = standard_3dgs_vertices(gaussians, keep, scale_factor)
    except (CaptureError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    summary = {"gaussians_in": len(gaussians), "gaussians_out": int(keep.sum()), "far_field_dropped": far,
               "far_field_cut": None if cut is None else {"centre": cut.centre.tolist(), "radius": cut.radius,
                                                          "basis": cut.basis},
               "emitters": int(emitters.sum()), "emitters_dropped": int((emitters & ~keep).sum()) if
               args.no_emitters else 0, "scale_factor": scale_factor, "kernel_p": settings.tracer.kernel_p}
    log.info("exporting %d of %d Gaussians (far field dropped: %d%s; emitters: %d, %s)", summary["gaussians_out"],
             len(gaussians), far, f", beyond {cut.basis} = {cut.radius:.4g}" if cut else "", summary["emitters"],
             "dropped" if args.no_emitters else "kept, clamped")
    config = {"model": str(args.model), "capture": None if args.capture is None else str(args.capture),
              "far_field_factor": args.far_field_factor, "keep_far_field": args.keep_far_field,
              "no_emitters": args.no_emitters, "scale_factor": args.scale_factor}
    with staged_folder(args.out) as out:
        write_3dgs_ply(out / PLY_NAME, vertices)
        write_stage_json(out, "export", config, time.perf_counter() - start, extra={"export": summary})
    print(args.out / PLY_NAME)
    return 0


def _scale_factor(value: str, kernel_p: int) -> float:
    if value == "kernel":
        from models.gaussians.export import kernel_scale_factor

        return kernel_scale_factor(kernel_p)
    try:
        factor = float(value)
    except ValueError:
        raise ValueError(f"--scale-factor must be a positive number or 'kernel', got {value!r}") from None
    if not factor > 0 or not np.isfinite(factor):
        raise ValueError(f"--scale-factor must be a positive number or 'kernel', got {value!r}")
    return factor


if __name__ == "__main__":
    sys.exit(run_stage(main))
