"""``poses`` stage: COLMAP structure from motion (pycolmap, CPU) on a folder of photos -> a capture.

``photos.py`` finds and checks the photos (no pycolmap: the workflow uses it at parse time),
``sfm.py`` runs SIFT / matching / mapping / undistortion, ``normalise.py`` centres and scales the
scene (and aligns camera sets for evaluation), ``pipeline.py`` writes the capture.
"""

from .config import PosesConfig
from .normalise import Normalisation, normalisation_of, normalise_capture, pose_errors, umeyama
from .photos import PosesError, check_photos, has_poses, list_photos, missing_photos_message, photos_dir
from .pipeline import run_poses

__all__ = ["Normalisation", "PosesConfig", "PosesError", "check_photos", "has_poses", "list_photos",
           "missing_photos_message", "normalisation_of", "normalise_capture", "photos_dir", "pose_errors",
           "run_poses", "umeyama"]
