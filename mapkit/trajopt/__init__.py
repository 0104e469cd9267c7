"""Differentiable minimum-snap trajectory optimisation (MSTO), flight corridors and time allocation.

Key-points and segment times in, a dynamically feasible trajectory out, with exact gradients back to
both: :func:`min_snap` (a closed form, or with a ``corridor`` or limits a QP per element differentiated
through its active set's KKT system), :class:`Trajectory` (evaluation, costs, limits) and
:func:`allocate_times` (``uniform``, ``trapezoid``, ``poly5``, ``gradient`` or ``net``).

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
]
