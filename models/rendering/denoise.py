"""Intel Open Image Denoise (pyoidn, CPU) with albedo + normal guides."""

from __future__ import annotations

import numpy as np


def denoise(color: np.ndarray, albedo: np.ndarray | None = None, normal: np.ndarray | None = None) -> np.ndarray:
    """Denoise an HDR float image. color, albedo, normal: [H, W, 3]; normal in [-1, 1] (OIDN needs the
    albedo guide whenever the normal guide is given). Returns [H, W, 3] float32."""
    import pyoidn

    color = np.ascontiguousarray(color, dtype=np.float32)
    out = np.zeros_like(color)
    device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
    device.commit()
    filt = pyoidn.Filter(device, "RT")
    filt.set_image(pyoidn.OIDN_IMAGE_COLOR, color, pyoidn.OIDN_FORMAT_FLOAT3)
    guides = []
    if albedo is not None:
        guides.append(np.ascontiguousarray(np.clip(albedo, 0, 1), dtype=np.float32))
        filt.set_image(pyoidn.OIDN_IMAGE_ALBEDO, guides[-1], pyoidn.OIDN_FORMAT_FLOAT3)
        if normal is not None:
            guides.append(np.ascontiguousarray(normal, dtype=np.float32))
            filt.set_image(pyoidn.OIDN_IMAGE_NORMAL, guides[-1], pyoidn.OIDN_FORMAT_FLOAT3)
    filt.set_image(pyoidn.OIDN_IMAGE_OUTPUT, out, pyoidn.OIDN_FORMAT_FLOAT3)
    filt.set_bool("hdr", True)
    filt.commit()
    filt.execute()
    error = device.get_error()
    filt.release()
    device.release()
    if error and error[0]:
        raise RuntimeError(f"OIDN denoising failed: {error}")
    return out
