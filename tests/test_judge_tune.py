"""The flown-path judge: points along each candidate's trajectory as flown, what the depth image shows
about them, candidates recorded in flight (``EvalConfig.record_judge``) and `mapkit lab tune-judge`."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from mapkit.cli.main import main
from mapkit.evaluation import EvalConfig, EvalError, evaluate
from mapkit.evaluation._run import Judgement
from mapkit.flight import Execution, Planner, under_stack
from mapkit.flight._learned import JudgeInput
from mapkit.planner import (
    CLEARANCE_CAP,
    FLOWN_FEATURES,
    CameraInput,
    PlannerConfig,
    PlannerError,
    PlannerNet,
    arclength_points,
    flown_clearance,
    flown_features,
    planner_preset,
)
from mapkit.train import (
    JudgeRecords,
    JudgeTuneConfig,
    JudgeTuneError,
    clearance_rule,
    fit_flown_head,
    load_judge_records,
)
from mapkit.trajopt import min_snap

CONFIG = planner_preset("cpu", input_size=(48, 64), num_candidates=2)


def _wall_camera(distance: float = 2.0):
    """A 160 × 96 pinhole (f = 80 px) looking along the body's x axis from its origin, and the
    preprocessed image of a wall ``distance`` metres ahead filling it."""
    H, W = 96, 160
    K = np.array([[80.0, 0.0, W / 2 - 0.5], [0.0, 80.0, H / 2 - 0.5], [0.0, 0.0, 1.0]])
    T_body_camera = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)
    x = torch.stack([torch.full((1, H, W), distance / 10.0), torch.ones(1, H, W)], dim=1)
    return CameraInput.from_calibration(K, W, H, T_body_camera), x


def test_arclength_points_along_a_straight_flight_and_a_short_one():
    """Rest to rest along x: the points lie at 1.5 · i / N metres (the path is straight, so exactly);
    a 1 m flight is 1 m long within the 1.5 m and repeats its end."""
    for d, length in ((3.0, 1.5), (1.0, 1.0)):
        traj = min_snap(torch.tensor([[[0.0, 0.0, 0.0], [d, 0.0, 0.0]]], dtype=torch.float64),
                        torch.tensor([[2.0]], dtype=torch.float64))
        points, lengths = arclength_points(traj, horizon=1.5, count=6)
        expected = np.minimum(1.5 * np.arange(1, 7) / 6, d)
        np.testing.assert_allclose(points[0, :, 0].numpy(), expected, atol=1e-9)
        assert float(points[0, :, 1:].abs().max()) == 0.0 and float(lengths[0]) == pytest.approx(length, abs=1e-9)


def test_flown_features_against_a_wall():
    """A wall 2 m ahead: a point 0.5 m ahead is 1.5 m from it, in view and 1.5 m in front of it; one
    3 m ahead lies behind it; one behind the camera is out of view; all-invalid pixels show nothing."""
    camera, x = _wall_camera(2.0)
    points = torch.tensor([[[[0.5, 0.0, 0.0], [3.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]]])
    near = flown_clearance(points, x, camera, max_depth=10.0)
    assert near[0, 0].tolist() == pytest.approx([1.5, 1.0, 3.0], abs=0.02)  # the last one: capped
    f = flown_features(points, x, camera, max_depth=10.0)
    assert f.shape == (1, 1, 3, FLOWN_FEATURES)
    assert f[0, 0, :, 0].tolist() == pytest.approx([1.5 / CLEARANCE_CAP, 1.0 / CLEARANCE_CAP, 1.0], abs=0.01)
    assert f[0, 0, :, 1].tolist() == [1.0, 1.0, 0.0]  # in view
    assert f[0, 0, :, 2].tolist() == pytest.approx([0.75, -0.5, 0.0], abs=0.01)  # (measured − own depth) / 2
    blind = torch.zeros_like(x)  # no valid pixel: nothing seen, everything free
    assert flown_clearance(points, blind, camera, max_depth=10.0).tolist() == [[[CLEARANCE_CAP] * 3]]
    # a post seen in an earlier frame, now 1 m behind and 0.5 m left of the body: the point behind
    # the camera is 0.5 m from it; padding rows (1e6 m) change nothing
    recent = torch.tensor([[[-1.0, 0.5, 0.0], [1e6, 1e6, 1e6]]])
    near = flown_clearance(points, blind, camera, max_depth=10.0, recent=recent)
    assert near[0, 0].tolist() == pytest.approx([(1.5**2 + 0.5**2) ** 0.5, CLEARANCE_CAP, 0.5], abs=1e-6)
    both = flown_features(points, x, camera, max_depth=10.0, recent=recent)
    assert both[0, 0, :, 0].tolist() == pytest.approx([1.5 / CLEARANCE_CAP, 1.0 / CLEARANCE_CAP, 0.5 / CLEARANCE_CAP], abs=0.01)


def test_a_flight_remembers_its_recent_frames_for_the_head_in_the_current_body_frame():
    """A wall 2 m ahead seen at t = 0; at t = 0.5 the vehicle is 1 m further on, turned 90° left: the
    wall's points lie 1 m to its right (body y = −1). Frames older than ``flown_history`` are dropped,
    the current frame is not among the recent ones, and a new flight starts with none."""
    from mapkit.flight import Observation
    from mapkit.flight._learned import LearnedMethod

    camera, x = _wall_camera(2.0)
    method = LearnedMethod("learned", PlannerNet(dataclasses.replace(CONFIG, flown_samples=4, flown_history=1.0)),
                           camera=camera)
    turned = np.array([[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])

    def observe(t: float, T_world_body: np.ndarray, goal: float = 9.0) -> Observation:
        obs = Observation(t=t, T_world_body=T_world_body, state_world=np.zeros((4, 3)), goal_world=np.array([goal, 0, 0]),
                          local_goal_body=np.zeros(3), depth=np.zeros((2, 2), np.float32))
        method._subgoal_in_force(obs)
        method._remember_frame(x, obs, 1.0)
        return obs

    first = observe(0.0, np.eye(4))
    assert method._recent_points(first, 1.0) is None  # only the current frame
    recent = method._recent_points(observe(0.5, turned), 1.0)
    assert recent is not None and recent.shape[0] == 1 and recent.shape[1] > 100
    np.testing.assert_allclose(recent[0, :, 1].numpy(), -1.0, atol=1e-6)
    assert float(recent[0, :, 0].abs().max()) > 0.5  # the wall spreads along the body's x
    assert method._recent_points(observe(2.0, turned), 1.0) is None  # both older than a second
    observe(2.5, turned)
    assert method._recent_points(observe(0.0, np.eye(4), goal=5.0), 1.0) is None  # a new flight


def _two_candidates(net: PlannerNet, camera: CameraInput, x: torch.Tensor):
    """The net's output with two candidates: straight into the wall 2 m ahead (scored higher) and
    along it, 1 m to the left."""
    out = net(x, torch.tensor([[6.0, 0.0, 0.0]]), camera=camera)
    line = torch.tensor([[1.2, 0.0, 0.0], [2.4, 0.0, 0.0], [3.6, 0.0, 0.0], [4.8, 0.0, 0.0], [6.0, 0.0, 0.0]])
    aside = torch.tensor([[0.2, 0.6, 0.0], [0.3, 1.5, 0.0], [0.3, 2.5, 0.0], [0.3, 3.5, 0.0], [0.3, 4.5, 0.0]])
    candidates = torch.stack([line, aside])[None]
    out = dataclasses.replace(out, candidates=candidates, scores=torch.tensor([[2.0, 1.0]]))
    wp = torch.cat([torch.zeros(2, 1, 3), candidates[0]], dim=1).double()
    return out, min_snap(wp, torch.full((2, 5), 0.6, dtype=torch.float64))


def test_judge_flown_flies_the_best_scored_candidate_its_head_expects_free(monkeypatch):
    """A head that calls a path colliding when a point comes within 0.3 m of the image's points: the
    straight candidate (scored higher, into the wall) is passed over for the one along the wall; with
    the wall nearer both collide, the best-scored flies and η gates it."""
    torch.manual_seed(0)
    net = PlannerNet(dataclasses.replace(CONFIG, input_size=(96, 160), flown_samples=8, flown_horizon=2.0)).eval()
    rule = lambda f, lengths: 50.0 * (0.3 / CLEARANCE_CAP - f[..., 0].amin(-1))  # noqa: E731
    monkeypatch.setattr(net, "flown_logits", rule)
    for distance, chosen, free in ((2.0, 1, True), (0.45, 0, False)):
        camera, x = _wall_camera(distance)
        out, flown = _two_candidates(net, camera, x)
        judged = net.judge_flown(out, flown, x, camera)
        assert int(judged.chosen[0]) == chosen and (float(judged.eta[0]) < 0.5) == free, distance
        torch.testing.assert_close(judged.keypoints, out.candidates[:, chosen])
        assert judged.candidate_eta_logits is not None and bool(judged.candidate_eta_logits[0, 0] > 0)


def test_the_flown_head_refuses_other_shapes_and_settings():
    net = PlannerNet(dataclasses.replace(CONFIG, flown_samples=4))
    with pytest.raises(PlannerError, match=r"\(\.\.\., 4, 3\)"):
        net.flown_logits(torch.zeros(2, 5, FLOWN_FEATURES), torch.zeros(2))
    with pytest.raises(PlannerError, match="tune-judge"):
        PlannerNet(CONFIG).flown_logits(torch.zeros(2, 4, FLOWN_FEATURES), torch.zeros(2))
    for bad in ({"flown_samples": -1}, {"flown_horizon": 0.0}, {"flown_history": -0.5}):
        with pytest.raises(PlannerError, match="flown_samples >= 0, flown_horizon > 0 metres and flown_history >= 0"):
            PlannerConfig(**bad)


def test_a_recorded_candidate_is_labelled_by_its_closest_approach():
    """Judgement.label: a wall at x = 2 (signed distance 2 − x); a stretch reaching x = 1.8 comes within
    0.3 m of it, one reaching 1.6 does not."""
    class Wall:
        def signed_distance(self, p: np.ndarray) -> np.ndarray:
            return 2.0 - p[:, 0]

    along = np.linspace(0.1, 1.0, 10)[:, None] * np.array([1.0, 0.0, 0.0])
    points = np.stack([along * 1.8, along * 1.6]).astype(np.float32)
    judged = JudgeInput(features=np.zeros((2, 4, FLOWN_FEATURES), np.float32), lengths=np.ones(2, np.float32),
                        points_world=points)
    assert Judgement.label(judged, Wall(), 0.3).collides.tolist() == [True, False]


def _synthetic_records(n: int, seed: int) -> JudgeRecords:
    """Candidates whose label is what the image shows: colliding when a point comes within 0.3 m of it."""
    g = torch.Generator().manual_seed(seed)
    start = torch.rand(n, 1, generator=g) * 2.5
    slope = torch.rand(n, 1, generator=g) * 2 - 1
    near = (start + slope * torch.linspace(0, 1, 8)).clamp(0.0, CLEARANCE_CAP)  # clearance along the stretch
    features = torch.stack([near / CLEARANCE_CAP, torch.ones_like(near), (near / 2).clamp(max=1.0)], dim=-1)
    return JudgeRecords(features, torch.full((n,), 1.5), near.amin(-1) < 0.3, horizon=1.5, robot_radius=0.3)


def test_fitting_the_head_learns_what_the_image_shows_on_unseen_candidates():
    torch.manual_seed(0)
    net = PlannerNet(dataclasses.replace(CONFIG, flown_samples=8))
    train, val, test = _synthetic_records(4000, 0), _synthetic_records(1000, 1), _synthetic_records(2000, 2)
    assert clearance_rule(test).caught == 1.0 and clearance_rule(test).false_alarms == 0.0
    score, step = fit_flown_head(net, train, val, JudgeTuneConfig(steps=1500, lr=3e-3, batch_size=256, check_every=150), progress=False)
    assert step > 0
    with torch.no_grad():
        expects = net.flown_logits(test.features, test.lengths) >= 0
    caught = float(expects[test.collides].float().mean())
    false = float(expects[~test.collides].float().mean())
    assert caught > 0.85 and false < 0.05 and score.caught > 0.85, (caught, false)


def test_record_judge_then_tune_judge_through_the_cli(tmp_path: Path):
    run = tmp_path / "run"
    run.mkdir()
    torch.manual_seed(0)
    net = PlannerNet(CONFIG)
    torch.save({"state_dict": net.state_dict(), "planner_config": CONFIG.to_dict()}, run / "model.pt")
    (run / "config.json").write_text(json.dumps({"planner": {}, "planner_resolved": CONFIG.to_dict()}))
    for seed in (3, 4):
        config = EvalConfig(worlds=("office",), pairs=1, seed=seed, methods=("learned",), stacks=("none",),
                            record_judge=True, judge_history=1.0)
        evaluate(run, tmp_path / f"e{seed}", config, progress=False)
        doc = json.loads((tmp_path / f"e{seed}" / "results.json").read_text())
        assert "record_judge" not in doc["config"] and "judge_history" not in doc["config"]  # no result depends on them
        with np.load(tmp_path / f"e{seed}" / "judge.npz") as z:
            plans = sum(e["plans"] for e in doc["episodes"])
            # every candidate of every plan (a plan may try a second goal)
            assert len(z["collides"]) >= CONFIG.num_candidates * plans > 0
            assert z["features"].shape[1:] == (16, FLOWN_FEATURES) and z["collides"].dtype == bool
            assert float(z["horizon"]) == 1.5 and float(z["robot_radius"]) == 0.3 and float(z["history"]) == 1.0
            assert np.all((z["lengths"] > 0) & (z["lengths"] <= 1.5)) and set(z["world"]) == {"office"}
    out = CliRunner().invoke(main, ["lab", "tune-judge", "--model", str(run), "--records", str(tmp_path / "e3"),
                                    "--val", str(tmp_path / "e4"), "-o", str(tmp_path / "judged"), "--steps", "20"])
    assert out.exit_code == 0, out.output
    assert "depth image, clearance < robot radius" in out.output and "fitted head" in out.output
    assert "clearances to the image and the last 1 s of frames" in out.output
    judged = Planner.load(tmp_path / "judged").net
    assert judged.config.flown_samples == 16 and judged.config.flown_history == 1.0 and judged.flown_mlp is not None
    for name, value in net.state_dict().items():
        torch.testing.assert_close(judged.state_dict()[name], value)  # only the new head is new
    run_config = json.loads((tmp_path / "judged" / "config.json").read_text())
    assert run_config["planner"] == {"flown_samples": 16, "flown_horizon": 1.5, "flown_history": 1.0}
    assert run_config["judge_tune"]["train_rows"] > 0
    PlannerNet(PlannerConfig.from_dict(run_config["planner_resolved"])).load_state_dict(judged.state_dict())
    # the head flies without the stack; with it (by default) the model flies exactly as the one it was
    # fitted on, unless asked (Execution.flown_judge)
    config = EvalConfig(worlds=("office",), pairs=2, seed=5, methods=("learned",), stacks=("none",))
    assert evaluate(tmp_path / "judged", tmp_path / "e5", config, progress=False).summary["success"]
    full = dataclasses.replace(config, stacks=("full",))
    evaluate(tmp_path / "judged", tmp_path / "e5n", full, progress=False)
    evaluate(run, tmp_path / "e5s", full, progress=False)
    flights = [json.loads((tmp_path / e / "results.json").read_text())["episodes"] for e in ("e5n", "e5s")]
    assert flights[0] == flights[1]
    assert Execution().flown_judge is False and under_stack(Execution(), "none").flown_judge is True
    # a head that reads 16 points over 1.5 m refuses records of another horizon
    with np.load(tmp_path / "e3" / "judge.npz") as z:
        other = {k: z[k] for k in z.files}
    other["horizon"] = np.float64(2.5)
    (tmp_path / "e6").mkdir()
    np.savez(tmp_path / "e6" / "judge.npz", **other)
    out = CliRunner().invoke(main, ["lab", "tune-judge", "--model", str(tmp_path / "judged"), "--records", str(tmp_path / "e6"),
                                    "--val", str(tmp_path / "e6"), "-o", str(tmp_path / "again")])
    assert out.exit_code == 1 and "Traceback" not in out.output and "over 2.5 m" in out.output
    # records that read other histories do not mix
    other["horizon"], other["history"] = np.float64(1.5), np.float64(0.5)
    np.savez(tmp_path / "e6" / "judge.npz", **other)
    out = CliRunner().invoke(main, ["lab", "tune-judge", "--model", str(run), "--records", str(tmp_path / "e3"),
                                    "--records", str(tmp_path / "e6"), "--val", str(tmp_path / "e4"), "-o", str(tmp_path / "mixed")])
    assert out.exit_code == 1 and "same judge_history" in out.output
    with pytest.raises(EvalError, match="set record_judge too"):
        EvalConfig(worlds=("office",), judge_history=1.0).validate()


def test_folders_without_recorded_candidates_are_refused_in_one_line(tmp_path: Path):
    with pytest.raises(JudgeTuneError, match="record_judge=True"):
        load_judge_records([tmp_path])
    out = CliRunner().invoke(main, ["lab", "tune-judge", "--records", str(tmp_path), "--val", str(tmp_path), "-o",
                                    str(tmp_path / "out")])
    assert out.exit_code == 1 and "Traceback" not in out.output and "record_judge=True" in out.output
    out = CliRunner().invoke(main, ["lab", "tune-judge", "--records", str(tmp_path), "--val", str(tmp_path), "-o",
                                    str(tmp_path / "out"), "--set", "positive_weight=0"])
    assert out.exit_code != 0 and "Traceback" not in out.output
