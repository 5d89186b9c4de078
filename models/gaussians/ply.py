"""PLY read/write with the 3DGS field names for the shared part.

A 3DGS viewer opens the file as the diffuse scene: x,y,z; nx,ny,nz (our normal);
f_dc_0..2 with diffuse = 0.5 + C0 * f_dc; opacity (logit); scale_0..2 (log);
rot_0..3 (wxyz, raw). Extra fields: roughness, f0_0..2.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError

from models.gaussians.scene import Gaussians

SH_C0 = 0.28209479177387814  # zeroth-order spherical harmonic constant

# (our parameter, its column) -> PLY field names
_FIELDS: list[tuple[str, list[str]]] = [
    ("means", ["x", "y", "z"]),
    ("normals", ["nx", "ny", "nz"]),
    ("f_dc", ["f_dc_0", "f_dc_1", "f_dc_2"]),
    ("opacity_logits", ["opacity"]),
    ("log_scales", ["scale_0", "scale_1", "scale_2"]),
    ("quats", ["rot_0", "rot_1", "rot_2", "rot_3"]),
    ("roughness", ["roughness"]),
    ("f0", ["f0_0", "f0_1", "f0_2"]),
]


def diffuse_to_f_dc(diffuse: torch.Tensor) -> torch.Tensor:
    return (diffuse - 0.5) / SH_C0


def f_dc_to_diffuse(f_dc: torch.Tensor) -> torch.Tensor:
    return 0.5 + SH_C0 * f_dc


def write_ply(path: str | os.PathLike, gaussians: Gaussians) -> None:
    """Write atomically (temp file in the same folder, then rename). Stored as float32."""
    path = Path(path)
    columns = {k: v.detach().cpu().double() for k, v in gaussians.params().items()}
    columns["f_dc"] = diffuse_to_f_dc(columns["diffuse"])
    names = [n for _, ns in _FIELDS for n in ns]
    data = np.empty(len(gaussians), dtype=[(n, "f4") for n in names])
    for key, ns in _FIELDS:
        col = columns[key].reshape(len(gaussians), -1).numpy()
        for j, n in enumerate(ns):
            data[n] = col[:, j]
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        PlyData([PlyElement.describe(data, "vertex")]).write(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_ply(path: str | os.PathLike, device="cpu", dtype=torch.float32) -> Gaussians:
    """Read a PLY written by `write_ply` (or a plain 3DGS PLY: missing normals -> 0,
    roughness -> 0, f0 -> 0.04; higher-order SH fields are ignored)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"PLY file not found: {path}")
    try:
        ply = PlyData.read(str(path))
    except (PlyParseError, ValueError, EOFError) as e:  # plyfile's parse errors, numpy's on a short buffer
        raise ValueError(f"{path}: truncated or corrupt PLY ({e})") from None
    if "vertex" not in ply:
        raise ValueError(f"{path}: PLY has no 'vertex' element (elements: {[el.name for el in ply.elements]})")
    vertex = ply["vertex"]
    present = set(vertex.data.dtype.names)
    n = len(vertex.data)
    defaults = {"normals": 0.0, "roughness": 0.0, "f0": 0.04}
    out: dict[str, torch.Tensor] = {}
    for key, ns in _FIELDS:
        missing = [c for c in ns if c not in present]
        if missing and key not in defaults:
            raise ValueError(f"{path}: PLY vertex element lacks required field(s) {missing}")
        if missing:
            col = np.full((n, len(ns)), defaults[key], dtype=np.float64)
        else:
            col = np.stack([np.asarray(vertex[c], dtype=np.float64) for c in ns], axis=1)
        t = torch.from_numpy(col)
        out[key] = t[:, 0] if len(ns) == 1 else t
    out["diffuse"] = f_dc_to_diffuse(out.pop("f_dc"))
    return Gaussians(**{k: v.to(device=device, dtype=dtype).contiguous() for k, v in out.items()})
