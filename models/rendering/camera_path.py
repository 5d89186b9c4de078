"""A novel camera path through the test cameras."""

from __future__ import annotations

import numpy as np

from models.capture import Camera


def camera_path(cameras: list[Camera], count: int) -> list[Camera]:
    """``count`` cameras interpolated through ``cameras`` (positions linearly, rotations by slerp), closed loop."""
    from scipy.spatial.transform import Rotation, Slerp

    if len(cameras) == 1 or count <= 0:
        return cameras[:max(count, 0)]
    keys = cameras + [cameras[0]]
    times = np.arange(len(keys), dtype=float)
    slerp = Slerp(times, Rotation.from_matrix(np.stack([c.c2w[:3, :3] for c in keys])))
    positions = np.stack([c.origin for c in keys])
    out = []
    for t in np.linspace(0, len(keys) - 1, count, endpoint=False):
        i = min(int(t), len(keys) - 2)
        c2w = np.eye(4)
        c2w[:3, :3] = slerp([t]).as_matrix()[0]
        c2w[:3, 3] = positions[i] + (t - i) * (positions[i + 1] - positions[i])
        ref = cameras[0]
        out.append(Camera(ref.width, ref.height, ref.fl_x, ref.fl_y, ref.cx, ref.cy, c2w))
    return out
