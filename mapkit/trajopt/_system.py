"""The smoothness cost as a quadratic form in the knot states, batched in torch.

Knot ``k`` (0..M) carries the time derivatives of orders ``0..r-1`` of every axis; segment ``i`` is
determined by knots ``i`` and ``i+1`` (continuity by construction) and costs
``T_i^(1-2r) d^T S R S d`` (``d`` its 2r knot entries, ``S = diag(T_i^q)``), so ``J = sum_axes X^T H X``
with H block-tridiagonal. Knot entries are fixed (boundary conditions, key-points) or free.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
import torch

from mapkit.trajopt._basis import basis_row, boundary_inverse, knot_cost_matrix
from mapkit.trajopt._errors import TrajoptError


def batched_waypoints(waypoints: torch.Tensor) -> tuple[torch.Tensor, bool]:
    """(B, M+1, 3) key-points and whether the input was batched; :class:`TrajoptError` for a bad dtype or shape."""
    if not waypoints.is_floating_point():
        raise TrajoptError(f"waypoints must be float32 or float64, got {waypoints.dtype}")
    if waypoints.ndim not in (2, 3) or waypoints.shape[-1] != 3 or waypoints.shape[-2] < 2:
        raise TrajoptError(f"waypoints must have shape (B, M+1, 3) or (M+1, 3) with M >= 1, got {tuple(waypoints.shape)}")
    batched = waypoints.ndim == 3
    return (waypoints if batched else waypoints.unsqueeze(0)), batched


@dataclass(frozen=True)
class Layout:
    """Which knot entries are free (per axis; identical for every axis and batch element)."""

    M: int
    r: int
    free: np.ndarray  # indices into the r(M+1) knot vector
    fixed: np.ndarray

    @property
    def n_knot(self) -> int:
        return self.r * (self.M + 1)


@cache
def layout(M: int, r: int, free_positions: bool) -> Layout:
    """Free entries: interior derivatives 1..r-1, plus interior positions when ``free_positions``."""
    free, fixed = [], []
    for k in range(M + 1):
        for q in range(r):
            idx = k * r + q
            interior = 0 < k < M
            if interior and (q > 0 or free_positions):
                free.append(idx)
            else:
                fixed.append(idx)
    return Layout(M, r, np.array(free, dtype=np.int64), np.array(fixed, dtype=np.int64))


_CONST_CACHE: dict[tuple[object, ...], torch.Tensor] = {}


def _const(name: str, r: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Constant ``name`` ("R" or "Ainv") of order ``r``, made once per dtype and device."""
    key = (name, r, dtype, str(device))
    t = _CONST_CACHE.get(key)
    if t is None:
        arr = knot_cost_matrix(r) if name == "R" else boundary_inverse(r)
        with torch.inference_mode(False):
            t = torch.as_tensor(arr, dtype=dtype, device=device)
        _CONST_CACHE[key] = t
    return t


def index_tensor(arr: np.ndarray, device: torch.device) -> torch.Tensor:
    """``arr`` as an index tensor on ``device``, made once per content and device."""
    key = ("index", arr.tobytes(), str(device))
    t = _CONST_CACHE.get(key)
    if t is None:
        # a tensor made under torch.inference_mode (a planner at run time) could never be used by
        # autograd again (training later in the same process): cache ordinary tensors only
        with torch.inference_mode(False):
            t = torch.as_tensor(arr, device=device)
        _CONST_CACHE[key] = t
    return t


def time_powers(T: torch.Tensor, r: int) -> torch.Tensor:
    """(B, M, 2r): [T^0 .. T^(r-1), T^0 .. T^(r-1)]."""
    pows = [torch.ones_like(T)]
    for _ in range(1, r):
        pows.append(pows[-1] * T)
    sv = torch.stack(pows, dim=-1)
    return torch.cat([sv, sv], dim=-1)


@cache
def _perm_scatter_index(M: int, r: int, free_positions: bool) -> np.ndarray:
    """Flat indices into an (N, N) matrix of every entry of the M local (2r, 2r) blocks, in the
    knot vector reordered as [free entries, fixed entries]."""
    lay = layout(M, r, free_positions)
    N = r * (M + 1)
    pos = np.empty(N, dtype=np.int64)
    pos[np.concatenate([lay.free, lay.fixed])] = np.arange(N)
    loc = np.arange(2 * r)
    out = np.empty((M, 2 * r, 2 * r), dtype=np.int64)
    for i in range(M):
        g = pos[i * r + loc]
        out[i] = g[:, None] * N + g[None, :]
    return out.reshape(-1)


def partitioned_hessian(T: torch.Tensor, r: int, lay: Layout) -> tuple[torch.Tensor, torch.Tensor]:
    """(H_ff (B, nf, nf), H_fp (B, nf, nfix)) of the per-axis cost ``X^T H X`` of the knot vector X,
    assembled directly in the [free, fixed] order so the blocks are slices (no gathers)."""
    B, M = T.shape
    R = _const("R", r, T.dtype, T.device)
    sv = time_powers(T, r)
    blocks = (T ** (1 - 2 * r)).unsqueeze(-1).unsqueeze(-1) * sv.unsqueeze(-1) * sv.unsqueeze(-2) * R
    N = r * (M + 1)
    idx = index_tensor(_perm_scatter_index(M, r, lay.free.size > (M - 1) * (r - 1)), T.device)
    H = torch.zeros(B, N * N, dtype=T.dtype, device=T.device).index_add(1, idx, blocks.reshape(B, -1))
    H = H.reshape(B, N, N)
    nf = lay.free.size
    return H[:, :nf, :nf], H[:, :nf, nf:]


def solve_knots(T: torch.Tensor, X: torch.Tensor, lay: Layout) -> torch.Tensor:
    """Minimise ``sum_axes X^T H X`` (durations T) over the free entries of X; returns the full knot
    vector (B, N, A). Exact dense solve of the reduced system, scaled to unit diagonal."""
    if lay.free.size == 0:
        return X
    Hff, Hfp = partitioned_hessian(T, lay.r, lay)
    return _reduced_solve(Hff, Hfp, X, lay)


def _reduced_solve(Hff: torch.Tensor, Hfp: torch.Tensor, X: torch.Tensor, lay: Layout) -> torch.Tensor:
    dev = X.device
    fi = index_tensor(lay.free, dev)
    xi = index_tensor(lay.fixed, dev)
    Xp = X.index_select(1, xi)
    rhs = -(Hfp @ Xp)
    dscale = torch.rsqrt(torch.diagonal(Hff, dim1=-2, dim2=-1)).detach()
    A = Hff * dscale.unsqueeze(-1) * dscale.unsqueeze(-2)
    y = torch.linalg.solve(A, rhs * dscale.unsqueeze(-1))
    xf = y * dscale.unsqueeze(-1)
    return X.index_copy(1, fi, xf)


def knot_values(
    points: torch.Tensor, start: torch.Tensor, end: torch.Tensor, r: int
) -> torch.Tensor:
    """Knot vector template (B, N, A) from points (B, M+1, A) and start/end derivatives 1..r-1
    (B, r-1, A); the interior derivatives zero."""
    B, M1, A = points.shape
    zeros = torch.zeros(B, M1 - 2, r - 1, A, dtype=points.dtype, device=points.device)
    der = torch.cat([start.unsqueeze(1), zeros, end.unsqueeze(1)], dim=1)  # (B, M+1, r-1, A)
    X = torch.cat([points.unsqueeze(2), der], dim=2)  # (B, M+1, r, A)
    return X.reshape(B, M1 * r, A)


def coefficients(X: torch.Tensor, T: torch.Tensor, r: int) -> torch.Tensor:
    """Polynomial coefficients (B, M, A, 2r) from the full knot vector X (B, N, A)."""
    B, _, A = X.shape
    M = T.shape[1]
    K = X.reshape(B, M + 1, r, A)
    d = torch.cat([K[:, :-1], K[:, 1:]], dim=2)  # (B, M, 2r, A)
    ds = d * time_powers(T, r).unsqueeze(-1)
    Ainv = _const("Ainv", r, T.dtype, T.device)
    dsT = ds.transpose(-1, -2).reshape(-1, 2 * r)  # one GEMM instead of many tiny batched ones
    return (dsT @ Ainv.T).reshape(B, M, A, 2 * r)


def sample_rows(T: torch.Tensor, s: np.ndarray, q: int, r: int) -> torch.Tensor:
    """Rows (B, M, K, 2r) mapping a segment's 2r knot entries to the q-th time derivative at ``s`` (K,)."""
    phi = torch.as_tensor(basis_row(s, 2 * r, q), dtype=T.dtype, device=T.device)  # (K, 2r)
    Ainv = _const("Ainv", r, T.dtype, T.device)
    base = phi @ Ainv  # (K, 2r) acting on s-derivatives
    sv = time_powers(T, r)  # (B, M, 2r)
    rows = base.unsqueeze(0).unsqueeze(0) * sv.unsqueeze(2)
    if q:
        rows = rows / (T ** q).unsqueeze(-1).unsqueeze(-1)
    return rows

