"""Viewer responsiveness without a browser: frames per second at 1 spp and time to the first frame after an edit.

Timed on the session's own view, i.e. what a browser tab's render thread does minus the JPEG encoding and
the websocket (a few ms at the default size). Time to first frame = ``session.apply(op)`` (the spec re-applied
to the original model, the followed selection recomputed) + the next ``step()`` (BVH refit / rebuild inside
the first trace, primary segment, 1 reflection sample, tonemapping).
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from models.capture import Camera

from .session import ViewerSession


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _settle(session: ViewerSession) -> None:
    """Render the current scene once (first frame after a change) so the next timing starts clean."""
    session.step()


def run_view_benchmark(session: ViewerSession, camera: Camera, frames: int = 10, repeats: int = 3,
                       material_selection: str | None = None, move_selection: str | None = None) -> dict:
    """FPS (camera still: accumulating; camera moving: primary every frame), denoiser time, and time to first
    frame after a material edit, a move (BVH refit) and a duplicate (BVH rebuild), median of ``repeats``."""
    view = session.view
    view.configure(max_spp=10 ** 6)
    session.set_camera(camera)
    first, t_first = _timed(session.step)
    still = [_timed(session.step)[1] for _ in range(frames)]
    assert view.frames == frames + 1
    # camera moving: a new camera every frame, so the primary segment is traced each time
    moving = []
    for i in range(max(frames // 2, 2)):
        c2w = camera.c2w.copy()
        c2w[:3, 3] += (1e-4 * (i + 1)) * camera.rotation[:, 0]
        session.set_camera(Camera(camera.width, camera.height, camera.fl_x, camera.fl_y, camera.cx, camera.cy, c2w))
        moving.append(_timed(session.step)[1])
    session.set_camera(camera)
    _settle(session)
    # denoiser at this size (view.layers() denoises once denoise_after samples are in)
    layers = view.layers()
    from models.rendering import denoise

    _, t_denoise = _timed(lambda: denoise(layers["specular_noisy"], albedo=layers["f0"], normal=layers["normal"]))

    def edit_case(selection: str | None, op: dict) -> dict:
        rows = []
        for _ in range(repeats):
            if selection is not None:
                session.select(selection)
            else:
                session.select_mapping({"all": True}, "all")
            _settle(session)
            t0 = time.perf_counter()
            session.apply(op)
            t_edit = time.perf_counter() - t0
            frame = session.step()
            total = time.perf_counter() - t0
            assert frame is not None and frame.spp <= 1
            bvh = session.tracer.bvh
            rows.append({"total_s": total, "edit_s": t_edit, "frame_s": total - t_edit,
                         "bvh_update_s": bvh.last_update_s, "bvh_rebuilt": bool(bvh.last_was_rebuild),
                         "gaussians": len(session.scene()[0])})
            session.undo()
            _settle(session)
        med = {k: statistics.median(r[k] for r in rows) for k in ("total_s", "edit_s", "frame_s", "bvh_update_s")}
        return {**med, "bvh_rebuilt": rows[0]["bvh_rebuilt"], "gaussians": rows[0]["gaussians"],
                "selection": selection or "all", "op": op, "runs": rows}

    extent = float(np.linalg.norm(np.ptp(session.original.means.detach().float().cpu().numpy(), axis=0)))
    cases = {
        "material": edit_case(material_selection, {"op": "set_roughness", "value": 0.05}),
        "move": edit_case(move_selection, {"op": "translate", "offset": [0.05 * extent, 0.0, 0.0]}),
        "duplicate": edit_case(move_selection, {"op": "duplicate", "offset": [0.1 * extent, 0.0, 0.0]}),
    }
    return {
        "resolution": [camera.width, camera.height],
        "gaussians": len(session.original),
        "max_path_length": view.settings.max_path_length,
        "threads": session.tracer._threads,
        "device": session.tracer.device,
        "first_frame_s": t_first,
        "still_frame_s": statistics.median(still),
        "fps_still": 1.0 / statistics.median(still),
        "moving_frame_s": statistics.median(moving),
        "fps_moving": 1.0 / statistics.median(moving),
        "denoise_s": t_denoise,
        "time_to_first_frame": cases,
        "frames": frames,
        "repeats": repeats,
    }


def format_table(r: dict) -> str:
    w, h = r["resolution"]
    lines = [
        f"viewer benchmark: {r['gaussians']:,} Gaussians, {w}x{h}, max path length {r['max_path_length']}, "
        f"{r['threads']} tracer thread(s) on {r['device']}",
        f"  camera still (1 spp/frame, primary cached): {r['fps_still']:.2f} fps ({1000 * r['still_frame_s']:.0f} ms)",
        f"  camera moving (primary + 1 spp per frame):  {r['fps_moving']:.2f} fps "
        f"({1000 * r['moving_frame_s']:.0f} ms)",
        f"  denoiser (OIDN, specular + guides):         {1000 * r['denoise_s']:.0f} ms",
        "  time to first frame after an edit (median):",
        f"  {'edit':<10} {'total ms':>9} {'edit ms':>8} {'frame ms':>9} {'BVH ms':>7} {'BVH':>8} {'Gaussians':>10}",
    ]
    for name, c in r["time_to_first_frame"].items():
        lines.append(f"  {name:<10} {1000 * c['total_s']:9.0f} {1000 * c['edit_s']:8.1f} {1000 * c['frame_s']:9.0f} "
                     f"{1000 * c['bvh_update_s']:7.1f} {'rebuild' if c['bvh_rebuilt'] else 'refit':>8} "
                     f"{c['gaussians']:>10,}")
    return "\n".join(lines)
