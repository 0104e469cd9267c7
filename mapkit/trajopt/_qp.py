"""Batched inequality-constrained QPs: an exact solve per element, then a differentiable
active-set KKT solve in torch.

Per element (float64): minimise ``1/2 z^T P z + q^T z`` subject to ``lo <= C z <= hi`` (lo may be
-inf). A qpsolvers backend (DAQP by default, called directly) solves it on the CPU; the rows with
positive multipliers are held at their bound and the solution recomputed in torch from that
equality-constrained KKT system, whose autograd is the implicit-function gradient (no unrolling) and
which polishes the answer to machine precision. ``mapkit.trajopt._minsnap`` repairs active sets that
do not reproduce a feasible point.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

SOLVERS = ("daqp", "proxqp", "clarabel", "piqp")
"""Backends the corridor path can use (``solver=`` of :func:`mapkit.trajopt.min_snap`)."""

DEFAULT_SOLVER = "daqp"


@dataclass
class QPResult:
    """Per-element outcome of :func:`solve_batch` (numpy, float64)."""

    z: np.ndarray  # (B, n)
    active: list[np.ndarray]  # per element: row indices held at a bound
    upper: list[np.ndarray]  # per element: True where the held bound is ``hi``
    ok: np.ndarray  # (B,) bool
    status: list[str]  # per element: "optimal" or the failure reason
    seconds: float  # wall time of the solver calls


def _active_from_duals(lam: np.ndarray, C: np.ndarray, z: np.ndarray, lo: np.ndarray,
                       hi: np.ndarray, exact: bool) -> tuple[np.ndarray, np.ndarray]:
    """Held rows and their side. An active-set solver (``exact``) returns exact zeros for the
    multipliers of free rows; interior-point solvers need a slack test as well."""
    scale = max(1.0, float(np.abs(lam).max(initial=0.0)))
    cz = C @ z
    if exact:
        act = np.nonzero(np.abs(lam) > 1e-12 * scale)[0]
    else:
        slack = np.minimum(np.abs(cz - hi), np.abs(cz - lo))
        act = np.nonzero((np.abs(lam) > 1e-5 * scale) & (slack < 1e-3))[0]
    up = np.abs(cz[act] - hi[act]) <= np.abs(cz[act] - lo[act])
    return act, up


def _solve_daqp(P: np.ndarray, q: np.ndarray, C: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                sense: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """Solution z, multipliers and "optimal", or (None, None, the reason) when DAQP fails."""
    import daqp

    lo_d = np.where(np.isfinite(lo), lo, -1e30)
    hi_d = np.where(np.isfinite(hi), hi, 1e30)
    if sense is None:
        sense = np.zeros(C.shape[0], dtype=np.int32)
    z, _fval, flag, info = daqp.solve(
        np.ascontiguousarray(P), np.ascontiguousarray(q), np.ascontiguousarray(C), hi_d, lo_d, sense,
        primal_tol=1e-9, dual_tol=1e-12, iter_limit=2000,
    )
    if flag < 1:
        reason = {-1: "infeasible", -2: "cycling", -3: "unbounded", -4: "iteration limit",
                  -5: "non-convex", -6: "initial active set infeasible"}.get(int(flag), f"exitflag {flag}")
        return None, None, reason
    lam = np.asarray(info["lam"], dtype=np.float64)
    return np.asarray(z, dtype=np.float64), lam, "optimal"


# ProxQP's tolerance (the others' defaults serve): the active-set KKT polish supplies the last digits,
# so the backends only need to identify the active set reliably.
_KW: dict[str, dict[str, Any]] = {"proxqp": dict(eps_abs=1e-9, eps_rel=0.0)}


def _solve_qpsolvers(name: str, P: np.ndarray, q: np.ndarray, C: np.ndarray, lo: np.ndarray,
                     hi: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """Solution z, multipliers and "optimal", or (None, None, the reason) when backend ``name`` fails."""
    from qpsolvers import Problem, solve_problem

    fin_hi = np.isfinite(hi)
    fin_lo = np.isfinite(lo)
    G = np.vstack([C[fin_hi], -C[fin_lo]])
    h = np.concatenate([hi[fin_hi], -lo[fin_lo]])
    kw = _KW.get(name, {})
    sol = solve_problem(Problem(P, q, G, h), solver=name, **kw)
    if not sol.found or sol.x is None or not np.all(np.isfinite(sol.x)):
        return None, None, "infeasible or not solved"
    lam_g = np.asarray(sol.z, dtype=np.float64)
    lam = np.zeros(C.shape[0])
    idx_hi = np.nonzero(fin_hi)[0]
    idx_lo = np.nonzero(fin_lo)[0]
    lam[idx_hi] += lam_g[: idx_hi.size]
    lam[idx_lo] -= lam_g[idx_hi.size:]
    return np.asarray(sol.x, dtype=np.float64), lam, "optimal"


def solve_batch(P: np.ndarray, q: np.ndarray, C: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                *, solver: str = DEFAULT_SOLVER) -> QPResult:
    """Solve every element's QP with ``solver``; shapes P (B,n,n), q (B,n), C (B,m,n), lo/hi (B,m)."""
    B, n = q.shape
    zs = np.zeros((B, n))
    ok = np.zeros(B, dtype=bool)
    active: list[np.ndarray] = []
    upper: list[np.ndarray] = []
    status: list[str] = []
    t0 = time.perf_counter()
    for b in range(B):
        if solver == "daqp":
            z, lam, st = _solve_daqp(P[b], q[b], C[b], lo[b], hi[b])
        else:
            z, lam, st = _solve_qpsolvers(solver, P[b], q[b], C[b], lo[b], hi[b])
        status.append(st)
        if z is None or lam is None:
            active.append(np.zeros(0, dtype=np.int64))
            upper.append(np.zeros(0, dtype=bool))
            continue
        zs[b] = z
        ok[b] = True
        a, u = _active_from_duals(lam, C[b], z, lo[b], hi[b], solver == "daqp")
        active.append(a)
        upper.append(u)
    return QPResult(zs, active, upper, ok, status, time.perf_counter() - t0)


def kkt_solve(P: torch.Tensor, q: torch.Tensor, Ca: torch.Tensor, ba: torch.Tensor,
              mask: torch.Tensor) -> torch.Tensor:
    """Differentiable solution z (B, n) of ``min 1/2 z^T P z + q^T z  s.t.  Ca z = ba`` for the
    rows where ``mask`` (B, k) is True (padding rows are ignored).

    Solves the KKT system ``[P Ca^T; Ca 0] [z; lam] = [-q; ba]`` after a unit-diagonal scaling of P
    and unit-norm rows (detached, so an exact reformulation), by LU; autograd through that solve is
    the implicit derivative of the QP solution at this active set.
    """
    _, n = q.shape
    dt = q.dtype
    k = Ca.shape[1]
    d = torch.rsqrt(torch.diagonal(P, dim1=-2, dim2=-1)).detach()
    Ps = P * d.unsqueeze(-1) * d.unsqueeze(-2)
    qs = q * d
    if k == 0:
        y = torch.linalg.solve(Ps, -qs.unsqueeze(-1)).squeeze(-1)
        z_free: torch.Tensor = y * d
        return z_free
    mf = mask.to(dt)
    Cs = Ca * d.unsqueeze(1)
    rn = Cs.detach().norm(dim=-1).clamp_min(1e-300)
    Cs = Cs / rn.unsqueeze(-1) * mf.unsqueeze(-1)
    bs = ba / rn * mf
    top = torch.cat([Ps, Cs.transpose(1, 2)], dim=2)
    bot = torch.cat([Cs, torch.diag_embed(mf - 1.0)], dim=2)
    K = torch.cat([top, bot], dim=1)
    rhs = torch.cat([-qs, bs], dim=1).unsqueeze(-1)
    sol = torch.linalg.solve(K, rhs).squeeze(-1)
    z: torch.Tensor = sol[:, :n] * d
    return z
