# Validates the merged config (configs/default.yaml < scene < presets < --config)
# against workflow/schemas/ before any rule runs, and derives what each scene needs.
import functools
import json
import os
import re
import shlex
import sys

from snakemake.utils import min_version

from stages.config import CONFIGS, ConfigError, known, load_config

min_version("9.0")

# a scene is one folder under the results root (its name: config.schema.yaml's pattern): results/sweep/<scene>/...
# and results/<scene>/edits/<edit>/... never match a rule's {scene}
wildcard_constraints:
    scene="[A-Za-z0-9_-]+",

PY = sys.executable  # the interpreter running Snakemake runs the stages too
# the command line that started the workflow, stated in the reports' headers (rules pass "$ER_WORKFLOW_COMMAND":
# the environment, not a param, so that another invocation does not rerun a report); set once, by the first
# Snakemake process: the jobs a cluster executor starts inherit it
os.environ.setdefault("ER_WORKFLOW_COMMAND", shlex.join(["snakemake", *sys.argv[1:]]))


@functools.cache
def scene_config(scene):
    """Merged, validated config of one scene (command-line --config applies to every scene)."""
    overrides = {k: v for k, v in config.items() if k not in ("scene", "scenes", "batch")}
    return load_config(scene, overrides=overrides)


def _batch_scenes(name):
    """Scenes of configs/batches/<name>.yaml."""
    import yaml

    path = CONFIGS / "batches" / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"unknown batch {name!r}; known batches: {', '.join(known('batches'))} (configs/batches/)")
    scenes = (yaml.safe_load(path.read_text()) or {}).get("scenes")
    if not isinstance(scenes, list) or not scenes:
        raise ConfigError(f"{path}: needs a non-empty list 'scenes'")
    return [str(s) for s in scenes]


def _scenes():
    if config.get("batch"):
        return _batch_scenes(str(config["batch"]))
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

# a batch report when several scenes run together: named after the batch, else "scenes"
BATCH = str(config["batch"]) if config.get("batch") else ("scenes" if len(SCENES) > 1 else None)


def scenes_of_kind(kind):
    """Wildcard regex of the scenes of one kind (the merged config for the scenes of this run, the scene file
    for the others): rules writing the same output (synth, poses -> capture) never compete for a scene."""
    names = [s for s in known("scenes") if _scene_kind(s) == kind]
    return "|".join(re.escape(n) for n in names) or "(?!)"


@functools.cache
def _scene_kind(scene):
    """The kind of a scene; None, with one warning, for another scene's file that does not read (a broken scene
    file must not stop the others: it fails, named, when it is run)."""
    from stages.config import read_yaml

    if scene in SCENES:
        return scene_config(scene).get("kind")
    try:
        return read_yaml(CONFIGS / "scenes" / f"{scene}.yaml").get("kind")
    except ConfigError as error:
        print(f"warning: scene {scene!r} skipped: {error}", file=sys.stderr)
        return None


def _check_photos(scene):
    """A photos scene needs its photos before anything runs (unless its capture was already made)."""
    from models.poses.photos import missing_photos_message

    cfg = scene_config(scene)
    if cfg["kind"] != "photos" or cfg.get("photos_of") or os.path.isfile(f"{RESULTS}/{scene}/capture/transforms.json"):
        return
    poses = cfg["poses"]
    if not poses.get("images"):
        sys.exit(f"error: scene {scene!r}: poses.images is not set (the folder of photos)")
    message = missing_photos_message(poses["images"], poses.get("min_images", 3), poses.get("download", ""))
    if message:
        sys.exit(f"error: scene {scene!r}: {message}")


def _check_capture(scene):
    """A ``kind: capture`` scene (a capture folder with its buffers, written by another tool) must be in place:
    nothing in the workflow makes it."""
    if scene_config(scene)["kind"] != "capture":
        return
    folder = f"{RESULTS}/{scene}/capture"
    if not os.path.isfile(f"{folder}/transforms.json"):
        sys.exit(f"error: scene {scene!r} is kind: capture, so its capture must already exist: put the folder "
                 f"(transforms.json + images/, the format of README 'The capture format') at {folder}/")


for _scene in SCENES:
    _check_photos(_scene)
    _check_capture(_scene)


def scene_gpus(wildcards):
    """Resource ``gpu`` of a job of one scene: 1 when the scene runs on CUDA (config device), else 0. Locally
    ``--resources gpu=1`` then runs one GPU job at a time; the slurm executor asks for that many GPUs."""
    return int(scene_config(wildcards.scene)["device"] == "cuda")


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
        targets.append(f"{RESULTS}/{scene}/report.html")
    if BATCH:
        targets.append(f"{RESULTS}/batch_{BATCH}.html")
    return targets


def edit_targets(scene):
    """Per named edit of the scene: metrics.json where a ground truth can be rendered, else the edited renders."""
    cfg = scene_config(scene)
    return [f"{RESULTS}/{scene}/edits/{name}/"
            + ("metrics.json" if edit.get("truth") or (cfg["kind"] == "synthetic" and edit.get("ground_truth"))
               else "renders")
            for name, edit in (cfg.get("edits") or {}).items()]


def edit_truth(wildcards):
    """The ground truth an edit is scored against: the edit's ``truth`` folder when the scene config names one
    (a capture of the edited scene the user already has), else the synth stage's re-render of the edit."""
    truth = scene_edit(wildcards.scene, wildcards.edit).get("truth")
    if truth:
        if not os.path.isfile(os.path.join(truth, "transforms.json")):
            raise ConfigError(f"scene {wildcards.scene!r}, edit {wildcards.edit!r}: truth {truth!r} is not a capture "
                              "folder (no transforms.json)")
        return truth
    return f"{RESULTS}/{wildcards.scene}/edits/{wildcards.edit}/truth"


def scene_edit(scene, name):
    """The named edit ``name`` of ``scene`` (a target results/<scene>/edits/<name>/...); an error listing the
    scene's edits when it has none of that name."""
    edits = scene_config(scene).get("edits") or {}
    if name not in edits:
        raise ConfigError(f"scene {scene!r} has no edit {name!r} (target {RESULTS}/{scene}/edits/{name}/); "
                          f"known edits: {', '.join(edits) or 'none'} (edits: of configs/scenes/{scene}.yaml)")
    return edits[name]


def report_inputs(wildcards):
    """What a scene's report shows: the stages that ran for it (its named edits when edits_in_all is on)."""
    base = f"{RESULTS}/{wildcards.scene}"
    inputs = {"metrics": f"{base}/metrics.json", "renders": f"{base}/renders", "model": f"{base}/model/model.yaml"}
    if scene_config(wildcards.scene).get("edits_in_all"):
        inputs["edits"] = edit_targets(wildcards.scene)
    return inputs


def predicts_buffers(scene):
    """The scene's config asks the buffer network for some buffers (rule buffers runs)."""
    return bool((scene_config(scene).get("buffers") or {}).get("predict"))


def training_capture(wildcards):
    """What init and reconstruct train on: the capture, or the capture with network-predicted buffers."""
    base = f"{RESULTS}/{wildcards.scene}"
    return f"{base}/capture_net" if predicts_buffers(wildcards.scene) else f"{base}/capture"


def photos_of(scene):
    """The scene's photos_of section ({truth: <synthetic scene>}) when its photos are rendered by the workflow,
    else None."""
    return scene_config(scene).get("photos_of")


def scenes_with_photos_of():
    """Wildcard regex of the scenes whose photos the workflow renders (photos_of)."""
    from stages.config import read_yaml

    names = [s for s in known("scenes") if _scene_kind(s) == "photos"
             and (scene_config(s) if s in SCENES else read_yaml(CONFIGS / "scenes" / f"{s}.yaml")).get("photos_of")]
    return "|".join(re.escape(n) for n in names) or "(?!)"


def photos_input(wildcards):
    """The photos the poses stage poses: those the workflow renders (photos_of), else the config's poses.images."""
    if photos_of(wildcards.scene):
        return f"{RESULTS}/{wildcards.scene}/photos"
    return scene_config(wildcards.scene)["poses"]["images"]


def eval_capture(wildcards):
    """The test views render and evaluate use: the rendered truth moved into the posed frame (photos_of), else
    the scene's capture."""
    base = f"{RESULTS}/{wildcards.scene}"
    return f"{base}/capture_eval" if photos_of(wildcards.scene) else f"{base}/capture"


def buffernet_model(scene):
    """buffers.model: a bare name = a network this workflow trains (<results>/buffernet/<name>/pipeline), else a
    path to a saved buffer network."""
    from models.buffernet.fill import network_path

    return str(network_path(str(scene_config(scene)["buffers"]["model"]), RESULTS))


def print_reports():
    """At the end of a successful run: where to look (the batch report, else each scene's report, when written)."""
    batch = f"{RESULTS}/batch_{BATCH}.html" if BATCH else None
    reports = [batch] if batch and os.path.isfile(batch) else \
        [f"{RESULTS}/{s}/report.html" for s in SCENES if os.path.isfile(f"{RESULTS}/{s}/report.html")]
    for path in reports:
        print(f"open {path}", file=sys.stderr)


def buffernet_section(key):
    """One key of the buffernet section (global: the first scene's merged config)."""
    return scene_config(SCENES[0])["buffernet"][key]
