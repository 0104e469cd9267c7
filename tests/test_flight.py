"""The pilot (mapkit.flight): its reference against finite differences and its limits, continuity at
every switch, the camera contract, the status on stale or inconsistent inputs, and one-line errors."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from mapkit.flight import (
    FlightError,
    MethodPlan,
    Observation,
    Pieces,
    Pilot,
    PilotConfig,
    Reference,
    VehicleState,
    hold,
    pieces_from_body,
)
from mapkit.flight._recorded import RunCamera
from mapkit.flight._reference import YawFollower
from mapkit.trajopt import min_snap

W, H = 160, 120
K = np.array([[100.0, 0.0, W / 2 - 0.5], [0.0, 100.0, H / 2 - 0.5], [0.0, 0.0, 1.0]])
T_BODY_CAMERA = np.array([[0.0, 0.0, 1.0, 0.1], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
CAMERA = RunCamera(W, H, K, T_BODY_CAMERA, "test")
GOAL = np.array([20.0, 0.0, 1.5])


class Ahead:
    """Plans one minimum-snap segment from the reference's state to the local goal (3 s), η given."""

    name, needs_depth, replans = "ahead", True, True

    def __init__(self, eta: float = 0.0, blocked: bool = False) -> None:
        self.eta, self.blocked = eta, blocked
        self.within_limits = True
        self.seen: list[Observation] = []

    def plan(self, obs: Observation) -> MethodPlan:
        self.seen.append(obs)
        start = obs.start_body()
        goal = obs.local_goal_body * min(1.0, 3.0 / np.linalg.norm(obs.local_goal_body))
        wp = torch.from_numpy(np.stack([start[0], goal]))[None]
        traj = min_snap(wp, torch.tensor([[3.0]], dtype=torch.float64), start=torch.from_numpy(start[1:])[None])
        pieces = pieces_from_body(traj.coeffs[0].numpy(), np.array([3.0]), obs.T_world_body, obs.t)
        return MethodPlan(pieces=pieces, latency_ms=0.0, eta=self.eta, blocked=self.blocked,
                          within_limits=self.within_limits)


def depth_image() -> np.ndarray:
    return np.full((H, W), 5.0, dtype=np.float32)


def level(position: np.ndarray, yaw: float = 0.0, pitch: float = 0.0) -> np.ndarray:
    """T_world_body at ``position``, yawed then pitched (nose down for pitch > 0, FLU)."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    T = np.eye(4)
    T[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    T[:3, 3] = position
    return T


def fly(pilot: Pilot, steps: int, interval: float = 0.5, **frame: object) -> list:
    """Steps of a vehicle that follows its reference exactly, one frame per interval."""
    out, t, p = [], 0.0, np.array([0.0, 0.0, 1.5])
    for _ in range(steps):
        ref = pilot.reference
        state = VehicleState(p) if ref is None else VehicleState(ref.derivative(t, 0)[0], ref.derivative(t, 1)[0],
                                                                   yaw=float(ref.yaw(t)[0]))
        out.append(pilot.step(t, state, GOAL, depth_image(), T_world_body=level(state.position, state.yaw), **frame))
        t += interval
    return out


def test_a_reference_samples_position_through_snap_and_yaw_consistently():
    rng = np.random.default_rng(0)
    pieces = Pieces(t0=1.0, durations=np.array([0.8, 1.1]), coeffs=rng.normal(size=(2, 3, 8)))
    ref = Reference(pieces, YawFollower(lambda t: np.full(len(t), 2.0), 1.0, 0.3, 0.0, 3.0, 12.0, pieces.t_end + 3.0))
    t, h = 1.37, 1e-6
    a, b, mid = ref.sample(t - h), ref.sample(t + h), ref.sample(t)
    for lo, hi in (("position", "velocity"), ("velocity", "acceleration"), ("acceleration", "jerk"), ("jerk", "snap")):
        assert np.allclose((getattr(b, lo) - getattr(a, lo)) / (2 * h), getattr(mid, hi), rtol=1e-4, atol=1e-4)
    # yaw rate: the yaw's derivative (linear between samples); within the rate and acceleration limits
    times = np.linspace(1.0, ref.t_end + 2.0, 2001)
    yaw = np.unwrap(ref.yaw(times))
    rate = ref.yaw_rate(times)
    assert np.abs(np.gradient(yaw, times) - rate).max() < 0.2
    assert np.abs(rate).max() <= 3.0 + 1e-9 and np.abs(np.diff(rate) / np.diff(times)).max() <= 12.0 + 1e-6
    assert yaw[0] == pytest.approx(0.3) and yaw[-1] == pytest.approx(2.0, abs=1e-3)  # it gets there


def test_every_new_reference_is_C3_with_the_last_at_the_switch_and_yaw_continuous():
    pilot = Pilot(Ahead(), camera=CAMERA)
    steps = fly(pilot, 8)
    assert all(s.status == "cruising" and s.taken for s in steps)
    for k, (old, new) in enumerate(itertools.pairwise(steps), start=1):
        t = 0.5 * k + pilot.config.plan_latency
        assert np.abs(old.reference.state(t) - new.reference.state(t)).max() < 1e-6  # position … jerk
        switch = 0.5 * k
        assert new.reference.yaw(switch)[0] == pytest.approx(old.reference.yaw(switch)[0], abs=1e-9)
        assert new.reference.yaw_rate(switch)[0] == pytest.approx(old.reference.yaw_rate(switch)[0], abs=1e-9)


def test_plans_start_from_the_reference_not_the_noisy_vehicle_state():
    pilot = Pilot(Ahead(), camera=CAMERA)
    fly(pilot, 2)
    ref = pilot.reference
    assert ref is not None
    t = 1.0
    noisy = VehicleState(ref.derivative(t, 0)[0] + [0.1, -0.1, 0.05], ref.derivative(t, 1)[0] + 0.5)
    pilot.step(t, noisy, GOAL, depth_image(), T_world_body=level(noisy.position))
    obs = pilot.planner.seen[-1]
    assert np.allclose(obs.state_world, ref.state(t + pilot.config.plan_latency))


def test_frames_stopping_brake_the_vehicle_to_rest_then_hold():
    config = PilotConfig(frame_timeout=0.5, brake_deceleration=3.0)
    pilot = Pilot(Ahead(), camera=CAMERA, config=config)
    steps = fly(pilot, 4)
    ref = steps[-1].reference
    t = 1.5

    def state(at: float) -> VehicleState:
        return VehicleState(ref.derivative(at, 0)[0], ref.derivative(at, 1)[0])

    assert pilot.step(t + 0.3, state(t + 0.3), GOAL).status == "cruising"  # within the timeout: keep flying
    braking = pilot.step(t + 0.6, state(t + 0.6), GOAL)
    assert braking.status == "braking" and "no depth frame" in braking.reason
    brake = braking.reference
    tb = np.linspace(t + 0.6, brake.t_end, 400)
    assert np.abs(brake.derivative(tb, 2)).max() <= 1.1 * config.brake_deceleration  # within the brake's rate
    assert np.linalg.norm(brake.derivative(brake.t_end, 1)) < 1e-9  # to rest
    assert np.abs(brake.state(t + 0.6) - ref.state(t + 0.6)).max() < 1e-6  # from where it was
    later = pilot.step(brake.t_end + 0.1, VehicleState(brake.derivative(brake.t_end, 0)[0]), GOAL)
    assert later.status == "blocked" and later.reference is brake  # holds, never a plan past its end


def test_frames_that_see_nothing_mid_flight_count_as_missing_frames():
    pilot = Pilot(Ahead(), camera=CAMERA, config=PilotConfig(frame_timeout=0.5))
    ref = fly(pilot, 4)[-1].reference  # frames with valid pixels up to t = 1.5 s
    empty = np.full((H, W), np.nan, dtype=np.float32)  # e.g. pitched toward open space: nothing in range

    def step(at: float):
        state = VehicleState(ref.derivative(at, 0)[0], ref.derivative(at, 1)[0])
        return pilot.step(at, state, GOAL, empty, T_world_body=level(state.position))

    kept = step(1.8)
    assert kept.status == "cruising" and not kept.replanned and kept.reference is ref
    braking = step(2.1)
    assert braking.status == "braking" and "no depth frame with a valid pixel" in braking.reason


def test_a_plan_that_breaks_the_limits_is_not_flown():
    planner = Ahead()
    pilot = Pilot(planner, camera=CAMERA)
    ref = fly(pilot, 2)[-1].reference
    planner.within_limits = False
    step = pilot.step(1.0, VehicleState(ref.derivative(1.0, 0)[0], ref.derivative(1.0, 1)[0]), GOAL,
                      depth_image(), T_world_body=level(ref.derivative(1.0, 0)[0]))
    assert step.replanned and not step.taken and step.reference is ref
    assert step.status == "cruising" and "breaks the speed or acceleration limits" in step.reason


def test_a_frame_far_from_the_vehicle_state_brakes_and_says_why():
    pilot = Pilot(Ahead(), camera=CAMERA, config=PilotConfig(pose_tolerance=0.5))
    fly(pilot, 2)
    ref = pilot.reference
    assert ref is not None
    state = VehicleState(ref.derivative(1.0, 0)[0], ref.derivative(1.0, 1)[0])
    step = pilot.step(1.0, state, GOAL, depth_image(), T_world_body=level(state.position + [2.0, 0.0, 0.0]))
    assert step.status == "braking" and "2.00 m from the vehicle's state" in step.reason and not step.replanned


def test_a_vehicle_pushed_off_its_reference_brakes_from_its_own_state():
    pilot = Pilot(Ahead(eta=0.9), camera=CAMERA, config=PilotConfig(resync_distance=1.0))
    fly(pilot, 1)
    pushed = VehicleState([0.0, 3.0, 1.5], [0.0, 1.0, 0.0])
    step = pilot.step(0.5, pushed, GOAL, depth_image(), T_world_body=level(pushed.position))
    assert np.allclose(step.reference.derivative(0.5, 0)[0], pushed.position)
    assert np.allclose(step.reference.derivative(0.5, 1)[0], pushed.velocity)
    assert step.status == "braking"


def test_a_vetoed_plan_at_rest_turns_to_look_elsewhere_and_reaching_the_goal_stops_planning():
    pilot = Pilot(Ahead(eta=0.9), camera=CAMERA)
    steps = fly(pilot, 3)
    assert [s.status for s in steps] == ["blocked"] * 3 and not any(s.taken for s in steps)
    turns = steps[-1].reference.yaw(3.0)[0] / math.radians(pilot.config.look_turn_deg)  # counter-clockwise
    assert turns >= 1.0 - 1e-3 and abs(turns - round(turns)) < 1e-3  # whole look turns, each one finished
    at_goal = pilot.step(2.0, VehicleState(GOAL + 0.1), GOAL, depth_image(), T_world_body=level(GOAL + 0.1))
    assert at_goal.status == "reached" and not at_goal.replanned


def test_a_camera_that_tilts_with_the_airframe_is_described_in_the_level_planning_frame():
    pilot = Pilot(Ahead(), camera=CAMERA)
    pitch = math.radians(12.0)
    pilot.step(0.0, VehicleState([0.0, 0.0, 1.5], yaw=0.4), GOAL, depth_image(),
               T_world_body=level(np.array([0.0, 0.0, 1.5]), yaw=0.4, pitch=pitch))
    obs = pilot.planner.seen[-1]
    R = obs.T_world_body[:3, :3]
    assert np.allclose(R[:, 2], [0, 0, 1]) and math.atan2(R[1, 0], R[0, 0]) == pytest.approx(0.4)  # level, yawed
    assert obs.camera is not None
    T_plan_camera = np.linalg.inv(obs.camera.T_camera_body[0].double().numpy())
    optical_axis = T_plan_camera[:3, 2]
    assert math.degrees(math.asin(-optical_axis[2])) == pytest.approx(12.0, abs=1e-3)  # looks 12° down
    same = Pilot(Ahead(), camera=CAMERA)  # the same pose given as T_world_camera
    T_wc = level(np.array([0.0, 0.0, 1.5]), yaw=0.4, pitch=pitch) @ T_BODY_CAMERA
    same.step(0.0, VehicleState([0.0, 0.0, 1.5], yaw=0.4), GOAL, depth_image(), T_world_camera=T_wc)
    other = same.planner.seen[-1]
    assert np.allclose(other.camera.T_camera_body.numpy(), obs.camera.T_camera_body.numpy(), atol=1e-5)


def test_an_image_at_another_resolution_with_the_same_field_of_view_is_used():
    pilot = Pilot(Ahead(), camera=CAMERA)
    K2 = K.copy()
    K2[:2] *= 2.0
    K2[:2, 2] = [W - 0.5, H - 0.5]
    step = pilot.step(0.0, VehicleState([0.0, 0.0, 1.5]), GOAL, np.full((2 * H, 2 * W), 5.0, np.float32), K=K2,
                      T_world_body=level(np.array([0.0, 0.0, 1.5])))
    assert step.replanned


@pytest.mark.parametrize(("change", "message"), [
    ({"depth": np.zeros((H, W), dtype=np.uint16)}, "dtype uint16; pass float metres"),
    ({"depth": np.full((H, W), np.nan, dtype=np.float32)}, "no valid pixel"),
    ({"depth": np.zeros((2, H, W), dtype=np.float32)}, "one \\(H, W\\) image"),
    ({"K": K * [[1.3], [1.3], [1.0]]}, "trained on .* crop or resize"),
    ({"depth": np.full((60, 80), 5.0, np.float32)}, "no K was given"),
    ({"T_world_body": np.full((4, 4), np.nan)}, "T_world_body is not finite"),
    ({"goal": np.array([1.0, np.nan, 0.0])}, "goal_world .* is not finite"),
    ({"T_world_body": None}, "needs the camera's pose"),
])
def test_bad_inputs_are_refused_in_one_line_naming_the_fix(change: dict, message: str):
    pilot = Pilot(Ahead(), camera=CAMERA)
    kw = {"depth": depth_image(), "K": None, "T_world_body": level(np.array([0.0, 0.0, 1.5])), "goal": GOAL} | change
    with pytest.raises(FlightError, match=message) as info:
        pilot.step(0.0, VehicleState([0.0, 0.0, 1.5]), kw["goal"], kw["depth"], K=kw["K"], T_world_body=kw["T_world_body"])
    assert "\n" not in str(info.value)


def test_stamps_that_go_backwards_and_bad_states_are_refused():
    pilot = Pilot(Ahead(), camera=CAMERA)
    fly(pilot, 2)
    with pytest.raises(FlightError, match="before the last call's"):
        pilot.step(0.1, VehicleState([0.0, 0.0, 1.5]), GOAL)
    with pytest.raises(FlightError, match=r"state.velocity .* is not finite"):
        VehicleState([0.0, 0.0, 1.5], [np.inf, 0.0, 0.0])
    with pytest.raises(FlightError, match=r"PilotConfig.frame_timeout must be"):
        Pilot(Ahead(), config=PilotConfig(frame_timeout=0.0))


def test_a_first_call_while_moving_plans_from_the_vehicles_velocity():
    pilot = Pilot(Ahead(), camera=CAMERA)
    moving = VehicleState([0.0, 0.0, 1.5], [1.5, 0.5, 0.0])
    step = pilot.step(3.0, moving, GOAL, depth_image(), T_world_body=level(moving.position))
    assert step.taken and np.allclose(step.reference.derivative(3.0, 1)[0], moving.velocity)
    obs = pilot.planner.seen[-1]  # planned from (nearly) that velocity, not from rest
    assert np.linalg.norm(obs.state_world[1] - moving.velocity) < 0.1


def test_a_new_goal_starts_a_new_flight_from_the_reference_being_flown():
    pilot = Pilot(Ahead(), camera=CAMERA)
    steps = fly(pilot, 3)
    ref = steps[-1].reference
    state = VehicleState(ref.derivative(1.5, 0)[0], ref.derivative(1.5, 1)[0])
    new = pilot.step(1.5, state, np.array([0.0, 20.0, 1.5]), depth_image(), T_world_body=level(state.position))
    assert new.replanned and np.abs(new.reference.state(1.5) - ref.state(1.5)).max() < 1e-9


def test_without_a_frame_a_planner_that_needs_none_plans_at_its_interval():
    class Blind(Ahead):
        needs_depth = False

    pilot = Pilot(Blind())
    first = pilot.step(0.0, VehicleState([0.0, 0.0, 1.5]), GOAL)
    second = pilot.step(0.2, VehicleState(first.reference.derivative(0.2, 0)[0]), GOAL)
    third = pilot.step(0.5, VehicleState(first.reference.derivative(0.5, 0)[0]), GOAL)
    assert first.replanned and not second.replanned and third.replanned
    assert hold(np.zeros(3), 0.0).degree == 7


def test_a_plan_too_sharp_for_the_limits_is_flown_slower_within_them():
    """Key-points zig-zagging 1 m apart in 0.4 s segments ask for tens of m/s²; with the acceleration
    limit the plan keeps it (norm, on a dense grid), through the same key-points."""
    from mapkit.flight import Execution, SpeedProfile
    from mapkit.flight._learned import _limited

    wp = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, -1.0, 0.0], [3.0, 1.0, 0.0]]], dtype=torch.float64)
    T = torch.full((1, 3), 0.4, dtype=torch.float64)
    start, end = torch.zeros(1, 3, 3, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64)
    free = Execution(speed=SpeedProfile(v_max=math.inf, a_max=math.inf))
    assert float(_limited(wp, T, start, end, free, None).max_acceleration(samples_per_segment=256)) > 20.0
    kept = _limited(wp, T, start, end, Execution(), None)
    assert float(kept.max_acceleration(samples_per_segment=256)) <= 4.0 + 1e-6
    assert float(kept.max_velocity(samples_per_segment=256)) <= 3.0 + 1e-6
    knots = torch.cumsum(kept.durations, dim=-1)
    assert torch.allclose(kept.position(knots[0]), wp[0, 1:], atol=1e-6)  # the same path, flown slower


def test_bounds_in_the_qp_keep_the_norms_of_a_diagonal_plan():
    """Per-axis bounds at the limit would allow √3 times it along a diagonal: the bounds are limit / √3."""
    from mapkit.flight import SpeedProfile
    from mapkit.flight._learned import _bounded

    wp = torch.tensor([[[0.0, 0.0, 0.0], [2.0, 2.0, 2.0], [0.0, 0.0, 0.0], [2.0, 2.0, 2.0]]], dtype=torch.float64)
    T = torch.full((1, 3), 2.4, dtype=torch.float64)
    start, end = torch.zeros(1, 3, 3, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64)
    limits = SpeedProfile(v_max=3.0, a_max=4.0)
    free = min_snap(wp, T, start=start, end=end)
    assert float(free.max_acceleration(samples_per_segment=256)) > 4.0  # the plan needs the bounds
    kept = _bounded(wp, T, start, end, limits, [{}], free)
    assert float(kept.max_acceleration(samples_per_segment=256)) <= 4.0 + 1e-6
    assert float(kept.max_velocity(samples_per_segment=256)) <= 3.0 + 1e-6
