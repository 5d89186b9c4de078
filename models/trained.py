"""A trained model folder describes itself: ``gaussians.ply`` + ``model.yaml``.

``model.yaml`` (written by ``stages.reconstruct``, carried along by ``stages.edit``) holds what every consumer
needs to render the model the way it was trained::

    format: 1
    gaussians: gaussians.ply      # the Gaussians, in this folder
    tracer: {kernel_p: 3, transmittance_threshold: 0.01, ...}   # TracerConfig (runtime fields left out)
    path: {max_path_length: 3, sampler: vndf, ...}               # PathConfig
    colour: linear                # diffuse / f_dc hold linear outgoing radiance (HDR: emitters exceed 1)
    units: meters                 # the capture's
    training: {config_hash: ..., steps: ..., gaussians: ...}    # provenance

``load_model(folder)`` returns the Gaussians and these settings; render, evaluate, edit, view and the sweep all
read models through it. A new TracerConfig / PathConfig field is stored and read back without further code.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from models.gaussians import Gaussians, read_ply, write_ply
from models.pathtrace.paths import PathConfig
from models.settings import read_yaml_mapping, to_dict
from models.tracer.config import TracerConfig

log = logging.getLogger("models.trained")

FORMAT = 1
MODEL_FILE = "model.yaml"
GAUSSIANS_FILE = "gaussians.ply"
COLOUR = "linear"  # the only colour convention the tracer produces


@dataclass
class ModelSettings:
    """How a model renders: tracer and path settings, colour convention, units, provenance."""

    tracer: TracerConfig = field(default_factory=TracerConfig)
    path: PathConfig = field(default_factory=PathConfig)
    colour: str = COLOUR
    units: str | None = None
    training: dict = field(default_factory=dict)
    source: str = ""  # the model.yaml read, or why there was none

    def tracer_config(self, num_threads: int | None = None, **overrides) -> TracerConfig:
        """The model's TracerConfig with this run's thread count and any render-time ``overrides``."""
        if num_threads is not None:
            overrides["num_threads"] = num_threads
        return dataclasses.replace(self.tracer, **overrides)

    def to_dict(self) -> dict:
        return {"format": FORMAT, "gaussians": GAUSSIANS_FILE, "tracer": to_dict(self.tracer, runtime=False),
                "path": to_dict(self.path), "colour": self.colour, "units": self.units, "training": self.training}


def model_folder(path: str | Path) -> Path:
    """The model folder of ``path``: the folder itself, or the folder of a ``gaussians.ply`` given directly."""
    path = Path(path)
    return path.parent if path.suffix == ".ply" else path


def _read_section(cls, data, where: str):
    if data is None:
        return cls()
    if not isinstance(data, dict):
        raise ValueError(f"{where}: must be a mapping, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown} (written by a newer version?); known: {sorted(names)}")
    try:
        return cls(**data)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: {e}") from None


def _legacy_tracer(data):
    """Tracer settings written before the traversal became one option (commit b9fab46): the two booleans
    become ``traversal``, and the old hard replay ceiling (4096) is dropped. Every traversal blends the same
    hits in the same order, so this never changes an image."""
    if not isinstance(data, dict) or not {"repeated_kbuffer", "ordered_traversal"} & set(data):
        return data
    data = dict(data)
    kbuffer, ordered = data.pop("repeated_kbuffer", False), data.pop("ordered_traversal", False)
    data.setdefault("traversal", "kbuffer" if kbuffer else "ordered" if ordered else "interval")
    if data.get("max_replay_capacity") == 4096:
        data["max_replay_capacity"] = None
    return data


# path settings that became options after models were written, with the value those models were trained and
# rendered with: the paper's Schlick Fresnel (F90 = 1), reflections from the expected depth, a diffuse radiance the
# same from every side, a fixed reflection offset at grazing angles, a normal met from behind flipped
LEGACY_PATH = {"fresnel": "schlick", "reflection_origin": "expected", "diffuse_lobe": "lambert",
               "origin_grazing": 1.0, "back_normal": "flip"}


def _legacy_path(data):
    """Path settings as written, with ``LEGACY_PATH``'s value for every option the model does not name."""
    if data is None:
        data = {}
    if isinstance(data, dict):
        data = {**LEGACY_PATH, **data}
    return data


def read_settings(path: str | Path) -> ModelSettings:
    """The settings of the model folder ``path`` (or of the folder of a gaussians.ply). A folder without
    ``model.yaml`` (made before models described themselves) gets the default tracer and path settings, except
    the Fresnel: such a model was trained with the paper's Schlick (F90 = 1, as ``_legacy_path``); with a warning."""
    folder = model_folder(path)
    file = folder / MODEL_FILE
    if not file.is_file():
        log.warning("%s has no %s: rendering with the default tracer / path settings and the Fresnel models of "
                    "that time were trained with (schlick)", folder, MODEL_FILE)
        return ModelSettings(path=_read_section(PathConfig, _legacy_path(None), f"{folder} (no {MODEL_FILE})"),
                             source=f"defaults ({file} missing)")
    data = read_yaml_mapping(file)
    if data.get("format", FORMAT) > FORMAT:
        raise ValueError(f"{file}: format {data['format']} is newer than this code reads ({FORMAT})")
    colour = data.get("colour", COLOUR)
    if colour != COLOUR:
        raise ValueError(f"{file}: colour {colour!r} is not supported (expected {COLOUR!r})")
    return ModelSettings(tracer=_read_section(TracerConfig, _legacy_tracer(data.get("tracer")),
                                                f"{file} tracer"),
                         path=_read_section(PathConfig, _legacy_path(data.get("path")), f"{file} path"),
                         colour=colour, units=data.get("units"), training=data.get("training") or {},
                         source=str(file))


def load_model(path: str | Path) -> tuple[Gaussians, ModelSettings]:
    """The Gaussians and settings of a model folder (or of the folder of a gaussians.ply given directly)."""
    path = Path(path)
    ply = path if path.suffix == ".ply" else path / GAUSSIANS_FILE
    if not ply.is_file():
        raise FileNotFoundError(f"model {path}: {ply} does not exist (train one with stages.reconstruct)")
    settings = read_settings(path)
    return read_ply(ply), settings


def save_model(folder: str | Path, gaussians: Gaussians, settings: ModelSettings) -> Path:
    """Write ``gaussians.ply`` and ``model.yaml`` into ``folder`` (each atomically); returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_ply(folder / GAUSSIANS_FILE, gaussians)
    text = ("# How this model renders (models/trained.py); read by render, evaluate, edit, view and the sweep.\n"
            + yaml.safe_dump(settings.to_dict(), sort_keys=False))
    tmp = folder / f".{MODEL_FILE}.tmp{os.getpid()}"
    tmp.write_text(text)
    os.replace(tmp, folder / MODEL_FILE)
    return folder
