"""The detour excess of the goal cost (`LossConfig.detour_weight`) and the winner's collision penalty."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mapkit.esdf import EsdfMap, signed_distance
from mapkit.planner import (
    DetourGrid,
    LossConfig,
    PlannerError,
    PlannerNet,
    candidate_loss,
    detour_excess,
    planner_preset,
)

VOXEL = 0.1
ORIGIN = (-2.0, -6.0, -1.0)
SHAPE = (100, 120, 30)  # x in [-2, 7.9], y in [-6, 5.9], z in [-1, 1.9]


def _map(occupied) -> EsdfMap:
    esdf = signed_distance(occupied, voxel_size=VOXEL, max_dist=20.0)
    return EsdfMap(esdf=esdf, esdf_raw=esdf, voxel_size=VOXEL, origin=ORIGIN)


def _axes():
    return [ORIGIN[a] + VOXEL * np.arange(SHAPE[a]) for a in range(3)]


@pytest.fixture(scope="module")
def wall_map() -> EsdfMap:
    """A wall across x = 3 (0.2 m thick, the whole height) from y = -6 up to y = 2; open beyond."""
    x, y, _ = _axes()
    occ = np.zeros(SHAPE, bool)
    occ[np.ix_((x > 2.85) & (x < 3.15), y < 2.0, np.ones(SHAPE[2], bool))] = True
    return _map(occ)


def _excess(esdf_map: EsdfMap, ends, goal, **kw) -> np.ndarray:
    e = torch.tensor(ends, dtype=torch.float64)[None]
    g = torch.tensor(goal, dtype=torch.float64)[None]
    return detour_excess(e, g, esdf_map, **kw)[0].numpy()


def test_open_space_has_no_excess():
    m = _map(np.zeros(SHAPE, bool))
    ends = [[0.0, 0.0, 0.5], [1.37, -2.71, 0.5], [6.5, 4.9, 0.2], [5.02, 0.03, 0.5]]
    np.testing.assert_allclose(_excess(m, ends, [5.0, 0.0, 0.5]), 0.0, atol=1e-9)


def test_excess_behind_a_wall_is_the_way_round_its_end(wall_map):
    """From (1, 0) to (5, 0) the way round the wall's end (kept 0.3 m clear: round (3, 2.3)) is
    2·√(2² + 2.3²) ≈ 6.10 m against 4 m straight; the 8-connected grid overestimates a route by
    at most 8 %. Points on the goal's side of the wall, in line of sight, have none."""
    goal = [5.0, 0.0, 0.5]
    way_round = 2.0 * math.hypot(2.0, 2.3) - 4.0
    got = _excess(wall_map, [[1.0, 0.0, 0.5], [4.0, -1.0, 0.5], [3.0, 3.5, 0.5]], goal)
    assert way_round - 0.25 <= got[0] <= way_round * 1.08 + 0.25
    assert got[1] == 0.0 and got[2] < 0.1
    # nothing farther than the cap counts
    assert _excess(wall_map, [[1.0, -5.0, 0.5]], goal, cap=1.0)[0] == pytest.approx(1.0)


def test_a_wall_outside_the_height_band_is_no_obstacle():
    """A 0.5 m kerb under the goal's band (±0.6 m round 1.5 m) is flown over."""
    x, _, z = _axes()
    occ = np.zeros(SHAPE, bool)
    occ[np.ix_((x > 2.85) & (x < 3.15), np.ones(SHAPE[1], bool), z < -0.5)] = True
    m = _map(occ)
    assert _excess(m, [[1.0, 0.0, 1.5]], [5.0, 0.0, 1.5])[0] == 0.0
    assert _excess(m, [[1.0, 0.0, 1.5]], [5.0, 0.0, -0.8], grid=DetourGrid(band=0.3))[0] > 1.0


def test_excess_gradient_matches_finite_differences(wall_map):
    goal = torch.tensor([[5.0, 0.0, 0.5]], dtype=torch.float64)
    end = torch.tensor([[[1.23, 0.57, 0.5]]], dtype=torch.float64, requires_grad=True)
    value = detour_excess(end, goal, wall_map)
    value.sum().backward()
    h = 1e-4
    for axis in (0, 1):
        step = torch.zeros(1, 1, 3, dtype=torch.float64)
        step[..., axis] = h
        fd = (detour_excess(end.detach() + step, goal, wall_map) - detour_excess(end.detach() - step, goal, wall_map)) / (2 * h)
        assert float(end.grad[0, 0, axis]) == pytest.approx(float(fd), abs=1e-6)
    assert float(value.detach()) > 0 and float(end.grad[0, 0, 2]) == 0.0


def test_detour_weight_adds_the_excess_to_the_goal_cost(wall_map):
    """Candidates that stop 2.5 m short of a goal behind the wall: the goal term grows by λ × the
    excess of the deployed candidate's end; weights below zero are refused."""
    torch.manual_seed(0)
    net = PlannerNet(planner_preset("cpu", num_candidates=4, input_size=(32, 48), encoder_width=0.125))
    with torch.no_grad():
        last = net.keypoint_mlp[-1]
        last.weight.zero_()
        last.bias.fill_(-2.5)  # every key-point 2.5 m short: the paths end before the wall
        last.bias[1::3] = 0.0
        last.bias[2::3] = 0.0
    depth = torch.full((1, 48, 64), 5.0)
    goal = torch.tensor([[4.0, 0.0, 0.0]])
    T = torch.eye(4)[None].clone()
    T[0, :3, 3] = torch.tensor([1.0, 0.0, 0.5])
    with torch.no_grad():
        out = net(net.preprocess(depth), goal)
        terms = {w: candidate_loss(net, out, goal=goal, T_world_body=T, esdf_map=wall_map,
                                   config=LossConfig(detour_weight=w))[1] for w in (0.0, 2.0)}
        end_world = out.keypoints[:, -1] + T[:, :3, 3]
        expect = detour_excess(end_world[:, None].double(), (goal + T[:, :3, 3]).double(), wall_map)[0, 0]
    assert float(expect) > 1.0
    assert float(terms[2.0]["goal"] - terms[0.0]["goal"]) == pytest.approx(2.0 * float(expect), rel=1e-4)
    with pytest.raises(PlannerError, match="detour_weight"):
        LossConfig(detour_weight=-1.0)


def test_the_collision_penalty_lets_a_clear_candidate_win(wall_map):
    """Toward a goal straight behind the wall every candidate but the widest crosses it; the
    cheapest path (by obstacle, goal and smoothness cost) is one that crosses, so without the
    penalty the winner collides (with this seed's time allocation), and with it the clear one wins."""
    torch.manual_seed(0)
    net = PlannerNet(planner_preset("cpu", num_candidates=8, input_size=(32, 48), encoder_width=0.125))
    with torch.no_grad():
        net.keypoint_mlp[-1].weight.zero_()
        net.keypoint_mlp[-1].bias.zero_()
    depth = torch.full((1, 48, 64), 5.0)
    goal = torch.tensor([[6.0, 0.0, 0.0]])
    T = torch.eye(4)[None].clone()
    T[0, :3, 3] = torch.tensor([0.0, 0.5, 0.5])
    runs = {}
    with torch.no_grad():
        out = net(net.preprocess(depth), goal)
        for kappa in (0.0, 10.0):
            runs[kappa] = candidate_loss(net, out, goal=goal, T_world_body=T, esdf_map=wall_map,
                                         config=LossConfig(obstacle_softness=0.3, winner_collision_penalty=kappa))[1]
    assert float(runs[0.0]["winner_collision_rate"]) == 1.0
    assert float(runs[10.0]["winner_collision_rate"]) == 0.0
