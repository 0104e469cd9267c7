"""Flight stacks and ablations in `mapkit eval`: stacks, runs and labels, the untrained and
straight-key-point methods, paired differences with bootstrap intervals (analytic answers), and an
ablation run end to end through the CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from mapkit._formats import EpisodeRecord
from mapkit.cli.main import main
from mapkit.evaluation import (
    EvalConfig,
    EvalError,
    Run,
    ablation,
    evaluate,
    paired_ratio,
    parse_stacks,
    plan_runs,
    split_label,
    success_difference,
    untrained_copy,
)
from mapkit.evaluation._ablation import ablation_lines
from mapkit.flight import Execution, under_stack
from mapkit.planner import PlannerNet, planner_preset


# ------------------------------------------------------------------------------ stacks and runs
def test_stack_none_turns_off_exactly_the_layers_around_the_planner():
    full = Execution()
    none = under_stack(full, "none")
    assert under_stack(full, "full") is full
    changed = {f.name for f in dataclasses.fields(Execution) if getattr(full, f.name) != getattr(none, f.name)}
    assert changed == {"memory", "route", "corridor", "follow", "keep_choice", "shift", "flown_judge"}
    assert none.flown_judge and not full.flown_judge  # without the stack the model's own flown-path head gates
    assert none.memory is None and none.route is None and none.follow == 0.0 and none.keep_choice is None
    assert none.shift == () and len(full.shift) > 0
    assert not none.corridor.check and not none.corridor.check_memory
    # the corridor's widths, the pace and the limits stay; unchecked, it flies at its unchecked width
    assert none.corridor.width == full.corridor.width and none.speed == full.speed
    assert none.corridor.widest(False) == full.corridor.unchecked_width < full.corridor.widest(True)


def test_every_stacked_method_flies_under_every_stack_and_the_others_once():
    runs = plan_runs(("learned", "untrained", "straight", "oracle"), ("full", "none"))
    assert [r.label for r in runs] == ["learned", "learned@none", "untrained", "untrained@none", "straight", "oracle"]
    for r in runs:
        assert split_label(r.label) == r
    assert Run("oracle", None).label == "oracle" and split_label("iplanner-style@none") == Run("iplanner-style", "none")
    with pytest.raises(ValueError, match="unknown flight stack 'lots'"):
        split_label("learned@lots")


def test_untrained_flies_each_of_several_initial_weights_as_its_own_run():
    runs = plan_runs(("learned", "untrained"), ("full", "none"), (0, 5))
    assert [r.label for r in runs] == ["learned", "learned@none", "untrained#0", "untrained#5", "untrained#0@none",
                                       "untrained#5@none"]
    for r in runs:
        assert split_label(r.label) == r
    assert runs[4].init_seed == 0 and runs[4].pooled == "untrained@none" and runs[1].pooled == "learned@none"
    # one seed: the plain label, as before
    assert [r.label for r in plan_runs(("untrained",), ("none",), (7,))] == ["untrained@none"]
    with pytest.raises(ValueError, match="'x' that is not a whole number"):
        split_label("untrained#x@none")


@pytest.mark.parametrize("text, message", [("full,bogus", "unknown flight stack 'bogus'"),
                                           ("none,none", "given twice: 'none'"), (" , ", "--stack is empty")])
def test_bad_stacks_are_refused_with_the_choices(text: str, message: str):
    with pytest.raises(EvalError, match=message) as err:
        parse_stacks(text)
    assert "full, none" in str(err.value)
    assert parse_stacks("none, full") == ("none", "full")


def test_an_evaluation_config_with_an_unknown_stack_is_refused():
    with pytest.raises(EvalError, match=r"unknown flight stack 'half'.*full, none"):
        EvalConfig(stacks=("full", "half")).validate()  # type: ignore[arg-type]  # a bad value on purpose


def test_cli_refuses_an_unknown_stack_and_untrained_without_a_model(tmp_path: Path):
    r = CliRunner().invoke(main, ["eval", "--stack", "paper", "--methods", "straight", "-o", str(tmp_path / "a")])
    assert r.exit_code == 2 and "Traceback" not in r.output  # a usage error
    assert r.output.strip().splitlines()[-1].endswith("use a comma list of full, none (see main eval --help)")
    r = CliRunner().invoke(main, ["eval", "--methods", "untrained", "-o", str(tmp_path / "b")])
    assert r.exit_code == 1 and "--model pretrained" in r.output and "untrained copies its architecture" in r.output


# ------------------------------------------------------------------------------ the twins of learned
def _tiny_net() -> PlannerNet:
    torch.manual_seed(5)
    return PlannerNet(planner_preset("cpu", input_size=(48, 64), num_candidates=4))


def test_the_untrained_copy_is_seeded_the_same_everywhere_and_leaves_the_generator_alone():
    net = _tiny_net()
    torch.manual_seed(123)
    before = torch.rand(3)
    torch.manual_seed(123)
    a, b, c = untrained_copy(net, 0), untrained_copy(net, 0), untrained_copy(net, 1)
    assert torch.equal(torch.rand(3), before)  # the global generator continues as if nothing happened
    sa, sb, sc, trained = a.state_dict(), b.state_dict(), c.state_dict(), net.state_dict()
    assert a.config == net.config and sa.keys() == trained.keys()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert any(not torch.equal(sa[k], sc[k]) for k in sa if sa[k].is_floating_point())


def test_straight_keypoints_lie_evenly_on_the_line_to_the_goal():
    from mapkit.flight import LearnedMethod, Observation

    net = _tiny_net()
    method = LearnedMethod("straight-keypoints", net, keypoints="straight")
    obs = Observation(t=0.0, T_world_body=np.eye(4), state_world=np.zeros((4, 3)), goal_world=np.array([6.0, 3.0, 0.6]),
                      local_goal_body=np.array([6.0, 3.0, 0.6]), depth=np.full((48, 64), 4.0, dtype=np.float32))
    plan = method.plan(obs)
    K = net.config.num_keypoints
    expected = np.arange(1, K + 1)[:, None] / K * np.array([6.0, 3.0, 0.6])
    assert np.allclose(plan.keypoints_world, expected, atol=1e-6)
    assert plan.eta is not None and plan.eta < 1e-6
    assert np.allclose(plan.pieces.state(plan.pieces.t_end)[0], [6.0, 3.0, 0.6], atol=1e-6)


# ------------------------------------------------------------------------------ paired statistics
def _episodes(label: str, outcomes: list[str], efforts: list[float], world: str = "office") -> list[EpisodeRecord]:
    return [EpisodeRecord(world=world, pair=i, method=label, outcome=o, start=[0, 0, 0], goal=[1, 0, 0],  # type: ignore[arg-type]
                          control_effort=e, time_s=10.0 + i) for i, (o, e) in enumerate(zip(outcomes, efforts, strict=True))]


def test_success_difference_is_the_paired_mean_and_its_interval_covers_it():
    a = _episodes("learned@none", ["success"] * 20, [1.0] * 20)
    b = _episodes("untrained@none", ["success", "collision"] * 10, [1.0] * 20)
    d = success_difference(a + b, "learned@none", "untrained@none")
    assert d is not None and d.pairs == 20 and d.estimate == pytest.approx(50.0)
    # the resampled mean of 20 draws of {0, 1}: the binomial's 95 % range, about ±22 points
    assert 25.0 < d.low < 40.0 and 60.0 < d.high < 75.0
    same = success_difference(a + a, "learned@none", "learned@none")
    assert same is not None and (same.estimate, same.low, same.high) == (0.0, 0.0, 0.0)
    assert success_difference(a, "learned@none", "missing") is None


def test_a_constant_effort_ratio_has_a_degenerate_interval_and_failed_pairs_are_left_out():
    a = _episodes("learned", ["success"] * 6, [2.0, 4.0, 6.0, 8.0, 10.0, 12.0])
    b = _episodes("untrained", ["success"] * 5 + ["timeout"], [4.0, 8.0, 12.0, 16.0, 20.0, 1.0])
    r = paired_ratio(a + b, "learned", "untrained", "control_effort")
    assert r is not None and r.pairs == 5
    assert r.estimate == pytest.approx(0.5) and r.low == pytest.approx(0.5) and r.high == pytest.approx(0.5)
    t = paired_ratio(a + b, "learned", "untrained", "time_s")
    assert t is not None and t.estimate == pytest.approx(1.0)


def test_the_interval_resamples_within_each_world():
    """Two worlds, learned better only in one: every resample keeps 10 pairs of each, so the
    difference never leaves what the better world alone can vary."""
    a = _episodes("learned", ["success"] * 10, [1.0] * 10, "forest") + _episodes("learned", ["success"] * 10, [1.0] * 10, "office")
    b = (_episodes("untrained", ["success"] * 10, [1.0] * 10, "forest")
         + _episodes("untrained", ["collision"] * 10, [1.0] * 10, "office"))
    d = success_difference(a + b, "learned", "untrained")
    assert d is not None and (d.estimate, d.low, d.high) == (50.0, 50.0, 50.0)


def test_learned_is_compared_with_the_mean_over_the_untrained_initial_weights():
    """Per pair, learned against the mean of the pooled untrained runs; a ratio over the weights that
    reached the goal; the table shows each seed and the pool."""
    eps = (_episodes("learned@none", ["success"] * 4, [1.0] * 4)
           + _episodes("untrained#0@none", ["success"] * 4, [2.0] * 4)
           + _episodes("untrained#1@none", ["collision", "collision", "success", "success"], [8.0] * 4))
    labels = ["learned@none", "untrained#0@none", "untrained#1@none"]
    result = ablation(eps, labels, resamples=200)
    assert [(r.label, r.inits, r.flights) for r in result.runs] == [
        ("learned@none", 1, 4), ("untrained#0@none", 1, 4), ("untrained#1@none", 1, 4), ("untrained@none", 2, 8)]
    assert result.runs[3].success == 6 and result.runs[3].method == "untrained"
    (d,) = result.success_difference
    assert (d.a, d.b, d.estimate) == ("learned@none", "untrained@none", 25.0)
    (e,) = result.effort_ratio  # pairs 0, 1: 1/2; pairs 2, 3: the mean log of 1/2 and 1/8 = 1/4
    assert e.pairs == 4 and e.estimate == pytest.approx(np.exp(np.mean(np.log([0.5, 0.5, 0.25, 0.25]))))
    table = "\n".join(ablation_lines(result))
    assert "| untrained#1 | none |" in table and "| untrained, 2 initial weights pooled | none |" in table


def test_the_ablation_compares_learned_with_its_twins_under_the_same_stack():
    eps = (_episodes("learned", ["success"] * 4, [1.0] * 4) + _episodes("untrained", ["success"] * 4, [2.0] * 4)
           + _episodes("learned@none", ["success"] * 4, [1.0] * 4)
           + _episodes("untrained@none", ["collision"] * 4, [1.0] * 4)
           + _episodes("straight-keypoints@none", ["success", "collision"] * 2, [4.0] * 4))
    labels = ["learned", "learned@none", "untrained", "untrained@none", "straight-keypoints@none"]
    result = ablation(eps, labels, resamples=200)
    assert [r.label for r in result.runs] == labels
    assert result.runs[3].collisions == 4 and result.runs[3].stack == "none" and result.runs[2].stack == "full"
    assert [(d.a, d.b, d.estimate) for d in result.success_difference] == [
        ("learned", "untrained", 0.0), ("learned@none", "untrained@none", 100.0),
        ("learned@none", "straight-keypoints@none", 50.0)]
    assert [(d.a, d.estimate) for d in result.effort_ratio] == [("learned", 0.5), ("learned@none", 0.25)]


# ------------------------------------------------------------------------------ end to end
@pytest.mark.slow
def test_an_ablation_run_records_the_stack_of_every_episode_and_reports_the_differences(tmp_path: Path, monkeypatch):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    cfg = planner_preset("cpu", input_size=(48, 64), num_candidates=4, depth_check=True)
    torch.manual_seed(0)
    torch.save({"state_dict": PlannerNet(cfg).state_dict(), "planner_config": cfg.to_dict()}, run_dir / "model.pt")
    (run_dir / "config.json").write_text("{}")
    out = tmp_path / "ev"
    monkeypatch.setattr("mapkit.evaluation._run.UNTRAINED_SEEDS", (0, 5))  # two of the four weights: quicker
    # the office: fewer obstacles than the forest to fly past and draw, the same runs and labels
    evaluate(run_dir, out, EvalConfig(worlds=("office",), pairs=1, seed=3, stacks=("full", "none"),
                                      methods=("learned", "untrained", "straight-keypoints", "oracle")), progress=False)
    doc = json.loads((out / "results.json").read_text())
    labels = ["learned", "learned@none", "untrained#0", "untrained#5", "untrained#0@none", "untrained#5@none",
              "straight-keypoints", "straight-keypoints@none", "oracle"]
    assert doc["methods"] == labels and doc["config"]["stacks"] == ["full", "none"]
    assert [(e["method"], e["stack"]) for e in doc["episodes"]] == [(m, split_label(m).stack) for m in labels]
    assert set(doc["summary"]) == set(labels)
    report = (out / "report.md").read_text()
    assert "## Ablation" in report and "learned@none − untrained@none" in report
    assert "untrained, 2 initial weights pooled" in report
    assert "learned − straight-keypoints" in report


def test_eval_help_lists_every_option_and_the_stack_layers_are_settings():
    """--help names every option; the flight stack's layers are tables of `mapkit config eval`."""
    import re

    r = CliRunner().invoke(main, ["eval", "--help"])
    assert r.exit_code == 0
    for param in main.commands["eval"].params:
        for opt in param.opts:
            assert len(re.findall(rf"(?<![\w-]){re.escape(opt)}(?![\w-])", r.output)) >= 1, opt
    settings = CliRunner().invoke(main, ["config", "eval"]).output
    assert {"[execution.corridor]", "[execution.memory]", "[execution.route]", "[execution.speed]"} <= set(settings.split("\n"))
    section = settings.split("\n[execution.speed]\n")[1].split("\n[")[0]
    assert "\ncruise = 1.2\n" in section and "\nv_max = 3.0\n" in section and "\nseconds = " not in section


@pytest.mark.parametrize("stack", ["full", "none"])
def test_iplanner_style_flies_its_spline_under_either_stack(stack: str):
    """Under the full stack the spline's key-points come through the memory (it remembers what it saw);
    under none it has no memory. Either way the reference is iPlanner's cubic spline to the goal."""
    from mapkit.flight import LearnedMethod, Observation
    from mapkit.planner import CameraInput

    net = _tiny_net()
    K = np.array([[32.0, 0.0, 31.5], [0.0, 32.0, 23.5], [0.0, 0.0, 1.0]])
    T_bc = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    method = LearnedMethod("iplanner-style", net, spline=True, camera=CameraInput.from_calibration(K, 64, 48, T_bc),
                           execution=under_stack(Execution(), stack))  # type: ignore[arg-type]
    obs = Observation(t=0.0, T_world_body=np.eye(4), state_world=np.zeros((4, 3)), goal_world=np.array([5.0, 0.0, 0.0]),
                      local_goal_body=np.array([5.0, 0.0, 0.0]), depth=np.full((48, 64), 8.0, dtype=np.float32))
    plan = method.plan(obs)
    assert plan.pieces.degree == 3 and plan.allocation_ms is None
    assert np.allclose(plan.pieces.state(plan.pieces.t_end)[0], plan.keypoints_world[-1], atol=1e-9)
    memory = method._memory
    assert (memory is not None and len(memory.frames) == 1) if stack == "full" else memory is None


@pytest.mark.parametrize("stack", ["full", "none"])
def test_the_full_stack_judges_the_shifted_candidates_and_none_the_trained_ones_alone(stack: str):
    from mapkit.flight import LearnedMethod, Observation
    from mapkit.planner import CameraInput

    net = _tiny_net()
    K = np.array([[32.0, 0.0, 31.5], [0.0, 32.0, 23.5], [0.0, 0.0, 1.0]])
    T_bc = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    execution = under_stack(Execution(shift=(-0.5, 0.5)), stack)  # type: ignore[arg-type]
    method = LearnedMethod("learned", net, camera=CameraInput.from_calibration(K, 64, 48, T_bc), execution=execution)
    obs = Observation(t=0.0, T_world_body=np.eye(4), state_world=np.zeros((4, 3)), goal_world=np.array([5.0, 0.0, 0.0]),
                      local_goal_body=np.array([5.0, 0.0, 0.0]), depth=np.full((48, 64), 8.0, dtype=np.float32))
    _, out = method._keypoints(obs, obs.start_body(), np.array([5.0, 0.0, 0.0]))
    assert out.candidates is not None
    assert out.candidates.shape[1] == (4 * 3 if stack == "full" else 4)


def test_the_run_table_gives_each_world_and_the_whole():
    from mapkit.evaluation._ablation import run_lines, summarise_runs

    eps = (_episodes("learned", ["success", "collision"], [1.0, 1.0], "office")
           + _episodes("learned", ["success"] * 2, [1.0] * 2, "forest"))
    (run,) = summarise_runs(eps, ["learned"])
    assert run.success_by_world == {"office": 0.5, "forest": 1.0} and run.success_rate == 0.75
    lines = run_lines([run])
    assert lines[0].startswith("| method | stack | office | forest | success %")
    assert lines[2].startswith("| learned | full | 50.0 | 100.0 | **75.0** | 1 | 0 |")
