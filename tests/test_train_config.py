"""TrainConfig with typed planner / loss configs, serialised as config.json always had them."""

from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path

import pytest
import torch

from mapkit._choices import PRESET_NAMES, TRAINED_WEIGHTS
from mapkit.planner import LossConfig, PlannerConfig, PlannerError, PlannerNet
from mapkit.planner._loss import REMOVED_FIELDS as REMOVED_LOSS_FIELDS
from mapkit.train import PRESETS, TrainConfig, TrainConfigError, preset
from mapkit.train._config import REMOVED_FIELDS

PRETRAINED = Path(__file__).resolve().parents[1] / "mapkit" / "flight" / "pretrained"

OLD_CONFIG = {  # a config.json's options as the code before typed nested configs wrote them
    "name": "cpu", "preset": "cpu", "epochs": 8, "batch_size": 16, "lr": 0.0005, "weight_decay": 0.0, "seed": 0,
    "device": "cpu", "max_steps": None, "val_batches": None, "goals_together": True, "grad_clip": 10.0,
    "corridor": None, "init": None, "only": "all",
    "planner": {"input_size": [96, 160], "encoder_width": 0.25, "num_candidates": 8, "head_activation": "leaky_relu",
                "depth_check": True, "velocity_input": True, "num_keypoints": 5},
    "loss": {"obstacle_softness": 0.3, "time_target_iters": 5, "score_temperature": 0.5, "robot_radius": 0.3},
}


def test_an_old_config_dict_loads_typed_and_writes_back_unchanged() -> None:
    config = TrainConfig.from_saved(OLD_CONFIG)
    assert isinstance(config.planner, PlannerConfig) and isinstance(config.loss, LossConfig)
    assert config.planner.input_size == (96, 160) and config.planner.num_candidates == 8
    assert config.loss.obstacle_softness == 0.3 and config.loss.gamma_time == LossConfig().gamma_time
    # Fields named at their default value (num_keypoints, robot_radius) stay named, in their order.
    assert json.dumps(config.to_dict()) == json.dumps({k: v for k, v in OLD_CONFIG.items() if k not in REMOVED_FIELDS})


def test_round_trip_and_fields_changed_in_python_are_written() -> None:
    config = preset("cpu", name="x", planner={"input_size": [48, 64]}, loss={"robot_radius": 0.35})
    again = TrainConfig.from_dict(config.to_dict())
    assert again == config and again.to_dict() == config.to_dict()
    changed = dataclasses.replace(config, planner=dataclasses.replace(config.planner, num_keypoints=7))
    assert changed.to_dict()["planner"]["num_keypoints"] == 7
    direct = TrainConfig(planner=PlannerConfig(num_keypoints=3))
    assert direct.to_dict()["planner"] == {"num_keypoints": 3} and direct.to_dict()["loss"] == {}


def test_presets_are_written_as_before() -> None:
    assert PRESETS["paper"].to_dict()["planner"] == {"input_size": [360, 640], "encoder_width": 1.0}
    assert list(PRESETS["cpu"].to_dict()["planner"]) == ["input_size", "encoder_width", "num_candidates",
                                                         "head_activation", "depth_check", "velocity_input"]
    assert PRESETS["cpu"].to_dict()["loss"] == {"obstacle_softness": 0.3, "time_target_iters": 5,
                                                "score_temperature": 0.5}


def test_the_shipped_models_config_loads_and_fits_its_weights() -> None:
    saved = json.loads((PRETRAINED / "config.json").read_text())
    config = TrainConfig.from_saved(saved)
    assert config.to_dict()["planner"] == saved["planner"] and config.to_dict()["loss"] == saved["loss"]
    assert config.planner == PlannerConfig.from_dict(saved["planner_resolved"])
    model = torch.load(PRETRAINED / "model.pt", map_location="cpu", weights_only=True)
    PlannerNet(config.planner).load_state_dict(model["state_dict"])  # strict: every weight fits


def test_a_saved_config_with_removed_loss_fields_at_their_old_behaviour_loads() -> None:
    saved = json.loads((PRETRAINED / "config.json").read_text())
    old = {**saved, "loss": {**saved["loss"], **REMOVED_LOSS_FIELDS, "detour_cap": 3.0}}  # no weight: the cap is moot
    assert TrainConfig.from_saved(old) == TrainConfig.from_saved(saved)
    radius = {**saved, "loss": {**saved["loss"], "robot_radius": 0.4, "collision_distance": 0.4}}
    assert TrainConfig.from_saved(radius).loss.robot_radius == 0.4  # the label's distance was the radius
    older = {**saved, **REMOVED_FIELDS, "planner": {**saved["planner"], "candidate_anchors": [], "extra": {"a": 1}}}
    assert TrainConfig.from_saved(older) == TrainConfig.from_saved(saved)


@pytest.mark.parametrize(("table", "name", "value"), [("", "grad_clip", None), ("", "weight_decay", 1e-4),
                                                    ("planner", "candidate_anchors", [[1.0, 0.0]]),
                                                    ("planner", "keypoint_init_scale", 0.1)])
def test_a_saved_config_with_a_removed_option_in_use_is_refused(table: str, name: str, value: object) -> None:
    saved = json.loads((PRETRAINED / "config.json").read_text())
    old = {**saved, table: {**saved[table], name: value}} if table else {**saved, name: value}
    with pytest.raises(TrainConfigError, match=rf"^{table + ' ' if table else ''}{name}=.*: the field was removed"):
        TrainConfig.from_saved(old)
    if table:  # a saved model's planner config likewise
        with pytest.raises(PlannerError, match=rf"^planner {name}=.*: the field was removed"):
            PlannerConfig.from_dict({**saved["planner_resolved"], name: value})


@pytest.mark.parametrize(("name", "value"), [("detour_weight", 2.0), ("eta_horizon", 2.5), ("eta_label", "seen"),
                                           ("eta_positive_weight", 4.0), ("collision_distance", 0.5),
                                           ("obstacle_reduction", "sum"), ("smoothness_on", "samples")])
def test_a_saved_config_with_a_removed_loss_field_in_use_is_refused(name: str, value: object) -> None:
    saved = json.loads((PRETRAINED / "config.json").read_text())
    with pytest.raises(TrainConfigError, match=rf"^loss {name}=.*: the field was removed in mapkit 0\.1\.0 \(issue 57\)") as exc:
        TrainConfig.from_saved({**saved, "loss": {**saved["loss"], name: value}})
    assert "\n" not in str(exc.value)


def test_a_removed_loss_field_on_the_command_line_is_unknown(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from mapkit.cli.main import main

    r = CliRunner().invoke(main, ["train", "-w", str(tmp_path), "--set", "loss.detour_weight=0"])
    assert r.exit_code == 2 and "has no setting 'loss.detour_weight'" in r.output, r.output
    assert "`mapkit config train` lists every one" in r.output and "Traceback" not in r.output
    with pytest.raises(TrainConfigError, match="has no field 'detour_weight'"):
        TrainConfig.from_dict({"loss": {"detour_weight": 0.0}})  # removed fields load from saved runs only


def test_a_non_object_nested_config_is_one_line() -> None:
    with pytest.raises(TrainConfigError, match="planner: expected PlannerConfig fields"):
        TrainConfig.from_dict({"planner": [1, 2]})


def test_choices_are_the_librarys() -> None:
    from mapkit._choices import VEHICLES
    from mapkit.evaluation import EvalConfig

    assert set(PRESET_NAMES) == set(PRESETS)
    assert TRAINED_WEIGHTS == typing.get_args(typing.get_type_hints(TrainConfig)["only"])
    assert VEHICLES == typing.get_args(typing.get_type_hints(EvalConfig)["vehicle"])
