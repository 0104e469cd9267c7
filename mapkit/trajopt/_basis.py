"""Exact constants of the normalised-time polynomial basis.

A segment of duration ``T`` is ``p(t) = sum_k c[k] * s**k`` with ``s = t / T`` in ``[0, 1]``.
A trajectory whose smoothness cost penalises the ``r``-th derivative uses ``2r`` coefficients
(degree ``2r - 1``: 7 for minimum snap, 3 for minimum yaw acceleration) and carries ``r`` derivatives
(orders ``0 .. r-1``) through every knot.

All matrices are computed once in exact rational arithmetic and cached as float64 numpy arrays.
"""

from __future__ import annotations

from fractions import Fraction
from functools import cache
from math import factorial

import numpy as np


def _falling(k: int, q: int) -> int:
    """k! / (k - q)!  (0 when q > k)."""
    if q > k:
        return 0
    return factorial(k) // factorial(k - q)


def _invert(mat: list[list[Fraction]]) -> list[list[Fraction]]:
    """Gauss-Jordan inverse of a small non-singular rational matrix."""
    n = len(mat)
    aug = [row[:] + [Fraction(int(i == j)) for j in range(n)] for i, row in enumerate(mat)]
    for col in range(n):
        piv = next(r for r in range(col, n) if aug[r][col] != 0)
        aug[col], aug[piv] = aug[piv], aug[col]
        inv_p = 1 / aug[col][col]
        aug[col] = [v * inv_p for v in aug[col]]
        for r in range(n):
            if r != col and aug[r][col] != 0:
                f = aug[r][col]
                aug[r] = [a - f * b for a, b in zip(aug[r], aug[col], strict=True)]
    return [row[n:] for row in aug]


def _floats(mat: tuple[tuple[Fraction, ...], ...]) -> np.ndarray:
    return np.array([[float(v) for v in row] for row in mat], dtype=np.float64)


@cache
def boundary_inverse(r: int) -> np.ndarray:
    """``Ainv`` (2r, 2r): coefficients = Ainv @ [s-derivatives 0..r-1 at s=0; at s=1].

    The s-derivative of order q equals ``T**q`` times the time derivative of order q.
    """
    return _floats(_exact_boundary_inverse(r))


@cache
def cost_matrix(r: int) -> np.ndarray:
    """``Qhat`` (2r, 2r): ``integral_0^1 (d^r p / ds^r)^2 ds = c^T Qhat c``."""
    return _floats(_exact_cost(r))


@cache
def knot_cost_matrix(r: int) -> np.ndarray:
    """``R = Ainv^T Qhat Ainv`` (2r, 2r): the cost as a quadratic form in boundary s-derivatives."""
    a, q = _exact_boundary_inverse(r), _exact_cost(r)
    n = range(2 * r)
    return _floats(tuple(tuple(sum((a[k][i] * q[k][m] * a[m][j] for k in n for m in n), Fraction(0)) for j in n)
                         for i in n))


@cache
def _exact_boundary_inverse(r: int) -> tuple[tuple[Fraction, ...], ...]:
    n = 2 * r
    a = [[Fraction(0)] * n for _ in range(n)]
    for q in range(r):
        a[q][q] = Fraction(factorial(q))
        for k in range(n):
            a[r + q][k] = Fraction(_falling(k, q))
    return tuple(tuple(row) for row in _invert(a))


@cache
def _exact_cost(r: int) -> tuple[tuple[Fraction, ...], ...]:
    n = range(2 * r)
    return tuple(tuple(Fraction(_falling(j, r) * _falling(k, r), j + k - 2 * r + 1) if j >= r and k >= r else Fraction(0)
                       for k in n) for j in n)


def basis_row(s: np.ndarray, n: int, q: int) -> np.ndarray:
    """Rows ``d^q/ds^q [s^0 .. s^(n-1)]`` at the points ``s`` (K,), shape (K, n)."""
    s = np.asarray(s, dtype=np.float64)
    out = np.zeros((s.shape[0], n), dtype=np.float64)
    for k in range(q, n):
        out[:, k] = _falling(k, q) * s ** (k - q)
    return out
