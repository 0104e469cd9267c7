"""Differentiable minimum-snap trajectory optimisation (MSTO), flight corridors and time allocation.

The lower level of the planner: key-points and segment times in, a dynamically feasible trajectory
out, with exact gradients back to both.

- :func:`min_snap` — piecewise 7th-order polynomials per axis minimising the integral of squared
  snap (plus an optional cubic minimum-yaw-acceleration spline). Without inequalities the optimum
  is an exact dense solve over the free knot derivatives (float64 inside, unit-diagonal scaling);
  with a flight ``corridor`` or ``v_max``/``a_max`` limits it is a QP solved exactly per element
  (DAQP by default), then re-solved in torch from the KKT system of its active set, which gives the
  implicit gradient (no unrolling). Infeasible elements are flagged in ``Trajectory.solved`` and
  never crash the batch.
- :class:`Trajectory` — evaluation, costs and limits.
- :func:`allocate_times` — segment durations: ``uniform``, ``trapezoid``, ``poly5``, ``gradient``
  (Mellinger & Kumar) or ``net`` (:class:`TimeAllocationNet`).

>>> import torch
>>> from mapkit.trajopt import min_snap, allocate_times
>>> wp = torch.tensor([[0.0, 0, 1], [2, 1, 1], [4, 0, 1.5]])
>>> T = allocate_times(wp, method="trapezoid", v_max=2.0, a_max=2.0)
>>> traj = min_snap(wp, T)
>>> traj.snap_cost().shape
torch.Size([])
"""

from mapkit._choices import BoundaryScale
from mapkit.trajopt._errors import TrajoptError
from mapkit.trajopt._minsnap import TrajoptWarning, min_snap
from mapkit.trajopt._qp import DEFAULT_SOLVER, SOLVERS
from mapkit.trajopt._timealloc import (
    ALLOCATION_METHODS,
    TimeAllocationNet,
    TimeAllocationNetConfig,
    allocate_times,
    profile_time,
    snap_cost_of_times,
)
from mapkit.trajopt._trajectory import Trajectory

__all__ = [
    "ALLOCATION_METHODS",
    "BoundaryScale",
    "DEFAULT_SOLVER",
    "SOLVERS",
    "TimeAllocationNet",
    "TimeAllocationNetConfig",
    "Trajectory",
    "TrajoptError",
    "TrajoptWarning",
    "allocate_times",
    "min_snap",
    "profile_time",
    "snap_cost_of_times",
]
