"""`mapkit lab compare-timing`: a model's TAN against the gradient-descent split on the same recorded
plans (the paper's Table III, plus the part of each plan a replanning flight flies), free of the
closed loop's noise.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from mapkit.train._timing_tune import PlanInputs, TimingTuneError, _timed, load_plan_inputs

if TYPE_CHECKING:
    from mapkit.planner import PlannerConfig
    from mapkit.trajopt import TimeAllocationNet, Trajectory

WINDOW_SAMPLES = 201
"""Simpson samples over the flown window (odd)."""


@dataclass(frozen=True)
class CostRatios:
    """A cost of the TAN's split against the gradient-descent split's, over the same plans."""

    summed: float
    """Ratio of the summed costs (what an average over many plans sees)."""
    median: float
    """Median of the per-plan ratios."""
    geomean: float
    """Geometric mean of the per-plan ratios (sensitive to a tail of plans the TAN splits badly)."""

    @classmethod
    def of(cls, tan: torch.Tensor, reference: torch.Tensor) -> CostRatios:
        """The ratios of the (P,) costs ``tan`` to the (P,) costs ``reference`` of the same plans."""
        ratio = tan.clamp_min(1e-300) / reference.clamp_min(1e-300)
        return cls(float(tan.sum() / reference.sum()), float(ratio.median()), float(torch.exp(torch.log(ratio).mean())))


@dataclass(frozen=True)
class TimingComparison:
    """What `mapkit lab compare-timing` measured."""

    plans: int
    window: float
    """Seconds of each plan counted as flown (``mapkit eval``'s replanning interval, 0.5 s)."""
    whole: CostRatios
    """The snap of each whole plan (the paper's Table III quantity)."""
    flown: CostRatios
    """The snap of each plan's first ``window`` seconds."""


def flown_snap(trajectory: Trajectory, window: float) -> torch.Tensor:
    """(B,) ∫‖snap‖² dt over the first ``window`` seconds of each trajectory (all of it if shorter)."""
    span = torch.clamp(trajectory.total_time.reshape(-1, 1), max=window)
    t = torch.linspace(0.0, 1.0, WINDOW_SAMPLES, dtype=span.dtype).unsqueeze(0) * span
    snap2 = (trajectory.derivative(t, 4) ** 2).sum(-1)
    weights = torch.ones(WINDOW_SAMPLES, dtype=span.dtype)
    weights[1:-1:2], weights[2:-1:2] = 4.0, 2.0
    return (snap2 * weights).sum(-1) * span[:, 0] / (3 * (WINDOW_SAMPLES - 1))


def allocation_costs(tan: TimeAllocationNet | None, config: PlannerConfig, plans: PlanInputs,
                     window: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(whole-plan snap, snap of the first ``window`` s), each (P,), of the minimum-snap trajectories
    through the plans timed by ``tan`` (None: gradient descent) as the planner times them in flight."""
    from mapkit.trajopt import min_snap

    with torch.no_grad():
        durations, end = _timed(tan, config, plans)
        trajectory = min_snap(plans.waypoints, durations, start=plans.start, end=end)
        return trajectory.snap_cost(), flown_snap(trajectory, window)


def compare_timing(model: str | Path, plans: Sequence[Path], *, window: float = 0.5) -> TimingComparison:
    """The TAN of ``model`` (a run directory or "pretrained") against gradient descent on every plan
    recorded in the eval folders ``plans`` (``EvalConfig.record_plans``)."""
    from mapkit.flight import Planner

    if not (math.isfinite(window) and window > 0):
        raise TimingTuneError(f"--window must be > 0 seconds, got {window}")
    net = Planner.load(model).net
    recorded = load_plan_inputs(plans, num_segments=net.tan.config.num_segments)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small batched solves: one thread is as fast
    try:
        tan = allocation_costs(net.tan, net.config, recorded, window)
        reference = allocation_costs(None, net.config, recorded, window)
    finally:
        torch.set_num_threads(threads)
    return TimingComparison(plans=len(recorded), window=window, whole=CostRatios.of(tan[0], reference[0]),
                            flown=CostRatios.of(tan[1], reference[1]))
