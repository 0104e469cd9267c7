"""mapkit.trajopt: time allocation (heuristics, Mellinger & Kumar gradient descent, TAN module)."""

from __future__ import annotations

import math

import pytest
import torch

from mapkit.trajopt import (
    TimeAllocationNet,
    TimeAllocationNetConfig,
    TrajoptError,
    allocate_times,
    min_snap,
)
from mapkit.trajopt._timealloc import _snap_cost

F64 = torch.float64


def path(B: int = 4, M: int = 5, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    steps = torch.randn(B, M, 3, generator=g, dtype=F64) * 0.6 + torch.tensor([1.0, 0.2, 0.0], dtype=F64)
    return torch.cat([torch.zeros(B, 1, 3, dtype=F64), torch.cumsum(steps, 1)], 1)


def test_uniform_and_trapezoid():
    w = torch.tensor([[0.0, 0, 0], [4.0, 0, 0], [4.0, 0.5, 0]], dtype=F64)
    T = allocate_times(w, "uniform", total_time=3.0)
    assert torch.allclose(T, torch.tensor([1.5, 1.5], dtype=F64))
    T = allocate_times(w, "trapezoid", v_max=2.0, a_max=1.0)
    # 4 m: cruise (4 >= v^2/a = 4): 4/2 + 2/1 = 4 s; 0.5 m: triangle 2 sqrt(0.5/1)
    assert torch.allclose(T, torch.tensor([4.0, 2.0 * math.sqrt(0.5)], dtype=F64))
    assert torch.allclose(allocate_times(w, "trapezoid", total_time=10.0).sum(), torch.tensor(10.0, dtype=F64))


def test_poly5_profile():
    # symmetric, evenly spaced path: symmetric allocation, end segments slower than the middle
    w = torch.stack([torch.tensor([float(i), 0.0, 0.0], dtype=F64) for i in range(5)])
    T = allocate_times(w, "poly5", v_max=1.0, a_max=10.0)
    assert torch.allclose(T, T.flip(0), atol=1e-9)
    assert T[0] > T[1]
    assert abs(float(T.sum()) - 15.0 / 8.0 * 4.0) < 1e-9  # speed-limited total of the quintic
    # the quintic profile's peak speed equals v_max
    traj_total = float(T.sum())
    assert abs(4.0 * 15.0 / 8.0 / traj_total - 1.0) < 1e-12


def test_gradient_with_fixed_total_lowers_cost_and_keeps_total():
    w = path(4, 5, seed=2)
    T0 = allocate_times(w, "trapezoid")
    T = allocate_times(w, "gradient")
    assert torch.allclose(T.sum(-1), T0.sum(-1), rtol=1e-12)
    assert (_snap_cost(w, T, None, None, False)[0] < _snap_cost(w, T0, None, None, False)[0]).all()
    assert (T > 0).all()
    # first-order optimality on the simplex: equal partial derivatives
    _, g, _ = _snap_cost(w, T, None, None, True)
    spread = (g.amax(-1) - g.amin(-1)) / g.abs().mean(-1)
    assert (spread < 0.05).all()


def test_gradient_envelope_derivative_matches_autograd():
    w = path(2, 4, seed=3)
    T = allocate_times(w, "trapezoid").requires_grad_(True)
    (ga,) = torch.autograd.grad(min_snap(w, T).snap_cost().sum(), T)
    _, gb, _ = _snap_cost(w, T.detach(), None, None, True)
    assert torch.allclose(ga, gb, rtol=1e-9)


def test_time_allocation_net():
    torch.manual_seed(0)
    net = TimeAllocationNet(TimeAllocationNetConfig(num_segments=5, hidden=(32, 32)))
    w = path(6, 5, seed=5).float()
    T = allocate_times(w, "net", net=net, total_time=torch.full((6,), 7.0))
    assert T.shape == (6, 5) and (T > 0).all()
    assert torch.allclose(T.sum(-1), torch.full((6,), 7.0), atol=1e-5)
    T_default = net(w)
    assert (T_default > 0).all()
    # trainable: gradient reaches the parameters through min_snap
    J = min_snap(w, T_default).snap_cost().mean()
    J.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
    with pytest.raises(TrajoptError, match="net"):
        allocate_times(w, "net")
    with pytest.raises(TrajoptError, match="M=5"):
        net(path(2, 3).float())


def test_bad_method():
    with pytest.raises(TrajoptError, match="method"):
        allocate_times(path(1, 2), "magic")
