"""mapkit.trajopt: the inequality path (flight corridor, velocity/acceleration limits)."""

from __future__ import annotations

import importlib.util
import itertools

import numpy as np
import pytest
import torch

from mapkit.trajopt import SOLVERS, TrajoptError, TrajoptWarning, min_snap
from mapkit.trajopt._system import coefficients, knot_values, layout, solve_knots
from mapkit.trajopt._trajectory import Trajectory

F64 = torch.float64


def random_problem(B: int, M: int, *, seed: int = 0, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    steps = torch.randn(B, M, 3, generator=g, dtype=F64) * 0.6 + torch.tensor([1.0, 0.2, 0.0], dtype=F64)
    w = torch.cat([torch.zeros(B, 1, 3, dtype=F64), torch.cumsum(steps, 1)], 1)
    T = 0.6 + torch.rand(B, M, generator=g, dtype=F64)
    return w.to(dtype), T.to(dtype)


def corridor_samples_deviation(traj: Trajectory, w: torch.Tensor, T: torch.Tensor, n: int) -> torch.Tensor:
    """Largest per-axis perpendicular deviation at the corridor's sample points, (B,)."""
    B, M = T.shape
    s = torch.cat([torch.zeros(1), torch.arange(1, n + 1) / (n + 1), torch.ones(1)]).to(F64)
    starts = torch.cumsum(T, 1) - T
    worst = torch.zeros(B, dtype=F64)
    for i in range(M):
        ss = s
        if i == 0:
            ss = ss[1:]
        if i == M - 1:
            ss = ss[:-1]
        t = starts[:, i:i + 1] + ss.unsqueeze(0) * T[:, i:i + 1]
        p = traj.position(t)
        u = w[:, i + 1] - w[:, i]
        u = u / u.norm(dim=-1, keepdim=True)
        e = p - w[:, i:i + 1]
        e = e - (e * u[:, None]).sum(-1, keepdim=True) * u[:, None]
        worst = torch.maximum(worst, e.abs().amax(dim=(1, 2)))
    return worst


def free_interior_cost(w, T):
    """Snap cost with the same start/end and durations and no interior constraint at all."""
    B, M = T.shape
    z = torch.zeros(B, 3, 3, dtype=F64)
    X = solve_knots(T, knot_values(w, z, z, 4), layout(M, 4, True))
    return Trajectory(coefficients(X, T, 4), T).snap_cost()


def test_inactive_corridor_single_segment_equals_closed_form():
    d, T = 2.5, 1.3
    w = torch.tensor([[[0.0, 0.0, 0.0], [d, 0.0, 0.0]]], dtype=F64)
    traj = min_snap(w, torch.tensor([[T]], dtype=F64), corridor=1.0)
    assert traj.info["path"] == "qp"
    expected = 100800.0 * d * d / T**7
    assert abs(float(traj.snap_cost()) - expected) <= 1e-9 * expected


def test_inactive_limits_equal_closed_form():
    w, T = random_problem(8, 5, seed=1)
    closed = min_snap(w, T)
    qp = min_snap(w, T, v_max=1e3, a_max=1e4)
    assert qp.info["path"] == "qp" and max(qp.info["active"]) == 0
    assert torch.allclose(qp.snap_cost(), closed.snap_cost(), rtol=1e-10)
    assert torch.allclose(qp.coeffs, closed.coeffs, atol=1e-9)


def test_corridor_satisfied_and_active():
    w, T = random_problem(16, 5, seed=2)
    traj = min_snap(w, T, corridor=0.1, corridor_samples=5)
    assert bool(traj.solved.all())
    assert min(traj.info["active"]) > 0
    dev = corridor_samples_deviation(traj, w, T, 5)
    assert (dev <= 0.1 + 1e-6).all()
    assert (dev >= 0.1 - 1e-9).any()  # some constraint is tight


def test_without_gradients_the_solution_is_daqps_own_to_rounding():
    """Under no_grad the corridor and limits come straight from DAQP; with gradients the active set is
    re-solved in torch. Both are the same optimum (tight constraints included), not two answers."""
    w, T = random_problem(6, 5, seed=7)
    closed = min_snap(w, T)
    kw = dict(corridor=0.1, corridor_samples=5, v_max=0.95 * closed.max_velocity(per_axis=True).amax(-1),
              a_max=0.95 * closed.max_acceleration(per_axis=True).amax(-1))
    polished = min_snap(w, T, **kw)
    with torch.no_grad():
        direct = min_snap(w, T, **kw)
    assert min(polished.info["active"]) > 0 and polished.info["active"] == direct.info["active"]
    assert not torch.equal(direct.coeffs, polished.coeffs)  # really the other path ...
    torch.testing.assert_close(direct.coeffs, polished.coeffs.detach(), rtol=0, atol=1e-8)  # ... to the same optimum
    torch.testing.assert_close(direct.snap_cost(), polished.snap_cost().detach(), rtol=1e-9, atol=0)


def test_limits_satisfied():
    w, T = random_problem(8, 4, seed=3)
    T2 = T * 1.2
    closed = min_snap(w, T2)
    vlim = 0.95 * closed.max_velocity(per_axis=True).amax(-1)  # (B,) limits
    alim = 0.95 * closed.max_acceleration(per_axis=True).amax(-1)
    traj = min_snap(w, T2, v_max=vlim, a_max=alim, corridor_samples=5)
    assert bool(traj.solved.all())
    assert min(traj.info["active"]) > 0
    assert bool(traj.solved.all())
    n = 5
    s = torch.cat([torch.zeros(1), torch.arange(1, n + 1) / (n + 1)]).to(F64)
    starts = torch.cumsum(T2, 1) - T2
    t = (starts.unsqueeze(-1) + s * T2.unsqueeze(-1)).reshape(8, -1)
    assert (traj.derivative(t, 1).abs().amax(dim=(1, 2)) <= vlim + 1e-6).all()
    assert (traj.derivative(t, 2).abs().amax(dim=(1, 2)) <= alim + 1e-6).all()


def test_cost_monotone_in_corridor_width_and_bounded_below():
    w, T = random_problem(6, 5, seed=4)
    lower = free_interior_cost(w, T)
    prev = torch.full((6,), float("inf"), dtype=F64)
    for width in (0.02, 0.05, 0.1, 0.2, 0.5, 2.0, 50.0):
        J = min_snap(w, T, corridor=width).snap_cost()
        assert (J <= prev * (1 + 1e-9)).all()
        assert (J >= lower * (1 - 1e-9)).all()
        prev = J
    assert torch.allclose(prev, lower, rtol=1e-8)  # a very wide corridor is inactive


def _central(fun, x, idx, h):
    xp, xm = x.detach().clone(), x.detach().clone()
    xp[idx] += h
    xm[idx] -= h
    with torch.no_grad():
        return (fun(xp) - fun(xm)) / (2 * h)


def _fd_check(fun, x, idx_list, h=1e-4, rtol=1e-6):
    """Central differences with one Richardson step (truncation O(h^4)) against autograd.

    A component far smaller than the largest one is compared at the differences' noise floor: the
    cost's rounding (and the QP solve's, ~1e-13 of the cost) divided by h. With a 5000 m²/s⁷ snap
    cost whose largest time derivative is 2.8e4, a derivative of 0.61 carries about 3e-6 of that
    noise (daqp 0.10/0.11, numpy 2.4), hence the absolute 1e-9 of the largest component."""
    x = x.detach().clone().requires_grad_(True)
    (g,) = torch.autograd.grad(fun(x), x)
    floor = 1e-9 * float(g.abs().max()) + 1e-8
    for idx in idx_list:
        fd = (4 * _central(fun, x, idx, h / 2) - _central(fun, x, idx, h)) / 3
        assert abs(float(fd) - float(g[idx])) <= rtol * abs(float(fd)) + floor, (idx, float(fd), float(g[idx]))


def test_corridor_gradients_vs_central_differences():
    w, T = random_problem(1, 5, seed=5)
    probe = min_snap(w, T, corridor=0.05)
    assert probe.info["active"][0] > 0  # active constraints present
    weights = torch.linspace(0.5, 1.5, 7, dtype=F64)

    def f_w(wx):
        tr = min_snap(wx, T, corridor=0.05)
        return tr.snap_cost().sum() + (tr.position(torch.linspace(0, 3, 7, dtype=F64))[0, :, 1] * weights).sum()

    def f_T(Tx):
        return min_snap(w, Tx, corridor=0.05).snap_cost().sum()

    _fd_check(f_w, w, [(0, 1, 0), (0, 2, 1), (0, 3, 2), (0, 4, 0), (0, 5, 1)])
    _fd_check(f_T, T, [(0, i) for i in range(5)])


@pytest.mark.slow
def test_corridor_and_limits_gradcheck():
    w, T = random_problem(2, 3, seed=6)
    width = torch.tensor([[0.05, 0.08, 0.06], [0.1, 0.04, 0.07]], dtype=F64)

    def f(w_, T_, c_):
        tr = min_snap(w_, T_, corridor=c_, v_max=3.0)
        return tr.snap_cost(), tr.position(torch.tensor([0.4, 1.2], dtype=F64))

    assert torch.autograd.gradcheck(
        f, (w.requires_grad_(), T.requires_grad_(), width.requires_grad_()), eps=1e-6, atol=1e-4, rtol=1e-5
    )


def test_corridor_batched_equals_per_element_and_float32():
    w, T = random_problem(5, 4, seed=7)
    batch = min_snap(w, T, corridor=0.08)
    for b in range(5):
        one = min_snap(w[b], T[b], corridor=0.08)
        assert torch.allclose(one.coeffs, batch.coeffs[b], atol=1e-10)
    b32 = min_snap(w.float(), T.float(), corridor=0.08)
    assert b32.coeffs.dtype == torch.float32
    rel = ((b32.snap_cost().double() - batch.snap_cost()).abs() / batch.snap_cost()).max()
    assert rel < 1e-5


def test_infeasible_elements_are_flagged_not_nan():
    w, T = random_problem(4, 3, seed=8)
    start = torch.zeros(4, 3, 3, dtype=F64)
    start[2, 0] = torch.tensor([0.0, 30.0, 0.0], dtype=F64)  # 30 m/s sideways out of a 5 cm corridor
    with pytest.warns(TrajoptWarning, match="1 of 4"):
        traj = min_snap(w, T, start=start, corridor=0.05)
    assert traj.solved.tolist() == [True, True, False, True]
    assert "batch element 2" in traj.messages[0]
    assert torch.isfinite(traj.coeffs).all()
    good = min_snap(w[[0, 1, 3]], T[[0, 1, 3]], corridor=0.05)
    assert torch.allclose(traj.coeffs[[0, 1, 3]], good.coeffs, atol=1e-10)
    with pytest.raises(TrajoptError, match="could not be solved"):
        min_snap(w, T, start=start, corridor=0.05, on_infeasible="raise")
    quiet = min_snap(w, T, start=start, corridor=0.05, on_infeasible="ignore")
    assert not bool(quiet.solved[2])


def test_bad_corridor_arguments():
    w, T = random_problem(2, 3)
    with pytest.raises(TrajoptError, match="corridor"):
        min_snap(w, T, corridor=-0.1)
    with pytest.raises(TrajoptError, match="corridor"):
        min_snap(w, T, corridor=torch.ones(2, 2, dtype=F64))
    with pytest.raises(TrajoptError, match="corridor_samples"):
        min_snap(w, T, corridor=0.1, corridor_samples=0)
    with pytest.raises(TrajoptError, match="v_max"):
        min_snap(w, T, v_max=0.0)


_MODULES = {"daqp": "daqp", "proxqp": "proxsuite", "clarabel": "clarabel", "piqp": "piqp"}


@pytest.mark.parametrize("solver", SOLVERS)
def test_backends_agree(solver):
    if importlib.util.find_spec(_MODULES[solver]) is None:
        pytest.skip(f"{solver} not installed")
    w, T = random_problem(6, 4, seed=9)
    ref = min_snap(w, T, corridor=0.1)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            got = min_snap(w, T, corridor=0.1, solver=solver, on_infeasible="ignore")
    ok = got.solved
    assert ok.sum() >= 4
    assert torch.allclose(got.snap_cost()[ok], ref.snap_cost()[ok], rtol=1e-8)


def test_active_set_correction_recovers_from_a_wrong_guess():
    """The polish step repairs an inexact active set (as interior-point backends return)."""
    import mapkit.trajopt._qp as qp_mod
    from mapkit.trajopt._minsnap import _correct_active_set

    w, T = random_problem(1, 4, seed=10)
    captured = {}
    orig = qp_mod.solve_batch

    def spy(P, q, C, lo, hi, *, solver):
        res = orig(P, q, C, lo, hi, solver=solver)
        captured.update(P=P[0], q=q[0], C=C[0], lo=lo[0], hi=hi[0], act=res.active[0], up=res.upper[0])
        return res

    qp_mod.solve_batch = spy
    try:
        min_snap(w, T, corridor=0.05)
    finally:
        qp_mod.solve_batch = orig
    act, up = captured["act"], captured["up"]
    assert act.size >= 3
    inactive = np.setdiff1d(np.arange(captured["C"].shape[0]), act)[:2]
    guess = np.concatenate([act[1:], inactive])  # one held row missing, two spurious ones
    guess_up = np.concatenate([up[1:], [True, True]])
    got, got_up = _correct_active_set(captured["P"], captured["q"], captured["C"], captured["lo"],
                                      captured["hi"], guess, guess_up)
    assert got.tolist() == sorted(act.tolist())
    order = np.argsort(act)
    assert got_up.tolist() == up[order].tolist()


def test_unbatched_corridor_and_sampling():
    w, T = random_problem(1, 3, seed=11)
    traj = min_snap(w[0], T[0], corridor=0.1, yaw=torch.zeros(4, dtype=F64))
    assert not traj.batched and traj.coeffs.shape == (3, 3, 8)
    assert bool(traj.solved)
    t = torch.linspace(0.0, float(T[0].sum()), 20, dtype=F64)
    assert traj.position(t).ndim == 2 and traj.position(t).shape[1] == 3 and traj.yaw(t).ndim == 1


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    w, T = random_problem(8, 4, seed=12)
    for kw in ({}, {"corridor": 0.08}):
        cpu = min_snap(w, T, **kw)
        wg = w.cuda().requires_grad_(True)
        Tg = T.cuda().requires_grad_(True)
        gpu = min_snap(wg, Tg, **kw)
        assert gpu.coeffs.device.type == "cuda"
        assert torch.allclose(gpu.snap_cost().cpu(), cpu.snap_cost(), rtol=1e-9)
        gpu.snap_cost().sum().backward()
        assert torch.isfinite(wg.grad).all() and torch.isfinite(Tg.grad).all()


def test_limit_gradients_vs_central_differences():
    w, T = random_problem(1, 4, seed=13)
    closed = min_snap(w, T)
    vlim = 0.97 * float(closed.max_velocity(per_axis=True).max())
    alim = 0.97 * float(closed.max_acceleration(per_axis=True).max())
    probe = min_snap(w, T, v_max=vlim, a_max=alim)
    assert bool(probe.solved) and probe.info["active"][0] > 0

    def f_T(Tx):
        return min_snap(w, Tx, v_max=vlim, a_max=alim).snap_cost().sum()

    def f_w(wx):
        return min_snap(wx, T, v_max=vlim, a_max=alim).snap_cost().sum()

    _fd_check(f_T, T, [(0, i) for i in range(4)])
    _fd_check(f_w, w, [(0, 1, 0), (0, 2, 1), (0, 3, 2)])


def test_corridor_is_bounded_along_each_segment():
    """A door-like sharp turn, long legs split into collinear segments (free interior key-points):
    every corridor sample stays within its segment extended by the corridor, and the whole
    trajectory stays near the path (bounding only the deviation across the lines let it run on
    1.4 m past the corner along the first leg)."""
    from mapkit.trajopt import allocate_times

    corner = torch.tensor([[16.0, 1.5, 1.6], [15.5, 3.0, 1.6], [7.5, 7.25, 1.35], [7.5, 8.25, 1.35],
                           [2.25, 13.25, 2.1]], dtype=F64)
    pts = [corner[0]]
    for a, b in itertools.pairwise(corner):
        k = int(torch.ceil((b - a).norm() / 3.0))
        pts += [a + (b - a) * j / k for j in range(1, k + 1)]
    w = torch.stack(pts)[None]
    T = allocate_times(w, "trapezoid", v_max=2.0, a_max=2.0)
    width, n = 0.1, 5
    traj = min_snap(w, T, corridor=width, corridor_samples=n)
    assert bool(traj.solved.all())
    M = T.shape[1]
    assert float(corridor_samples_deviation(traj, w, T, n)[0]) <= width + 1e-7
    s = torch.cat([torch.zeros(1), torch.arange(1, n + 1) / (n + 1), torch.ones(1)]).to(F64)
    starts = torch.cumsum(T, 1) - T
    for i in range(M):
        p = traj.position(starts[:, i:i + 1] + s[None] * T[:, i:i + 1])[0]
        a, b = w[0, i], w[0, i + 1]
        u = (b - a) / (b - a).norm()
        along = (p - a) @ u
        assert float(along.min()) >= -width - 1e-7
        assert float(along.max()) <= float((b - a).norm()) + width + 1e-7
    dense = traj.position(torch.linspace(0, float(T.sum()), 800, dtype=F64))[0]
    seg_a, seg_b = corner[:-1], corner[1:]
    d = seg_b - seg_a
    t = ((dense[:, None] - seg_a[None]) * d[None]).sum(-1) / (d * d).sum(-1)[None]
    closest = seg_a[None] + t.clamp(0, 1)[..., None] * d[None]
    assert float((dense[:, None] - closest).norm(dim=-1).min(dim=1).values.max()) < 0.25


@pytest.mark.parametrize("which", ["both", "speed", "acceleration"])
def test_relimited_problem_equals_one_set_up_with_those_limits(which):
    """Tightening the limits re-uses the problem and changes only the limits' bounds: the result
    equals the problem set up from scratch with the new limits, entry for entry."""
    from mapkit.trajopt._minsnap import _position_qp

    w, T = random_problem(3, 4, seed=5)
    z = torch.zeros(3, 3, 3, dtype=F64)
    corr = torch.full((3, 4), 0.4, dtype=F64)
    vm = torch.tensor([2.0, 2.5, 3.0], dtype=F64) if which != "acceleration" else None
    am = torch.tensor([3.0, 4.0, 5.0], dtype=F64) if which != "speed" else None
    qp = _position_qp(w, T, z, z, corridor=corr, corridor_samples=4, v_max=vm, a_max=am)
    assert qp.limit_rows[0] > 0 if vm is not None else qp.limit_rows[0] == 0
    vm2 = None if vm is None else vm * torch.tensor([0.9, 0.8, 1.0], dtype=F64)
    am2 = None if am is None else am * torch.tensor([1.0, 0.7, 0.95], dtype=F64)
    fresh = _position_qp(w, T, z, z, corridor=corr, corridor_samples=4, v_max=vm2, a_max=am2)
    again = qp.relimited(vm2, am2)
    for name in ("lo", "hi", "C", "c_fix", "P", "q", "local"):
        assert torch.equal(getattr(again, name), getattr(fresh, name)), name
    assert not torch.equal(again.lo, qp.lo)
    assert np.array_equal(again.seg_np, fresh.seg_np) and again.limit_rows == fresh.limit_rows
