"""The :class:`Trajectory` returned by :func:`mapkit.trajopt.min_snap`."""

from __future__ import annotations

from typing import Any

import torch

from mapkit.trajopt._basis import cost_matrix
from mapkit.trajopt._errors import TrajoptError


def _falling_row(n: int, q: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    k = torch.arange(n, dtype=dtype, device=device)
    out = torch.ones(n, dtype=dtype, device=device)
    for j in range(q):
        out = out * (k - j)
    return out


def _poly_eval(coeffs: torch.Tensor, s: torch.Tensor, q: int) -> torch.Tensor:
    """q-th s-derivative of ``sum_k coeffs[..., k] s^k``; ``s`` broadcasts against coeffs[..., 0]."""
    n = coeffs.shape[-1]
    fall = _falling_row(n, q, coeffs.dtype, coeffs.device)
    c = coeffs[..., q:] * fall[q:]
    # Horner on the derivative polynomial.
    acc = c[..., -1]
    for k in range(c.shape[-1] - 2, -1, -1):
        acc = acc * s + c[..., k]
    return acc


class Trajectory:
    """A batch of piecewise-polynomial trajectories: segment ``i`` of element ``b`` is, per axis ``a``,
    ``p(t) = sum_k coeffs[b, i, a, k] * s**k`` with ``s = (t - t_i) / durations[b, i]`` in [0, 1].
    All methods are differentiable with respect to ``coeffs`` and ``durations``.

    Attributes:
        coeffs: (B, M, 3, 8) position coefficients, metres.
        durations: (B, M) segment durations, seconds.
        yaw_coeffs: (B, M, 4) yaw coefficients, radians, or None.
        solved: (B,) bool: False where a constrained problem was infeasible or the solver failed;
            such an element holds the fallback solution named in ``messages``.
        messages: one line per failed element (empty when everything solved).
        batched: False when the inputs were unbatched; then every result drops the batch axis.
        info: how the problem was solved: ``path`` ("closed_form" or "qp"), and for the QP path
            ``solver``, ``solver_seconds`` and ``active`` (held constraints per element).
    """

    def __init__(
        self,
        coeffs: torch.Tensor,
        durations: torch.Tensor,
        *,
        yaw_coeffs: torch.Tensor | None = None,
        solved: torch.Tensor | None = None,
        messages: tuple[str, ...] = (),
        batched: bool = True,
        info: dict[str, Any] | None = None,
    ) -> None:
        if coeffs.ndim != 4 or coeffs.shape[2] != 3:
            raise TrajoptError(f"coeffs must have shape (B, M, 3, n), got {tuple(coeffs.shape)}")
        if durations.shape != coeffs.shape[:2]:
            raise TrajoptError(f"durations shape {tuple(durations.shape)} does not match coeffs {tuple(coeffs.shape)}")
        self._coeffs = coeffs
        self._durations = durations
        self._yaw_coeffs = yaw_coeffs
        self._solved = torch.ones(coeffs.shape[0], dtype=torch.bool, device=coeffs.device) if solved is None else solved
        self.messages = tuple(messages)
        self.batched = batched
        self.info = dict(info or {})

    # ------------------------------------------------------------------ basics
    @property
    def coeffs(self) -> torch.Tensor:
        """(B, M, 3, 8) position coefficients (unbatched: (M, 3, 8))."""
        return self._out(self._coeffs)

    @property
    def durations(self) -> torch.Tensor:
        """(B, M) segment durations in seconds (unbatched: (M,))."""
        return self._out(self._durations)

    @property
    def solved(self) -> torch.Tensor:
        """(B,) bool (unbatched: a 0-d bool tensor)."""
        return self._out(self._solved)

    @property
    def batch_size(self) -> int:
        return int(self._coeffs.shape[0])

    @property
    def num_segments(self) -> int:
        return int(self._coeffs.shape[1])

    @property
    def total_time(self) -> torch.Tensor:
        """(B,) seconds."""
        return self._out(self._durations.sum(-1))

    def _out(self, x: torch.Tensor) -> torch.Tensor:
        return x if self.batched else x[0]

    def _times(self, t: torch.Tensor | float) -> torch.Tensor:
        t = torch.as_tensor(t, dtype=self._durations.dtype, device=self._durations.device)
        if t.ndim == 0:
            t = t.reshape(1, 1).expand(self.batch_size, 1)
        elif t.ndim == 1:
            t = t.unsqueeze(0).expand(self.batch_size, -1)
        elif t.ndim != 2 or t.shape[0] != self.batch_size:
            raise TrajoptError(f"t must be a scalar, (K,) or (B={self.batch_size}, K) tensor of seconds, "
                               f"got shape {tuple(t.shape)}")
        return t

    def _locate(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Segment index (B, K) and local normalised time s (B, K), t clamped to [0, total]."""
        T = self._durations
        ends = torch.cumsum(T, dim=-1)
        starts = ends - T
        total = ends[:, -1:]
        tc = torch.minimum(torch.clamp(t, min=0.0), total)
        seg = torch.searchsorted(ends.detach().contiguous(), tc.detach().contiguous(), right=True)
        seg = seg.clamp(max=self.num_segments - 1)
        t0 = torch.gather(starts, 1, seg)
        Ts = torch.gather(T, 1, seg)
        s = (tc - t0) / Ts
        return seg, s

    def _eval(self, coeffs: torch.Tensor, t: torch.Tensor, order: int) -> torch.Tensor:
        seg, s = self._locate(t)
        B, K = seg.shape
        tail = coeffs.shape[2:]
        idx = seg.reshape(B, K, *([1] * len(tail))).expand(B, K, *tail)
        c = torch.gather(coeffs, 1, idx)  # (B, K, ..., n)
        Ts = torch.gather(self._durations, 1, seg)
        s_b = s.reshape(B, K, *([1] * (len(tail) - 1)))
        val = _poly_eval(c, s_b, order)
        if order:
            val = val / Ts.reshape(B, K, *([1] * (len(tail) - 1))) ** order
        return val

    # ------------------------------------------------------------------ evaluation
    def position(self, t: torch.Tensor | float) -> torch.Tensor:
        """Position at times ``t`` (scalar, (K,) or (B, K) seconds from the start) → (B, K, 3)."""
        return self.derivative(t, 0)

    def derivative(self, t: torch.Tensor | float, order: int) -> torch.Tensor:
        """``order``-th time derivative at ``t`` → (B, K, 3) (m/s^order). Times outside
        [0, total] are clamped to the ends."""
        if order < 0 or order >= self._coeffs.shape[-1]:
            raise TrajoptError(f"order must be in [0, {self._coeffs.shape[-1] - 1}], got {order}")
        return self._out(self._eval(self._coeffs, self._times(t), order))

    def yaw(self, t: torch.Tensor | float, order: int = 0) -> torch.Tensor:
        """Yaw (order 0, radians) or its derivatives at ``t`` → (B, K)."""
        if self._yaw_coeffs is None:
            raise TrajoptError("this trajectory has no yaw; pass yaw=... to min_snap")
        if order < 0 or order > 3:
            raise TrajoptError(f"yaw order must be in [0, 3], got {order}")
        return self._out(self._eval(self._yaw_coeffs.unsqueeze(2), self._times(t), order)[..., 0])

    def _dense(self, order: int, samples_per_segment: int) -> torch.Tensor:
        """order-th derivative at a uniform grid in every segment → (B, M, S, 3)."""
        s = torch.linspace(0.0, 1.0, samples_per_segment, dtype=self._coeffs.dtype, device=self._coeffs.device)
        val = _poly_eval(self._coeffs.unsqueeze(2), s.reshape(1, 1, -1, 1), order)  # (B, M, S, 3)
        if order:
            val = val / self._durations.reshape(*self._durations.shape, 1, 1) ** order
        return val

    # ------------------------------------------------------------------ costs and limits
    def snap_cost(self) -> torch.Tensor:
        """(B,) ``sum_axes integral (d^4 p/dt^4)^2 dt`` in m²/s⁷ (no factor 1/2)."""
        Q = torch.as_tensor(cost_matrix(4), dtype=self._coeffs.dtype, device=self._coeffs.device)
        c = self._coeffs
        per = ((c.reshape(-1, c.shape[-1]) @ Q).reshape(c.shape) * c).sum(dim=(-1, -2))
        return self._out((per * self._durations ** (-7)).sum(-1))

    def max_velocity(self, *, per_axis: bool = False, samples_per_segment: int = 64) -> torch.Tensor:
        """Largest speed (B,) — or largest |v| per axis (B, 3) — over a dense per-segment grid, m/s."""
        return self._max_of(1, per_axis, samples_per_segment)

    def max_acceleration(self, *, per_axis: bool = False, samples_per_segment: int = 64) -> torch.Tensor:
        """Largest acceleration norm (B,) — or per axis (B, 3) — over a dense grid, m/s²."""
        return self._max_of(2, per_axis, samples_per_segment)

    def _max_of(self, order: int, per_axis: bool, samples_per_segment: int) -> torch.Tensor:
        if samples_per_segment < 2:
            raise TrajoptError(f"samples_per_segment must be >= 2, got {samples_per_segment}")
        v = self._dense(order, samples_per_segment)
        if per_axis:
            return self._out(v.abs().amax(dim=(1, 2)))
        return self._out(v.norm(dim=-1).amax(dim=(1, 2)))

    def __repr__(self) -> str:
        n_bad = int((~self._solved).sum())
        return (
            f"Trajectory(batch={self.batch_size}, segments={self.num_segments}, "
            f"dtype={self._coeffs.dtype}, yaw={'yes' if self._yaw_coeffs is not None else 'no'}, "
            f"failed={n_bad})"
        )
