"""Segment-time allocation: heuristics, Mellinger & Kumar gradient descent, and the Time Allocation
Net module. Entry point: :func:`allocate_times`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from numpy.typing import ArrayLike
from torch import nn

from mapkit._choices import BOUNDARY_SCALES, BoundaryScale
from mapkit.trajopt._basis import knot_cost_matrix
from mapkit.trajopt._errors import TrajoptError
from mapkit.trajopt._system import batched_waypoints, knot_values, layout, solve_knots, time_powers

ALLOCATION_METHODS = ("uniform", "trapezoid", "poly5", "gradient", "net")
"""Names accepted by ``allocate_times(method=...)``."""

_WORK = torch.float64
# 5th-order rest-to-rest profile s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5: peak speed and acceleration
# per unit length and time.
_POLY5_VPEAK = 15.0 / 8.0
_POLY5_APEAK = 10.0 / math.sqrt(3.0)


def _prep(waypoints: torch.Tensor | ArrayLike) -> tuple[torch.Tensor, bool]:
    """(B, M+1, 3) key-points as a tensor and whether the input was batched; checks dtype and shape."""
    if not isinstance(waypoints, torch.Tensor):
        waypoints = torch.as_tensor(np.asarray(waypoints, dtype=np.float64))
    return batched_waypoints(waypoints)


def _lengths(w: torch.Tensor) -> torch.Tensor:
    """(B, M) segment lengths of key-points (B, M+1, 3)."""
    lengths: torch.Tensor = (w[:, 1:] - w[:, :-1]).norm(dim=-1)
    return lengths


def _trapezoid_time(length: torch.Tensor, v_max: float, a_max: float) -> torch.Tensor:
    """Rest-to-rest time over ``length`` with bounded speed and acceleration."""
    cruise = length / v_max + v_max / a_max
    short = 2.0 * torch.sqrt(length.clamp_min(0.0) / a_max)
    return torch.where(length >= v_max * v_max / a_max, cruise, short)


def _poly5_total(length: torch.Tensor, v_max: float, a_max: float) -> torch.Tensor:
    """Shortest total time of the quintic rest-to-rest profile within v_max and a_max."""
    return torch.maximum(_POLY5_VPEAK * length / v_max, torch.sqrt(_POLY5_APEAK * length.clamp_min(0.0) / a_max))


def _poly5_inverse(y: torch.Tensor) -> torch.Tensor:
    """tau in [0, 1] with 10 tau^3 - 15 tau^4 + 6 tau^5 = y (bisection, then one Newton step for
    gradients)."""
    yd = y.detach().clamp(0.0, 1.0)
    lo = torch.zeros_like(yd)
    hi = torch.ones_like(yd)
    for _ in range(52):
        mid = 0.5 * (lo + hi)
        val = mid ** 3 * (10.0 - 15.0 * mid + 6.0 * mid * mid)
        below = val < yd
        lo = torch.where(below, mid, lo)
        hi = torch.where(below, hi, mid)
    tau = 0.5 * (lo + hi)
    val = tau ** 3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)
    slope = 30.0 * tau ** 2 * (1.0 - tau) ** 2
    return tau - (val - y) / slope.clamp_min(1e-12)


def profile_time(length: torch.Tensor, v_start: torch.Tensor, v_end: torch.Tensor, *,
                 cruise_speed: float | torch.Tensor, accel: float,
                 decel: float | torch.Tensor | None = None) -> torch.Tensor:
    """Seconds (B,) to cover ``length`` (B,) metres from ``v_start`` (B,) m/s to ``v_end`` (B,) m/s (both
    clipped to [0, cruise_speed]): a trapezoid in speed at ``accel`` m/s² up to ``cruise_speed`` (scalar
    or (B,)) and ``decel`` (None: ``accel``) down; triangular or a ramp on shorter paths."""
    vc = torch.as_tensor(cruise_speed, dtype=_WORK)
    d = torch.as_tensor(accel if decel is None else decel, dtype=_WORK)
    if not (bool((vc > 0).all()) and bool(torch.isfinite(vc).all()) and accel > 0 and bool((d > 0).all())):
        raise TrajoptError(f"cruise_speed, accel and decel must be > 0, got {cruise_speed}, {accel} and {decel}")
    L = torch.as_tensor(length, dtype=_WORK).clamp_min(0.0)
    v0 = torch.minimum(torch.as_tensor(v_start, dtype=_WORK).clamp_min(0.0), vc)
    ve = torch.minimum(torch.as_tensor(v_end, dtype=_WORK).clamp_min(0.0), vc)
    a = float(accel)
    d_up, d_down = (vc ** 2 - v0 ** 2) / (2 * a), (vc ** 2 - ve ** 2) / (2 * d)
    trapezoid = (vc - v0) / a + (vc - ve) / d + (L - d_up - d_down) / vc
    # the peak speed whose speeding-up and slowing-down distances add up to L
    peak = torch.sqrt((L + v0 ** 2 / (2 * a) + ve ** 2 / (2 * d)) / (1 / (2 * a) + 1 / (2 * d)))
    triangle = (peak - v0) / a + (peak - ve) / d
    ramp = 2.0 * L / (v0 + ve).clamp_min(1e-9)
    return torch.where(d_up + d_down <= L, trapezoid, torch.where(peak >= torch.maximum(v0, ve), triangle, ramp))


def _min_duration(total: torch.Tensor, M: int) -> torch.Tensor:
    # 2 % of the mean segment: below ~1 % the cost's float64 evaluation loses its digits
    return 0.02 * total / M


def _snap_cost(waypoints: torch.Tensor, durations: torch.Tensor, start: torch.Tensor | None,
               end: torch.Tensor | None, with_grad: bool) -> tuple[torch.Tensor, torch.Tensor | None, bool]:
    """Minimum snap cost J(T) (B,) through the key-points (no inequalities), m²/s⁷, with ``with_grad`` its
    gradient dJ/dT (B, M) (analytic: the envelope theorem; else None), and whether the input was batched.
    Inputs as in :func:`mapkit.trajopt.min_snap`; float64 inside; non-finite costs are +inf."""
    w, batched = _prep(waypoints)
    w = w.to(_WORK)
    B, M1, _ = w.shape
    M = M1 - 1
    T = torch.as_tensor(durations).to(device=w.device, dtype=_WORK)
    T = torch.broadcast_to(T if T.ndim == 2 else T.unsqueeze(0), (B, M))
    z = torch.zeros(B, 3, 3, dtype=_WORK, device=w.device)
    st = z if start is None else torch.broadcast_to(torch.as_tensor(start).to(w.device, _WORK), (B, 3, 3))
    en = z if end is None else torch.broadcast_to(torch.as_tensor(end).to(w.device, _WORK), (B, 3, 3))
    X = solve_knots(T, knot_values(w, st, en, 4), layout(M, 4, False))
    K = X.reshape(B, M + 1, 4, 3)
    d = torch.cat([K[:, :-1], K[:, 1:]], dim=2)  # (B, M, 8, 3)
    ds = d * time_powers(T, 4).unsqueeze(-1)
    R = torch.as_tensor(knot_cost_matrix(4), dtype=_WORK, device=w.device)
    Rds = torch.einsum("kl,bmla->bmka", R, ds)
    quad = (ds * Rds).sum(dim=(2, 3))  # (B, M)
    J = (quad * T ** (-7)).sum(-1)
    J = torch.where(torch.isfinite(J), J, torch.full_like(J, math.inf))
    if not with_grad:
        return J, None, batched
    qv = torch.tensor([0, 1, 2, 3, 0, 1, 2, 3], dtype=_WORK, device=w.device)
    dds = ds * (qv.reshape(1, 1, 8, 1) / T.reshape(B, M, 1, 1))
    cross = (dds * Rds).sum(dim=(2, 3))
    return J, -7.0 * quad * T ** (-8) + 2.0 * cross * T ** (-7), batched


@dataclass
class _SnapTimeProblem:
    """Minimise J(T) over durations T (B, M) ≥ t_min with ΣT = total (B,), float64."""

    w: torch.Tensor  # (B, M+1, 3) key-points
    start: torch.Tensor | None
    end: torch.Tensor | None
    total: torch.Tensor
    t_min: torch.Tensor

    def cost(self, Tc: torch.Tensor) -> torch.Tensor:
        """(B,) objective."""
        return _snap_cost(self.w, Tc, self.start, self.end, False)[0]

    def cost_and_grad(self, Tc: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B,) objective and its gradient (B, M)."""
        J, g, _ = _snap_cost(self.w, Tc, self.start, self.end, True)
        assert g is not None  # asked for
        return J, g

    def project(self, Tc: torch.Tensor) -> torch.Tensor:
        """The nearest feasible durations: T ≥ t_min and ΣT = total (sort-based simplex projection)."""
        t_min = self.t_min
        M = Tc.shape[-1]
        y = Tc - t_min
        s = (self.total - t_min.sum(-1)).unsqueeze(-1)
        u, _ = torch.sort(y, dim=-1, descending=True)
        css = torch.cumsum(u, dim=-1) - s
        k = torch.arange(1, M + 1, dtype=Tc.dtype, device=Tc.device)
        cond = u - css / k > 0
        rho = cond.to(torch.int64).cumsum(-1).argmax(-1, keepdim=True)
        theta = torch.gather(css, 1, rho) / (rho + 1).to(Tc.dtype)
        return torch.clamp(y - theta, min=0.0) + t_min


def _line_search(problem: _SnapTimeProblem, T: torch.Tensor, f: torch.Tensor, g: torch.Tensor, step: torch.Tensor,
                 active: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Armijo backtracking along the projected gradient: (accepted (B,), new T, new cost, last trial step)."""
    B = T.shape[0]
    accepted = torch.zeros(B, dtype=torch.bool, device=T.device)
    T_new = T.clone()
    f_new = f.clone()
    trial = step.clone()
    for _ls in range(40):
        todo = active & ~accepted
        if not bool(todo.any()):
            break
        cand = problem.project(T - trial * g)
        fc = problem.cost(cand)
        dec = ((cand - T) ** 2).sum(-1)
        # A snap cost is never negative: a negative value is lost precision, not a descent.
        ok = torch.isfinite(fc) & (fc >= 0) & (fc <= f - 1e-4 / trial.squeeze(-1) * dec)
        take = todo & ok
        T_new = torch.where(take.unsqueeze(-1), cand, T_new)
        f_new = torch.where(take, fc, f_new)
        accepted |= take
        trial = torch.where((todo & ~ok).unsqueeze(-1), 0.5 * trial, trial)
    return accepted, T_new, f_new, trial


def _gradient_allocation(
    w: torch.Tensor,
    T0: torch.Tensor,
    *,
    total: torch.Tensor | None,
    start: torch.Tensor | None,
    end: torch.Tensor | None,
    max_iters: int,
    rel_tol: float,
    min_duration: torch.Tensor | None = None,
) -> torch.Tensor:
    """Projected gradient descent with Armijo backtracking, batched over problems (float64)."""
    B, M = T0.shape
    total = T0.sum(-1) if total is None else total
    T = T0 * (total / T0.sum(-1)).unsqueeze(-1)
    t_min = _min_duration(T.sum(-1), M).unsqueeze(-1).expand(B, M)
    if min_duration is not None:
        t_min = torch.maximum(t_min, min_duration.reshape(-1, 1).expand(B, M))
    problem = _SnapTimeProblem(w=w, start=start, end=end, total=total, t_min=t_min)

    with torch.no_grad():
        if min_duration is not None:
            T = problem.project(T)  # the start must respect the floor too
        f, g = problem.cost_and_grad(T)
        if not bool(torch.isfinite(f).all()):
            raise TrajoptError(
                "gradient time allocation: the initial durations give no finite cost for some "
                "elements; start from longer durations"
            )
        step = 0.1 * T.mean(-1, keepdim=True) / g.abs().amax(-1, keepdim=True).clamp_min(1e-300)
        active = torch.ones(B, dtype=torch.bool, device=T.device)
        for _ in range(max_iters):
            if not bool(active.any()):
                break
            accepted, T_new, f_new, trial = _line_search(problem, T, f, g, step, active)
            rel = (f - f_new) / f.abs().clamp_min(1e-300)
            moved = accepted & (rel > rel_tol)
            active = active & moved
            step = torch.where(accepted.unsqueeze(-1), 2.0 * trial, trial)
            T = torch.where(accepted.unsqueeze(-1), T_new, T)
            if bool(active.any()):
                f, g = problem.cost_and_grad(T)
    return T


def allocate_times(
    waypoints: torch.Tensor,
    method: Literal["uniform", "trapezoid", "poly5", "gradient", "net"] = "trapezoid",
    *,
    v_max: float = 2.0,
    a_max: float = 2.0,
    total_time: float | torch.Tensor | None = None,
    start: torch.Tensor | None = None,
    end: torch.Tensor | None = None,
    max_iters: int = 100,
    rel_tol: float = 1e-6,
    net: TimeAllocationNet | None = None,
    min_duration: float | torch.Tensor | None = None,
) -> torch.Tensor:
    """Segment durations (B, M) — or (M,) for unbatched (M+1, 3) waypoints — in seconds.

    Methods:
        ``uniform``: ``total_time`` (default: the trapezoid time of the whole path) split evenly.
        ``trapezoid``: every segment gets its own rest-to-rest time under ``v_max`` (m/s) and
            ``a_max`` (m/s²); rescaled to ``total_time`` when given.
        ``poly5``: the whole path follows one quintic rest-to-rest arc-length profile
            ``s(tau) = L (10 tau^3 - 15 tau^4 + 6 tau^5)`` whose duration is the shortest within
            ``v_max``/``a_max`` (or ``total_time``); each key-point gets the time the profile
            reaches its arc length, so segments near the ends are slower.
        ``gradient``: Mellinger & Kumar: minimise the snap cost J(T) with sum(T) fixed
            (``total_time``, default the trapezoid total); projected gradient descent with Armijo
            backtracking from the trapezoid rule, every duration kept >= 0.02 * total / M and
            >= ``min_duration`` seconds (scalar or (B,); needs a total of at least M × it). Not
            differentiable.
        ``net``: the :class:`TimeAllocationNet` ``net`` (required) predicts the shares of
            ``total_time`` (default: its poly5 total time).
    """
    if method not in ALLOCATION_METHODS:
        raise TrajoptError(f"method must be one of {ALLOCATION_METHODS}, got {method!r}")
    if not (v_max > 0 and a_max > 0):
        raise TrajoptError(f"v_max and a_max must be > 0, got {v_max} and {a_max}")
    w, batched = _prep(waypoints)
    out_dtype = w.dtype
    tot = _total_times(total_time, w.shape[0], w.device)

    if method == "net":
        if net is None:
            raise TrajoptError("method='net' needs net=TimeAllocationNet(...)")
        T: torch.Tensor = net(w.to(next(net.parameters()).dtype), total_time=None if tot is None else tot)
        return (T if batched else T[0]).to(out_dtype)

    w64 = w.to(_WORK)
    lengths = _lengths(w64)
    if bool((lengths.sum(-1) <= 0).any()):
        raise TrajoptError("waypoints: every path needs a positive length (start and end coincide)")
    if method == "gradient":
        T = _gradient_times(w64, lengths, tot, v_max=v_max, a_max=a_max, start=start, end=end,
                            max_iters=max_iters, rel_tol=rel_tol, min_duration=min_duration)
    else:
        T = _rule_times(method, lengths, tot, v_max, a_max)
    return (T if batched else T[0]).to(out_dtype)


def _total_times(total_time: float | torch.Tensor | None, B: int, device: torch.device) -> torch.Tensor | None:
    """(B,) total times in float64 (None when not given); checked > 0."""
    if total_time is None:
        return None
    tot = torch.as_tensor(total_time).to(device=device, dtype=_WORK)
    tot = torch.broadcast_to(tot.reshape(-1) if tot.ndim else tot, (B,))
    if bool((tot <= 0).any()):
        raise TrajoptError(f"total_time must be > 0 seconds, got {total_time}")
    return tot


def _rule_times(method: str, lengths: torch.Tensor, tot: torch.Tensor | None, v_max: float,
                a_max: float) -> torch.Tensor:
    """(B, M) durations of the "uniform", "trapezoid" or "poly5" rule (see :func:`allocate_times`)."""
    B, M = lengths.shape
    if method == "uniform":
        total = tot if tot is not None else _trapezoid_time(lengths.sum(-1), v_max, a_max)
        return (total / M).unsqueeze(-1).expand(B, M).clone()
    if method == "trapezoid":
        T = _trapezoid_time(lengths, v_max, a_max)
        T = torch.maximum(T, _min_duration(T.sum(-1), M).unsqueeze(-1).clamp_min(1e-6))
        return T * (tot / T.sum(-1)).unsqueeze(-1) if tot is not None else T
    L = lengths.sum(-1)  # poly5
    total = tot if tot is not None else _poly5_total(L, v_max, a_max)
    frac = torch.cumsum(lengths, dim=-1) / L.unsqueeze(-1)
    tau = _poly5_inverse(frac[:, :-1])
    tau = torch.cat([torch.zeros_like(tau[:, :1]), tau, torch.ones_like(tau[:, :1])], dim=1)
    T = (tau[:, 1:] - tau[:, :-1]) * total.unsqueeze(-1)
    return torch.maximum(T, _min_duration(total, M).unsqueeze(-1))


def _gradient_times(w64: torch.Tensor, lengths: torch.Tensor, tot: torch.Tensor | None, *, v_max: float,
                    a_max: float, start: torch.Tensor | None, end: torch.Tensor | None, max_iters: int,
                    rel_tol: float, min_duration: float | torch.Tensor | None) -> torch.Tensor:
    """(B, M) durations of the "gradient" method, from the trapezoid rule."""
    B, M = lengths.shape
    T0 = _rule_times("trapezoid", lengths, None, v_max, a_max)
    floor = None
    if min_duration is not None:
        floor = torch.broadcast_to(torch.as_tensor(min_duration, dtype=_WORK).to(w64.device).reshape(-1), (B,))
        total_now = tot if tot is not None else T0.sum(-1)
        if bool((floor * M > total_now * (1 + 1e-9)).any()):
            raise TrajoptError(f"min_duration {min_duration} s × {M} segments exceeds the total time")
        tot = total_now
    return _gradient_allocation(
        w64.detach(), T0.detach(), total=tot, start=start, end=end,
        max_iters=max_iters, rel_tol=rel_tol, min_duration=floor,
    )


@dataclass
class TimeAllocationNetConfig:
    """Configuration of :class:`TimeAllocationNet`."""

    num_segments: int = 5
    """M, the number of segments (key-points minus one) the net allocates."""
    hidden: tuple[int, ...] = (128, 128)
    """Widths of the hidden layers of the MLP (ReLU between them)."""
    v_max: float = 2.0
    """m/s; with ``a_max`` (m/s²) gives the default total time (poly5 rule) when none is passed."""
    a_max: float = 2.0
    boundary_inputs: bool = False
    """The net also reads the start velocity and acceleration and the end speed (0: rest), made unitless
    by ``boundary_scale``."""
    boundary_scale: BoundaryScale = "limits"
    """``limits``: velocities ÷ ``v_max``, accelerations ÷ ``a_max``. ``duration``: velocities × T / L and
    accelerations × T² / L (T the plan's total time, L its path length: the same at every pace); needs
    the total time (:meth:`TimeAllocationNet.shares`)."""


class TimeAllocationNet(nn.Module):
    """Time Allocation Net (TAN): an MLP over the key-point geometry (segment vectors and lengths over
    the path length, its log; with ``boundary_inputs`` the boundary conditions) predicts each segment's
    share of the total time (softmax): durations positive, summing to the total."""

    def __init__(self, config: TimeAllocationNetConfig | None = None) -> None:
        super().__init__()
        self.config = config or TimeAllocationNetConfig()
        M = self.config.num_segments
        if M < 1:
            raise TrajoptError(f"num_segments must be >= 1, got {M}")
        if self.config.boundary_scale not in BOUNDARY_SCALES:
            raise TrajoptError(f"boundary_scale must be one of {BOUNDARY_SCALES}, got {self.config.boundary_scale!r}")
        dims = [4 * M + 1 + (7 if self.config.boundary_inputs else 0), *self.config.hidden, M]
        layers: list[nn.Module] = []
        for i in range(len(dims) - 1):
            layers.append(nn.Linear(dims[i], dims[i + 1]))
            if i < len(dims) - 2:
                layers.append(nn.ReLU())
        self.mlp = nn.Sequential(*layers)

    def shares(self, waypoints: torch.Tensor, *, start: torch.Tensor | None = None,
               end_speed: torch.Tensor | None = None, total_time: torch.Tensor | None = None) -> torch.Tensor:
        """(B, M) shares of the total time for waypoints (B, M+1, 3); with ``boundary_inputs`` also ``start``
        (B, 3, 3) rows (default rest), ``end_speed`` (B,) m/s (default 0) and, for
        ``boundary_scale="duration"``, ``total_time`` (B,) seconds."""
        M = self.config.num_segments
        if waypoints.ndim != 3 or waypoints.shape[1] != M + 1 or waypoints.shape[2] != 3:
            raise TrajoptError(
                f"TimeAllocationNet for M={M} segments needs waypoints (B, {M + 1}, 3), "
                f"got {tuple(waypoints.shape)}"
            )
        seg = waypoints[:, 1:] - waypoints[:, :-1]
        lengths = seg.norm(dim=-1)
        L = lengths.sum(-1, keepdim=True).clamp_min(1e-6)
        parts = [(seg / L.unsqueeze(-1)).flatten(1), lengths / L, torch.log(L)]
        if self.config.boundary_inputs:
            parts += self._boundary(waypoints, L, start, end_speed, total_time)
        return torch.softmax(self.mlp(torch.cat(parts, dim=-1)), dim=-1)

    def _boundary(self, waypoints: torch.Tensor, L: torch.Tensor, start: torch.Tensor | None,
                  end_speed: torch.Tensor | None, total_time: torch.Tensor | None) -> list[torch.Tensor]:
        """The unitless boundary inputs: start velocity (B, 3), acceleration (B, 3), end speed (B, 1)."""
        B, dtype, device = waypoints.shape[0], waypoints.dtype, waypoints.device
        st = torch.zeros(B, 3, 3, dtype=dtype, device=device) if start is None else start.to(dtype)
        es = torch.zeros(B, dtype=dtype, device=device) if end_speed is None else end_speed.to(dtype)
        if self.config.boundary_scale == "limits":
            return [st[:, 0] / self.config.v_max, st[:, 1] / self.config.a_max, es.reshape(B, 1) / self.config.v_max]
        if total_time is None:
            raise TrajoptError("a TimeAllocationNet with boundary_scale='duration' needs the plans' total_time")
        T = torch.as_tensor(total_time, dtype=dtype, device=device).reshape(B, 1)
        return [st[:, 0] * T / L, st[:, 1] * T**2 / L, es.reshape(B, 1) * T / L]

    def forward(self, waypoints: torch.Tensor, total_time: torch.Tensor | None = None) -> torch.Tensor:
        """Durations (B, M) for waypoints (B, M+1, 3); ``total_time`` (B,) seconds, default the
        poly5 rule's total time from the config limits."""
        shares = self.shares(waypoints)
        if total_time is None:
            L = _lengths(waypoints).sum(-1)
            total_time = _poly5_total(L, self.config.v_max, self.config.a_max)
        total_time = torch.as_tensor(total_time, dtype=shares.dtype, device=shares.device)
        return shares * total_time.reshape(-1, 1)
