"""python -m stages.view RESULTS_DIR | MODEL.ply: edit a trained scene in the browser (viser).

Serves a web page (open the printed URL; from a remote GPU box forward the port: ssh -L 8080:localhost:8080)
showing the scene rendered by our path tracer: 1 reflection sample per pixel per frame, accumulated while the
camera is still, denoised once --denoise-after samples are in; the camera follows the browser's view.

Editing: pick a named selection (the scene config's edits:) or a box (shift + drag on the image draws one),
move / rotate it with the gizmo (Apply commits), duplicate, delete, set roughness / F0 / diffuse colour;
switch the shown layer (final, diffuse, specular, normal, depth, roughness, f0) and the max path length.
"Save edit spec" writes an edit-spec YAML that the edit stage replays exactly:
    python -m stages.edit apply --edit-file <saved.yaml> --edit <name> --model ... --capture ... --out ...

--benchmark renders without a browser and prints frames per second and time to first frame after a material
edit, a move (BVH refit) and a duplicate (BVH rebuild); --out writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
from pathlib import Path

import numpy as np


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 160x120, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"resolution must be positive, got {text!r}")
    return w, h


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m stages.view", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", type=Path, help="a results folder (results/<scene>: model/, capture/), a model folder "
                   "(gaussians.ply + model.yaml) or a gaussians.ply")
    p.add_argument("--scene", help="scene config whose edits: give the named selections (default: the results "
                   "folder's name when configs/scenes/<name>.yaml exists)")
    p.add_argument("--preset", action="append", default=[], help="extra preset(s) applied with --scene")
    p.add_argument("--capture", type=Path, help="capture whose first test view is the starting camera "
                   "(default: <results>/capture)")
    p.add_argument("--host", default="127.0.0.1", help="interface to serve on (0.0.0.0: every interface)")
    p.add_argument("--port", type=int, default=8080, help="HTTP + websocket port")
    p.add_argument("--resolution", type=_resolution, default=(160, 120),
                   help="render size WIDTHxHEIGHT as a pixel budget: the image follows the browser canvas' aspect "
                   "with about this many pixels (default 160x120, for a 2-core CPU)")
    p.add_argument("--device", default="cpu", help="cpu | cuda")
    p.add_argument("--threads", type=int, default=2, help="CPU tracer threads")
    p.add_argument("--max-path-length", type=int, help="path segments (1 = no reflections; default: the model's, "
                   "model.yaml)")
    p.add_argument("--max-spp", type=int, default=64, help="accumulation stops at this many samples")
    p.add_argument("--denoise-after", type=int, default=4, help="denoise from this many samples on (0 = never)")
    p.add_argument("--seed", type=int, default=0, help="seed of every accumulation (equal seed + spp = equal image)")
    p.add_argument("--layer", default="final", help="layer shown first")
    p.add_argument("--name", default="viewer_edit", help="name of the saved edit")
    p.add_argument("--save-dir", type=Path, help="where 'Save edit spec' writes (default: <results>/edits/viewer)")
    p.add_argument("--image-format", choices=["jpeg", "png"], default="jpeg", help="streamed image format")
    p.add_argument("--headless", action="store_true", help="never open a local browser; print one JSON line "
                   "{url, port} once serving (scripts, tests)")
    p.add_argument("--benchmark", action="store_true", help="no server: measure FPS and time to first frame")
    p.add_argument("--frames", type=int, default=10, help="--benchmark: frames timed")
    p.add_argument("--repeats", type=int, default=3, help="--benchmark: runs per edit (median kept)")
    p.add_argument("--out", type=Path, help="--benchmark: write the result as JSON here")
    return p.parse_args(argv)


def _resolve(args) -> tuple[Path, Path | None, str | None, Path]:
    src = args.source
    if src.is_dir() and not (src / "gaussians.ply").is_file():  # a results folder
        model = src / "model" / "gaussians.ply"
        capture = args.capture or (src / "capture" if (src / "capture").is_dir() else None)
        save_dir = args.save_dir or src / "edits" / "viewer"
        scene = args.scene
        if scene is None:
            from stages.config import known

            scene = src.name if src.name in known("scenes") else None
    else:
        model = src / "gaussians.ply" if src.is_dir() else src  # a model folder, or a gaussians.ply
        capture, scene, save_dir = args.capture, args.scene, args.save_dir or Path.cwd()
    if not model.is_file():
        raise FileNotFoundError(f"no model at {model} (give a results folder with model/gaussians.ply, a model "
                                "folder or a .ply)")
    return model, capture, scene, save_dir


def _start_camera(capture: Path | None, gaussians, resolution: tuple[int, int]):
    """First test view of the capture (else train), at the viewer's pixel budget; else a view of the
    Gaussians' bounds from +z."""
    from models.capture import Camera, read_capture

    if capture is not None:
        cap = read_capture(capture, layers=["mask"])
        views = cap.split("test") or cap.split("train")
        from .camera import resize_camera

        return resize_camera(views[0].camera, resolution[0] * resolution[1])
    p = gaussians.means.detach().float().cpu().numpy()
    lo, hi = np.percentile(p, 2, axis=0), np.percentile(p, 98, axis=0)
    centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    c2w = np.eye(4)
    c2w[:3, 3] = centre + np.array([0.0, 0.0, 1.2 * size])
    w, h = resolution
    f = h / 2 / np.tan(np.radians(30))
    return Camera(w, h, f, f, w / 2, h / 2, c2w)


def open_session(args: argparse.Namespace):
    """(session, starting camera, model path, save folder) of the parsed arguments: the model is read with its
    settings (model.yaml), so the viewer renders it the way it was trained."""
    from models.trained import load_model
    from stages.config import load_config

    from .progressive import ViewSettings
    from .session import ViewerSession, named_selections

    model, capture, scene, save_dir = _resolve(args)
    edits = load_config(scene, presets=args.preset).get("edits") or {} if scene else {}
    gaussians, model_settings = load_model(model)
    settings = ViewSettings(layer=args.layer, max_path_length=args.max_path_length or
                            model_settings.path.max_path_length, max_spp=args.max_spp,
                            denoise_after=args.denoise_after, seed=args.seed)
    session = ViewerSession(gaussians, named_selections(edits), edits, name=args.name, device=args.device,
                            threads=args.threads, settings=settings, model=model_settings)
    return session, _start_camera(capture, gaussians, args.resolution), model, save_dir


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("models.editing").setLevel(logging.WARNING)  # apply_edit logs every op of every re-apply
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING  # no init banner: stdout stays for the URL line
    from models.capture import CaptureError
    from stages.cli import single_threaded_torch
    from stages.config import ConfigError

    single_threaded_torch()
    try:
        session, camera, model, save_dir = open_session(args)
    except (CaptureError, ConfigError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1

    if args.benchmark:
        from .benchmark import format_table, run_view_benchmark

        names = list(session.selections)
        material = next((n for n in names if "floor" in n), names[0] if names else None)
        move = next((n for n in names if "ball" in n), names[0] if names else None)
        result = run_view_benchmark(session, camera, frames=args.frames, repeats=args.repeats,
                                    material_selection=material, move_selection=move)
        result["model"] = str(model)
        print(format_table(result))
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            tmp = args.out.with_suffix(".tmp")
            tmp.write_text(json.dumps(result, indent=1))
            tmp.replace(args.out)
        return 0

    from .app import ViewerApp

    app = ViewerApp(session, host=args.host, port=args.port, pixels=args.resolution[0] * args.resolution[1],
                    initial_camera=camera, save_dir=save_dir, image_format=args.image_format)
    url = app.url
    if args.headless:
        print(json.dumps({"url": url, "port": app.server.get_port()}), flush=True)
    else:
        print(f"viewer: open {url} in a browser (remote machine: ssh -L {app.server.get_port()}:localhost:"
              f"{app.server.get_port()} <host>, then open http://localhost:{app.server.get_port()}); Ctrl-C stops",
              flush=True)
        if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") or sys.platform == "darwin":
            import webbrowser

            webbrowser.open(url)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    try:
        done.wait()
    except KeyboardInterrupt:
        pass
    finally:
        app.stop()
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
