"""Options from the typed configs: few options per command, every other field a setting (`--config
FILE.toml`, `--set KEY=VALUE`, `mapkit config COMMAND`), one default per field, commands in pipeline order."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import click
import pytest
from click.testing import CliRunner

from mapkit.cli._config import SPECS, FieldOption, read_settings, render
from mapkit.cli.main import main
from mapkit.errors import MapkitError

OPTION_LINE = "  -"  # how click's --help starts an option's line (as `grep -cE "^  -"` counts them)


def _commands() -> dict[str, click.Command]:
    """Every command by its path below `mapkit` (`eval`, `lab tune-timing`)."""
    found: dict[str, click.Command] = {}
    for name, command in main.commands.items():
        if isinstance(command, click.Group):
            found.update({f"{name} {sub}": c for sub, c in command.commands.items()})
        else:
            found[name] = command
    return found


@pytest.mark.parametrize("path", sorted(_commands()))
def test_no_command_shows_more_than_20_options_and_eval_at_most_15(path: str):
    r = CliRunner().invoke(main, [*path.split(), "--help"], prog_name="mapkit", terminal_width=200)
    assert r.exit_code == 0, r.output
    shown = [line for line in r.output.splitlines() if line.startswith(OPTION_LINE)]
    assert len(shown) <= (15 if path == "eval" else 20), shown


def test_mapkit_help_lists_the_commands_in_pipeline_order():
    r = CliRunner().invoke(main, ["--help"], prog_name="mapkit")
    listed = [line.split()[0] for line in r.output.split("Commands:\n")[1].splitlines() if line.startswith("  ")]
    assert listed == ["info", "ingest", "fuse", "fuse-world", "esdf", "slice", "export", "batch", "simulate", "dataset",
                      "train", "eval", "plan", "fly", "replay", "view", "export-foxglove", "export-rerun", "copy-store",
                      "config", "lab"]
    lab = CliRunner().invoke(main, ["lab", "--help"], prog_name="mapkit").output
    assert "the shipped recipe runs them for you" in lab and "mapkit train --recipe" in lab
    assert [line.split()[0] for line in lab.split("Commands:\n")[1].splitlines()] == ["tune-timing", "tune-judge"]


def test_an_option_that_fills_a_field_has_no_default_of_its_own():
    """One place for each default: the dataclass. A field's option is None unless given, and its
    --help shows the dataclass's value."""
    from mapkit.evaluation import EvalConfig

    filling = [(path, p) for path, c in _commands().items() for p in c.params if isinstance(p, FieldOption)]
    assert len(filling) >= 30
    assert [f"{path} {p.opts[0]}" for path, p in filling if p.default is not None] == []
    pairs = next(p for p in main.commands["eval"].params if p.name == "pairs")
    assert pairs.default_text() == str(EvalConfig().pairs)
    r = CliRunner().invoke(main, ["eval", "--help"], terminal_width=200)
    assert f"[default: {EvalConfig().pairs}]" in r.output


@pytest.mark.parametrize("command", sorted(SPECS))
def test_the_printed_settings_read_back_as_the_defaults(command: str, tmp_path: Path):
    """`mapkit config COMMAND` is valid TOML that --config reads back to the defaults, every table."""
    spec = SPECS[command]
    text = CliRunner().invoke(main, ["config", *command.split()]).output
    assert text == render(spec) and text.count(" = ") >= len([e for e in spec.entries.values() if e.table is None])
    path = tmp_path / "c.toml"
    path.write_text(text)
    settings = read_settings(spec, path, ())
    assert settings.file  # every key was read
    for prefix, default in spec.defaults.items():
        assert settings.build(default, table=prefix) == default


class _Stop(MapkitError):
    """Raised by the stand-in for the library call: the command got as far as its config."""


@pytest.fixture
def eval_config(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """`mapkit eval` up to the config it hands the library (which is not run)."""
    import mapkit.evaluation

    seen: dict[str, Any] = {}

    def capture(model: Any, output: Any, config: Any, **kw: Any) -> None:
        seen["config"] = config
        raise _Stop("stopped before flying")

    monkeypatch.setattr(mapkit.evaluation, "evaluate", capture)
    return seen


def _eval(tmp_path: Path, *args: str) -> Any:
    return CliRunner().invoke(main, ["eval", "--methods", "straight", "-o", str(tmp_path / "ev"), *args],
                              prog_name="mapkit")


def test_eval_config_round_trips_through_the_command(eval_config: dict[str, Any], tmp_path: Path):
    """The TOML `mapkit config eval` prints, fed back with --config, flies the defaults."""
    from mapkit.evaluation import EvalConfig

    path = tmp_path / "eval.toml"
    path.write_text(CliRunner().invoke(main, ["config", "eval"]).output)
    r = CliRunner().invoke(main, ["eval", "--config", str(path), "-o", str(tmp_path / "ev")])
    assert r.exit_code == 1 and "stopped before flying" in r.output, r.output
    assert eval_config["config"] == EvalConfig()


def test_set_reaches_nested_fields_and_turns_layers_off(eval_config: dict[str, Any], tmp_path: Path):
    r = _eval(tmp_path, "--set", "loop.pilot.replan_interval=1.0", "--set", "execution.corridor.width=0.75",
              "--set", "execution.memory=none", "--set", "worlds=office,forest", "--set", "execution.shift=[]",
              "--set", "vehicle=rotorpy", "--faults", "0.1,0.05,0.02")
    assert r.exit_code == 1 and "stopped before flying" in r.output, r.output
    config = eval_config["config"]
    assert config.loop.pilot.replan_interval == 1.0 and config.execution.corridor.width == 0.75
    assert config.execution.memory is None and config.execution.shift == () and config.worlds == ("office", "forest")
    assert config.vehicle == "rotorpy" and config.execution.corridor.check is True  # the rest stays
    faults = config.loop.faults
    assert (faults.drop, faults.delay, faults.pose_noise, faults.seed) == (0.1, 0.05, 0.02, config.seed)


def test_precedence_is_defaults_then_config_then_options_then_set(eval_config: dict[str, Any], tmp_path: Path):
    path = tmp_path / "eval.toml"
    path.write_text("pairs = 5\nseed = 7\n[execution.speed]\ncruise = 2.0\n[execution]\nmemory = \"none\"\n")
    assert _eval(tmp_path, "--config", str(path)).exit_code == 1
    config = eval_config["config"]
    assert (config.pairs, config.seed, config.execution.speed.cruise, config.execution.memory) == (5, 7, 2.0, None)
    assert config.execution.speed.v_max == 3.0  # a table sets the fields it names
    _eval(tmp_path, "--config", str(path), "--pairs", "9")
    assert eval_config["config"].pairs == 9  # an option over the file
    _eval(tmp_path, "--config", str(path), "--pairs", "9", "--set", "pairs=11", "--set", "execution.memory.seconds=4")
    config = eval_config["config"]
    assert config.pairs == 11 and config.execution.memory.seconds == 4.0  # --set over both; a layer back on


@pytest.mark.parametrize("args, needles", [
    (["--set", "loop.pilot.replan_intervall=0.5"],
     ["has no setting 'loop.pilot.replan_intervall'", "closest: loop.pilot.replan_interval", "`mapkit config eval`"]),
    (["--set", "replan_interval=0.5"], ["closest: loop.pilot.replan_interval"]),
    (["--set", "pairs=many"], ["pairs takes an integer, got \"many\"", "(e.g. pairs = 60)"]),
    (["--set", "execution.corridor.check=maybe"], ["execution.corridor.check takes true or false"]),
    (["--set", "execution.speed.cruise=inf"], ["execution.speed.cruise takes a finite number or \"none\""]),
    (["--set", "vehicle=boat"], ['vehicle takes one of "tracker", "rotorpy"']),
    (["--set", "execution.corridor=none"], ["execution.corridor is a table of settings (width, check"]),
    (["--set", "pairs"], ["--set 'pairs': expected KEY=VALUE"]),
    (["--set", "record_plans=true"], ["has no setting 'record_plans'"]),  # research-only
])
def test_a_bad_setting_is_a_usage_error_naming_it(tmp_path: Path, args: list[str], needles: list[str]):
    r = _eval(tmp_path, *args)
    lines = r.output.strip().splitlines()
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: mapkit eval: "), r.output
    assert all(n in lines[0] for n in needles), lines[0]
    assert not (tmp_path / "ev").exists()


def test_a_bad_config_file_is_a_usage_error_naming_the_file_and_key(tmp_path: Path):
    path = tmp_path / "bad.toml"
    path.write_text("[loop.pilot]\nreplan_interval = 0.5\nhorizn = 6\n")
    r = _eval(tmp_path, "--config", str(path))
    assert r.exit_code == 2 and f"--config {path}: mapkit eval has no setting 'loop.pilot.horizn'" in r.output
    assert "closest: loop.pilot.horizon" in r.output
    path.write_text("pairs = [1\n")
    r = _eval(tmp_path, "--config", str(path))
    assert r.exit_code == 2 and "not TOML" in r.output and "Traceback" not in r.output


def test_train_settings_reach_the_preset_and_its_nested_configs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    import mapkit.train

    seen: dict[str, Any] = {}

    def capture(workspaces: Any, config: Any, **kw: Any) -> None:
        seen["config"] = config
        raise _Stop("stopped before training")

    monkeypatch.setattr(mapkit.train, "train", capture)
    r = CliRunner().invoke(main, ["train", "-w", str(tmp_path), "--epochs", "2", "--set", "planner.accel=1.5",
                                  "--set", "planner.tan_hidden=256,256,256", "--set", "loss.gamma_time=0",
                                  "--set", "lr=2e-4", "--set", "max_steps=3"])
    assert r.exit_code == 1 and "stopped before training" in r.output, r.output
    config = seen["config"]
    want = mapkit.train.preset("cpu", name="cpu", epochs=2, lr=2e-4, max_steps=3,
                               planner={"accel": 1.5, "tan_hidden": [256, 256, 256]}, loss={"gamma_time": 0.0})
    assert config == want and config.to_dict() == want.to_dict()
    assert dataclasses.asdict(config.planner)["encoder_width"] == 0.25  # the preset's, untouched
    r = CliRunner().invoke(main, ["train", "--recipe", "pretrained", "-o", str(tmp_path / "r"), "--set", "lr=1"])
    assert r.exit_code == 2 and "a recipe declares the settings" in r.output


def test_config_of_an_unknown_command_names_the_ones_with_settings():
    r = CliRunner().invoke(main, ["config", "slice"], prog_name="mapkit")
    assert r.exit_code == 2 and "'slice' is not a command with settings" in r.output and "eval" in r.output
    assert CliRunner().invoke(main, ["config", "tune-timing"]).output == render(SPECS["lab tune-timing"])
