"""The photos a ``poses`` run starts from: where they are, and checks before any SfM work.

No pycolmap here: the workflow imports this at parse time to say what is missing.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from models.capture import CaptureError
from models.capture.colmap_layout import image_size
from models.capture.points import colmap_model_dir

PHOTO_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")  # what COLMAP reads


class PosesError(ValueError):
    """A problem with the photos or the SfM result; the message names the files / values."""


def photos_dir(root: str | Path) -> Path:
    """Where the photos are: ``root/images`` when it exists (COLMAP / released layouts), else ``root``."""
    root = Path(root)
    return root / "images" if (root / "images").is_dir() else root


def has_poses(root: str | Path) -> bool:
    """``root`` is a COLMAP folder with a model (``sparse/0`` or ``sparse``) beside ``images/``."""
    root = Path(root)
    return (root / "images").is_dir() and colmap_model_dir(root) is not None


def list_photos(root: str | Path) -> list[str]:
    """Photo file names in ``photos_dir(root)`` (sorted; not recursive: sub-folders such as priors/ are not
    photos). Hidden files and files of other types are skipped."""
    folder = photos_dir(root)
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in PHOTO_EXTENSIONS and not p.name.startswith("."))


def missing_photos_message(root: str | Path, min_images: int, download: str = "") -> str | None:
    """None when ``root`` holds >= ``min_images`` photos (or a posed COLMAP folder), else a one-line message
    saying what is missing and, with ``download``, what to download and where to put it."""
    root = Path(root)
    if has_poses(root):
        return None
    n = len(list_photos(root))
    if n >= min_images:
        return None
    found = f"{photos_dir(root)} holds {n} photo(s)" if root.is_dir() else f"{root} does not exist"
    hint = download or f"put at least {min_images} photos ({', '.join(PHOTO_EXTENSIONS)}) there"
    return f"needs at least {min_images} photos but {found}; {hint}"


def check_photos(root: str | Path, min_images: int) -> tuple[list[str], tuple[int, int]]:
    """Photo names and their common (width, height). Raises PosesError naming the folder, unreadable files,
    or the photos of each size when the resolutions are mixed."""
    message = missing_photos_message(root, min_images)
    if message:
        raise PosesError(message)
    folder = photos_dir(root)
    names = list_photos(root)
    by_size: dict[tuple[int, int], list[str]] = defaultdict(list)
    unreadable = []
    for name in names:
        try:
            by_size[image_size(folder / name)].append(name)
        except CaptureError as e:
            unreadable.append(str(e))
    if unreadable:
        raise PosesError(f"{len(unreadable)} unreadable photo(s) in {folder}: " + "; ".join(unreadable))
    if len(by_size) > 1:
        groups = sorted(by_size.items(), key=lambda kv: -len(kv[1]))
        listed = "; ".join(f"{w}x{h}: {len(ns)} photo(s) ({', '.join(ns[:3])}{', ...' if len(ns) > 3 else ''})"
                           for (w, h), ns in groups)
        raise PosesError(f"photos in {folder} have mixed resolutions ({listed}); one camera at one resolution "
                         "is expected: resize or remove the odd ones")
    return names, next(iter(by_size))
