"""The CLI is generated from the config dataclasses: every field of the trainer's, each model's and each
stage's config is an option (nested configs nested), its help is the attribute docstring, presets are defaults."""

import argparse
import dataclasses
import typing
import warnings

import pytest
import tyro

from nerfpipe.cli import main
from nerfpipe.commands.mesh import MeshCommand
from nerfpipe.commands.render import RenderCommand
from nerfpipe.commands.run import run_command_type, stage_command_type
from nerfpipe.commands.train import command_type
from nerfpipe.mesh.pipeline import MeshConfig
from nerfpipe.mesh.trained import RenderedViews
from nerfpipe.models.registry import models, presets
from nerfpipe.outputs.novel_views import RenderConfig
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


def other_value(kind, default):
    """A valid value of type ``kind`` other than ``default``, and its command-line words after the option."""
    if kind is bool:
        return not default, []
    if typing.get_origin(kind) is typing.Literal:
        value = next(c for c in typing.get_args(kind) if c != default)
        return value, [value]
    if default is None:  # "int | None", "float | None": a value inside every such field's range
        kind = next(a for a in typing.get_args(kind) if a is not type(None))
        default = 5000 if kind is int else 0.5
        return default, [str(default)]
    value = default + 1 if kind is int else default / 2
    return value, [str(value)]


def every_field_changed(config, prefix: str = "", given: "dict | None" = None) -> "tuple[dict, list[str]]":
    """Every field of ``config`` at another value (``given``'s for text fields), and the ``--prefix.field VALUE``
    words that set them."""
    values, argv = {}, []
    for name, kind in typing.get_type_hints(type(config)).items():
        value, words = (given[name], [given[name]]) if name in (given or {}) else other_value(kind, getattr(config, name))
        option = prefix + name.replace("_", "-")
        assert value != getattr(config, name), name  # every field is moved off its default
        values[name] = value
        argv += ([f"--{option}"] if value else [f"--{prefix}no-{name.replace('_', '-')}"]) if kind is bool else [f"--{option}", *words]
    return values, argv


@pytest.mark.parametrize("command, groups", [
    (MeshCommand, {"mesh": ("", MeshConfig(), {}), "views": ("views.", RenderedViews(), {})}),
    (RenderCommand, {"render": ("", RenderConfig(), {"path": "test", "size": "64x48"})}),
])
def test_every_mesh_and_render_field_is_an_option_that_reaches_the_config(command, groups):
    """nerfpipe mesh: MeshConfig's fields as --FIELD, RenderedViews' as --views.FIELD; nerfpipe render:
    RenderConfig's as --FIELD. Each set to a value other than its default lands in the parsed config."""
    parsed = bare(parser_options(get_parser(command)))
    for prefix, config, _ in groups.values():
        expected = leaf_options(config, prefix)
        assert expected <= parsed, sorted(expected - parsed)
    argv, changed = ["RUN"], {}
    for attr, (prefix, config, given) in groups.items():
        values, words = every_field_changed(config, prefix, given)
        changed[attr], argv = dataclasses.replace(config, **values), argv + words
    cmd = tyro.cli(command, args=argv)
    for attr, expected in changed.items():
        assert getattr(cmd, attr) == expected, attr
    assert str(cmd.run_dir) == "RUN" and {"--device"} <= parsed


def test_mesh_and_run_name_the_mesh_options_alike():
    """nerfpipe run --mesh.mesh.X is nerfpipe mesh --X and --mesh.views.Y is --views.Y."""
    mesh = bare(parser_options(get_parser(MeshCommand)))
    run = {o.removeprefix("--mesh.") for o in bare(parser_options(get_parser(run_command_type(stages(), {})))) if o.startswith("--mesh.")}
    assert {"--" + o.removeprefix("mesh.") for o in run if o.startswith("mesh.")} | {"--" + o for o in run if o.startswith("views.")} <= mesh
    assert {"--out", "--device", "--threads"} <= mesh and "--tsdf-views" not in mesh


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


@pytest.mark.parametrize("argv", [["train", "--help"], ["train", "--model", "vanilla", "--help"], ["stage", "mesh", "--help"], ["run", "--help"], ["--help"],
                                  ["mesh", "--help"], ["render", "--help"]])
def test_help_reads_as_plain_text(argv, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit) as done:
        main(argv)
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "usage: nerfpipe" in out and "``" not in out and ":class:`" not in out and ":func:`" not in out
