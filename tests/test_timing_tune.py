"""Plans recorded in flight (``EvalConfig.record_plans``) and `mapkit lab tune-timing`: the TAN fine-tuned on plans made in flight."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from mapkit.cli.main import main
from mapkit.evaluation import PLANS_FILE, EvalConfig, evaluate
from mapkit.flight import Planner
from mapkit.planner import PlannerConfig, PlannerNet, planner_preset
from mapkit.train import PlanInputs, TimingTuneConfig, TimingTuneError, load_plan_inputs, tune_tan, tune_timing
from mapkit.train._timing_tune import _objective, _Reference, _timed, plan_costs

CONFIG = planner_preset("cpu", input_size=(48, 64))


def synthetic_plans(n: int, seed: int) -> PlanInputs:
    """Key-point paths as the planner makes them: roughly ahead, bending, from a moving start."""
    rng = np.random.default_rng(seed)
    M = CONFIG.num_keypoints
    steps = rng.uniform(0.6, 1.6, (n, M, 1)) * np.array([1.0, 0.0, 0.0])
    steps[..., 1] = rng.normal(0.0, 0.4, (n, M))
    steps[..., 2] = rng.normal(0.0, 0.1, (n, M))
    waypoints = np.concatenate([np.zeros((n, 1, 3)), np.cumsum(steps, axis=1)], axis=1)
    start = np.zeros((n, 3, 3))
    start[:, 0] = rng.uniform(0.0, 2.0, (n, 1)) * np.array([1.0, 0.0, 0.0]) + rng.normal(0, 0.3, (n, 3))
    start[:, 1] = rng.normal(0.0, 0.5, (n, 3))
    end_speed = np.where(rng.random(n) < 0.7, 2.0, 0.0)
    return PlanInputs(torch.from_numpy(waypoints), torch.from_numpy(start), torch.from_numpy(end_speed))


def _first_segment_error(tan: torch.nn.Module, plans: PlanInputs) -> float:
    """Median |log| ratio of the first segment's duration to the gradient-descent split's."""
    with torch.no_grad():
        ours, _ = _timed(tan, CONFIG, plans)
        theirs, _ = _timed(None, CONFIG, plans)
    return float(torch.log(ours[:, 0] / theirs[:, 0]).abs().median())


def test_imitation_fits_the_gradient_descent_split_on_unseen_plans():
    """The split a replanning flight executes is its first segment: an untrained TAN tuned to imitate
    gradient descent's durations comes close to them on plans it never saw."""
    train, val = synthetic_plans(512, 1), synthetic_plans(128, 2)
    torch.manual_seed(0)
    net = PlannerNet(CONFIG)
    untrained = _first_segment_error(net.tan, val)
    tune = TimingTuneConfig(steps=300, check_every=50, objective="imitate")
    outcome = tune_tan(net.tan, CONFIG, train, val, tune, progress=False)
    assert outcome.best_step > 0 and outcome.objective[1] < 0.6 * outcome.objective[0]
    assert _first_segment_error(net.tan, val) < 0.5 * untrained  # 0.31 → 0.12 (a 12 % error)
    # the objective's own check: the kept weights score what the outcome says
    with torch.no_grad():
        score = _objective(net.tan, CONFIG, val, _Reference.of(CONFIG, val), tune).mean()
    assert float(score) == pytest.approx(outcome.objective[1], rel=1e-9)
    # snap cost ratios to the gradient-descent split: the kept weights are what the net now holds
    with torch.no_grad():
        ref = plan_costs(None, CONFIG, val)
        now = plan_costs(net.tan, CONFIG, val)
    assert float(now.sum() / ref.sum()) == pytest.approx(outcome.after[1], rel=1e-9)


def test_bad_tuning_options_are_refused():
    for bad in ({"objective": "fast"}, {"first_weight": 0.0}, {"first_weight": float("nan")}, {"steps": 0},
                {"boundary_scale": "metres", "boundary_inputs": True}, {"boundary_scale": "duration"},
                {"tan_hidden": ()}, {"tan_hidden": (64, 0)}):
        with pytest.raises(TimingTuneError, match=next(iter(bad))):  # the message names the field
            TimingTuneConfig(**bad).validate()


def test_plan_costs_use_the_planners_timing_and_the_analytic_cost():
    """One segment from rest to rest: the TAN has nothing to split, so both allocations give the
    rest-to-rest minimum snap cost 100800·d²/T⁷ over the planner's total time."""
    from mapkit.planner._timing import total_time

    config = CONFIG.__class__.from_dict({**CONFIG.to_dict(), "num_keypoints": 1})
    net = PlannerNet(config)
    wp = torch.tensor([[[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]]], dtype=torch.float64)
    plans = PlanInputs(wp, torch.zeros(1, 3, 3, dtype=torch.float64), torch.zeros(1, dtype=torch.float64))
    T = float(total_time(wp, plans.start, plans.end_speed, config)[0])
    with torch.no_grad():
        for tan in (net.tan, None):
            assert float(plan_costs(tan, config, plans)[0]) == pytest.approx(100800 * 9.0 / T ** 7, rel=1e-6)
    # A plan flown slower (a turn's cruise speed, a gentler stop) is timed and costed as it was flown;
    # NaN (a recording without them) is the model's own profile.
    slow, gentle = torch.tensor([1.0], dtype=torch.float64), torch.tensor([0.5], dtype=torch.float64)
    recorded = PlanInputs(wp, plans.start, plans.end_speed, slow, gentle)
    T_slow = float(total_time(wp, plans.start, plans.end_speed, config, slow, gentle)[0])
    assert T_slow > T
    unknown = torch.full((1,), float("nan"), dtype=torch.float64)
    with torch.no_grad():
        for tan in (net.tan, None):
            assert float(plan_costs(tan, config, recorded)[0]) == pytest.approx(100800 * 9.0 / T_slow ** 7, rel=1e-6)
            assert float(plan_costs(tan, config, PlanInputs(wp, plans.start, plans.end_speed, unknown, unknown))[0]) == \
                pytest.approx(100800 * 9.0 / T ** 7, rel=1e-6)
    assert len(recorded.take(torch.tensor([0, 0]))) == 2


@pytest.mark.slow
def test_record_plans_then_tune_timing_through_the_cli(tmp_path: Path):
    run = tmp_path / "run"
    run.mkdir()
    torch.manual_seed(0)
    net = PlannerNet(CONFIG)
    torch.save({"state_dict": net.state_dict(), "planner_config": CONFIG.to_dict()}, run / "model.pt")
    (run / "config.json").write_text(json.dumps({"planner": {}, "planner_resolved": CONFIG.to_dict()}))
    for seed in (3, 4):
        config = EvalConfig(worlds=("office",), pairs=1, seed=seed, methods=("learned", "straight"), record_plans=True)
        evaluate(run, tmp_path / f"e{seed}", config, progress=False)
        doc = json.loads((tmp_path / f"e{seed}" / "results.json").read_text())
        learned = [e for e in doc["episodes"] if e["method"] == "learned"]
        with np.load(tmp_path / f"e{seed}" / PLANS_FILE) as z:
            # every plan the learned method timed: at least one per replan it made
            assert len(z["end_speed"]) >= sum(e["plans"] for e in learned) > 0
            assert z["waypoints"].shape[1:] == (CONFIG.num_keypoints + 1, 3) and set(z["world"]) == {"office"}
            # each plan's speed profile as flown: turns slowed (at least the 1 m/s floor), stops at the model's rate
            assert np.all((z["cruise_speed"] >= 1.0 - 1e-9) & (z["cruise_speed"] <= CONFIG.cruise_speed + 1e-9))
            assert np.allclose(z["decel"], CONFIG.accel) and np.all(z["end_speed"] <= z["cruise_speed"] + 1e-9)
        assert "record_plans" not in doc["config"]  # results.json does not depend on it
    out = CliRunner().invoke(main, ["lab", "tune-timing", "--model", str(run), "--plans", str(tmp_path / "e3"),
                                    "--val", str(tmp_path / "e4"), "-o", str(tmp_path / "tuned"), "--steps", "20"])
    assert out.exit_code == 0, out.output
    assert "gradient-descent split" in out.output
    tuned = Planner.load(tmp_path / "tuned").net
    for (name, a), b in zip(net.state_dict().items(), tuned.state_dict().values(), strict=True):
        assert name.startswith("tan.") or torch.equal(a, b), name  # only the TAN may change
    record = json.loads((tmp_path / "tuned" / "config.json").read_text())["timing_tune"]
    assert record["train_plans"] > 0 and record["val_plans"] > 0
    # A new TAN that reads the boundary conditions: the rest of the network is kept as it was.
    out = CliRunner().invoke(main, ["lab", "tune-timing", "--model", str(run), "--plans", str(tmp_path / "e3"),
                                    "--val", str(tmp_path / "e4"), "-o", str(tmp_path / "tunedB"), "--steps", "20",
                                    "--set", "boundary_inputs=true"])
    assert out.exit_code == 0, out.output
    boundary = Planner.load(tmp_path / "tunedB").net
    assert boundary.config.tan_boundary and boundary.tan.config.boundary_inputs
    # config.json says so too: the net its resolved planner config builds takes the new weights
    run_config = json.loads((tmp_path / "tunedB" / "config.json").read_text())
    assert run_config["planner"] == {"tan_boundary": True, "tan_boundary_scale": "limits",
                                     "tan_hidden": list(CONFIG.tan_hidden)}
    PlannerNet(PlannerConfig.from_dict(run_config["planner_resolved"])).load_state_dict(boundary.state_dict())
    for (name, a), b in zip(net.state_dict().items(), boundary.state_dict().values(), strict=False):
        assert name.startswith("tan.") or torch.equal(a, b), name
    # ... scaled by each plan's duration, wider, imitating gradient descent (the recipe's objective, which
    # only the library sets): a new TAN again, from the one above
    tuned_d = tune_timing(tmp_path / "tunedB", [tmp_path / "e3"], [tmp_path / "e4"], tmp_path / "tunedD",
                          TimingTuneConfig(steps=20, boundary_inputs=True, boundary_scale="duration", objective="imitate",
                                           tan_hidden=(24, 16, 8)), progress=False)
    assert tuned_d.objective[0] >= 0 and tuned_d.objective[1] >= 0
    scaled = Planner.load(tmp_path / "tunedD").net
    assert scaled.config.tan_boundary_scale == "duration" and scaled.tan.config.boundary_scale == "duration"
    assert scaled.config.tan_hidden == (24, 16, 8) and [m.out_features for m in scaled.tan.mlp[::2]] == [24, 16, 8, 5]
    run_config = json.loads((tmp_path / "tunedD" / "config.json").read_text())
    PlannerNet(PlannerConfig.from_dict(run_config["planner_resolved"])).load_state_dict(scaled.state_dict())
    record = json.loads((tmp_path / "tunedD" / "config.json").read_text())["timing_tune"]
    assert record["config"]["objective"] == "imitate" and record["val_after"]["objective"] >= 0


def test_folders_without_recorded_plans_are_refused_in_one_line(tmp_path: Path):
    with pytest.raises(TimingTuneError, match="record_plans=True"):
        load_plan_inputs([tmp_path], num_segments=CONFIG.num_keypoints)
    out = CliRunner().invoke(main, ["lab", "tune-timing", "--plans", str(tmp_path), "--val", str(tmp_path), "-o",
                                    str(tmp_path / "out")])
    assert out.exit_code == 1 and "Traceback" not in out.output and "record_plans=True" in out.output
