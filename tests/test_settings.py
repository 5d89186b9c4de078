"""Config defaults and types are stated once: the settings dataclasses (models/) are the source; the section
schemas in workflow/schemas/ are generated from them and must be current; configs/default.yaml's values must be
the dataclass defaults; every shipped scene and preset validates and builds every section it has."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pytest

from models.buffernet.fill import BuffersConfig
from models.buffernet.training.config import TrainConfig
from models.initialisation import InitConfig
from models.poses.config import PosesConfig
from models.reconstruction import ReconstructConfig
from models.rendering import RenderConfig
from models.settings import defaults, from_dict, schema, setting, to_dict
from models.tracer import TracerConfig
from stages.config import CONFIGS, SCHEMAS, generated_schemas, known, load_config, read_yaml, schema_text

SECTIONS = {("init",): InitConfig, ("reconstruct",): ReconstructConfig, ("render",): RenderConfig,
            ("poses",): PosesConfig, ("buffers",): BuffersConfig, ("buffernet", "train"): TrainConfig}


def test_generated_schemas_are_current():
    stale = [name for name, s in generated_schemas().items()
             if not (SCHEMAS / name).is_file() or (SCHEMAS / name).read_text() != schema_text(s)]
    assert not stale, f"{stale} are stale: run python -m stages.config --write-schemas"


def _section(config: dict, path: tuple[str, ...]):
    for key in path:
        config = config.get(key, {})
    return config


def _assert_agrees(values: dict, cls, where: str):
    """Every key of ``values`` is a field of ``cls`` with that default (nested sections recursively)."""
    hints = {f.name: f for f in dataclasses.fields(cls)}
    reference = defaults(cls)
    for key, value in values.items():
        assert key in hints, f"{where}.{key} is not a field of {cls.__name__}"
        if isinstance(value, dict) and dataclasses.is_dataclass(getattr(cls(), key)):
            _assert_agrees(value, type(getattr(cls(), key)), f"{where}.{key}")
        else:
            assert value == reference[key], f"{where}.{key}: default.yaml says {value!r}, {cls.__name__} {reference[key]!r}"


# buffernet.train in default.yaml is the workflow's own CPU-sized training run (TrainConfig's defaults are the
# paper's recipe, used by hand runs): choices, not defaults; the generated schema still checks their types / limits
@pytest.mark.parametrize("path", [p for p in SECTIONS if p != ("buffernet", "train")], ids=".".join)
def test_default_yaml_is_the_dataclass_defaults(path):
    cls = SECTIONS[path]
    _assert_agrees(_section(read_yaml(CONFIGS / "default.yaml"), path), cls, ".".join(path))


@pytest.mark.parametrize("cls", SECTIONS.values(), ids=lambda c: c.__name__)
def test_defaults_round_trip_through_the_schema(cls):
    """The defaults validate against the generated schema and read back equal (nested sections included)."""
    values = defaults(cls)
    if cls is TrainConfig:
        values["data"] = ["captures:x"]
    assert to_dict(cls.from_dict(values)) == values


def test_every_scene_and_preset_builds_its_sections():
    for scene in known("scenes"):  # every preset on every kind of scene (ci on photos: its sizes, no synth:)
        for presets in ([], *[[p] for p in known("presets")]):
            config = load_config(scene, presets=presets)
            for path, cls in SECTIONS.items():
                section = _section(config, path)
                if path == ("buffernet", "train"):
                    section = {**section, "data": ["captures:x"]}
                if path == ("poses",) and not section:
                    continue
                cls.from_dict(section)


def test_unused_top_level_threads_is_gone():
    assert "threads" not in read_yaml(CONFIGS / "default.yaml")
    with pytest.raises(ValueError):  # neither at the top level of reconstruct (now tracer.num_threads)
        ReconstructConfig.from_dict({"threads": 2})


def test_schema_and_messages_follow_the_dataclass():
    @dataclass
    class Example:
        """An example section."""

        count: int = setting(3, "how many", minimum=1)
        mode: str = setting("a", "which", enum=["a", "b"])
        tracer: TracerConfig = setting(default_factory=TracerConfig, doc="nested")
        threads: int = setting(2, "runtime", runtime=True, minimum=1)

    s = schema(Example)
    assert s["properties"]["count"] == {"type": "integer", "minimum": 1, "description": "how many"}
    assert s["properties"]["tracer"]["properties"]["kernel_p"]["minimum"] == 1
    assert "threads" not in schema(Example, runtime=False)["properties"]
    assert "num_threads" not in schema(Example, runtime=False)["properties"]["tracer"]["properties"]
    built = from_dict(Example, {"count": 5, "tracer": {"kernel_p": 2}}, "example")
    assert built.count == 5 and built.tracer == TracerConfig(kernel_p=2)
    assert "threads" not in to_dict(built, runtime=False) and "num_threads" not in to_dict(built, runtime=False)["tracer"]
    for bad, message in (({"count": 0}, "example.count must be >= 1, got 0"),
                         ({"mode": "c"}, "example.mode must be one of a, b, got 'c'"),
                         ({"count": "3"}, "example.count must be of type integer, got str '3'"),
                         ({"tracer": {"kernel": 2}}, "unknown example.tracer option(s) ['kernel']"),
                         ({"cont": 1}, "unknown example option(s) ['cont']; known: ")):
        with pytest.raises(ValueError) as e:
            from_dict(Example, bad, "example")
        assert str(e.value).startswith(message), (str(e.value), message)


def test_moved_tracer_options_say_where_they_went():
    with pytest.raises(ValueError, match="reconstruct.kernel_p is now reconstruct.tracer.kernel_p"):
        ReconstructConfig.from_dict({"kernel_p": 2})
    assert ReconstructConfig.from_dict({"tracer": {"kernel_p": 2}}).tracer.kernel_p == 2


def test_top_level_typos_are_refused_with_a_suggestion():
    from stages.config import ConfigError

    for typo, meant in (("presset", "presets"), ("reconstuct", "reconstruct")):
        with pytest.raises(ConfigError, match=rf"unknown top-level option\(s\) \['{typo}'\].*did you mean '{meant}'"):
            load_config("demo", overrides={typo: "ci" if typo == "presset" else {"iterations": 200}})


def test_command_line_strings_are_coerced_by_the_schema():
    """Snakemake hands nested --config values over as strings: they take the schema's types."""
    from stages.config import ConfigError

    config = load_config("demo", overrides={"reconstruct": {"iterations": "200", "warmup": "20",
                                                            "tracer": {"kernel_p": "2", "max_replay_capacity": "null",
                                                                       "window": "2.5"}},
                                            "render": {"denoise": "false"}, "buffernet": {"train": {"iterations": "7"}}})
    assert config["reconstruct"]["iterations"] == 200 and config["reconstruct"]["tracer"] == \
        {"kernel_p": 2, "max_replay_capacity": None, "window": 2.5}
    assert config["render"]["denoise"] is False and config["buffernet"]["train"]["iterations"] == 7
    ReconstructConfig.from_dict(config["reconstruct"])
    with pytest.raises(ConfigError, match="reconstruct.iterations must be >= 1, got -5"):
        load_config("demo", overrides={"reconstruct": {"iterations": "-5"}})
    with pytest.raises(ConfigError, match="reconstruct.iterations must be of type integer, got str 'many'"):
        load_config("demo", overrides={"reconstruct": {"iterations": "many"}})


def test_config_json_by_hand_is_validated_like_the_workflow(tmp_path, capsys):
    from stages.reconstruct.__main__ import main

    rc = main(["--config-json", '{"iterations": -5}', "--capture", str(tmp_path), "--init", str(tmp_path / "p.ply"),
               "--out", str(tmp_path / "model")])
    assert rc != 0 and "reconstruct.iterations must be >= 1, got -5" in capsys.readouterr().err
    assert not (tmp_path / "model").exists()


def test_preset_applies_without_a_scene():
    """By hand, `--preset fast` without `--scene` gives the fast schedule (it used to be ignored silently), and is
    refused beside --config-json (which is the whole section)."""
    import argparse

    from stages.cli import add_config_args, load_section

    parser = argparse.ArgumentParser()
    add_config_args(parser, "reconstruct")
    fast = read_yaml(CONFIGS / "presets" / "fast.yaml")["reconstruct"]
    section = load_section(parser.parse_args(["--preset", "fast"]), "reconstruct")
    assert {k: section[k] for k in fast} == fast  # the defaults, the preset over them
    assert load_section(parser.parse_args([]), "reconstruct") == {}
    with pytest.raises(ValueError, match="unknown preset 'nope'; known presets: ci, fast"):
        load_section(parser.parse_args(["--preset", "nope"]), "reconstruct")
    with pytest.raises(ValueError, match="--preset fast cannot be combined with --config-json"):
        load_section(parser.parse_args(["--preset", "fast", "--config-json", "{}"]), "reconstruct")
