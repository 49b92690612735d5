"""The CLI is generated from the config dataclasses: every field of the trainer's, each model's and each
stage's config is an option (nested configs nested), its help is the attribute docstring, presets are defaults."""

import argparse
import dataclasses
import typing
import warnings

import pytest
import tyro

from nerfpipe.cli import main
from nerfpipe.commands.run import run_command_type, stage_command_type
from nerfpipe.commands.train import command_type
from nerfpipe.models.registry import models, presets
from nerfpipe.pipeline.stages import stages
from nerfpipe.training.trainer import TrainerConfig


def leaf_options(config: object, prefix: str = "") -> "set[str]":
    """``--a.b-c`` for every field of a config dataclass, walking nested config dataclasses (their prefix)."""
    out = set()
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        name = prefix + f.name.replace("_", "-")
        if dataclasses.is_dataclass(value):
            out |= leaf_options(value, name + ".")
        else:
            out.add("--" + name)
    return out


def parser_options(parser: argparse.ArgumentParser) -> "set[str]":
    """Every option string of a parser and its subcommands (booleans also as ``--no-...``)."""
    found = set()
    for action in parser._actions:
        found |= set(action.option_strings)
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found |= parser_options(sub)
    return found


def get_parser(cls) -> argparse.ArgumentParser:
    with warnings.catch_warnings():  # deprecated in tyro 1.0 without a replacement that lists the options
        warnings.simplefilter("ignore", DeprecationWarning)
        return tyro.extras.get_parser(cls)


def bare(options: "set[str]") -> "set[str]":
    return {o for o in options if not o.startswith("--no-") and ".no-" not in o}


@pytest.mark.parametrize("model", sorted(models()))
def test_every_trainer_and_model_field_is_an_option(model):
    spec = models()[model]
    parsed = bare(parser_options(get_parser(command_type(model))))
    expected = leaf_options(TrainerConfig()) | {"--model." + o[2:] for o in leaf_options(spec.config())}
    assert expected <= parsed, sorted(expected - parsed)
    assert {"--model", "--out"} <= parsed


def test_every_stage_field_is_an_option():
    registry = stages()
    members = {typing.get_args(m)[0].stage_name: typing.get_args(m)[0] for m in typing.get_args(stage_command_type(registry, {}))}
    assert set(members) == set(registry)
    for name, spec in registry.items():
        parsed = bare(parser_options(get_parser(members[name])))
        expected = leaf_options(spec.config())
        assert expected <= parsed, (name, sorted(expected - parsed))


def test_every_stage_field_is_an_option_of_run():
    registry = stages()
    parsed = bare(parser_options(get_parser(run_command_type(registry, {}))))
    for name, spec in registry.items():
        expected = {f"--{name}.{o[2:]}" for o in leaf_options(spec.config())}
        assert expected <= parsed, (name, sorted(expected - parsed))


def test_run_options_change_a_pipeline_files_values(tmp_path):
    from nerfpipe.commands.run import _pipeline

    (tmp_path / "pipe.toml").write_text('stages = ["load", "render"]\n[render]\nframes = 7\nfps = 5.0\n')
    registry = stages()
    defaults = dict(_pipeline(None, tmp_path / "pipe.toml", registry).configs)
    cmd = tyro.cli(run_command_type(registry, defaults), args=["DATA", "--pipeline", str(tmp_path / "pipe.toml"), "--render.fps", "9",
                                                              "--train.model-options", '{"levels": [16, 32]}'])
    assert (cmd.render.frames, cmd.render.fps) == (7, 9.0) and cmd.train.model_options == {"levels": [16, 32]}


def test_nested_options_and_presets_reach_the_configs():
    cmd = tyro.cli(command_type("fast-small"), args=["DATA", "--model", "fast-small", "--model.occupancy.resolution", "32", "--iters", "7"])
    assert cmd.model_options.preset == "small" and cmd.model_options.occupancy.resolution == 32
    assert cmd.trainer.iters == 7 and cmd.trainer.rays_per_step == presets()["fast-small"].trainer["rays_per_step"]
    vanilla = tyro.cli(command_type("vanilla"), args=["DATA", "--model", "vanilla", "--model.num-samples", "8"])
    assert vanilla.model_options.num_samples == 8 and type(vanilla.model_options) is type(models()["vanilla"].config())


def test_unknown_model_is_one_line(capsys):
    assert main(["train", "DATA", "--model", "nosuch"]) == 2
    err = capsys.readouterr().err
    assert "nosuch" in err and "fast-small" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("argv", [["train", "--help"], ["train", "--model", "vanilla", "--help"], ["stage", "mesh", "--help"], ["run", "--help"], ["--help"]])
def test_help_reads_as_plain_text(argv, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit) as done:
        main(argv)
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "usage: nerfpipe" in out and "``" not in out and ":class:`" not in out and ":func:`" not in out
