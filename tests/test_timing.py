"""How plans are timed (mapkit.planner.plan_timing and friends): the speed profile, per-segment
minima, cruise-through plans, the TAN's boundary inputs and dense speed/acceleration limits."""

from __future__ import annotations

import math

import pytest
import torch

from mapkit.planner import PlannerConfig, PlannerNet, plan_timing, time_targets, total_time, turn_speed
from mapkit.planner._timing import durations_from_shares, end_state
from mapkit.trajopt import (
    TimeAllocationNet,
    TimeAllocationNetConfig,
    TrajoptError,
    allocate_times,
    min_snap,
    profile_time,
)

F64 = torch.float64


@pytest.mark.parametrize(("length", "v0", "ve", "expected"), [
    (6.0, 2.0, 2.0, 3.0),  # cruise all the way
    (6.0, 0.0, 2.0, 4.0),  # 2 s / 2 m speeding up, 2 s / 4 m cruise
    (6.0, 2.0, 0.0, 4.0),  # cruise 4 m, brake 2 m
    (1.0, 0.0, 0.0, 2.0),  # triangle: peak 1 m/s
    (0.5, 2.0, 0.0, 0.5),  # too short to brake at 1 m/s²: constant deceleration
    (6.0, 5.0, 2.0, 3.0),  # start speeds above cruise count as cruise
])
def test_profile_time_is_the_hand_computed_profile(length: float, v0: float, ve: float, expected: float):
    T = profile_time(torch.tensor([length]), torch.tensor([v0]), torch.tensor([ve]), cruise_speed=2.0, accel=1.0)
    assert float(T[0]) == pytest.approx(expected, rel=1e-12)


def test_profile_time_takes_a_cruise_speed_per_plan():
    length, v0, ve = torch.tensor([6.0, 6.0, 1.0]), torch.tensor([0.0, 2.0, 0.0]), torch.tensor([2.0, 2.0, 0.0])
    cruise = torch.tensor([2.0, 1.0, 0.5])
    T = profile_time(length, v0, ve, cruise_speed=cruise, accel=1.0)
    each = [profile_time(length[i:i + 1], v0[i:i + 1], ve[i:i + 1], cruise_speed=float(cruise[i]), accel=1.0)
            for i in range(3)]
    assert torch.equal(T, torch.cat(each))
    assert float(T[1]) == pytest.approx(6.0, rel=1e-12)  # start and end speeds above 1 m/s count as 1 m/s
    with pytest.raises(TrajoptError, match="cruise_speed, accel and decel must be > 0"):
        profile_time(length, v0, ve, cruise_speed=torch.tensor([2.0, 0.0, 1.0]), accel=1.0)


@pytest.mark.parametrize(("length", "v0", "ve", "expected"), [
    (6.0, 2.0, 0.0, 4.0 + 1.0),  # brake 4 s over 4 m at 0.5 m/s², cruise 2 m
    (6.0, 0.0, 2.0, 4.0),  # no slowing down: as before
    (1.0, 0.0, 0.0, (2.0 / 3.0) ** 0.5 * 3.0),  # peak √(2/3): 1/3 m up at 1 m/s², 2/3 m down at 0.5
])
def test_profile_time_slows_down_at_its_own_rate(length: float, v0: float, ve: float, expected: float):
    T = profile_time(torch.tensor([length]), torch.tensor([v0]), torch.tensor([ve]), cruise_speed=2.0, accel=1.0,
                     decel=0.5)
    assert float(T[0]) == pytest.approx(expected, rel=1e-12)


def test_turn_speed_is_the_arc_of_the_sharpest_turn():
    """√(a R), R the radius of the arc tangent to both segments at half the shorter one from the
    corner: a right angle between 2 m and 1 m segments has R = 0.5 m; a 60° turn between 1 m segments
    R = 0.5 / tan 30°; a straight path none."""
    right = torch.tensor([[[0.0, 0, 0], [2, 0, 0], [2, 1, 0]]], dtype=F64)
    sixty = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [1.5, 3 ** 0.5 / 2, 0], [2.5, 3 ** 0.5 / 2, 0]]], dtype=F64)
    v = turn_speed(torch.cat([right[:, [0, 1, 2, 2]], sixty, straight(3)]), 2.0)
    assert v[0] == pytest.approx((2.0 * 0.5) ** 0.5, rel=1e-12)  # the repeated last key-point is no turn
    assert v[1] == pytest.approx((2.0 * 0.5 / math.tan(math.pi / 6)) ** 0.5, rel=1e-12)
    assert math.isinf(float(v[2]))


def straight(n: int = 5, length: float = 6.0) -> torch.Tensor:
    x = torch.linspace(0.0, length, n + 1, dtype=F64)
    return torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], dim=-1)[None]


def test_cruise_through_plans_on_straight_evenly_spaced_keypoints_have_zero_snap():
    config = PlannerConfig()
    wp = straight()
    start = torch.zeros(1, 3, 3, dtype=F64)
    start[0, 0, 0] = config.cruise_speed
    speed = torch.tensor([config.cruise_speed], dtype=F64)
    total = total_time(wp, start, speed, config)
    assert float(total[0]) == pytest.approx(6.0 / config.cruise_speed, rel=1e-12)
    end = end_state(wp, speed)
    # The TAN's target (the gradient allocation under the same conditions) keeps the even split …
    target = time_targets(wp, total_time=total, start=start, end=end, min_segment=config.min_segment_time,
                          max_iters=50, rel_tol=1e-12)
    T = durations_from_shares(target, total, config.min_segment_time)
    assert torch.allclose(T, torch.full_like(T, 0.6), atol=1e-6)
    # … and the plan through it is the straight flight at cruise speed: no snap at all.
    assert float(min_snap(wp, T, start=start, end=end).snap_cost()[0]) < 1e-6
    timing = plan_timing(wp, start, speed, config, allocation="gradient")
    assert float(min_snap(wp, timing.durations, start=start, end=timing.end).snap_cost()[0]) < 1e-6


@pytest.mark.parametrize("allocation", ["tan", "gradient", "uniform", "poly5"])
def test_every_segment_gets_the_minimum_duration(allocation: str):
    config = PlannerConfig(tan_boundary=True)
    net = PlannerNet(config)
    g = torch.Generator().manual_seed(0)
    # Crowded key-points (the last centimetres before a goal) and long uneven ones.
    steps = torch.randn(6, 5, 3, generator=g, dtype=F64) * torch.tensor([0.02, 0.02, 0.02, 1.0, 1.0, 0.5],
                                                                         dtype=F64).reshape(6, 1, 1)
    wp = torch.cat([torch.zeros(6, 1, 3, dtype=F64), torch.cumsum(steps, 1)], 1)
    start = torch.zeros(6, 3, 3, dtype=F64)
    start[:, 0] = torch.randn(6, 3, generator=g, dtype=F64)
    speed = torch.tensor([0.0, 2.0, 0.0, 2.0, 0.0, 2.0], dtype=F64)
    with torch.no_grad():
        timing = plan_timing(wp, start, speed, config, allocation=allocation, tan=net.tan)
    assert (timing.durations >= config.min_segment_time - 1e-9).all()
    assert torch.allclose(timing.durations.sum(-1), timing.total, rtol=1e-9)
    assert (timing.total >= config.num_keypoints * config.min_segment_time - 1e-9).all()
    assert torch.allclose(timing.shares.sum(-1), torch.ones(6, dtype=F64), atol=1e-6)


def test_gradient_allocation_respects_a_per_segment_floor():
    wp = straight(5, 1.0)
    T = allocate_times(wp, "gradient", total_time=torch.tensor([2.0], dtype=F64), min_duration=0.3)
    assert (T >= 0.3 - 1e-12).all() and float(T.sum()) == pytest.approx(2.0)
    with pytest.raises(Exception, match="min_duration"):
        allocate_times(wp, "gradient", total_time=torch.tensor([1.0], dtype=F64), min_duration=0.3)


def test_a_tan_with_boundary_inputs_reads_the_start_and_the_end():
    torch.manual_seed(0)
    tan = TimeAllocationNet(TimeAllocationNetConfig(num_segments=5, boundary_inputs=True))
    wp = straight().float()
    rest = tan.shares(wp)
    start = torch.zeros(1, 3, 3)
    start[0, 0, 0] = 2.0
    moving = tan.shares(wp, start=start)
    passing = tan.shares(wp, end_speed=torch.tensor([2.0]))
    assert not torch.allclose(rest, moving) and not torch.allclose(rest, passing)
    plain = TimeAllocationNet(TimeAllocationNetConfig(num_segments=5))
    assert plain.mlp[0].in_features + 7 == tan.mlp[0].in_features


def test_a_duration_scaled_tan_splits_a_slower_flight_alike():
    """A path flown k times slower from a start k (k²) times slower, to an end k times slower, has the
    same minimum-snap split (gradient descent finds the same shares); a TAN with
    ``boundary_scale="duration"`` sees the same inputs, one with ``limits`` does not."""
    wp = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.2, 0.0], [2.2, 1.0, 0.1], [3.0, 2.2, 0.0], [3.5, 3.5, 0.2],
                        [4.5, 4.0, 0.0]]], dtype=F64)
    start = torch.tensor([[[1.2, 0.3, 0.0], [0.4, -0.6, 0.1], [0.0, 0.0, 0.0]]], dtype=F64)
    end_speed, T, k = torch.tensor([1.0], dtype=F64), torch.tensor([4.0], dtype=F64), 1.7
    slow = start / torch.tensor([k, k**2, k**3], dtype=F64).reshape(1, 3, 1)
    gd = [allocate_times(wp, "gradient", total_time=t, start=s, end=end_state(wp, e), max_iters=200) / t
          for t, s, e in ((T, start, end_speed), (k * T, slow, end_speed / k))]
    assert torch.allclose(gd[0], gd[1], atol=1e-3)
    torch.manual_seed(0)
    for scale, alike in (("duration", True), ("limits", False)):
        tan = TimeAllocationNet(TimeAllocationNetConfig(num_segments=5, boundary_inputs=True,
                                                        boundary_scale=scale)).double()
        shares = [tan.shares(wp, start=s, end_speed=e, total_time=t)
                  for t, s, e in ((T, start, end_speed), (k * T, slow, end_speed / k))]
        assert torch.allclose(shares[0], shares[1], atol=1e-12) == alike
    with pytest.raises(TrajoptError, match="total_time"):
        tan = TimeAllocationNet(TimeAllocationNetConfig(num_segments=5, boundary_inputs=True, boundary_scale="duration"))
        tan.shares(wp.float(), start=start.float())
    with pytest.raises(TrajoptError, match="boundary_scale"):
        TimeAllocationNet(TimeAllocationNetConfig(num_segments=5, boundary_scale="metres"))  # type: ignore[arg-type]


def test_speed_and_acceleration_limits_hold_at_1khz():
    wp = torch.tensor([[[0.0, 0.0, 0.0], [2.0, 1.5, 0.0], [4.0, -1.0, 0.5], [6.0, 0.0, 0.0]]], dtype=F64)
    T = torch.tensor([[0.9, 0.8, 1.0]], dtype=F64)
    free = min_snap(wp, T)
    v_max = 0.8 * float(free.max_velocity(per_axis=True).amax())
    a_max = 0.8 * float(free.max_acceleration(per_axis=True).amax())
    traj = min_snap(wp, T, corridor=0.5, v_max=v_max, a_max=a_max, limits_everywhere=True)
    assert bool(traj.solved.all())
    t = torch.arange(0.0, float(T.sum()), 1e-3, dtype=F64)
    assert float(traj.derivative(t, 1).abs().max()) <= v_max * (1 + 1e-6)
    assert float(traj.derivative(t, 2).abs().max()) <= a_max * (1 + 1e-6)
