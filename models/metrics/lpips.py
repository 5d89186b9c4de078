"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric"), version
0.1, AlexNet trunk, in plain torch from weights the user points to (nothing is downloaded, no torchvision).

Weights: ``backbone``, torchvision's ImageNet AlexNet state dict (``alexnet-owt-7be5be79.pth``: the convolutions
``features.{0,3,6,8,10}.{weight,bias}``; ``classifier.*`` and other keys are ignored); ``lin``, the LPIPS v0.1
linear heads (``alex.pth`` of the ``lpips`` package: ``lin{0..4}.model.1.weight``, [1, C, 1, 1], no bias).

Distance of two images in [-1, 1] (``lpips_distance``): scale each by the LPIPS scaling layer ((x - SHIFT) / SCALE
per channel), run AlexNet's ``features`` (conv 11/4/2, ReLU, max-pool 3/2, conv 5/1/2, ReLU, max-pool 3/2, conv
3/1/1, ReLU, conv 3/1/1, ReLU, conv 3/1/1, ReLU) and take the five ReLU outputs; per layer unit-normalise the
features over channels (x / (||x|| + 1e-10)), square their difference, weight the channels by the layer's lin
(a 1x1 convolution), average over pixels; sum over the layers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from models.settings import file_sha256

# torchvision AlexNet ``features``: (state-dict prefix, in channels, out channels, kernel, stride, padding,
# max-pool 3/2 before the conv); the ReLU after each conv is one tapped layer
ALEXNET_CONVS = (("features.0", 3, 64, 11, 4, 2, False), ("features.3", 64, 192, 5, 1, 2, True),
                 ("features.6", 192, 384, 3, 1, 1, True), ("features.8", 384, 256, 3, 1, 1, False),
                 ("features.10", 256, 256, 3, 1, 1, False))
CHANNELS = tuple(c[2] for c in ALEXNET_CONVS)  # of the tapped layers
SHIFT = (-0.030, -0.088, -0.188)  # the LPIPS scaling layer, on inputs in [-1, 1]
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10  # added to the feature norm
MIN_SIZE = 31  # smaller images leave nothing for the second max-pool
LIN_KEY = "lin{}.model.1.weight"  # the lpips package's key (index 1: after its training-time dropout)


@dataclass(frozen=True)
class LpipsWeights:
    """What one LPIPS needs, with where it came from (``describe``)."""

    convs: tuple[tuple[torch.Tensor, torch.Tensor], ...]  # (weight [Cout, Cin, k, k], bias [Cout]) per conv
    lins: tuple[torch.Tensor, ...]  # [1, C, 1, 1] per tapped layer
    backbone: Path
    lin: Path
    backbone_sha256: str  # first 12 hex digits
    lin_sha256: str

    def to(self, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> LpipsWeights:
        return LpipsWeights(tuple((w.to(device, dtype), b.to(device, dtype)) for w, b in self.convs),
                            tuple(w.to(device, dtype) for w in self.lins), self.backbone, self.lin,
                            self.backbone_sha256, self.lin_sha256)

    def describe(self) -> str:
        return (f"AlexNet v0.1, backbone {self.backbone} (sha256 {self.backbone_sha256}), lin {self.lin} "
                f"(sha256 {self.lin_sha256})")


def _state_dict(path: Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"LPIPS weights file not found: {path}")
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # a truncated or foreign file: torch's many pickle / zip errors
        raise ValueError(f"{path}: not a torch state dict ({type(e).__name__}: {e})") from e
    if not isinstance(sd, dict):
        raise ValueError(f"{path}: expected a state dict (a mapping of tensors), got {type(sd).__name__}")
    return sd


def _tensor(sd: dict, path: Path, key: str, shape: tuple[int, ...], what: str) -> torch.Tensor:
    if key not in sd:
        raise ValueError(f"{path}: missing key {key!r} (expected {what})")
    t = sd[key]
    if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
        got = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
        raise ValueError(f"{path}: key {key!r} has shape {got}, expected {shape} ({what})")
    return t.detach().to(torch.float32)


def load_lpips(backbone: str | Path, lin: str | Path) -> LpipsWeights:
    """Read both weight files, strict on every key and shape LPIPS uses (extra keys ignored): FileNotFoundError
    or ValueError naming the file and the key."""
    backbone, lin = Path(backbone), Path(lin)
    sd = _state_dict(backbone)
    convs = tuple((_tensor(sd, backbone, f"{p}.weight", (co, ci, k, k), "torchvision AlexNet features"),
                   _tensor(sd, backbone, f"{p}.bias", (co,), "torchvision AlexNet features"))
                  for p, ci, co, k, _, _, _ in ALEXNET_CONVS)
    sd = _state_dict(lin)
    lins = tuple(_tensor(sd, lin, LIN_KEY.format(i), (1, c, 1, 1), "LPIPS v0.1 AlexNet lin layers")
                 for i, c in enumerate(CHANNELS))
    return LpipsWeights(convs, lins, backbone, lin, file_sha256(backbone)[:12], file_sha256(lin)[:12])


def alexnet_features(x: torch.Tensor, convs) -> list[torch.Tensor]:
    """The five ReLU outputs of AlexNet ``features`` for x [N, 3, H, W]."""
    out = []
    for (w, b), (_, _, _, _, stride, pad, pool) in zip(convs, ALEXNET_CONVS):
        if pool:
            x = F.max_pool2d(x, kernel_size=3, stride=2)
        x = F.relu(F.conv2d(x, w, b, stride=stride, padding=pad))
        out.append(x)
    return out


def lpips_layers(a: torch.Tensor, b: torch.Tensor, weights: LpipsWeights) -> torch.Tensor:
    """[N, 5]: each tapped layer's term of LPIPS(a, b) for images a, b [N, 3, H, W] in [-1, 1], H, W >= MIN_SIZE
    (computed in the dtype and on the device of ``weights``)."""
    if a.shape != b.shape or a.ndim != 4 or a.shape[1] != 3:
        raise ValueError(f"LPIPS needs two [N, 3, H, W] images of one shape, got {tuple(a.shape)} and {tuple(b.shape)}")
    if min(a.shape[2:]) < MIN_SIZE:
        raise ValueError(f"LPIPS (AlexNet) needs images of at least {MIN_SIZE} x {MIN_SIZE} pixels, got "
                         f"{a.shape[3]} x {a.shape[2]}")
    ref = weights.lins[0]
    shift = torch.tensor(SHIFT, dtype=ref.dtype, device=ref.device).view(1, 3, 1, 1)
    scale = torch.tensor(SCALE, dtype=ref.dtype, device=ref.device).view(1, 3, 1, 1)
    fa, fb = (alexnet_features((x.to(ref.device, ref.dtype) - shift) / scale, weights.convs) for x in (a, b))
    terms = []
    for xa, xb, lin in zip(fa, fb, weights.lins):
        ua = xa / (xa.square().sum(1, keepdim=True).sqrt() + EPS)
        ub = xb / (xb.square().sum(1, keepdim=True).sqrt() + EPS)
        terms.append(F.conv2d((ua - ub).square(), lin).mean((1, 2, 3)))
    return torch.stack(terms, 1)


def lpips_distance(a: torch.Tensor, b: torch.Tensor, weights: LpipsWeights) -> torch.Tensor:
    """[N]: LPIPS v0.1 of images a, b [N, 3, H, W] in [-1, 1]."""
    return lpips_layers(a, b, weights).sum(1)


@torch.no_grad()
def lpips_images(pred: np.ndarray, target: np.ndarray, weights: LpipsWeights) -> float:
    """LPIPS of two [H, W, 3] images in [0, 1] (e.g. sRGB-encoded), mapped to [-1, 1] as the lpips package's
    ``normalize=True``."""
    a, b = (torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).permute(2, 0, 1)[None] * 2 - 1
            for x in (pred, target))
    return float(lpips_distance(a, b, weights)[0])
