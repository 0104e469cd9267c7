"""Piecewise polynomials in world time (numpy): what a method hands the closed loop to fly."""

from __future__ import annotations

from dataclasses import dataclass
from math import comb, factorial

import numpy as np

# 4-point Gauss–Legendre on [0, 1]: exact for polynomials of degree <= 7, so for the squared snap
# (degree 6) of a degree-7 segment.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(4)
_GL_X = 0.5 * (_GL_X + 1.0)
_GL_W = 0.5 * _GL_W


def _falling(k: np.ndarray, q: int) -> np.ndarray:
    """k! / (k - q)! elementwise (0 where k < q)."""
    out = np.ones_like(k, dtype=np.float64)
    for i in range(q):
        out = out * (k - i)
    return np.where(k >= q, out, 0.0)


@dataclass
class Pieces:
    """Segments ``p(t) = sum_k coeffs[i, :, k] * s**k``, ``s = (t - knots[i]) / durations[i]``, world
    frame, ``t`` in seconds of episode time; after the last knot the end position is held at rest."""

    t0: float
    """Episode time of the start, seconds."""
    durations: np.ndarray
    """(M,) seconds, each > 0."""
    coeffs: np.ndarray
    """(M, 3, n) ascending powers of normalised time, metres."""

    def __post_init__(self) -> None:
        self.durations = np.asarray(self.durations, dtype=np.float64).reshape(-1)
        self.coeffs = np.asarray(self.coeffs, dtype=np.float64)
        if not (len(self.durations) and np.all(self.durations > 0) and np.all(np.isfinite(self.durations))):
            raise ValueError(f"segment durations must be finite and > 0 seconds, got {self.durations.tolist()}")
        if self.coeffs.shape[:2] != (len(self.durations), 3):
            raise ValueError(f"coeffs must have shape (M={len(self.durations)}, 3, n), got {self.coeffs.shape}")
        self.knots = self.t0 + np.concatenate([[0.0], np.cumsum(self.durations)])

    @property
    def t_end(self) -> float:
        return float(self.knots[-1])

    @property
    def degree(self) -> int:
        return self.coeffs.shape[-1] - 1

    def derivative(self, t: np.ndarray, order: int) -> np.ndarray:
        """``order``-th time derivative at episode times ``t`` (N,) → (N, 3). Before ``t0`` the
        start is held; after the end the end position is held and derivatives are zero."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        after = t >= self.t_end
        seg = np.clip(np.searchsorted(self.knots, t, side="right") - 1, 0, len(self.durations) - 1)
        T = self.durations[seg]
        s = np.clip((t - self.knots[seg]) / T, 0.0, 1.0)
        s = np.where(after, 1.0, s)
        n = self.coeffs.shape[-1]
        k = np.arange(n, dtype=np.float64)
        basis = _falling(k, order)[None, :] * s[:, None] ** np.maximum(k - order, 0)[None, :]  # (N, n)
        val = np.einsum("nak,nk->na", self.coeffs[seg], basis) / T[:, None] ** order
        if order:
            val = np.where(after[:, None], 0.0, val)
        return val

    def state(self, t: float) -> np.ndarray:
        """(4, 3) position, velocity, acceleration, jerk at ``t`` (from the segment that starts at a knot)."""
        return np.stack([self.derivative(np.array([t]), q)[0] for q in range(4)])

    def limits_at_knots(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Interior knots and the end: (times (J,), state just before (J, 4, 3), just after (J, 4, 3))."""
        n = self.coeffs.shape[-1]
        k = np.arange(n, dtype=np.float64)
        M = len(self.durations)
        before = np.empty((M, 4, 3))
        after = np.empty((M, 4, 3))
        for q in range(4):
            w1 = _falling(k, q)  # s = 1
            before[:, q] = np.einsum("mak,k->ma", self.coeffs, w1) / self.durations[:, None] ** q
            w0 = np.zeros(n)
            if q < n:
                w0[q] = factorial(q)  # s = 0
            after[:-1, q] = np.einsum("mak,k->ma", self.coeffs[1:], w0) / self.durations[1:, None] ** q
        after[-1] = 0.0
        after[-1, 0] = before[-1, 0]
        return self.knots[1:], before, after

    def splice(self, other: Pieces, t_from: float) -> Pieces:
        """This reference from ``t_from`` until ``other.t0`` (holding its end if it ended), then ``other``."""
        t_switch = other.t0
        n = max(self.coeffs.shape[-1], other.coeffs.shape[-1])

        def pad(c: np.ndarray) -> np.ndarray:
            """Coefficients ``c`` padded with zero high orders to ``n``."""
            return np.concatenate([c, np.zeros((*c.shape[:2], n - c.shape[-1]))], axis=-1)

        durations, coeffs = [], []
        a = min(t_from, t_switch)
        for i, T in enumerate(self.durations):
            lo, hi = max(a, self.knots[i]), min(t_switch, self.knots[i + 1])
            if hi - lo <= 1e-12:
                continue
            durations.append(hi - lo)
            coeffs.append(_reparametrise(pad(self.coeffs[i:i + 1])[0], (lo - self.knots[i]) / T, (hi - self.knots[i]) / T))
        held_from = max(a, self.t_end)
        if t_switch - held_from > 1e-12:
            c = np.zeros((3, n))
            c[:, 0] = self.derivative(np.array([self.t_end]), 0)[0]
            durations.append(t_switch - held_from)
            coeffs.append(c)
        if not durations:
            return other
        return Pieces(t0=a, durations=np.concatenate([durations, other.durations]),
                      coeffs=np.concatenate([np.stack(coeffs), pad(other.coeffs)]))

    def snap_effort(self, ta: float, tb: float) -> float:
        """Exact ``∫_ta^tb ‖d⁴p/dt⁴‖² dt`` (m²/s⁷) for segments of degree <= 7 (Gauss–Legendre)."""
        if self.degree < 4 or tb <= ta:
            return 0.0
        total = 0.0
        for i, _ in enumerate(self.durations):
            a, b = max(ta, self.knots[i]), min(tb, self.knots[i + 1])
            if b <= a:
                continue
            t = a + (b - a) * _GL_X
            snap = self.derivative(np.minimum(t, np.nextafter(self.knots[i + 1], -np.inf)), 4)
            total += (b - a) * float((_GL_W * (snap ** 2).sum(-1)).sum())
        return total


def _reparametrise(coeffs: np.ndarray, s0: float, s1: float) -> np.ndarray:
    """(3, n) coefficients of the same polynomial on s in [s0, s1], renormalised to u in [0, 1]."""
    n = coeffs.shape[-1]
    h = s1 - s0
    out = np.zeros_like(coeffs)
    # (s0 + h u)^k = sum_j C(k, j) s0^(k−j) h^j u^j
    for k in range(n):
        for j in range(k + 1):
            out[:, j] += coeffs[:, k] * comb(k, j) * s0 ** (k - j) * h ** j
    return out


def pieces_from_body(coeffs_body: np.ndarray, durations: np.ndarray, T_world_body: np.ndarray, t0: float) -> Pieces:
    """Body-frame segments (M, 3, n) → world-frame :class:`Pieces` starting at episode time ``t0``."""
    R, p = T_world_body[:3, :3], T_world_body[:3, 3]
    c = np.einsum("ij,mjk->mik", R, np.asarray(coeffs_body, dtype=np.float64))
    c[:, :, 0] += p[None, :]
    return Pieces(t0=float(t0), durations=np.asarray(durations, dtype=np.float64), coeffs=c)


def hold(position: np.ndarray, t0: float, duration: float = 1.0) -> Pieces:
    """A reference that stays at ``position`` (3,)."""
    c = np.zeros((1, 3, 8))
    c[0, :, 0] = position
    return Pieces(t0=float(t0), durations=np.array([duration]), coeffs=c)
