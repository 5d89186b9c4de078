"""COLMAP structure from motion through pycolmap (CPU): SIFT, matching, incremental mapping, undistortion.

Work folder layout (``--work``, kept for inspection and for COLMAP tools):

```
<work>/database.db        features and verified matches
<work>/sparse/<k>/        every model the incremental mapper found (COLMAP binary)
<work>/undistorted/       the largest model undistorted to PINHOLE: images/ + sparse/ (COLMAP layout)
```
"""

from __future__ import annotations

import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from .config import PosesConfig
from .photos import PosesError

log = logging.getLogger("models.poses")


@dataclass
class SfmResult:
    undistorted: Path  # COLMAP folder (images/ + sparse/) of the largest model, PINHOLE cameras
    model_index: int  # which <work>/sparse/<k> was chosen
    model_sizes: dict[int, int]  # model index -> registered images, every model found
    registered: list[str]  # photo names in the chosen model
    unregistered: list[str]  # photo names it misses
    verified_pairs: int  # image pairs with a verified two-view geometry
    seconds: dict[str, float] = field(default_factory=dict)  # per step


def _step(key: str, label: str, seconds: dict, fn, *args, **kwargs):
    """Run one long COLMAP step with a log line before and after; its wall time goes to ``seconds[key]``."""
    log.info("%s ...", label)
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    seconds[key] = round(time.perf_counter() - t0, 3)
    log.info("%s done in %.1f s", label, seconds[key])
    return out


def _match(db: Path, config: PosesConfig, threads: int, device) -> None:
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    if config.matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=matching, device=device)
    elif config.matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = config.sequential_overlap
        if config.vocab_tree:
            pairing.loop_detection = True
            pairing.vocab_tree_path = str(config.vocab_tree)
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=device)
    else:
        pairing = pycolmap.VocabTreePairingOptions()
        pairing.vocab_tree_path = str(config.vocab_tree)
        pairing.num_threads = threads
        pycolmap.match_vocabtree(db, matching_options=matching, pairing_options=pairing, device=device)


def check_vocab_tree(config: PosesConfig) -> None:
    """The vocabulary tree the matcher needs exists (it cannot be downloaded by the pipeline)."""
    if config.vocab_tree and not Path(config.vocab_tree).is_file():
        raise PosesError(f"poses.vocab_tree: {config.vocab_tree} does not exist; the vocabulary tree is not "
                         "downloaded by this pipeline: get a COLMAP 4.x vocabulary-tree file (see "
                         "https://colmap.github.io/faq.html) and give its path, or use matcher exhaustive / sequential")


def run_sfm(photos: Path, names: list[str], work: Path, config: PosesConfig, threads: int = 2,
            progress: bool = True) -> SfmResult:
    """SIFT + matching + incremental mapping of ``names`` (in ``photos``), then the largest model undistorted.
    Raises PosesError when no model is found or (unless ``allow_unregistered``) photos fail to register."""
    import pycolmap

    check_vocab_tree(config)
    work.mkdir(parents=True, exist_ok=True)
    db, sparse, undistorted = work / "database.db", work / "sparse", work / "undistorted"
    for stale in (db, sparse, undistorted):  # a fresh run: never mix with an earlier one
        if stale.is_dir():
            shutil.rmtree(stale)
        elif stale.exists():
            stale.unlink()
    sparse.mkdir()
    pycolmap.set_random_seed(config.seed)
    device = pycolmap.Device.cpu
    seconds: dict[str, float] = {}

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.max_image_size = config.max_image_size
    extraction.sift.max_num_features = config.max_features
    _step("features", f"SIFT features of {len(names)} photos", seconds, pycolmap.extract_features, db, photos,
          image_names=names, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
          extraction_options=extraction, device=device)
    _step("matching", f"{config.matcher} matching", seconds, _match, db, config, threads, device)
    database = pycolmap.Database.open(db)
    verified = int(database.num_verified_image_pairs())
    database.close()
    log.info("%d verified image pairs", verified)

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.random_seed = config.seed
    options.min_model_size = max(2, min(10, len(names) // 2))
    with tqdm(total=len(names), desc="poses: registered", unit="photo", disable=not progress) as bar:
        models = _step("mapping", "incremental mapping", seconds, pycolmap.incremental_mapping, db, photos, sparse,
                       options=options, initial_image_pair_callback=lambda: bar.update(2),
                       next_image_callback=lambda: bar.update(1))
    if not models:
        raise PosesError(f"COLMAP found no model for the {len(names)} photos in {photos} ({verified} verified "
                         "image pairs): the photos need overlap and texture (distinct features seen from several views)")
    sizes = {int(k): int(m.num_reg_images()) for k, m in models.items()}
    best = max(sizes, key=lambda k: (sizes[k], -k))
    model = models[best]
    registered = sorted(img.name for img in model.images.values() if img.has_pose)
    unregistered = [n for n in names if n not in set(registered)]
    log.info("models found (index: registered photos): %s; using model %d", sizes, best)
    if unregistered:
        what = (f"{len(unregistered)} of {len(names)} photo(s) failed to register in the largest COLMAP model "
                f"(model {best} holds {sizes[best]}; {len(sizes)} model(s) found): {', '.join(unregistered)}")
        if not config.allow_unregistered:
            raise PosesError(f"{what}. Remove them, add photos that overlap them, or set poses.allow_unregistered: true")
        log.warning("%s; dropped (allow_unregistered)", what)

    undistort = pycolmap.UndistortCameraOptions()
    _step("undistortion", "undistortion to PINHOLE", seconds, pycolmap.undistort_images, undistorted, sparse / str(best), photos,
          image_names=registered, output_type="COLMAP", undistort_options=undistort, num_threads=threads)
    return SfmResult(undistorted=undistorted, model_index=best, model_sizes=sizes, registered=registered,
                     unregistered=unregistered, verified_pairs=verified, seconds=seconds)
