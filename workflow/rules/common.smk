# Validates the merged config (configs/default.yaml < scene < presets < --config)
# against workflow/schemas/ before any rule runs, and derives what each scene needs.
import functools
import json
import sys

from snakemake.utils import min_version

from stages.config import ConfigError, load_config

min_version("9.0")

PY = sys.executable  # the interpreter running Snakemake runs the stages too


@functools.cache
def scene_config(scene):
    """Merged, validated config of one scene (command-line --config applies to every scene)."""
    overrides = {k: v for k, v in config.items() if k not in ("scene", "scenes")}
    return load_config(scene, overrides=overrides)


def _scenes():
    requested = config.get("scenes") or [config.get("scene") or load_config()["scene"]]
    if isinstance(requested, str):
        requested = [s for s in requested.split(",") if s]
    return list(requested)


try:
    SCENES = _scenes()
    for _scene in SCENES:
        scene_config(_scene)
except ConfigError as error:
    sys.exit(f"error: {error}")

RESULTS = scene_config(SCENES[0])["results"]


def section(name):
    """Params function: one config section of the wildcard's scene as canonical JSON
    (Snakemake reruns a rule when its params change, and never otherwise)."""
    return lambda wildcards: json.dumps(scene_config(wildcards.scene).get(name, {}), sort_keys=True)


def scene_targets(scenes):
    """Final outputs of each scene: only the stages the scene's config requires."""
    targets = []
    for scene in scenes:
        cfg = scene_config(scene)
        targets.append(f"{RESULTS}/{scene}/renders")
        targets.append(f"{RESULTS}/{scene}/metrics.json")
    return targets
