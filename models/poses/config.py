"""Settings of the ``poses`` stage: one dataclass, a comment per field."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from models.settings import from_dict, setting

MATCHERS = ("exhaustive", "sequential", "vocab_tree")
VOCAB_TREE_HINT = ("matcher vocab_tree needs the path of a COLMAP vocabulary-tree file: it is not downloaded by "
                   "this pipeline; get one matching COLMAP 4.x, see https://colmap.github.io/faq.html")
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass
class PosesConfig:
    """Structure-from-motion settings (the ``poses`` config section)."""

    images: str | None = setting(None, "folder of photos, or a COLMAP folder (images/ + sparse/ [+ priors/]) that "
                                 "already has poses")
    download: str = setting("", "what to download and where to put it, shown when `images` is missing")
    matcher: str = setting("exhaustive", "exhaustive (small sets, < ~300 photos) | sequential (video order) | "
                           "vocab_tree", enum=list(MATCHERS))
    vocab_tree: str | None = setting(None, "COLMAP vocabulary-tree file: required by vocab_tree; loop detection for "
                                     "sequential")
    sequential_overlap: int = setting(10, "sequential: match each photo with this many following ones", minimum=1)
    camera_model: str = setting("SIMPLE_RADIAL", "COLMAP model of the (single, shared) camera before undistortion",
                                enum=list(CAMERA_MODELS))
    max_image_size: int = setting(3200, "SIFT runs on photos downscaled to this long side", minimum=1)
    max_features: int = setting(8192, "SIFT features per photo", minimum=1)
    min_images: int = setting(3, "fewer photos than this is an error", minimum=2)
    allow_unregistered: bool = setting(False, "false: photos the largest model misses are an error; true: dropped "
                                       "(logged)")
    test_every: int = setting(8, "every n-th registered photo (in name order) is a test view (LLFF hold); 0 = none",
                              minimum=0)
    normalise: bool = setting(True, "centre the cameras on the origin and scale them into target_radius")
    target_radius: float = setting(1.0, "largest camera distance from the centre after normalisation (scene units)",
                                   exclusiveMinimum=0)
    seed: int = setting(0, "COLMAP's random seed (RANSAC, mapper), for repeatable runs")

    SCHEMA_EXTRA: ClassVar[dict] = {"allOf": [{"if": {"properties": {"matcher": {"const": "vocab_tree"}},
                                                      "required": ["matcher"]},
                                               "then": {"description": VOCAB_TREE_HINT, "required": ["vocab_tree"],
                                                        "properties": {"vocab_tree": {"type": "string"}}}}]}

    @classmethod
    def from_dict(cls, d: dict) -> "PosesConfig":
        cfg = from_dict(cls, d, "poses")
        cfg.check()
        return cfg

    def check(self) -> None:
        """Raise ValueError naming the bad option."""
        if self.matcher not in MATCHERS:
            raise ValueError(f"poses.matcher must be one of {', '.join(MATCHERS)}, got {self.matcher!r}")
        if self.camera_model not in CAMERA_MODELS:
            raise ValueError(f"poses.camera_model must be one of {', '.join(CAMERA_MODELS)}, got {self.camera_model!r}")
        if self.matcher == "vocab_tree" and not self.vocab_tree:
            raise ValueError(f"poses.matcher vocab_tree needs poses.vocab_tree ({VOCAB_TREE_HINT})")
        for name in ("sequential_overlap", "max_image_size", "max_features", "min_images"):
            if getattr(self, name) < 1:
                raise ValueError(f"poses.{name} must be >= 1, got {getattr(self, name)}")
        if self.min_images < 2:
            raise ValueError(f"poses.min_images must be >= 2 (two views are the least SfM needs), got {self.min_images}")
        if self.test_every < 0:
            raise ValueError(f"poses.test_every must be >= 0, got {self.test_every}")
        if not self.target_radius > 0:
            raise ValueError(f"poses.target_radius must be > 0, got {self.target_radius}")
