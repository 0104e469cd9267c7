"""Recipes (`mapkit train --recipe`): the shipped recipe reads, its miniature runs end to end and
resumes, and bad recipes are refused in one line naming the fix."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mapkit.recipe import RECIPES, FlightsStep, RecipeError, load_recipe, parse_recipe, run_recipe

DATASET = {"kind": "dataset", "name": "w", "worlds": 2, "seed": 1}
TRAIN = {"kind": "train", "name": "m", "dataset": "w", "val_worlds": 1}


def test_the_shipped_recipe_reads_and_declares_every_stage():
    recipe = load_recipe("pretrained")
    kinds = [type(s).__name__ for s in recipe.steps]
    for kind in ("DatasetStep", "TrainStep", "ConfigureStep", "FlightsStep", "TuneTimingStep", "TuneJudgeStep"):
        assert kind in kinds
    assert recipe.model == recipe.steps[-1].name
    assert (Path(__file__).resolve().parents[1] / "mapkit" / RECIPES["pretrained"]).is_file()


@pytest.mark.parametrize(("data", "message"), [
    ({"model": "m", "step": [DATASET, {**TRAIN, "epochs": 3}]}, "unknown field 'epochs'; valid fields: .*options"),
    ({"model": "m", "step": [DATASET, {**TRAIN, "kind": "fit"}]}, "kind 'fit'; use one of dataset, train"),
    ({"model": "m", "step": [{**TRAIN}]}, "reads 'w', which is not an earlier DatasetStep"),
    ({"model": "w", "step": [DATASET]}, "model = 'w' must name a step that makes a model"),
    ({"model": "m", "step": [DATASET, DATASET, TRAIN]}, "two steps are named 'w'"),
    ({"model": "m", "step": [{"kind": "dataset", "name": "w"}, TRAIN]}, "lacks a field; required: name, worlds, seed"),
    ({"model": "m", "stages": []}, "unknown field 'stages'"),
])
def test_bad_recipes_are_refused_in_one_line(data: dict, message: str):
    with pytest.raises(RecipeError, match=message) as info:
        parse_recipe(data)
    assert "\n" not in str(info.value)


def test_an_unknown_recipe_name_lists_the_valid_ones(tmp_path: Path):
    with pytest.raises(RecipeError, match=r"use one of pretrained or a \.toml file"):
        load_recipe("pretrainde")
    bad = tmp_path / "r.toml"
    bad.write_text("name = [")
    with pytest.raises(RecipeError, match="not TOML"):
        load_recipe(bad)


def test_an_unknown_option_of_a_stage_names_the_valid_fields(tmp_path: Path):
    recipe = parse_recipe({"model": "m", "step": [{**DATASET, "options": {"durations": 4.0}}, TRAIN]})
    with pytest.raises(RecipeError, match=r"DatasetConfig has no field 'durations'; valid: .*duration"):
        run_recipe(recipe, tmp_path / "out", progress=False)


def _in_the_office(recipe):
    """``recipe`` with its flights in the office world: the same steps, each evaluation about half as
    long as in the forest (fewer obstacles to simulate and to draw in the report)."""
    steps = tuple(replace(s, options={**s.options, "worlds": ["office"]}) if isinstance(s, FlightsStep) else s
                  for s in recipe.steps)
    return replace(recipe, steps=steps)


@pytest.mark.slow
def test_the_miniature_of_the_shipped_recipe_runs_resumes_and_flies(tmp_path: Path):
    from mapkit.flight import Pilot, VehicleState

    out = tmp_path / "made"
    mini = _in_the_office(load_recipe("pretrained").miniature())
    first = run_recipe(mini, out, progress=False)
    assert first.steps_run == [s.name for s in mini.steps]
    for name in ("model.pt", "config.json", "recipe.toml", "recipe.json"):
        assert (out / name).is_file()
    assert json.loads((out / "config.json").read_text())["judge_tune"]  # the last step's record
    # resumes: a finished run does nothing again; a step not marked done runs again, alone
    state = json.loads((out / "recipe.json").read_text())
    del state["done"]["head"]
    (out / "recipe.json").write_text(json.dumps(state))
    again = run_recipe(mini, out, progress=False)
    assert again.steps_run == ["head"] and len(again.steps_skipped) == len(mini.steps) - 1
    # another mapkit version refuses to resume unless forced
    state = json.loads((out / "recipe.json").read_text())
    (out / "recipe.json").write_text(json.dumps({**state, "mapkit": "0.0.0"}))
    with pytest.raises(RecipeError, match=r"started by mapkit 0\.0\.0.*--force"):
        run_recipe(mini, out, progress=False)
    assert run_recipe(mini, out, force=True, progress=False).steps_run == []
    # the result is a model the pilot flies
    pilot = Pilot.load(out)
    cam = pilot.camera
    assert cam is not None
    T_world_body = np.eye(4)
    T_world_body[2, 3] = 1.5
    step = pilot.step(0.0, VehicleState([0.0, 0.0, 1.5]), np.array([8.0, 0.0, 1.5]),
                      np.full((cam.height, cam.width), 6.0, np.float32), T_world_body=T_world_body)
    assert step.replanned and step.plan is not None


@pytest.mark.parametrize(("args", "message"), [
    (["--recipe", "pretrainde", "-o", "x"], "use one of pretrained or a .toml file"),
    (["--recipe", "pretrained"], "--recipe and -o go together"),
])
def test_the_cli_refuses_a_bad_recipe_as_a_usage_error(tmp_path: Path, args: list[str], message: str):
    from click.testing import CliRunner

    from mapkit.cli.main import main

    result = CliRunner().invoke(main, ["train", *args])
    assert result.exit_code == 2 and message in result.output


def test_the_eta_scales_the_estimates_by_the_pace_of_the_finished_steps():
    from mapkit.recipe._run import _eta

    recipe = parse_recipe({"model": "m", "step": [{**DATASET, "minutes": 10}, {**TRAIN, "minutes": 5}]})
    state = {"done": {"w": {"seconds": 1200.0}}}  # 20 min where 10 were expected: twice as slow
    assert _eta(recipe, state, 1, 60.0).endswith("ETA 10 min")
    assert _eta(recipe, {"done": {}}, 0, 0.0).endswith("ETA 15 min")
