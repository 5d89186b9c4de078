"""The merged pipeline config: defaults < scene < presets < overrides, validated against JSON schemas.

Snakemake (``workflow/rules/common.smk``) and every stage CLI load configs
through this module, so a stage run by hand sees what the workflow would give it.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any, Iterable

import jsonschema
import yaml

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
SCHEMAS = ROOT / "workflow" / "schemas"
# section -> schema file validating it (when both exist)
SECTION_SCHEMAS = {
    "synth": "synth.schema.yaml", "init": "init.schema.yaml",
    "reconstruct": "reconstruct.schema.yaml", "render": "render.schema.yaml",
    "poses": "poses.schema.yaml",
    "edits": "edit.schema.yaml",
}


class ConfigError(ValueError):
    """A bad scene name, preset, key or value; the message names it."""


def known(kind: str) -> list[str]:
    """Names of the YAML files under configs/<kind>/ (``scenes`` or ``presets``)."""
    return sorted(p.stem for p in (CONFIGS / kind).glob("*.yaml"))


def deep_merge(base: dict, over: dict) -> dict:
    """``over`` merged into a copy of ``base``: mappings merge recursively, anything else replaces."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def read_yaml(path: Path) -> dict:
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: invalid YAML ({e})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: must be a mapping at top level, got {type(data).__name__}")
    return data


def reject_unknown(cls, d: dict, section: str) -> None:
    """Raise ValueError naming ``d``'s keys that are not fields of the dataclass ``cls`` (a config section)."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(d) - known
    if unknown:
        raise ValueError(f"unknown {section} option(s) {sorted(unknown)}; known: {sorted(known)}")


def scene_file(scene: str, _seen: tuple = ()) -> dict:
    """configs/scenes/<scene>.yaml; a scene file with ``extends: <other>`` starts from that scene's file
    (its sections merged under this one's, recursively)."""
    data = read_yaml(CONFIGS / "scenes" / f"{scene}.yaml")
    base = data.pop("extends", None)
    if base is None:
        return data
    if base in _seen + (scene,):
        raise ConfigError(f"configs/scenes/{scene}.yaml: 'extends: {base}' makes a cycle")
    if base not in known("scenes"):
        raise ConfigError(f"configs/scenes/{scene}.yaml: extends unknown scene {base!r}")
    return deep_merge(scene_file(base, _seen + (scene,)), data)


def load_config(scene: str | None = None, presets: Iterable[str] = (), overrides: dict | None = None) -> dict:
    """The validated, merged config of ``scene``. ``overrides`` (e.g. Snakemake's --config) win last;
    their ``scene``/``presets`` keys are honoured too."""
    overrides = dict(overrides or {})
    config = read_yaml(CONFIGS / "default.yaml")
    scene = overrides.get("scene", scene) or config.get("scene")
    scenes = known("scenes")
    if scene not in scenes:
        raise ConfigError(f"unknown scene {scene!r}; known scenes: {', '.join(scenes)}")
    config = deep_merge(config, scene_file(scene))
    # presets named by the scene file come first, then those of the caller / command line
    preset_list = _as_list(config.get("presets", [])) + list(presets)
    preset_list += _as_list(overrides.pop("presets", [])) + _as_list(overrides.pop("preset", []))
    preset_list = list(dict.fromkeys(preset_list))
    for preset in preset_list:
        path = CONFIGS / "presets" / f"{preset}.yaml"
        if not path.is_file():
            raise ConfigError(f"unknown preset {preset!r}; known presets: {', '.join(known('presets'))}")
        config = deep_merge(config, read_yaml(path))
    config = deep_merge(config, overrides)
    config["scene"] = scene
    config["presets"] = preset_list
    validate(config)
    return config


def validate(config: dict) -> None:
    """Raise ConfigError naming the first bad key/value of ``config`` (top level, then each section)."""
    _check(config, SCHEMAS / "config.schema.yaml", prefix="")
    for section, schema in SECTION_SCHEMAS.items():
        if section in config and (SCHEMAS / schema).is_file():
            _check(config[section], SCHEMAS / schema, prefix=f"{section}.")


def config_hash(section: Any) -> str:
    """Stable short hash of a config section (provenance; Snakemake reruns on params change)."""
    blob = json.dumps(section, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def _check(data: Any, schema_path: Path, prefix: str) -> None:
    schema = yaml.safe_load(schema_path.read_text())
    error = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(schema).iter_errors(data))
    if error is not None:
        where = prefix + ".".join(str(p) for p in error.absolute_path)
        raise ConfigError(f"config {where or '<top>'}: {error.message} (schema {schema_path.name})")


def _as_list(value: Any) -> list[str]:
    if isinstance(value, str):
        return [v for v in value.split(",") if v]
    return list(value)
