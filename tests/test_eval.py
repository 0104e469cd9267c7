"""Closed-loop evaluation: the loop against analytic answers, determinism, reports, bad input."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from mapkit.cli.main import main
from mapkit.evaluation import EvalConfig, LoopConfig, StraightMethod, evaluate, judging_loop, load_paths, run_episode
from mapkit.flight import MethodPlan, Observation, Pieces, PilotConfig, hold, level_pose, pieces_from_body
from mapkit.planner import PlannerConfig, PlannerNet, planner_preset
from mapkit.sim import Box, World
from mapkit.trajopt import min_snap

BOUNDS = np.array([[0.0, 0.0, 0.0], [20.0, 10.0, 4.0]])
START, GOAL = np.array([1.0, 5.0, 1.5]), np.array([15.0, 5.0, 1.5])


def empty_world() -> World:
    return World(primitives=[], bounds=BOUNDS, kind="custom", flight_z=(0.5, 3.0))


def wall_world(x: float = 8.0, half: float = 0.1) -> World:
    return World(primitives=[Box(center=[x, 5.0, 2.0], half_extents=[half, 6.0, 3.0])], bounds=BOUNDS,
                 kind="custom", flight_z=(0.5, 3.0))


def rest_to_rest(d: float, T: float, t0: float = 0.0) -> Pieces:
    """One minimum-snap segment from rest at START to rest d metres along +x, in T seconds."""
    wp = torch.tensor([[[0.0, 0.0, 0.0], [d, 0.0, 0.0]]], dtype=torch.float64)
    traj = min_snap(wp, torch.tensor([[T]], dtype=torch.float64))
    T_wb = np.eye(4)
    T_wb[:3, 3] = START
    return pieces_from_body(traj.coeffs[0].numpy(), np.array([T]), T_wb, t0)


class Scripted:
    """Flies a fixed reference once (no camera, no replanning)."""

    name = "scripted"
    needs_depth = False
    replans = False

    def __init__(self, pieces: Pieces) -> None:
        self.pieces = pieces

    def plan(self, obs: Observation) -> MethodPlan:
        return MethodPlan(pieces=self.pieces, latency_ms=0.0)


# ------------------------------------------------------------------------------- the loop
def test_straight_line_reaches_the_goal_in_an_empty_world():
    loop = LoopConfig(pilot=PilotConfig(horizon=100.0))  # the whole line at once: a straight-line "planner"
    ep = run_episode(empty_world(), START, GOAL, StraightMethod(), loop)
    assert ep.outcome == "success"
    assert ep.collision_point is None
    assert np.linalg.norm(ep.samples[-1, 1:] - GOAL) <= loop.goal_radius + 1e-9
    # It flew the line: no sideways deviation, length = distance minus the goal radius.
    assert np.abs(ep.samples[:, 2:] - START[1:]).max() < 1e-9
    assert ep.path_length == pytest.approx(np.linalg.norm(GOAL - START) - loop.goal_radius, abs=0.02)


@pytest.mark.parametrize("x_wall", [6.0, 9.5])
def test_straight_line_hits_a_wall_across_it_where_the_wall_is(x_wall: float):
    loop = LoopConfig(control_rate=400.0, pilot=PilotConfig(horizon=100.0))
    half = 0.1
    ep = run_episode(wall_world(x_wall, half), START, GOAL, StraightMethod(), loop)
    assert ep.outcome == "collision"
    x, y, z = ep.collision_point
    # First sample closer than the robot radius to the face at x_wall - half.
    face = x_wall - half - loop.robot_radius
    speed = np.abs(np.diff(ep.samples[-3:, 1])).max() * loop.control_rate
    assert face <= x <= face + speed / loop.control_rate + 1e-9
    assert (y, z) == pytest.approx((START[1], START[2]), abs=1e-9)
    assert ep.min_distance < loop.robot_radius
    assert ep.samples[-1, 1] == pytest.approx(x)


def test_effort_of_a_rest_to_rest_segment_is_the_analytic_value():
    d, T = 6.0, 3.0
    ref = rest_to_rest(d, T)
    assert ref.snap_effort(0.0, T) == pytest.approx(100800.0 * d * d / T ** 7, rel=1e-9)
    # A goal past the end: the whole segment is flown, then the vehicle hovers until the time limit.
    goal = START + np.array([d + 5.0, 0.0, 0.0])
    ep = run_episode(empty_world(), START, goal, Scripted(ref), LoopConfig())
    assert ep.outcome == "timeout"
    assert ep.control_effort == pytest.approx(100800.0 * d * d / T ** 7, rel=1e-9)
    assert ep.path_length == pytest.approx(d, rel=1e-6)
    assert ep.samples[-1, 1:] == pytest.approx(START + [d, 0.0, 0.0])
    # Reaching the goal ends the flight there: the effort is the integral up to that sample.
    ep = run_episode(empty_world(), START, START + np.array([d / 2, 0.0, 0.0]), Scripted(ref), LoopConfig(goal_radius=0.01))
    assert ep.outcome == "success"
    assert ep.control_effort == pytest.approx(ref.snap_effort(0.0, ep.time_s), rel=1e-12)
    assert ep.control_effort < 100800.0 * d * d / T ** 7


def test_effort_is_additive_over_replans_of_the_same_trajectory():
    """Replanning from the vehicle's state onto the same curve changes nothing."""
    d, T = 5.0, 4.0
    whole = rest_to_rest(d, T)

    class Replanner(Scripted):
        replans = True

        def plan(self, obs: Observation) -> MethodPlan:
            # The rest of the same curve, restarted at obs.t: same polynomial, shifted knots.
            return MethodPlan(pieces=_tail(whole, obs.t), latency_ms=0.0)

    goal = START + np.array([d + 5.0, 0.0, 0.0])
    # No planning latency: the scripted tail ignores the state it is given (the first would start
    # 20 ms into the curve while the vehicle still hovers).
    ep = run_episode(empty_world(), START, goal, Replanner(whole),
                     LoopConfig(timeout_min=T, timeout_factor=0.1, pilot=PilotConfig(plan_latency=0.0)))
    assert ep.plans == 8
    assert ep.control_effort == pytest.approx(100800.0 * d * d / T ** 7, rel=1e-9)


def test_per_plan_effort_and_peaks_of_a_rest_to_rest_segment_are_analytic():
    d, T = 6.0, 3.0
    goal = START + np.array([d + 5.0, 0.0, 0.0])
    ep = run_episode(empty_world(), START, goal, Scripted(rest_to_rest(d, T)), LoopConfig())
    assert ep.plan_effort == pytest.approx(100800.0 * d * d / T ** 7, rel=1e-9)
    # s(τ) = 35τ⁴ − 84τ⁵ + 70τ⁶ − 20τ⁷: peak speed 35/16 · d/T at τ = 1/2 (a control sample).
    assert ep.peak_speed == pytest.approx(35.0 / 16.0 * d / T, rel=1e-9)
    # Peak acceleration (84·10/(9·√... ) evaluated numerically from the same polynomial, sampled at 200 Hz.
    tau = np.arange(0.0, T + 1e-9, 1.0 / 200.0) / T
    acc = d / T ** 2 * (420 * tau ** 2 - 1680 * tau ** 3 + 2100 * tau ** 4 - 840 * tau ** 5)
    assert ep.peak_acceleration == pytest.approx(np.abs(acc).max(), rel=1e-6)


class Jittery:
    """Replans every interval from the state it is given to a goal that moves (a net's jitter)."""

    name = "jittery"
    needs_depth = False
    replans = True

    def __init__(self) -> None:
        self.rng = np.random.default_rng(0)
        self.plans: list[Pieces] = []

    def plan(self, obs: Observation) -> MethodPlan:
        start = obs.start_body()
        target = obs.local_goal_body + self.rng.normal(0.0, 0.5, 3) * [0.0, 1.0, 0.3]
        wp = torch.from_numpy(np.stack([start[0], target]))[None]
        traj = min_snap(wp, torch.tensor([[3.0]], dtype=torch.float64), start=torch.from_numpy(start[1:])[None])
        pieces = pieces_from_body(traj.coeffs[0].numpy(), np.array([3.0]), obs.T_world_body, obs.t)
        self.plans.append(pieces)
        return MethodPlan(pieces=pieces, latency_ms=0.0)


@pytest.mark.parametrize("latency", [0.0, 0.02, 0.1])
def test_a_replanned_reference_is_C3_across_the_switch(latency: float):
    method = Jittery()
    loop = LoopConfig(timeout_min=3.0, timeout_factor=0.1, pilot=PilotConfig(plan_latency=latency))
    ep = run_episode(empty_world(), START, START + np.array([12.0, 0.0, 0.0]), method, loop)
    assert ep.plans == 6 and ep.outcome == "timeout"
    lag = np.ceil(latency * loop.control_rate - 1e-9) / loop.control_rate
    for k, (old, new) in enumerate(itertools.pairwise(method.plans), start=1):
        assert new.t0 == pytest.approx(k * loop.pilot.replan_interval + lag)
        # Position … jerk of the new plan at its start equal the old plan's there.
        assert np.abs(old.state(new.t0) - new.state(new.t0)).max() < 1e-6
    # The vehicle tracks a C³ reference exactly: it flies the planned positions.
    last = method.plans[-1]
    t_end = ep.samples[-1, 0]
    assert np.abs(ep.samples[-1, 1:] - last.derivative(np.array([t_end]), 0)[0]).max() < 1e-6


class Doubtful(Jittery):
    """Every plan has η = 0.9; ``override`` says whether the method asks to fly it anyway."""

    def __init__(self, override: bool) -> None:
        super().__init__()
        self.override = override

    def plan(self, obs: Observation) -> MethodPlan:
        mp = super().plan(obs)
        assert obs.reference is not None  # the loop shows the method what it flies now
        return MethodPlan(pieces=mp.pieces, latency_ms=0.0, eta=0.9, overrides_eta=self.override)


def test_a_method_may_fly_a_doubtful_plan_when_its_own_check_finds_the_old_one_no_safer():
    loop = LoopConfig(timeout_min=2.0, timeout_factor=0.1)
    goal = START + np.array([12.0, 0.0, 0.0])
    vetoed = run_episode(empty_world(), START, goal, Doubtful(override=False), loop)
    assert vetoed.rejected_plans == vetoed.plans and vetoed.path_length == 0.0
    flown = run_episode(empty_world(), START, goal, Doubtful(override=True), loop)
    assert flown.rejected_plans == 0 and flown.path_length > 0.5


def test_the_depth_check_prefers_the_path_away_from_a_seen_wall():
    from mapkit.flight._learned import _Checker, _reference_no_safer
    from mapkit.planner import CameraInput, preprocess_depth

    w, h = 160, 96
    K = np.array([[80.0, 0.0, w / 2 - 0.5], [0.0, 80.0, h / 2 - 0.5], [0.0, 0.0, 1.0]])
    T_body_camera = np.eye(4)
    T_body_camera[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]  # optical → FLU
    depth = np.full((h, w), 9.0, dtype=np.float32)
    depth[:, : w // 2] = 2.0  # a wall 2 m ahead on the left (+y), open space on the right
    x = preprocess_depth(torch.from_numpy(depth)[None], input_size=(h, w), max_depth=10.0)
    check = _Checker(x, CameraInput.from_calibration(K, w, h, T_body_camera), 10.0, None)

    def line(y: float):
        wp = torch.tensor([[[0.0, 0.0, 0.0], [4.0, y, 0.0]]], dtype=torch.float64)
        return min_snap(wp, torch.tensor([[3.0]], dtype=torch.float64))

    left, right = line(1.0), line(-1.0)
    assert check(left) > 0 and check(right) == 0

    def obs(flying) -> Observation:
        pieces = pieces_from_body(flying.coeffs[0].numpy(), np.array([3.0]), np.eye(4), 0.0)
        return Observation(t=0.0, T_world_body=np.eye(4), state_world=np.zeros((4, 3)), goal_world=np.zeros(3),
                           local_goal_body=np.zeros(3), depth=None, reference=pieces)

    assert _reference_no_safer(obs(left), right, check)  # flying into the wall: take the doubtful plan
    assert not _reference_no_safer(obs(right), left, check)  # flying clear: keep it


def test_splice_keeps_the_old_reference_until_the_new_one_starts():
    rng = np.random.default_rng(1)
    old = Pieces(t0=0.0, durations=np.array([0.4, 0.7]), coeffs=rng.normal(size=(2, 3, 8)))
    new = Pieces(t0=0.52, durations=np.array([0.5]), coeffs=rng.normal(size=(1, 3, 8)))
    both = old.splice(new, 0.25)
    t = np.linspace(0.25, 0.5199, 40)
    for q in range(5):
        assert np.abs(both.derivative(t, q) - old.derivative(t, q)).max() < 1e-9
    t = np.linspace(0.5201, 1.0, 40)
    assert np.abs(both.derivative(t, 0) - new.derivative(t, 0)).max() < 1e-9
    assert both.t0 == 0.25


def _tail(p: Pieces, t: float) -> Pieces:
    """The part of a one-segment reference after t, as its own segment (re-expressed in s')."""
    T = float(p.durations[0])
    a = t / T
    n = p.coeffs.shape[-1]
    # p(s) with s = a + (1 - a) s' : expand the polynomial in s'.
    from math import comb

    c = np.zeros_like(p.coeffs[0])
    for k in range(n):
        for j in range(k + 1):
            c[:, j] += p.coeffs[0, :, k] * comb(k, j) * a ** (k - j) * (1 - a) ** j
    return Pieces(t0=t, durations=np.array([T - t]), coeffs=c[None])


def test_a_reference_with_a_jump_is_tracked_smoothly():
    """A position step in the reference: the tracker converges, the executed path is continuous,
    and the snap stays finite (the effort is that of the critically damped error response)."""
    ref = hold(START + np.array([0.5, 0.0, 0.0]), 0.0, duration=0.5)
    loop = LoopConfig(goal_radius=0.01, tracking_bandwidth=5.0, pilot=PilotConfig(goal_radius=0.01))
    ep = run_episode(empty_world(), START, START + np.array([0.5, 0.0, 0.0]), Scripted(ref), loop)
    assert ep.outcome == "success"
    steps = np.linalg.norm(np.diff(ep.samples[:, 1:], axis=0), axis=1)
    assert steps.max() < 0.05  # no teleport
    # e(t) = 0.5 · (1 + ωt + (ωt)²/2 + (ωt)³/6) e^{-ωt}; its snap integral is finite and > 0.
    w = 5.0
    t = np.linspace(0.0, 12.0, 200001)
    k = (1 + w * t + (w * t) ** 2 / 2 + (w * t) ** 3 / 6)
    e = 0.5 * k * np.exp(-w * t)
    snap = np.gradient(np.gradient(np.gradient(np.gradient(e, t), t), t), t)
    assert ep.outcome == "success"
    assert 0.0 < ep.control_effort <= np.trapezoid(snap ** 2, t) * 1.05


# ------------------------------------------------------------------------------ evaluate()
def save_model(run_dir: Path, config: PlannerConfig, **run_cfg: object) -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    net = PlannerNet(config)
    torch.save({"state_dict": net.state_dict(), "planner_config": config.to_dict()}, run_dir / "model.pt")
    (run_dir / "config.json").write_text(json.dumps(run_cfg))
    return run_dir


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_model(tmp_path_factory.mktemp("run") / "tiny", planner_preset("cpu", input_size=(48, 64)))


def small_config(**kw: object) -> EvalConfig:
    return EvalConfig(worlds=("office",), pairs=2, seed=3, methods=("learned", "iplanner-style", "straight", "oracle"),
                      **kw)


@pytest.mark.slow
def test_same_seed_gives_identical_results_json(tiny_run: Path, tmp_path: Path):
    a = evaluate(tiny_run, tmp_path / "a", small_config(), progress=False)
    b = evaluate(tiny_run, tmp_path / "b", small_config(workers=2), progress=False)
    assert (tmp_path / "a" / "results.json").read_bytes() == (tmp_path / "b" / "results.json").read_bytes()
    doc = json.loads((tmp_path / "a" / "results.json").read_text())
    assert doc["format"] == "mapkit-eval/1"
    assert doc["model"]["sha256"] and doc["seed"] == 3 and doc["versions"]["mapkit"]
    assert len(doc["episodes"]) == 2 * 4
    assert {e["outcome"] for e in doc["episodes"]} <= {"success", "collision", "timeout"}
    # The oracle plans on the exact world: it gets there.
    assert all(e["outcome"] == "success" for e in doc["episodes"] if e["method"] == "oracle")
    paths = load_paths(tmp_path / "a")
    assert set(paths) == {f"office/{e['pair']:03d}/{e['method']}" for e in doc["episodes"]}
    for e in doc["episodes"]:
        p = paths[f"office/{e['pair']:03d}/{e['method']}"]
        assert p.shape[1] == 4 and np.allclose(p[0, 1:], e["start"], atol=1e-5)
    out = {p.name for p in a.files}
    assert {"results.json", "latency.json", "report.md", "trajectories.npz", "paths_office.png",
            "effort_latency.png", "office.world.json"} <= out
    report = (tmp_path / "a" / "report.md").read_text()
    assert "Table I" in report and "Table II" in report and "88.3" in report
    assert b.summary["success"]["oracle"]["office"]["success_rate"] == 1.0


@pytest.mark.slow
def test_cli_eval_runs_and_prints_the_table(tiny_run: Path, tmp_path: Path):
    r = CliRunner().invoke(main, ["eval", "--model", str(tiny_run), "--world", "office", "--pairs", "1", "--seed", "3",
                                  "--methods", "straight,oracle", "-o", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    assert "oracle" in r.output and "wrote" in r.output
    r = CliRunner().invoke(main, ["eval", "--model", str(tiny_run), "--world", "office", "--pairs", "1", "--seed", "3",
                                  "--methods", "straight", "-o", str(tmp_path / "ev")])
    assert r.exit_code == 1 and "exists" in r.output and "--overwrite" in r.output


# 2: a value the options alone rule out (a usage error); 1: one the worlds rule out once sampling starts
@pytest.mark.parametrize("args, message, code", [
    (["--world", "moon"], "unknown world 'moon'", 2),
    (["--methods", "learned,teleport"], "unknown method 'teleport'", 2),
    (["--world", "office", "--pairs", "3", "--set", "min_distance=200"], "could sample only 0 of 3", 1),
    (["--set", "loop.pilot.replan_interval=0.01"], "whole number of depth frames", 2),
    (["--set", "execution.corridor.width=-0.5"], "execution.corridor.width must be a positive number", 2),
    (["--set", "execution.corridor.unchecked_width=-1"], "execution.corridor.unchecked_width must be a positive number", 2),
    (["--set", "execution.speed.v_max=-1"], "execution.speed.v_max must be a positive number", 2),
    (["--set", "execution.memory.seconds=-8"], "execution.memory.seconds must be a positive number", 2),
    (["--set", "loop.pilot.plan_latency=0.7"], "loop.pilot.plan_latency must be in", 2),
    (["--set", "execution.speed.turn_accel=-1"], "execution.speed.turn_accel must be a positive number", 2),
    (["--set", "execution.speed.stop_decel=-1"], "execution.speed.stop_decel must be a positive number", 2),
    (["--set", "execution.route.after=-2"], "execution.route.after must be a positive number", 2),
    (["--set", "loop.pilot.horizon=-3"], "loop.pilot.horizon must be > 0", 2),
    (["--set", "min_distance=0"], "min_distance must be > 0", 2),
    (["--set", "gimbal=true"], "gimbal levels the camera of the rotorpy quadrotor", 2),
    (["--faults", "0,0.6,0"], "fault delay 0.6 must be in [0, replan interval 0.5 s)", 2),
    (["--set", "execution.follow=lots"], "execution.follow takes a finite number", 2),
    # research-only fields are no settings (the recipe sets them through the library)
    (["--set", "record_plans=true"], "has no setting 'record_plans'", 2),
])
def test_cli_bad_settings(tiny_run: Path, tmp_path: Path, args: list[str], message: str, code: int):
    r = CliRunner().invoke(main, ["eval", "--model", str(tiny_run), "-o", str(tmp_path / "ev"), *args])
    assert r.exit_code == code, r.output
    assert message in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_cli_bad_models(tmp_path: Path):
    empty = tmp_path / "empty_run"
    empty.mkdir()
    r = CliRunner().invoke(main, ["eval", "--model", str(empty), "-o", str(tmp_path / "ev")])
    assert r.exit_code == 1 and "has no model.pt" in r.output
    big = save_model(tmp_path / "big", PlannerConfig(input_size=(360, 640), encoder_width=0.125))
    r = CliRunner().invoke(main, ["eval", "--model", str(big), "-o", str(tmp_path / "ev")])
    assert r.exit_code == 1 and "360x640" in r.output and "120x160" in r.output
    r = CliRunner().invoke(main, ["eval", "-o", str(tmp_path / "ev"), "--methods", "learned"])
    assert r.exit_code == 1 and "--model" in r.output
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "model.pt").write_bytes(b"not a model")
    r = CliRunner().invoke(main, ["eval", "--model", str(tmp_path / "broken"), "-o", str(tmp_path / "ev")])
    assert r.exit_code == 1 and "is not a mapkit planner" in r.output
    assert not (tmp_path / "ev").exists()


def test_a_model_larger_than_its_recorded_training_camera_renders_that_camera(tmp_path: Path):
    """The paper preset (360x640) trained on a 160x120 dataset resizes those images up in training, and
    evaluating it renders the same camera and resizes the same way (only an unknown camera is refused,
    as in `test_cli_bad_models`)."""
    import dataclasses

    from mapkit.evaluation._run import _default_camera, _model_context

    recorded = dataclasses.replace(_default_camera(), source="recorded by the run")
    run = save_model(tmp_path / "paper", PlannerConfig(input_size=(360, 640), encoder_width=0.125),
                     camera=dataclasses.asdict(recorded))
    context = _model_context(run, EvalConfig(methods=("learned",)))
    assert (context.camera.height, context.camera.width) == (120, 160)
    assert context.camera.source == "recorded by the run"


def test_refuses_the_seed_of_a_training_world(tmp_path: Path):
    """The run's training workspace came from a simulated office with seed 3: evaluating office
    worlds with seed 3 would fly the training world."""
    from mapkit.ingest import ingest
    from mapkit.sim import SimConfig, simulate

    sim = simulate(SimConfig(world="office", seed=3, duration=1.0, width=48, height=36), tmp_path / "flight",
                   progress=False)
    ws = tmp_path / "ws"
    ingest([sim.bag_path], ws, progress=False)
    run = save_model(tmp_path / "run", planner_preset("cpu", input_size=(32, 48)), workspaces=[str(ws)])
    r = CliRunner().invoke(main, ["eval", "--model", str(run), "--world", "office", "--seed", "3", "--pairs", "1",
                                  "-o", str(tmp_path / "ev")])
    assert r.exit_code == 1 and "--seed 3 made the training world(s) office" in r.output, r.output
    # The camera comes from that workspace (48x36); a model with a taller input resizes its images up,
    # as its training did, and renders that camera.
    from mapkit.evaluation._run import _model_context

    tall = save_model(tmp_path / "tall", planner_preset("cpu", input_size=(48, 48)), workspaces=[str(ws)])
    context = _model_context(tall, EvalConfig(methods=("learned",)))
    assert (context.camera.width, context.camera.height) == (48, 36)


@pytest.mark.slow
def test_a_candidate_model_flies_with_the_rendered_camera_and_its_recorded_provenance(tmp_path: Path):
    """A model that checks its candidates against the depth image gets the loop camera's calibration;
    a run whose workspaces are gone (the shipped model) still names its camera and training worlds."""
    cfg = planner_preset("cpu", input_size=(48, 64), num_candidates=4, depth_check=True, velocity_input=True,
                         head_activation="leaky_relu")
    camera = {"width": 80, "height": 60, "K": [[48.4, 0.0, 39.5], [0.0, 48.4, 29.5], [0.0, 0.0, 1.0]],
              "T_body_camera": [[0.0, 0.0, 1.0, 0.08], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.02],
                                [0.0, 0.0, 0.0, 1.0]], "source": "recorded"}
    run = save_model(tmp_path / "multi", cfg, workspaces=["/nonexistent/ws"], camera=camera,
                     training_worlds=[["office", 5]])
    config = EvalConfig(worlds=("office",), pairs=1, seed=3, methods=("learned",))
    evaluate(run, tmp_path / "ev", config, progress=False)
    doc = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert doc["camera"]["width"] == 80 and doc["camera"]["source"] == "recorded"
    assert doc["episodes"][0]["plans"] >= 1
    r = CliRunner().invoke(main, ["eval", "--model", str(run), "--world", "office", "--seed", "5", "--pairs", "1",
                                  "-o", str(tmp_path / "ev5")])
    assert r.exit_code == 1 and "--seed 5 made the training world(s) office" in r.output, r.output


def test_a_blocked_plan_brakes_whatever_eta_says():
    """A method that finds no way ahead after its first plan: the vehicle comes to rest short of the
    wall the first plan runs into, although η never vetoes and the loop would fly on."""
    from mapkit.sim import HalfSpace

    world = World([HalfSpace((0.0, 0.0, 1.0), 0.0), Box((6.0, 0.0, 1.5), (0.1, 5.0, 1.5))],
                  np.array([[-2.0, -5.0, 0.0], [12.0, 5.0, 3.0]]))

    class Walled:
        name, needs_depth, replans = "walled", False, True

        def __init__(self) -> None:
            self.calls = 0

        def plan(self, obs: Observation) -> MethodPlan:
            self.calls += 1
            wp = torch.tensor([[[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]], dtype=torch.float64)
            with torch.no_grad():
                traj = min_snap(wp, torch.tensor([[5.0]], dtype=torch.float64),
                                start=torch.from_numpy(obs.state_world[1:4] @ obs.T_world_body[:3, :3])[None])
            pieces = pieces_from_body(traj.coeffs[0].numpy(), np.array([5.0]), obs.T_world_body, obs.t)
            return MethodPlan(pieces=pieces, latency_ms=0.0, eta=0.0, blocked=self.calls > 1)

    start, goal = np.array([0.0, 0.0, 1.5]), np.array([10.0, 0.0, 1.5])
    stopped = run_episode(world, start, goal, Walled(), LoopConfig(timeout_min=8.0))
    assert stopped.outcome == "timeout" and stopped.rejected_plans == stopped.plans - 1
    assert float(np.max(stopped.samples[:, 1])) < 6.0 - 0.1 - 0.3


def _forward_camera(w: int = 160, h: int = 96):
    from mapkit.planner import CameraInput

    K = np.array([[80.0, 0.0, w / 2 - 0.5], [0.0, 80.0, h / 2 - 0.5], [0.0, 0.0, 1.0]])
    T_body_camera = np.eye(4)
    T_body_camera[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]  # optical → FLU
    return CameraInput.from_calibration(K, w, h, T_body_camera)


def test_memory_keeps_a_wall_after_it_leaves_the_view_and_forgets_it_later():
    from mapkit.flight._learned import ROBOT_CLEARANCE, _Memory

    w, h = 160, 96
    depth = np.zeros((h, w), dtype=np.float32)  # no return
    depth[:, : w // 2] = 2.0  # a wall 2 m ahead on the left (+y)
    T0 = np.eye(4)
    memory = _Memory(seconds=4.0)

    def observe(t: float, T: np.ndarray, image: np.ndarray) -> None:
        memory.add(Observation(camera=_forward_camera(w, h), t=t, T_world_body=T, state_world=np.zeros((4, 3)), goal_world=np.array([9.0, 0.0, 0.0]),
                               local_goal_body=np.zeros(3), depth=image))

    observe(0.0, T0, depth)
    seen = memory.frames[0][1].data
    assert np.allclose(seen[:, 0], 2.0) and (seen[:, 1] > 0).all()  # on the plane x = 2, left half
    turned = np.eye(4)  # 90° to the right, nothing in view
    turned[:3, :3] = [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    observe(1.0, turned, np.zeros((h, w), dtype=np.float32))
    # body frame of the turned vehicle: +y (its left) is world +x; the wall is 2 m to its left
    near = torch.tensor([[[0.0, 2.0 - 0.5 * ROBOT_CLEARANCE, 0.0]], [[0.0, 2.0 - 2.0 * ROBOT_CLEARANCE, 0.0]]])
    assert memory.conflicts(near, turned).tolist() == [1, 0]
    observe(1.5, T0, np.full((h, w), 1.3, dtype=np.float32))  # a wall across x = 1.3 m: the second point's
    assert memory.conflicts(near, turned).tolist() == [1, 1]  # asked before, and the new image still counts
    observe(6.0, turned, np.zeros((h, w), dtype=np.float32))  # 6 s later: forgotten
    assert memory.conflicts(near, turned).tolist() == [0, 0]


def test_open_direction_points_through_the_doorway_and_none_when_walled_in():
    from mapkit.flight._learned import open_direction

    w, h = 160, 96
    camera = _forward_camera(w, h)
    depth = np.full((h, w), 2.0, dtype=np.float32)
    depth[:, 120:140] = 9.0  # an opening right of centre
    body = open_direction(depth, camera, np.array([6.0, 0.0, 0.0]), max_depth=10.0)
    assert body is not None and body[1] < 0 and body[2] == 0.0
    bearing = np.degrees(np.arctan2(-body[1], body[0]))
    column = np.degrees(np.arctan((np.array([120.0, 140.0]) - (w / 2 - 0.5)) / 80.0))
    assert column[0] - 0.5 <= bearing <= column[1] + 0.5
    assert abs(np.linalg.norm(body) - 5.0) < 1e-9  # capped reach
    assert open_direction(np.full((h, w), 2.0, dtype=np.float32), camera, np.array([6.0, 0.0, 0.0]), max_depth=10.0) is None


@pytest.mark.slow
def test_a_learned_method_carries_nothing_from_one_flight_to_the_next():
    """The same flight twice with one method instance (as a worker flies pair after pair): identical
    episodes, so the depth memory and the way-out subgoal start empty every flight."""
    from mapkit.flight._learned import LearnedMethod
    from mapkit.planner import CameraInput
    from mapkit.sim import CameraModel, render_depth

    torch.manual_seed(0)
    cfg = planner_preset("cpu", input_size=(48, 64), num_candidates=4, depth_check=True, velocity_input=True,
                         head_activation="leaky_relu")
    K = np.array([[48.4, 0.0, 39.5], [0.0, 48.4, 29.5], [0.0, 0.0, 1.0]])
    T_bc = np.array([[0.0, 0.0, 1.0, 0.08], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.02], [0.0, 0.0, 0.0, 1.0]])
    method = LearnedMethod("learned", PlannerNet(cfg), camera=CameraInput.from_calibration(K, 80, 60, T_bc))
    world = wall_world(x=6.0)
    camera = CameraModel(width=80, height=60, fx=48.4, fy=48.4)

    def render(T_world_body: np.ndarray) -> np.ndarray:
        return render_depth(world, T_world_body @ T_bc, camera)

    from mapkit.flight._recorded import RunCamera

    loop = LoopConfig(timeout_min=6.0, timeout_factor=0.1)
    rendered = RunCamera(80, 60, K, T_bc, "test")
    first = run_episode(world, START, GOAL, method, loop, render=render, camera=rendered)
    assert method._memory is not None and method._memory.frames  # it remembered the wall
    second = run_episode(world, START, GOAL, method, loop, render=render, camera=rendered)
    assert first.plans > 1 and first.outcome == second.outcome and first.plans == second.plans
    assert np.array_equal(first.samples, second.samples)


def test_a_blocked_vehicle_brakes_beside_a_remembered_wall_not_into_it():
    """Flying at 2 m/s toward a wall 1.2 m ahead (seen, remembered), the brake turns away from it; the
    pilot's brake goes along the direction the method gives, v² / a metres or farther (within its peak
    deceleration)."""
    from mapkit.flight import brake
    from mapkit.flight._learned import _Memory

    w, h = 160, 96
    memory = _Memory(seconds=4.0)
    depth = np.zeros((h, w), dtype=np.float32)
    depth[:, : w // 2 + 10] = 1.2  # a wall 1.2 m ahead, from the left edge to just right of the centre
    memory.add(Observation(camera=_forward_camera(w, h), t=0.0, T_world_body=np.eye(4), state_world=np.zeros((4, 3)), goal_world=np.zeros(3),
                           local_goal_body=np.zeros(3), depth=depth))
    state = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    direction = memory.clearest(np.eye(4), state)
    assert direction is not None and direction[1] < 0 and abs(np.linalg.norm(direction) - 1) < 1e-12  # to the right
    assert memory.clearest(np.eye(4), np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0, 0], [0, 0, 0]])) is None  # hovering
    stop = brake(state, 0.0, 3.0, direction)  # the body frame is the world's here
    end = stop.derivative(np.array([stop.t_end]), 0)[0]
    # along the direction, v² / a metres or farther: a turned brake is lengthened to keep its peak
    assert np.allclose(end / np.linalg.norm(end), direction, atol=1e-9) and np.linalg.norm(end) >= 2.0 ** 2 / 3.0
    t = np.linspace(stop.t0, stop.t_end, 400)
    assert np.linalg.norm(stop.derivative(t, 2), axis=1).max() <= 1.3 * 3.0 + 1e-6
    assert np.allclose(stop.derivative(np.array([stop.t_end]), 1)[0], 0.0, atol=1e-9)


def test_a_blocked_vehicle_turns_away_from_the_remembered_wall_beside_it():
    """Stopped with a wall 1 m to its right (seen and remembered), the vehicle turns left to look for
    a way; mirrored, right; with nothing remembered either way there is no preference."""
    from mapkit.flight._learned import _Memory

    w, h = 160, 96
    for yaw, expected in ((-90.0, 1.0), (90.0, -1.0)):  # looking right (the wall at y = −1 m), then left
        memory = _Memory(seconds=4.0)
        assert memory.open_side(np.eye(4)) is None
        memory.add(Observation(camera=_forward_camera(w, h), t=0.0, T_world_body=level_pose(np.zeros(3), np.radians(yaw)),
                               state_world=np.zeros((4, 3)), goal_world=np.zeros(3), local_goal_body=np.zeros(3),
                               depth=np.full((h, w), 1.0, dtype=np.float32)))
        assert memory.open_side(np.eye(4)) == expected


def test_the_hovering_vehicle_turns_the_way_the_method_asks():
    """A method that is blocked from the start and asks to turn clockwise: the camera turns clockwise,
    look turn after look turn; without an answer counter-clockwise."""
    world = World([Box((50.0, 50.0, 1.5), (0.1, 0.1, 0.1))], np.array([[-10.0, -10.0, 0.0], [60.0, 60.0, 3.0]]))

    class Stuck:
        name, needs_depth, replans = "stuck", False, True

        def __init__(self, side: float | None) -> None:
            self.side, self.yaws = side, []

        def plan(self, obs: Observation) -> MethodPlan:
            R = obs.T_world_body[:3, :3]
            self.yaws.append(float(np.degrees(np.arctan2(R[1, 0], R[0, 0]))))
            return MethodPlan(pieces=hold(obs.state_world[0], obs.t), latency_ms=0.0, eta=0.9, blocked=True,
                              turn_side=self.side)

    start, goal = np.array([0.0, 0.0, 1.5]), np.array([10.0, 0.0, 1.5])
    for side, step in ((-1.0, -60.0), (None, 60.0)):
        method = Stuck(side)
        run_episode(world, start, goal, method, LoopConfig(timeout_min=2.0))
        turns = (np.diff(method.yaws) + 180.0) % 360.0 - 180.0
        # the turns go the asked way, within the pilot's yaw rate, and keep going (a look around)
        assert len(turns) >= 4 and np.all(np.sign(turns[turns != 0]) == np.sign(step))
        assert np.abs(turns).max() <= np.degrees(PilotConfig().max_yaw_rate) * 0.5 + 1e-6
        assert abs(turns.sum()) > 2 * abs(step)


def test_a_hovering_vehicle_faces_the_point_its_method_names():
    """A method that hovers and names a point 90° to the left of the goal's bearing: from the second
    observation on, the camera turns to face that point (at the pilot's yaw rate limit) instead of the
    goal; naming none turns it back to the goal."""
    world = World([Box((50.0, 50.0, 1.5), (0.1, 0.1, 0.1))], np.array([[-10.0, -10.0, 0.0], [60.0, 60.0, 3.0]]))

    class Pointing:
        name, needs_depth, replans = "pointing", False, True

        def __init__(self) -> None:
            self.yaws: list[float] = []

        def plan(self, obs: Observation) -> MethodPlan:
            R = obs.T_world_body[:3, :3]
            self.yaws.append(float(np.degrees(np.arctan2(R[1, 0], R[0, 0]))))
            look = np.array([0.0, 5.0, 1.5]) if len(self.yaws) < 4 else None
            return MethodPlan(pieces=hold(obs.state_world[0], obs.t), latency_ms=0.0, eta=0.0, look_at=look)

    method = Pointing()
    run_episode(world, np.array([0.0, 0.0, 1.5]), np.array([10.0, 0.0, 1.5]), method, LoopConfig(timeout_min=3.0))
    yaws = method.yaws[:5]
    assert yaws[0] == pytest.approx(0.0, abs=1e-6) and 30.0 < yaws[1] < 90.0  # turning, within its limits
    assert yaws[3] == pytest.approx(90.0, abs=2.0)  # facing the point
    assert yaws[4] < yaws[3] - 10.0  # turning back toward the goal


def test_the_vehicle_looks_where_its_reference_turns():
    """With look-ahead the camera heads toward the reference 1.5 s on (into a left turn), without it
    along the velocity (both followed within the pilot's yaw limits)."""
    world = World([Box((50.0, 50.0, 1.5), (0.1, 0.1, 0.1))], np.array([[-10.0, -10.0, 0.0], [60.0, 60.0, 3.0]]))

    class Turning:
        name, needs_depth, replans = "turning", False, True

        def __init__(self) -> None:
            self.seen: list[Observation] = []
            self.first = None

        def plan(self, obs: Observation) -> MethodPlan:
            self.seen.append(obs)
            if self.first is None:  # one left turn, flown for the whole episode
                wp = torch.tensor([[[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [4.0, 4.0, 0.0]]], dtype=torch.float64)
                with torch.no_grad():
                    traj = min_snap(wp, torch.tensor([[2.0, 2.0]], dtype=torch.float64))
                self.first = pieces_from_body(traj.coeffs[0].numpy(), np.array([2.0, 2.0]), obs.T_world_body, obs.t)
            return MethodPlan(pieces=self.first, latency_ms=0.0, eta=0.0)

    start, goal = np.array([0.0, 0.0, 1.5]), np.array([4.0, 4.0, 1.5])
    yaws = {}
    for look in (0.0, 1.5):
        method = Turning()
        run_episode(world, start, goal, method, LoopConfig(timeout_min=3.0, pilot=PilotConfig(look_ahead=look, plan_latency=0.0)))
        obs = next(o for o in method.seen if 1.0 <= o.t <= 1.6)
        R = obs.T_world_body[:3, :3]
        v = obs.state_world[1]
        yaws[look] = (np.arctan2(R[1, 0], R[0, 0]), np.arctan2(v[1], v[0]),
                      method.first.derivative(np.array([obs.t + 1.5]), 0)[0] - obs.T_world_body[:3, 3])
    # the yaw follows its target within the yaw rate and acceleration limits: near it, not on it
    yaw, v_yaw, _ = yaws[0.0]
    assert abs(yaw - v_yaw) < 0.15
    yaw, v_yaw, ahead = yaws[1.5]
    assert abs(yaw - np.arctan2(ahead[1], ahead[0])) < 0.4 and yaw > v_yaw + 0.2  # turned further left


def test_follow_moves_interior_key_points_toward_the_reference_by_the_fraction_within_the_limit():
    """Each interior key-point moves ``fraction`` of the way to where the reference being flown is when
    the new plan reaches it, at most ``limit`` per axis; the start, the last key-point and key-points
    the reference does not reach in time stay."""
    from mapkit.flight._learned import follow_reference

    ref = rest_to_rest(4.0, 4.0)  # along +x from START, t in [0, 4]
    T_wb = np.eye(4)
    T_wb[:3, 3] = START
    obs = Observation(t=0.5, T_world_body=T_wb, state_world=ref.state(0.5), goal_world=GOAL,
                      local_goal_body=np.array([6.0, 0.0, 0.0]), depth=None, reference=ref)
    wp = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.4, 0.0], [2.0, -3.0, 0.2], [3.0, 0.0, 0.0], [6.0, 0.4, 0.0]]],
                      dtype=torch.float64)
    durations = torch.tensor([[1.0, 1.0, 2.0, 1.0]], dtype=torch.float64)  # key-points at t = 1.5, 2.5, 4.5, 5.5
    moved = follow_reference(wp, durations, obs, 0.5, 1.0)
    on_ref = ref.derivative(np.array([1.5, 2.5]), 0) - START  # body frame = world frame shifted
    want = wp.clone()
    want[0, 1:3] += 0.5 * (torch.from_numpy(on_ref) - wp[0, 1:3]).clamp(-1.0, 1.0)
    assert torch.allclose(moved, want, atol=1e-12)
    assert moved[0, 2, 1] == pytest.approx(-3.0 + 0.5)  # 3 m off: clipped to the 1 m limit, then halved
    assert torch.equal(moved[0, 3:], wp[0, 3:]) and torch.equal(moved[0, 0], wp[0, 0])
    assert torch.equal(follow_reference(wp, durations, obs, 0.0, 1.0), wp)
    no_ref = Observation(t=0.5, T_world_body=T_wb, state_world=ref.state(0.5), goal_world=GOAL,
                         local_goal_body=np.zeros(3), depth=None)
    assert torch.equal(follow_reference(wp, durations, no_ref, 0.5, 1.0), wp)


@pytest.mark.parametrize("follow", [-0.1, 1.5, float("nan")])
def test_a_follow_fraction_outside_0_1_is_refused_by_name(follow: float):
    from mapkit.evaluation import EvalError
    from mapkit.flight import Execution

    with pytest.raises(EvalError, match=r"execution\.follow must be in"):
        EvalConfig(execution=Execution(follow=follow)).validate()


@pytest.mark.parametrize("route, message", [
    ({"descend": -1.0}, "RouteConfig.descend must be >= 0 metres, got -1.0"),
    ({"cell": 0.0}, "RouteConfig.cell must be > 0 metres, got 0.0"),
    ({"height": float("nan")}, "RouteConfig.height must be > 0 metres"),
    ({"inflate": 1.2}, "RouteConfig.wary (1.0 m) must exceed RouteConfig.inflate (1.2 m)"),
    ({"ground": float("inf")}, "RouteConfig.ground must be a finite world height in metres"),
])
def test_a_bad_flight_map_setting_is_refused_by_name(route: dict[str, float], message: str):
    from mapkit.evaluation import EvalError
    from mapkit.flight import Execution, RouteConfig

    with pytest.raises(EvalError, match=re.escape(message)):
        EvalConfig(execution=Execution(route=RouteConfig(**route))).validate()


def _pace(**speed_profile: object):
    """The default flight stack with these :class:`SpeedProfile` settings."""
    from mapkit.flight import Execution, SpeedProfile

    return Execution(speed=SpeedProfile(**speed_profile))  # type: ignore[arg-type]  # each test's own values


def _tiny_learned_method(execution):
    from mapkit.flight._learned import LearnedMethod
    from mapkit.planner import CameraInput

    torch.manual_seed(0)
    cfg = planner_preset("cpu", input_size=(48, 64), num_candidates=4, depth_check=True, velocity_input=True,
                         head_activation="leaky_relu")
    K = np.array([[48.4, 0.0, 39.5], [0.0, 48.4, 29.5], [0.0, 0.0, 1.0]])
    T_bc = np.array([[0.0, 0.0, 1.0, 0.08], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.02], [0.0, 0.0, 0.0, 1.0]])
    return LearnedMethod("learned", PlannerNet(cfg), camera=CameraInput.from_calibration(K, 80, 60, T_bc),
                         execution=execution)


def _open_view_at_start(t: float = 0.0) -> Observation:
    T_wb = np.eye(4)
    T_wb[:3, 3] = START
    return Observation(t=t, T_world_body=T_wb, state_world=np.vstack([START, np.zeros((3, 3))]), goal_world=GOAL,
                       local_goal_body=np.array([6.0, 0.0, 0.0]), depth=np.full((60, 80), 5.0, dtype=np.float32),
                       goal_clipped=True)


def test_plans_are_timed_at_the_execution_speed_and_at_the_search_speed_once_stalled(monkeypatch):
    """Plans toward a local goal beyond the horizon pass it at ``SpeedProfile.cruise``, and the speed
    profile cruises at it (so the same plan at 1 m/s takes longer than at the model's 2 m/s). Once the
    flight has stalled, the rest of it flies at the model's own cruise speed; a new flight starts at
    ``cruise`` again."""
    from mapkit.flight import _learned as methods
    from mapkit.flight._route import Progress

    speeds: list[float] = []
    attempt = methods.LearnedMethod._attempt

    def recorded(self, obs, start, goal, end_speed):
        speeds.append(end_speed)
        return attempt(self, obs, start, goal, end_speed)

    monkeypatch.setattr(methods.LearnedMethod, "_attempt", recorded)
    slow, model = _tiny_learned_method(_pace(cruise=1.0)), _tiny_learned_method(_pace(cruise=None))
    durations = [m.plan(_open_view_at_start()).pieces.t_end for m in (slow, model)]
    assert speeds == [1.0, model.config.cruise_speed] and durations[0] > 1.5 * durations[1]
    monkeypatch.setattr(Progress, "update", lambda self, t, distance, config: t >= 0.5)  # stalled from 0.5 s
    fast = _tiny_learned_method(_pace(cruise=1.0))
    for t in (0.0, 0.5, 1.0):
        fast.plan(_open_view_at_start(t))
    fast.plan(_open_view_at_start(0.0))  # a new flight (time starts over): not stalled yet
    own = fast.config.cruise_speed
    assert own != 1.0 and speeds[2:] == [1.0, own, own, 1.0]


def test_plans_that_turn_are_timed_at_the_speed_of_their_sharpest_turn():
    """With ``turn_accel`` a plan's cruise speed and its speed at a passed goal are √(a R) of its
    sharpest turn (at least :data:`~mapkit.flight._layers.TURN_MIN_SPEED`); a straight plan keeps the cruise speed, and without
    ``turn_accel`` every plan does."""
    from mapkit.planner import plan_timing

    x = torch.linspace(0.0, 6.0, 6, dtype=torch.float64)
    line = torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], dim=-1)
    bent = line.clone()
    bent[3:, 0], bent[3:, 1] = bent[2, 0], x[1:4] - x[0]  # a right angle after 2.4 m, then 3.6 m sideways
    wp, start = torch.stack([line, bent]), torch.zeros(2, 3, 3, dtype=torch.float64)
    passing = torch.full((2,), 2.0, dtype=torch.float64)
    method = _tiny_learned_method(_pace(turn_accel=2.0, cruise=None))
    cruise = method.config.cruise_speed
    slow = (2.0 * 0.6) ** 0.5  # R = half the 1.2 m segment / tan 45°, above TURN_MIN_SPEED
    timing = method._timed(wp, start, passing)
    expected = plan_timing(wp, start, torch.tensor([2.0, slow], dtype=torch.float64), method.config,
                           tan=method.net.tan, cruise_speed=torch.tensor([cruise, slow], dtype=torch.float64))
    assert torch.allclose(timing.total, expected.total, rtol=1e-12) and float(timing.total[1]) > 1.5 * float(timing.total[0])
    assert timing.end[:, 0].norm(dim=-1).tolist() == pytest.approx([2.0, slow], rel=1e-12)
    floor = _tiny_learned_method(_pace(turn_accel=0.1, cruise=None))._timed(wp, start, passing)
    assert floor.end[1, 0].norm() == pytest.approx(1.0, rel=1e-12)  # TURN_MIN_SPEED
    plain = _tiny_learned_method(_pace(turn_accel=None, cruise=None))._timed(wp, start, passing)
    assert torch.allclose(plain.total, plan_timing(wp, start, passing, method.config, tan=method.net.tan).total, rtol=1e-12)
    assert plain.end[:, 0].norm(dim=-1).tolist() == pytest.approx([2.0, 2.0], rel=1e-12)


def test_plans_to_rest_slow_down_at_the_stop_deceleration():
    """A plan that ends at rest at its goal slows down at ``stop_decel`` (the model's ``accel``
    without it); a plan that passes its goal at speed keeps ``accel``."""
    from mapkit.planner import plan_timing

    x = torch.linspace(0.0, 6.0, 6, dtype=torch.float64)
    wp = torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], dim=-1).expand(2, 6, 3)
    start = torch.zeros(2, 3, 3, dtype=torch.float64)
    start[:, 0, 0] = 2.0
    end_speed = torch.tensor([0.0, 2.0], dtype=torch.float64)
    method = _tiny_learned_method(_pace(stop_decel=0.5, cruise=None))
    timing = method._timed(wp, start, end_speed)
    expected = plan_timing(wp, start, end_speed, method.config, tan=method.net.tan,
                           decel=torch.tensor([0.5, method.config.accel], dtype=torch.float64))
    assert torch.allclose(timing.total, expected.total, rtol=1e-12)
    plain = _tiny_learned_method(_pace(stop_decel=None, cruise=None))._timed(wp, start, end_speed)
    assert float(timing.total[0]) > float(plain.total[0]) and float(timing.total[1]) == float(plain.total[1])


def test_a_flight_searches_once_it_has_flown_much_farther_than_it_came_closer():
    """Straight at the goal (or weaving 1.1× the progress) is not searching; 2 m sideways is (flown 2 m
    > 1.4 × 0 + 1 m), and a flight that searched keeps searching when it then makes progress."""
    from mapkit.flight._learned import _Search

    straight, search = _Search(), _Search()
    for x in np.linspace(0.0, 8.0, 17):
        assert not straight.update(np.array([x, 0.0, 1.0]), 10.0 - x, 1.4, 1.0)
    weave = _Search()
    for k, x in enumerate(np.linspace(0.0, 8.0, 17)):
        assert not weave.update(np.array([x, 0.23 * (k % 2), 1.0]), 10.0 - x, 1.4, 1.0)
    assert not search.update(np.array([0.0, 0.0, 1.0]), 10.0, 1.4, 1.0)
    assert not search.update(np.array([0.0, 0.9, 1.0]), 10.0, 1.4, 1.0)
    assert search.update(np.array([0.0, 2.0, 1.0]), 10.0, 1.4, 1.0)
    assert search.update(np.array([5.0, 2.0, 1.0]), 5.0, 1.4, 1.0) and search.searching


@pytest.mark.parametrize("value", [0.0, float("nan"), -2.0])
def test_a_speed_that_is_not_positive_is_refused_by_name(value: float):
    from mapkit.evaluation import EvalError

    with pytest.raises(EvalError, match=r"execution\.speed\.cruise must be a positive speed in m/s"):
        EvalConfig(execution=_pace(cruise=value)).validate()


@pytest.mark.parametrize("setting, message", [({"search_ratio": 0.9}, "SpeedProfile.search_ratio must be >= 1"),
                                              ({"search_margin": float("nan")}, "SpeedProfile.search_margin must be >= 0")])
def test_a_bad_search_setting_is_refused_by_name(setting: dict[str, float], message: str):
    from mapkit.evaluation import EvalError

    with pytest.raises(EvalError, match=re.escape(message)):
        EvalConfig(execution=_pace(**setting)).validate()


def test_plans_toward_a_way_out_pass_it_at_the_cruise_speed(monkeypatch):
    """When nothing leads on toward the goal, the network plans toward the open direction, and keeps
    that way-out point for the next plans; those plans pass it at the cruise speed."""
    import dataclasses

    from mapkit.flight import Execution, Memory, SpeedProfile
    from mapkit.flight import _learned as methods

    method = _tiny_learned_method(Execution(memory=Memory(), speed=SpeedProfile(cruise=1.5)))
    expected = 1.5  # not the model's own 2 m/s
    speeds: list[float] = []
    attempt = methods.LearnedMethod._attempt

    def recorded(self, obs, start, goal, end_speed):
        speeds.append(end_speed)
        return attempt(self, obs, start, goal, end_speed)

    monkeypatch.setattr(methods.LearnedMethod, "_attempt", recorded)
    # The network's first plan is blocked by what the vehicle remembers; everything after it is clear.
    monkeypatch.setattr(methods.LearnedMethod, "_remembered",
                        lambda self, obs, start, a: dataclasses.replace(a, blocked=len(speeds) == 1))
    monkeypatch.setattr(methods, "open_direction", lambda *args, **kwargs: np.array([3.0, 1.0, 0.0]))
    obs = _open_view_at_start()
    method.plan(obs)
    assert speeds == [expected, expected] and method.config.cruise_speed != expected
    method.plan(dataclasses.replace(obs, t=0.5))  # the way out is kept for subgoal_time
    assert speeds[2] == expected


def test_the_corridor_keeps_clear_of_a_remembered_door_jamb():
    """Key-points turn left around a door jamb the camera no longer sees: the widest corridor cuts
    the corner into it. Checked against the depth image alone it is kept; with the memory
    (``Corridor.check_memory``) the corridor narrows until it keeps as clear as the key-points."""
    from scipy.spatial import cKDTree

    from mapkit.flight import Memory
    from mapkit.flight._learned import _Checker, _execute, _Memory, _samples
    from mapkit.planner import preprocess_depth

    w, h = 160, 96
    memory = _Memory(seconds=4.0)
    jamb = np.array([[1.0, 0.75, z] for z in np.linspace(-1.0, 1.0, 21)])  # inside the turn
    memory.frames = [(0.0, cKDTree(jamb))]
    x = preprocess_depth(torch.zeros(1, h, w), input_size=(h, w), max_depth=10.0)  # nothing in view now
    wp = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 1.0, 0.0], [2.0, 2.0, 0.0]]],
                      dtype=torch.float64)
    T = torch.full((1, 4), 0.6, dtype=torch.float64)
    start, end = torch.zeros(1, 3, 3, dtype=torch.float64), torch.zeros(1, 3, 3, dtype=torch.float64)
    how = _pace(v_max=math.inf, a_max=math.inf)
    in_view = _Checker(x, _forward_camera(w, h), 10.0, None)
    within = Memory().blocked_within
    recalled = _Checker(x, _forward_camera(w, h), 10.0, None, recall=(memory, np.eye(4), within))

    def near_jamb(traj) -> int:
        return int(memory.conflicts(_samples(traj, within=within)[0], np.eye(4))[0])

    pinned = min_snap(wp, T, start=start, end=end)
    widest = _execute(wp, T, start, end, how, in_view)
    assert near_jamb(pinned) == 0 and near_jamb(widest) > 0  # the corridor cuts the corner into the jamb
    kept = _execute(wp, T, start, end, how, recalled)
    assert near_jamb(kept) == 0
    assert not torch.allclose(kept.coeffs, widest.coeffs)


def test_an_unchecked_corridor_is_at_most_its_unchecked_width():
    """Without its check the corridor flies at ``Corridor.unchecked_width`` (the narrower of it and
    ``width``): the plan's reference is the one bounded by that width, closer to the key-points' path
    around a turn than the 1 m corridor the check would have allowed."""
    from dataclasses import replace

    from mapkit.flight import Corridor
    from mapkit.flight._learned import _execute, _limited

    assert Corridor().widest(True) == 1.0 and Corridor().widest(False) == 0.3
    assert Corridor(width=0.2).widest(False) == 0.2
    assert Corridor(width=None).widest(True) is None
    wp = torch.tensor([[[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 2.0, 0.0], [4.0, 2.0, 0.0]]], dtype=torch.float64)
    T = torch.full((1, 3), 1.5, dtype=torch.float64)
    start, end = torch.zeros(1, 3, 3, dtype=torch.float64), torch.zeros(1, 3, 3, dtype=torch.float64)
    how = _pace(v_max=math.inf, a_max=math.inf)
    unchecked = _execute(wp, T, start, end, replace(how, corridor=replace(how.corridor, check=False)))
    narrow, wide = _limited(wp, T, start, end, how, 0.3), _limited(wp, T, start, end, how, 1.0)
    assert torch.allclose(unchecked.coeffs, narrow.coeffs)
    corner = torch.tensor([2.0, 0.0, 0.0], dtype=torch.float64)

    def closest_to_corner(traj) -> float:
        t = torch.linspace(0.0, float(T.sum()), 901, dtype=torch.float64)
        return float((traj.position(t)[0] - corner).norm(dim=-1).min())

    assert closest_to_corner(unchecked) < closest_to_corner(wide)  # the wide corridor cuts the corner more


@pytest.mark.slow
def test_time_limit_follows_the_pace_the_flights_are_asked_for(tiny_run: Path, tmp_path: Path):
    """The time limit is timeout_factor × distance / cruise speed: the model's cruise speed, or execution.speed.cruise."""

    docs = {}
    for name, speed in (("model", None), ("slow", 0.8)):
        config = EvalConfig(worlds=("office",), pairs=1, seed=3, methods=("straight",), execution=_pace(cruise=speed),
                            loop=LoopConfig(timeout_min=0.0))
        evaluate(tiny_run, tmp_path / name, config, progress=False)
        docs[name] = json.loads((tmp_path / name / "results.json").read_text())
    assert docs["model"]["config"]["loop"]["cruise_speed"] == planner_preset("cpu").cruise_speed
    assert docs["slow"]["config"]["loop"]["cruise_speed"] == 0.8
    assert "4 × distance / 0.8 m/s" in (tmp_path / "slow" / "report.md").read_text()
    # the same judge for flights made elsewhere (over DDS): the limit eval wrote, from the loop it returns
    for name, speed in (("model", None), ("slow", 0.8)):
        loop = judging_loop(tiny_run, EvalConfig(execution=_pace(cruise=speed), loop=LoopConfig(timeout_min=0.0)))
        episode = docs[name]["episodes"][0]
        assert loop.cruise_speed == docs[name]["config"]["loop"]["cruise_speed"]
        assert loop.time_limit(episode["distance"]) == pytest.approx(4.0 * episode["distance"] / loop.cruise_speed)
    assert LoopConfig().time_limit(1.0) == 20.0  # never under timeout_min


# ------------------------------------------------------------------------------ keeping the last plan's candidate
def _three_candidates(scores: list[float], eta_logits: list[float]):
    """A network answer with three candidates (distinct lateral offsets), chosen as the network does."""
    from mapkit.planner import PlannerOutput
    from mapkit.planner._model import choose_candidate

    candidates = torch.zeros(1, 3, 2, 3)
    candidates[0, :, :, 1] = torch.tensor([[0.0], [1.5], [-1.5]])
    s, e = torch.tensor([scores]), torch.tensor([eta_logits])
    chosen = choose_candidate(s, e)
    logit = e[0, chosen]
    return PlannerOutput(keypoints=candidates[:, int(chosen[0])], eta=torch.sigmoid(logit), eta_logit=logit,
                         candidates=candidates, candidate_eta_logits=e, scores=s, chosen=chosen)


@pytest.mark.parametrize("margin, previous, scores, eta_logits, expected", [
    (3.0, 1, [2.0, 0.0, -5.0], [-1.0, -1.0, -1.0], 1),   # accepted and within the margin: kept
    (3.0, 1, [4.0, 0.0, -5.0], [-1.0, -1.0, -1.0], 0),   # scored more than the margin below the best: switch
    (3.0, 1, [2.0, 0.0, -5.0], [-1.0, 0.5, -1.0], 0),    # the judge rejects it now (η >= 0.5): switch
    (None, 1, [2.0, 0.0, -5.0], [-1.0, -1.0, -1.0], 0),  # the layer off: the network's choice
    (3.0, None, [2.0, 0.0, -5.0], [-1.0, -1.0, -1.0], 0),  # the first plan of a flight
])
def test_a_replan_keeps_the_last_candidate_only_while_accepted_and_within_the_margin(margin, previous, scores,
                                                                                       eta_logits, expected):
    from types import SimpleNamespace

    from mapkit.flight import Execution
    from mapkit.flight._learned import LearnedMethod

    method = SimpleNamespace(execution=Execution(keep_choice=margin), _chosen=previous)
    out = LearnedMethod._kept(method, _three_candidates(scores, eta_logits))  # type: ignore[arg-type]
    assert int(out.chosen[0]) == expected
    assert torch.equal(out.keypoints, out.candidates[:, expected])
    assert float(out.eta_logit[0]) == eta_logits[expected]


@pytest.mark.parametrize("margin", [-1.0, float("nan")])
def test_a_negative_keep_choice_margin_is_refused_by_name(margin: float):
    from mapkit.evaluation import EvalError
    from mapkit.flight import Execution

    with pytest.raises(EvalError, match=r"execution\.keep_choice must be a positive number"):
        EvalConfig(execution=Execution(keep_choice=margin)).validate()


def test_the_flown_candidate_is_found_among_the_networks_and_nothing_else_is():
    from mapkit.flight._learned import _Attempt, _candidate_index

    out = _three_candidates([0.0, 1.0, 2.0], [-1.0, -1.0, -1.0])
    flown = _Attempt(out.candidates[0, 2].double().numpy(), 0.1, None, 0.0, out=out)  # type: ignore[arg-type]
    assert _candidate_index(flown) == 2
    elsewhere = _Attempt(out.candidates[0, 2].double().numpy() + 0.3, 0.1, None, 0.0, out=out)  # type: ignore[arg-type]
    assert _candidate_index(elsewhere) is None  # key-points that are no candidate of that pass


def test_faults_drop_delay_and_noise_the_frames_the_pilot_gets():
    """Dropped frames reach the pilot without depth (it plans only from the others), a delayed frame is
    rendered and posed where the body was ``delay`` ago, and pose noise moves the state and the frame
    alike; the same pair draws the same faults."""
    from mapkit.evaluation import Faults
    from mapkit.flight._recorded import RunCamera

    K = np.array([[50.0, 0.0, 31.5], [0.0, 50.0, 23.5], [0.0, 0.0, 1.0]])
    T_bc = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    rendered: list[np.ndarray] = []

    def render(T_world_body: np.ndarray) -> np.ndarray:
        rendered.append(T_world_body[:3, 3].copy())
        return np.full((48, 64), 4.0, dtype=np.float32)

    class Seeing(Jittery):
        needs_depth = True

        def __init__(self) -> None:
            super().__init__()
            self.frames: list[np.ndarray] = []

        def plan(self, obs: Observation) -> MethodPlan:
            self.frames.append(obs.T_world_body[:3, 3].copy())
            return super().plan(obs)

    camera = RunCamera(64, 48, K, T_bc, "test")
    clean, faulty = Seeing(), Seeing()
    loop = LoopConfig(timeout_min=6.0, timeout_factor=0.1)
    run_episode(empty_world(), START, GOAL, clean, loop, render=render, camera=camera)
    rendered.clear()
    faults = Faults(drop=0.3, delay=0.1, pose_noise=0.05, seed=3)
    run_episode(empty_world(), START, GOAL, faulty, dataclasses.replace(loop, faults=faults), render=render, camera=camera)
    assert 0 < len(faulty.frames) < len(clean.frames)  # some frames lost
    assert len(rendered) == len(faulty.frames)
    moved = [np.linalg.norm(given - seen) for given, seen in zip(faulty.frames, rendered, strict=True)]
    assert 0.0 < np.mean(moved) < 0.15  # the planning frame is the seen pose plus the noise
    again = Seeing()
    run_episode(empty_world(), START, GOAL, again, dataclasses.replace(loop, faults=faults), render=render, camera=camera)
    assert np.allclose(np.array(again.frames), np.array(faulty.frames))


@pytest.mark.slow
def test_cli_eval_flies_the_rotorpy_quadrotor_and_reports_its_tracking(tmp_path: Path):
    """``--vehicle rotorpy``: the shipped pilot flies rotorpy's quadrotor (camera tilting with it); the
    flight is recorded with a tracking error that is not the tracker's zero, and the report says so."""
    pytest.importorskip("rotorpy")
    out = tmp_path / "ev"
    r = CliRunner().invoke(main, ["eval", "--model", "pretrained", "--world", "forest", "--pairs", "1", "--seed", "10003",
                                  "--methods", "learned", "--vehicle", "rotorpy", "-o", str(out)])
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "results.json").read_text())
    (episode,) = doc["episodes"]
    assert doc["config"]["vehicle"] == "rotorpy"
    assert 0.0 < episode["tracking_error_mean"] <= episode["tracking_error_max"] < 1.0
    assert 0.0 < episode["reference_peak_acceleration"] and episode["climb"] >= 0.0
    assert "## Tracking — the vehicle (rotorpy)" in (out / "report.md").read_text()
