"""The merged pipeline config: defaults < scene < presets < overrides, validated against JSON schemas.

Snakemake (``workflow/rules/common.smk``) and every stage CLI load configs
through this module, so a stage run by hand sees what the workflow would give it.

Schemas (``workflow/schemas/``): the sections read into a settings dataclass (init, reconstruct, render, poses,
buffers, buffernet.train) have schemas GENERATED from those dataclasses (``models/settings.py``): regenerate them
with ``python -m stages.config --write-schemas`` (a test fails while they are stale). The top level, synth, edits
and buffernet sections have hand-written schemas (their parsers are hand-written too).
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path
from typing import Any, Iterable

import yaml

from models.settings import config_hash, describe, read_yaml_mapping, reject_unknown  # noqa: F401  (config_hash, reject_unknown:
# re-exported for the stages)

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
SCHEMAS = ROOT / "workflow" / "schemas"
# section (dotted path) -> schema file validating it (when the section is present)
SECTION_SCHEMAS = {
    "synth": "synth.schema.yaml", "edits": "edit.schema.yaml", "buffernet": "buffernet.schema.yaml",  # by hand
    "init": "init.schema.yaml", "reconstruct": "reconstruct.schema.yaml", "render": "render.schema.yaml",
    "poses": "poses.schema.yaml", "buffers": "buffers.schema.yaml",
    "buffernet.train": "buffernet_train.schema.yaml",  # generated (generated_schemas)
}


def generated_schemas() -> dict[str, dict]:
    """Schema file name -> the schema generated from the settings dataclass of its section."""
    from models.buffernet.fill import BuffersConfig
    from models.buffernet.training.config import TrainConfig
    from models.initialisation import InitConfig
    from models.poses.config import PosesConfig
    from models.reconstruction import ReconstructConfig
    from models.rendering import RenderConfig
    from models.settings import schema

    return {"init.schema.yaml": schema(InitConfig), "reconstruct.schema.yaml": schema(ReconstructConfig),
            "render.schema.yaml": schema(RenderConfig), "poses.schema.yaml": schema(PosesConfig),
            "buffers.schema.yaml": schema(BuffersConfig),
            # data / out are given on the buffernet_train command line by the workflow
            "buffernet_train.schema.yaml": schema(TrainConfig, exclude=("data", "out"))}


def schema_text(schema: dict) -> str:
    return ("# GENERATED from the settings dataclass named in the title: do not edit; regenerate with\n"
            "#   python -m stages.config --write-schemas\n" + yaml.safe_dump(schema, sort_keys=False, width=120))


def write_schemas() -> list[Path]:
    """Write every generated schema into workflow/schemas/; returns the files written."""
    out = []
    for name, schema in generated_schemas().items():
        path = SCHEMAS / name
        path.write_text(schema_text(schema))
        out.append(path)
    return out


# sections only a scene of one kind has (presets leave them out for the other kinds)
KIND_SECTIONS = {"synth": "synthetic", "poses": "photos"}


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
    return read_yaml_mapping(path, ConfigError)


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
        config = deep_merge(config, for_kind(read_yaml(path), config.get("kind")))
    config = deep_merge(config, coerce_overrides(overrides))
    config["scene"] = scene
    config["presets"] = preset_list
    validate(config)
    return config


def for_kind(preset: dict, kind: str | None) -> dict:
    """The sections of ``preset`` that apply to a scene of ``kind``: a preset sizes the sections a scene has, it
    does not give a photos scene a ``synth`` section (the ci preset's tiny synth sizes would make it a synthetic
    scene without objects) nor a synthetic scene a ``poses`` one."""
    return {k: v for k, v in preset.items() if KIND_SECTIONS.get(k, kind) == kind}


def coerce_overrides(overrides: dict) -> dict:
    """Command-line values (strings from Snakemake's ``--config``) converted to the types the schemas want."""
    from models.settings import coerce

    out = coerce(overrides, yaml.safe_load((SCHEMAS / "config.schema.yaml").read_text()))
    for section, schema in SECTION_SCHEMAS.items():
        *parents, last = section.split(".")
        node = out
        for key in parents:
            node = node.get(key) if isinstance(node, dict) else None
        if isinstance(node, dict) and isinstance(node.get(last), dict):
            node[last] = coerce(node[last], yaml.safe_load((SCHEMAS / schema).read_text()))
    return out


def validate(config: dict) -> None:
    """Raise ConfigError naming the first bad key/value of ``config`` (top level, then each section)."""
    _check(config, SCHEMAS / "config.schema.yaml", prefix="")
    for section, schema in SECTION_SCHEMAS.items():
        value: Any = config
        for key in section.split("."):
            value = value.get(key) if isinstance(value, dict) else None
        if value is not None:
            _check(value, SCHEMAS / schema, prefix=f"{section}.")


def presets_section(presets: Iterable[str], section: str) -> dict:
    """``section`` of configs/default.yaml with ``presets`` merged over it, in order (no scene)."""
    config = read_yaml(CONFIGS / "default.yaml")
    for preset in presets:
        path = CONFIGS / "presets" / f"{preset}.yaml"
        if not path.is_file():
            raise ConfigError(f"unknown preset {preset!r}; known presets: {', '.join(known('presets'))}")
        config = deep_merge(config, read_yaml(path))
    node: Any = config
    for key in section.split("."):
        node = node.get(key, {}) if isinstance(node, dict) else {}
    return node if isinstance(node, dict) else {}


def check_section(section: str, value: dict) -> dict:
    """One config section given alone (a stage's --config-json), coerced and validated as ``load_config`` does
    the merged config's: ConfigError naming the bad key / value. Sections without a schema pass unchanged."""
    if section not in SECTION_SCHEMAS:
        return value
    from models.settings import coerce

    schema_path = SCHEMAS / SECTION_SCHEMAS[section]
    value = coerce(value, yaml.safe_load(schema_path.read_text()))
    _check(value, schema_path, prefix=f"{section}.")
    return value


def _check(data: Any, schema_path: Path, prefix: str) -> None:
    import jsonschema  # here, not at the top: a stage's --help does not pay for it

    schema = yaml.safe_load(schema_path.read_text())
    error = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(schema).iter_errors(data))
    if error is not None:
        raise ConfigError(f"config {describe(error, prefix.rstrip('.'))} (schema {schema_path.name})")


def _as_list(value: Any) -> list[str]:
    if isinstance(value, str):
        return [v for v in value.split(",") if v]
    return list(value)


if __name__ == "__main__":
    if sys.argv[1:] != ["--write-schemas"]:
        sys.exit("usage: python -m stages.config --write-schemas   (regenerates workflow/schemas/ from models/)")
    for written in write_schemas():
        print(written.relative_to(ROOT))
