"""Differentiable minimum-snap trajectories: :func:`min_snap`.

Example: from rest to rest over d metres in T seconds, the minimum-snap trajectory is the
7th-order smoothstep d (35 s⁴ − 84 s⁵ + 70 s⁶ − 20 s⁷), s = t/T: its snap cost is 100800 d²/T⁷,
and it is half-way at T/2 at the speed 35/16 d/T.

>>> import torch
>>> d, T = 2.0, 1.0
>>> traj = min_snap(torch.tensor([[0.0, 0.0, 0.0], [d, 0.0, 0.0]], dtype=torch.float64),
...                 torch.tensor([T], dtype=torch.float64))
>>> round(traj.snap_cost().item(), 6), 100800 * d**2 / T**7
(403200.0, 403200.0)
>>> t = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64) * T
>>> traj.position(t)[:, 0].round(decimals=9).tolist(), traj.derivative(t, 1)[:, 0].round(decimals=9).tolist()
([0.0, 1.0, 2.0], [0.0, 4.375, 0.0])
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from numpy.typing import ArrayLike

from mapkit.trajopt import _qp
from mapkit.trajopt._errors import TrajoptError
from mapkit.trajopt._system import (
    batched_waypoints,
    coefficients,
    index_tensor,
    knot_values,
    layout,
    partitioned_hessian,
    sample_rows,
    solve_knots,
)
from mapkit.trajopt._trajectory import Trajectory

_WORK = torch.float64  # internal precision: float32 cannot hold the ill-conditioned KKT

_Rows = tuple[torch.Tensor, np.ndarray, torch.Tensor, torch.Tensor]
"""Constraint rows (B, m, 3, 8) on one segment's coefficients, their segments (m,), bounds lo and hi (B, m)."""
_Solved = tuple[torch.Tensor, np.ndarray, list[str], dict[str, Any]]
"""Knot vectors (B, N, 3), ok mask (B,), per-element statuses and the ``Trajectory.info`` of a QP solve."""


class TrajoptWarning(UserWarning):
    """Some batch elements of a constrained problem could not be solved (see ``Trajectory.solved``)."""


# ---------------------------------------------------------------------------------------- inputs
def _as_tensor(x: torch.Tensor | ArrayLike, name: str, like: torch.Tensor) -> torch.Tensor:
    """``x`` as a tensor on ``like``'s device (non-tensors in ``like``'s dtype)."""
    if isinstance(x, torch.Tensor):
        return x.to(device=like.device)
    try:
        return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=like.dtype, device=like.device)
    except (TypeError, ValueError) as exc:
        raise TrajoptError(f"{name} must be a number or a tensor, got {type(x).__name__}") from exc


def _batch_param(x: torch.Tensor | ArrayLike, name: str, B: int, tail: tuple[int, ...], like: torch.Tensor) -> torch.Tensor:
    """Broadcast x to (B, *tail) in the work precision, naming the accepted shapes on error."""
    t = _as_tensor(x, name, like).to(_WORK)
    if t.shape == (B, *tail):
        return t
    try:
        return torch.broadcast_to(t, (B, *tail))
    except RuntimeError as exc:
        shapes = " or ".join(str(s) for s in [(B, *tail), tail] if s)
        raise TrajoptError(f"{name} must have shape {shapes} (or be a scalar), got {tuple(t.shape)}") from exc


def _check_finite(t: torch.Tensor, name: str) -> None:
    """Raise :class:`TrajoptError` naming ``name`` when ``t`` holds NaN or inf."""
    if not bool(torch.isfinite(t.detach()).all()):
        raise TrajoptError(f"{name} contains NaN or inf; pass finite values")


# ------------------------------------------------------------------------------- constraints
def _corridor_rows(w: torch.Tensor, T: torch.Tensor, half_width: torch.Tensor, n_samples: int) -> _Rows:
    """Local rows (B, m, 3, 8), their segment (m,) and bounds lo/hi (B, m): each sample's deviation across
    its segment's key-point line within +-half_width per world axis, and its position along the line
    within the segment's ends extended by half_width. Samples: n_samples interior points of every
    segment plus both ends of every segment but the trajectory's own start and end."""
    B, M = T.shape
    s = np.concatenate([[0.0], np.arange(1, n_samples + 1) / (n_samples + 1), [1.0]])
    K = s.size
    L = sample_rows(T, s, 0, 4)  # (B, M, K, 8)
    seg = w[:, 1:] - w[:, :-1]
    length = seg.norm(dim=-1, keepdim=True)
    degenerate = (length < 1e-9).unsqueeze(-1)
    u = seg / length.clamp_min(1e-9)
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    Pp = eye - u.unsqueeze(-1) * u.unsqueeze(-2)  # (B, M, 3, 3)
    Pp = torch.where(degenerate, eye.expand_as(Pp), Pp)
    rows = Pp.unsqueeze(2).unsqueeze(-1) * L.unsqueeze(3).unsqueeze(3)  # (B, M, K, 3a, 3b, 8)
    centre = torch.einsum("bmxy,bmy->bmx", Pp, w[:, :-1])  # (B, M, 3)
    centre = centre.unsqueeze(2).expand(B, M, K, 3)
    keep = np.ones((M, K), dtype=bool)
    keep[0, 0] = False
    keep[M - 1, K - 1] = False
    kept = np.nonzero(keep.reshape(-1))[0]
    keep_t = index_tensor(kept, w.device)
    rows = rows.reshape(B, M * K, 3, 3, 8).index_select(1, keep_t).reshape(B, -1, 3, 8)
    centre = centre.reshape(B, M * K, 3).index_select(1, keep_t).reshape(B, -1)
    hw = half_width.unsqueeze(-1).unsqueeze(-1).expand(B, M, K, 3).reshape(B, M * K, 3)
    hw = hw.index_select(1, keep_t).reshape(B, -1)
    # along the segment: u·p within [u·a − W, u·b + W] (else sharp turns are overshot by metres)
    along = u.unsqueeze(2).unsqueeze(-1) * L.unsqueeze(3)  # (B, M, K, 3b, 8)
    along = torch.where(degenerate.unsqueeze(-1), torch.zeros_like(along), along)
    along = along.reshape(B, M * K, 3, 8).index_select(1, keep_t)
    ua = (u * w[:, :-1]).sum(-1) - half_width  # (B, M)
    ub = (u * w[:, 1:]).sum(-1) + half_width
    big = torch.full_like(ua, 1e9)
    ua = torch.where(degenerate[..., 0, 0], -big, ua)
    ub = torch.where(degenerate[..., 0, 0], big, ub)
    a_lo = ua.unsqueeze(-1).expand(B, M, K).reshape(B, M * K).index_select(1, keep_t)
    a_hi = ub.unsqueeze(-1).expand(B, M, K).reshape(B, M * K).index_select(1, keep_t)
    rows = torch.cat([rows, along], dim=1)
    seg_of_row = np.concatenate([np.repeat(kept // K, 3), kept // K])
    return rows, seg_of_row, torch.cat([centre - hw, a_lo], dim=1), torch.cat([centre + hw, a_hi], dim=1)


def _limit_rows(T: torch.Tensor, q: int, limit: torch.Tensor, n_samples: int) -> _Rows:
    """Local rows (B, m, 3, 8), segments (m,) and bounds: |q-th derivative| <= limit per axis at
    the samples (segment starts except the first, and n_samples interior points of every segment)."""
    B, M = T.shape
    s = np.concatenate([[0.0], np.arange(1, n_samples + 1) / (n_samples + 1)])
    K = s.size
    L = sample_rows(T, s, q, 4)  # (B, M, K, 8)
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    rows = eye.reshape(1, 1, 1, 3, 3, 1) * L.unsqueeze(3).unsqueeze(3)  # (B, M, K, 3a, 3b, 8)
    keep = np.ones((M, K), dtype=bool)
    keep[0, 0] = False
    kept = np.nonzero(keep.reshape(-1))[0]
    keep_t = index_tensor(kept, T.device)
    rows = rows.reshape(B, M * K, 3, 3, 8).index_select(1, keep_t).reshape(B, -1, 3, 8)
    lo, hi = _limit_bounds(limit, rows.shape[1])
    return rows, np.repeat(kept // K, 3), lo, hi


def _limit_bounds(limit: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds (B, m) ``-limit`` and ``limit`` of m limit rows."""
    lim = limit.reshape(-1, 1).expand(limit.shape[0], m)
    return -lim, lim


def _to_global(local: torch.Tensor, seg: torch.Tensor, N: int) -> torch.Tensor:
    """Scatter local rows (B, m, 3, 8) of segments seg (B, m) into knot-vector rows (B, m, 3, N)."""
    B, m = seg.shape
    cols = (seg * 4).unsqueeze(-1) + torch.arange(8, device=seg.device)  # (B, m, 8)
    cols = cols.unsqueeze(2).expand(B, m, 3, 8)
    out = torch.zeros(B, m, 3, N, dtype=local.dtype, device=local.device)
    return out.scatter(3, cols, local)


# ------------------------------------------------------------------------------------ solver
@dataclass
class _PositionQp:
    """The inequality-constrained position problem of one batch over the free knot values z (B, 3·nf):
    minimise ½ zᵀPz + qᵀz subject to lo <= C z + c_fix <= hi (rows ``local`` of segments ``seg_np``)."""

    B: int
    N: int  # knot-vector length
    nf: int  # free knot values per axis
    fi: torch.Tensor  # indices of the free knot values
    xi: torch.Tensor  # indices of the fixed knot values
    X0: torch.Tensor  # (B, N, 3) knot values, the free ones to be replaced
    Xp: torch.Tensor  # (B, nfix, 3) fixed knot values
    P: torch.Tensor
    q: torch.Tensor
    local: torch.Tensor  # (B, m, 3, 8) constraint rows on one segment's coefficients
    seg_np: np.ndarray  # (m,) segment of each row
    lo: torch.Tensor
    hi: torch.Tensor
    C: torch.Tensor  # (B, m, 3·nf) rows on the free values (no autograd)
    c_fix: torch.Tensor  # (B, m) the fixed values' part of each row (no autograd)
    limit_rows: tuple[int, int] = (0, 0)  # how many of the last rows are speed, then acceleration limits

    def relimited(self, v_max: torch.Tensor | None, a_max: torch.Tensor | None) -> _PositionQp:
        """The same problem with other speed / acceleration limits (only their bounds change)."""
        n_v, n_a = self.limit_rows
        keep = self.lo.shape[1] - n_v - n_a
        lo, hi = [self.lo[:, :keep]], [self.hi[:, :keep]]
        for n, limit in ((n_v, v_max), (n_a, a_max)):
            if n:
                assert limit is not None  # a problem with limit rows is re-limited with limits
                lo_l, hi_l = _limit_bounds(limit, n)
                lo.append(lo_l)
                hi.append(hi_l)
        return dataclasses.replace(self, lo=torch.cat(lo, dim=1), hi=torch.cat(hi, dim=1))

    def solve_active(self, active: list[np.ndarray], upper: list[np.ndarray]) -> torch.Tensor:
        """Differentiable KKT solve holding each element's ``active`` rows at their bounds (``upper``: the upper)."""
        B, dev = self.B, self.P.device
        k = max([a.size for a in active] + [0])
        idx = np.zeros((B, k), dtype=np.int64)
        msk = np.zeros((B, k), dtype=bool)
        upm = np.zeros((B, k), dtype=bool)
        for b, (a, u) in enumerate(zip(active, upper, strict=True)):
            idx[b, : a.size] = a
            msk[b, : a.size] = True
            upm[b, : a.size] = u
        idx_t = torch.as_tensor(idx, device=dev)
        loc_a = torch.gather(self.local, 1, idx_t.reshape(B, k, 1, 1).expand(B, k, 3, 8))
        seg_a = index_tensor(self.seg_np, dev)[idx_t]
        Ca_full = _to_global(loc_a, seg_a, self.N)
        Ca = Ca_full.index_select(3, self.fi).reshape(B, k, 3 * self.nf)
        cfix_a = torch.einsum("bman,bna->bm", Ca_full.index_select(3, self.xi), self.Xp)
        bound = torch.where(torch.as_tensor(upm, device=dev), torch.gather(self.hi, 1, idx_t),
                            torch.gather(self.lo, 1, idx_t)) - cfix_a
        return _qp.kkt_solve(self.P, self.q, Ca, bound, torch.as_tensor(msk, device=dev))

    def violated(self, z: torch.Tensor) -> torch.Tensor:
        """(B,) elements whose rows are violated by more than ~1e-8 relative, or not finite."""
        lo, hi = self.lo.detach(), self.hi.detach()
        lo_p = (lo - self.c_fix)
        hi_p = (hi - self.c_fix)
        tol = 1e-8 * (1.0 + torch.maximum(lo.abs(), hi.abs()))
        zd = z.detach()
        cz = torch.einsum("bmn,bn->bm", self.C, zd)
        viol = torch.clamp(cz - hi_p - tol, min=0) + torch.clamp(lo_p - tol - cz, min=0)
        return (~torch.isfinite(zd).all(-1)) | (viol.amax(-1) > 0)


def _inequality_rows(w: torch.Tensor, T: torch.Tensor, corridor: torch.Tensor | None, corridor_samples: int,
                     v_max: torch.Tensor | None, a_max: torch.Tensor | None) -> tuple[_Rows, tuple[int, int]]:
    """Rows (B, m, 3, 8), their segments (m,) and bounds lo/hi (B, m) of the corridor and limits given,
    and how many of the last rows are speed, then acceleration limits."""
    row_sets = []
    if corridor is not None:
        row_sets.append(_corridor_rows(w, T, corridor, corridor_samples))
    limit_rows = []
    for q, limit in ((1, v_max), (2, a_max)):  # the limits last (see _PositionQp.relimited)
        if limit is not None:
            row_sets.append(_limit_rows(T, q, limit, corridor_samples))
        limit_rows.append(0 if limit is None else row_sets[-1][0].shape[1])
    local = torch.cat([r[0] for r in row_sets], dim=1)  # (B, m, 3, 8)
    seg_np = np.concatenate([r[1] for r in row_sets])
    lo = torch.cat([r[2] for r in row_sets], dim=1)
    hi = torch.cat([r[3] for r in row_sets], dim=1)
    return (local, seg_np, lo, hi), (limit_rows[0], limit_rows[1])


def _position_qp(w: torch.Tensor, T: torch.Tensor, start: torch.Tensor, end: torch.Tensor, *,
                 corridor: torch.Tensor | None, corridor_samples: int, v_max: torch.Tensor | None,
                 a_max: torch.Tensor | None) -> _PositionQp:
    """Set up the position QP: snap objective on the free knot values and the inequality rows."""
    B, M = T.shape
    lay = layout(M, 4, corridor is not None)
    X0 = knot_values(w, start, end, 4)
    dev = w.device
    fi = index_tensor(lay.free, dev)
    xi = index_tensor(lay.fixed, dev)
    nf = lay.free.size
    Hff, Hfp = partitioned_hessian(T, 4, lay)
    Xp = X0.index_select(1, xi)  # (B, nfix, 3)
    P = torch.zeros(B, 3 * nf, 3 * nf, dtype=_WORK, device=dev)
    for a in range(3):
        P[:, a * nf:(a + 1) * nf, a * nf:(a + 1) * nf] = 2.0 * Hff
    q = (2.0 * (Hfp @ Xp)).transpose(1, 2).reshape(B, 3 * nf)
    (local, seg_np, lo, hi), limit_rows = _inequality_rows(w, T, corridor, corridor_samples, v_max, a_max)
    # The whole constraint matrix, without autograd, for the numerical solve.
    with torch.no_grad():
        seg_all = index_tensor(seg_np, dev).unsqueeze(0).expand(B, local.shape[1])
        Cfull = _to_global(local.detach(), seg_all, lay.n_knot)
        C = Cfull.index_select(3, fi).reshape(B, local.shape[1], 3 * nf)
        c_fix = torch.einsum("bman,bna->bm", Cfull.index_select(3, xi), Xp.detach())
    return _PositionQp(B=B, N=lay.n_knot, nf=nf, fi=fi, xi=xi, X0=X0, Xp=Xp, P=P, q=q, local=local, seg_np=seg_np,
                       lo=lo, hi=hi, C=C, c_fix=c_fix, limit_rows=limit_rows)


def _scaled(qp: _PositionQp) -> tuple[np.ndarray, ...]:
    """The problem scaled for the numerical solvers (unit Hessian diagonal, unit-norm rows), numpy:
    P, q, C, lo, hi, and the variables' scale d (z = d · z_scaled)."""
    with torch.no_grad():
        d = torch.rsqrt(torch.diagonal(qp.P.detach(), dim1=-2, dim2=-1))
        Ps = qp.P.detach() * d.unsqueeze(-1) * d.unsqueeze(-2)
        qs = qp.q.detach() * d
        Cs = qp.C * d.unsqueeze(1)
        rn = Cs.norm(dim=-1)
        rn = torch.where(rn > 0, rn, torch.ones_like(rn))
        Cs = Cs / rn.unsqueeze(-1)
        los = (qp.lo.detach() - qp.c_fix) / rn
        his = (qp.hi.detach() - qp.c_fix) / rn
    return (Ps.cpu().numpy(), qs.cpu().numpy(), Cs.cpu().numpy(), los.cpu().numpy(), his.cpu().numpy(),
            d.cpu().numpy())


def _solve_position_qp(qp: _PositionQp, solver: str) -> _Solved:
    """Knot vectors (B, N, 3), ok mask (B,) numpy, statuses and info of the set-up problem ``qp``."""
    Ps_np, qs_np, Cs_np, los_np, his_np, scale = _scaled(qp)
    res = _qp.solve_batch(Ps_np, qs_np, Cs_np, los_np, his_np, solver=solver)
    ok = res.ok.copy()
    status = list(res.status)
    active, upper = res.active, res.upper
    if solver == "daqp" and not torch.is_grad_enabled():
        # Without gradients DAQP's own answer serves: an exact active-set method, its last KKT solve
        # is the torch one below to rounding (~1e-12), which is there for autograd.
        z = torch.from_numpy(np.where(ok[:, None], res.z * scale, 0.0)).to(qp.X0)
        return _knots(qp, z), ok, status, _info(solver, res, active, qp)
    try:
        z = qp.solve_active(active, upper)
        bad = qp.violated(z).cpu().numpy() & ok
    except RuntimeError:  # a singular KKT matrix somewhere in the batch
        bad = ok.copy()
    if bad.any():
        # the active set did not reproduce the solution (inexact multipliers, or degenerate): repair it
        active, upper = list(active), list(upper)
        for b in np.nonzero(bad)[0]:
            active[b], upper[b] = _correct_active_set(
                Ps_np[b], qs_np[b], Cs_np[b], los_np[b], his_np[b], active[b], upper[b]
            )
        z = qp.solve_active(active, upper)
        bad = qp.violated(z).cpu().numpy() & ok
        for b in np.nonzero(bad)[0]:
            ok[b] = False
            status[b] = "the active-set KKT solve did not reproduce a feasible solution"
    z = torch.where(torch.as_tensor(ok, device=z.device).unsqueeze(-1), z, torch.zeros_like(z))
    return _knots(qp, z), ok, status, _info(solver, res, active, qp)


def _knots(qp: _PositionQp, z: torch.Tensor) -> torch.Tensor:
    """Knot vectors (B, N, 3) with the free values ``z`` (B, 3·nf)."""
    return qp.X0.index_copy(1, qp.fi, z.reshape(qp.B, 3, qp.nf).transpose(1, 2))


def _info(solver: str, res: _qp.QPResult, active: list[np.ndarray], qp: _PositionQp) -> dict[str, Any]:
    return {"path": "qp", "solver": solver, "solver_seconds": res.seconds, "active": [int(a.size) for a in active],
            "rows": int(qp.local.shape[1]), "variables": int(3 * qp.nf)}


def _correct_active_set(P: np.ndarray, q: np.ndarray, C: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                        act: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Repair an inexact active set (numpy, scaled problem) with DAQP warm-started from it (unchanged if it fails)."""
    act = np.asarray(act, dtype=np.int64)
    sense = np.zeros(C.shape[0], dtype=np.int32)
    sense[act] = np.where(np.asarray(up, dtype=bool), 1, 3)  # ACTIVE (| LOWER)
    z, lam, _status = _qp._solve_daqp(P, q, C, lo, hi, sense=sense)
    if z is None or lam is None:
        return act, np.asarray(up, dtype=bool)
    a, u = _qp._active_from_duals(lam, C, z, lo, hi, True)
    kept = _independent(C, a)
    return kept, u[np.isin(a, kept)]


def _independent(C: np.ndarray, act: np.ndarray) -> np.ndarray:
    """Drop held rows that are linearly dependent on others (degenerate active sets)."""
    if act.size <= 1:
        return act
    from scipy.linalg import qr

    _, R, piv = qr(C[act].T, pivoting=True, mode="economic")
    diag = np.abs(np.diag(R))
    rank = int((diag > 1e-9 * diag[0]).sum())
    return np.sort(act[piv[:rank]])


def _tighten_limits(X: torch.Tensor, ok: np.ndarray, status: list[str], info: dict[str, Any], T: torch.Tensor,
                    vm: torch.Tensor | None, am: torch.Tensor | None, solver: str, qp: _PositionQp) -> _Solved:
    """Re-solve ``qp`` with ``vm``/``am`` scaled down by the excess found on a dense grid until the solution
    keeps them between the QP's samples too (at most 4 rounds)."""
    vm0, am0 = vm, am
    for _ in range(4):
        traj = Trajectory(coefficients(X, T, 4), T)
        scale = torch.ones(T.shape[0], dtype=_WORK, device=T.device)
        for limit, limit0, order in ((vm, vm0, 1), (am, am0, 2)):
            if limit is None or limit0 is None:  # both or neither
                continue
            peak = traj._dense(order, 256).detach().abs().amax(dim=(1, 2, 3))
            scale = torch.minimum(scale, torch.where(peak > limit0 * (1 + 1e-9), limit0 / peak, torch.ones_like(peak)))
        if bool((scale >= 1).all()):
            break
        vm = None if vm is None else vm * torch.where(scale < 1, 0.995 * scale, torch.ones_like(scale))
        am = None if am is None else am * torch.where(scale < 1, 0.995 * scale, torch.ones_like(scale))
        # only the limits' bounds change: the problem is not set up again (most of a solve's time)
        X, ok, status, info = _solve_position_qp(qp.relimited(vm, am), solver)
    return X, ok, status, info


def _yaw(yaw: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """Minimum yaw-acceleration cubic spline through unwrapped yaw key-points, rest at both ends."""
    B, M1 = yaw.shape
    d = yaw[:, 1:] - yaw[:, :-1]
    d = d - (2 * math.pi) * torch.round(d.detach() / (2 * math.pi))
    psi = torch.cat([yaw[:, :1], yaw[:, :1] + torch.cumsum(d, dim=1)], dim=1)
    zeros = torch.zeros(B, 1, 1, dtype=yaw.dtype, device=yaw.device)
    X0 = knot_values(psi.unsqueeze(-1), zeros, zeros, 2)
    X = solve_knots(T, X0, layout(M1 - 1, 2, False))
    return coefficients(X, T, 2)[:, :, 0, :]


# -------------------------------------------------------------------------------------- public
def min_snap(
    waypoints: torch.Tensor,
    durations: torch.Tensor,
    *,
    start: torch.Tensor | None = None,
    end: torch.Tensor | None = None,
    corridor: float | torch.Tensor | None = None,
    corridor_samples: int = 5,
    v_max: float | torch.Tensor | None = None,
    a_max: float | torch.Tensor | None = None,
    yaw: torch.Tensor | None = None,
    solver: str = _qp.DEFAULT_SOLVER,
    on_infeasible: Literal["warn", "raise", "ignore"] = "warn",
    limits_everywhere: bool = False,
) -> Trajectory:
    """Minimum-snap piecewise 7th-order polynomial trajectory through key-points (or within a corridor
    around them), differentiable with respect to the key-points, durations and boundary derivatives.

    - ``waypoints`` (B, M+1, 3) or (M+1, 3) metres: start, M-1 interior key-points, end;
      ``durations`` (B, M) or (M,) seconds, all > 0.
    - ``start``, ``end`` (B, 3, 3) or (3, 3): rows velocity, acceleration, jerk (default 0).
    - ``corridor``: half-width (m), a scalar, (M,) or (B, M). Interior key-points become free; at
      ``corridor_samples`` (>= 1) interior points of every segment and at every interior knot, each
      world-axis component of the deviation across the segment's key-point line stays within
      +-corridor, and the position along it within the segment extended by ``corridor``.
    - ``v_max``, ``a_max``: per-axis speed (m/s) and acceleration (m/s²) limits, scalar or (B,), at
      the same samples; ``limits_everywhere`` also holds them between the samples (checked on 256
      points per segment, solved again with the limit tightened by the excess, at most 4 times).
    - ``yaw`` (B, M+1) or (M+1,) radians: adds a minimum ``integral (d^2 psi/dt^2)^2`` cubic yaw
      spline (zero yaw rate at both ends); consecutive angles are unwrapped.
    - ``solver``: QP backend, one of ``mapkit.trajopt.SOLVERS``.
    - ``on_infeasible``: "warn" (a :class:`TrajoptWarning`), "raise" (:class:`TrajoptError`) or
      "ignore" when some elements of a constrained problem cannot be solved; either way
      ``Trajectory.solved`` is False for them and they hold the closed form through the key-points.

    Returns a :class:`Trajectory` in the dtype and on the device of ``waypoints`` (unbatched for
    unbatched inputs).
    """
    w, batched = _work_waypoints(waypoints)
    out_dtype = waypoints.dtype
    T_in = _durations(durations, out_dtype, w, w.shape[1] - 1)
    T = T_in.to(_WORK)
    start_t, end_t, corr, vm, am = _conditions(w, T, start, end, corridor, v_max, a_max,
                                               corridor_samples=corridor_samples, solver=solver,
                                               on_infeasible=on_infeasible)
    X, solved, messages, info = _solve_knots(w, T, start_t, end_t, corr, corridor_samples, vm, am, solver,
                                             limits_everywhere, on_infeasible)
    coeffs = coefficients(X, T, 4).to(out_dtype)
    yaw_c = None if yaw is None else _yaw_coefficients(yaw, w, T).to(out_dtype)
    return Trajectory(coeffs, T_in, yaw_coeffs=yaw_c, solved=solved, messages=messages, batched=batched, info=info)


def _conditions(
    w: torch.Tensor, T: torch.Tensor, start: torch.Tensor | None, end: torch.Tensor | None,
    corridor: float | torch.Tensor | None, v_max: float | torch.Tensor | None, a_max: float | torch.Tensor | None,
    *, corridor_samples: int, solver: str, on_infeasible: str,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]:
    """:func:`min_snap`'s inputs checked: (B, 3, 3) start and end derivatives, corridor, v_max, a_max."""
    B, M = w.shape[0], w.shape[1] - 1
    _check_finite(w, "waypoints")
    _check_positive_durations(T)
    start_t, end_t = _boundary(start, "start", B, w), _boundary(end, "end", B, w)
    _check_options(corridor_samples, solver, on_infeasible)
    corr, vm, am = _inequalities(corridor, v_max, a_max, B, M, w)
    return start_t, end_t, corr, vm, am


def _solve_knots(
    w: torch.Tensor, T: torch.Tensor, start_t: torch.Tensor, end_t: torch.Tensor, corr: torch.Tensor | None,
    corridor_samples: int, vm: torch.Tensor | None, am: torch.Tensor | None, solver: str, limits_everywhere: bool,
    on_infeasible: str,
) -> tuple[torch.Tensor, torch.Tensor, tuple[str, ...], dict[str, Any]]:
    """(knot values, solved (B,), messages, info) of :func:`min_snap`."""
    if corr is None and vm is None and am is None:
        B, M = w.shape[0], w.shape[1] - 1
        X = solve_knots(T, knot_values(w, start_t, end_t, 4), layout(M, 4, False))
        return X, torch.ones(B, dtype=torch.bool, device=w.device), (), {"path": "closed_form"}
    return _solve_constrained(w, T, start_t, end_t, corr, corridor_samples, vm, am, solver, limits_everywhere,
                              on_infeasible)


def _work_waypoints(waypoints: torch.Tensor) -> tuple[torch.Tensor, bool]:
    """(B, M+1, 3) waypoints in the work precision and whether the input was batched; checks type and shape."""
    if not isinstance(waypoints, torch.Tensor):
        raise TrajoptError(f"waypoints must be a torch tensor, got {type(waypoints).__name__}")
    w, batched = batched_waypoints(waypoints)
    return w.to(_WORK), batched


def _durations(durations: torch.Tensor | ArrayLike, out_dtype: torch.dtype, w: torch.Tensor, M: int) -> torch.Tensor:
    """(B, M) durations as given (dtype kept for the trajectory), broadcast over the batch."""
    if not isinstance(durations, torch.Tensor):
        durations = torch.as_tensor(np.asarray(durations, dtype=np.float64), dtype=out_dtype, device=w.device)
    T_in = durations if durations.ndim == 2 else durations.unsqueeze(0)
    if T_in.shape[-1] != M:
        raise TrajoptError(f"durations must have M={M} entries per element, got shape {tuple(durations.shape)}")
    return torch.broadcast_to(T_in, (w.shape[0], M))


def _check_positive_durations(T: torch.Tensor) -> None:
    """Raise :class:`TrajoptError` unless every duration is finite and > 0."""
    _check_finite(T, "durations")
    if bool((T.detach() <= 0).any()):
        raise TrajoptError("durations must all be > 0 seconds; got a zero or negative duration")


def _boundary(value: torch.Tensor | ArrayLike | None, name: str, B: int, w: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) velocity, acceleration and jerk at one end (zeros when not given)."""
    if value is None:
        return torch.zeros(B, 3, 3, dtype=_WORK, device=w.device)
    return _batch_param(value, name, B, (3, 3), w)


def _check_options(corridor_samples: int, solver: str, on_infeasible: str) -> None:
    """Raise :class:`TrajoptError` for a sample count, solver or infeasibility policy out of range."""
    if corridor_samples < 1:
        raise TrajoptError(f"corridor_samples must be >= 1, got {corridor_samples}")
    if solver not in _qp.SOLVERS:
        raise TrajoptError(f"solver must be one of {_qp.SOLVERS}, got {solver!r}")
    if on_infeasible not in ("warn", "raise", "ignore"):
        raise TrajoptError(f"on_infeasible must be 'warn', 'raise' or 'ignore', got {on_infeasible!r}")


def _inequalities(
    corridor: float | torch.Tensor | None, v_max: float | torch.Tensor | None, a_max: float | torch.Tensor | None,
    B: int, M: int, w: torch.Tensor,
) -> tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]:
    """Corridor half-widths (B, M), speed and acceleration limits (B,), each None when not given; checked > 0."""
    corr = None
    if corridor is not None:
        corr = _batch_param(corridor, "corridor", B, (M,), w)
        if bool((corr.detach() <= 0).any()) or not bool(torch.isfinite(corr.detach()).all()):
            raise TrajoptError("corridor half-widths must be finite and > 0 metres")
    vm = am = None
    if v_max is not None:
        vm = _batch_param(v_max, "v_max", B, (), w)
        if bool((vm.detach() <= 0).any()):
            raise TrajoptError("v_max must be > 0 m/s")
    if a_max is not None:
        am = _batch_param(a_max, "a_max", B, (), w)
        if bool((am.detach() <= 0).any()):
            raise TrajoptError("a_max must be > 0 m/s²")
    return corr, vm, am


def _solve_constrained(
    w: torch.Tensor, T: torch.Tensor, start_t: torch.Tensor, end_t: torch.Tensor, corr: torch.Tensor | None,
    corridor_samples: int, vm: torch.Tensor | None, am: torch.Tensor | None, solver: str, limits_everywhere: bool,
    on_infeasible: str,
) -> tuple[torch.Tensor, torch.Tensor, tuple[str, ...], dict[str, Any]]:
    """The inequality path: (X, solved mask, messages, info); unsolved elements fall back to the closed form."""
    qp = _position_qp(w, T, start_t, end_t, corridor=corr, corridor_samples=corridor_samples, v_max=vm, a_max=am)
    X, ok, status, info = _solve_position_qp(qp, solver)
    if limits_everywhere and (vm is not None or am is not None):
        X, ok, status, info = _tighten_limits(X, ok, status, info, T, vm, am, solver, qp)
    solved = torch.ones(w.shape[0], dtype=torch.bool, device=w.device)
    messages: tuple[str, ...] = ()
    if not ok.all():
        X, solved, messages, text = _fall_back_where_unsolved(X, ok, status, w, T, start_t, end_t)
        if on_infeasible == "raise":
            raise TrajoptError(text)
        if on_infeasible == "warn":
            warnings.warn(text, TrajoptWarning, stacklevel=4)  # at min_snap's caller (through _solve_knots)
    return X, solved, messages, info


def _fall_back_where_unsolved(
    X: torch.Tensor, ok: np.ndarray, status: list[str], w: torch.Tensor, T: torch.Tensor, start_t: torch.Tensor,
    end_t: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, tuple[str, ...], str]:
    """Unsolved elements take the closed form: (X, solved mask, messages, the text to warn or raise with)."""
    B, M = T.shape
    failed = np.nonzero(~ok)[0]
    messages = tuple(f"batch element {int(b)}: {status[b]}" for b in failed)
    X_eq = solve_knots(T, knot_values(w, start_t, end_t, 4), layout(M, 4, False))
    ok_t = torch.as_tensor(ok, device=w.device)
    X = torch.where(ok_t.reshape(B, 1, 1), X, X_eq)
    text = (
        f"min_snap: {failed.size} of {B} constrained problems could not be solved "
        f"({'; '.join(messages[:3])}{'; ...' if failed.size > 3 else ''}); they hold the "
        "solution through the key-points without corridor/limits. Widen the corridor, "
        "relax v_max/a_max or lengthen the durations."
    )
    return X, ok_t, messages, text


def _yaw_coefficients(yaw: torch.Tensor, w: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """Cubic yaw-spline coefficients from (B, M+1) or (M+1,) yaw key-points, in the work precision."""
    B, M1 = w.shape[0], w.shape[1]
    y = _as_tensor(yaw, "yaw", w).to(_WORK)
    y = y if y.ndim == 2 else y.unsqueeze(0)
    try:
        y = torch.broadcast_to(y, (B, M1))
    except RuntimeError as exc:
        raise TrajoptError(f"yaw must have shape (B, M+1) or (M+1,), got {tuple(yaw.shape)}") from exc
    _check_finite(y, "yaw")
    return _yaw(y, T)
