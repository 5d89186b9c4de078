"""The Gaussian scene: raw per-Gaussian parameters as torch tensors."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from models.gaussians.activations import opacities_from_logits, world_to_local

# Parameter name -> trailing shape (after the leading N).
PARAM_SHAPES: dict[str, tuple[int, ...]] = {
    "means": (3,),           # [N, 3] world positions
    "quats": (4,),           # [N, 4] rotation quaternion wxyz, raw (normalised by the activation)
    "log_scales": (3,),      # [N, 3] log standard deviation along the local axes
    "opacity_logits": (),    # [N]    opacity = sigmoid(logit)
    "diffuse": (3,),         # [N, 3] linear diffuse RGB (no spherical harmonics)
    "normals": (3,),         # [N, 3] normal (accumulated along rays, normalised by the consumer)
    "roughness": (),         # [N]    perceptual GGX roughness (alpha = roughness^2)
    "f0": (3,),              # [N, 3] base reflectance
}


@dataclass
class Gaussians:
    """Raw, optimisable parameters of N Gaussians (all tensors share device and dtype)."""

    means: torch.Tensor           # [N, 3]
    quats: torch.Tensor           # [N, 4] wxyz
    log_scales: torch.Tensor      # [N, 3]
    opacity_logits: torch.Tensor  # [N]
    diffuse: torch.Tensor         # [N, 3]
    normals: torch.Tensor         # [N, 3]
    roughness: torch.Tensor       # [N]
    f0: torch.Tensor              # [N, 3]

    def __post_init__(self) -> None:
        n = self.means.shape[0] if isinstance(self.means, torch.Tensor) and self.means.ndim > 0 else None
        for name, tail in PARAM_SHAPES.items():
            value = getattr(self, name)
            if not isinstance(value, torch.Tensor):
                raise TypeError(f"Gaussians.{name} must be a torch.Tensor, got {type(value).__name__}")
            if tuple(value.shape) != (n, *tail):
                raise ValueError(f"Gaussians.{name} has shape {tuple(value.shape)}, expected {(n, *tail)}")
            if value.device != self.means.device or value.dtype != self.means.dtype:
                raise ValueError(
                    f"Gaussians.{name} is {value.dtype} on {value.device}, "
                    f"expected {self.means.dtype} on {self.means.device} like means"
                )

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    def params(self) -> dict[str, torch.Tensor]:
        """Name -> tensor, in PARAM_SHAPES order."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to(self, device=None, dtype=None) -> "Gaussians":
        """Copy (detached) to another device / floating dtype."""
        return Gaussians(**{k: v.detach().to(device=device, dtype=dtype) for k, v in self.params().items()})

    def requires_grad_(self, flag: bool = True) -> "Gaussians":
        for v in self.params().values():
            v.requires_grad_(flag)
        return self

    def opacities(self) -> torch.Tensor:
        """[N] activated opacity."""
        return opacities_from_logits(self.opacity_logits)

    def world_to_local(self) -> torch.Tensor:
        """[N, 3, 3] M = S^-1 R^T (see activations.world_to_local)."""
        return world_to_local(self.quats, self.log_scales)

    @staticmethod
    def cat(parts: "list[Gaussians]") -> "Gaussians":
        """The Gaussians of ``parts`` (same device and dtype) one after the other, in order."""
        return Gaussians(**{k: torch.cat([getattr(p, k) for p in parts]) for k in PARAM_SHAPES})

    def subset(self, index: torch.Tensor) -> "Gaussians":
        """The Gaussians at ``index`` ([N] bool mask or integer rows)."""
        return Gaussians(**{k: v[index.to(v.device)] for k, v in self.params().items()})

    @staticmethod
    def empty(device="cpu", dtype=torch.float32) -> "Gaussians":
        return Gaussians(**{k: torch.zeros((0, *s), device=device, dtype=dtype) for k, s in PARAM_SHAPES.items()})
