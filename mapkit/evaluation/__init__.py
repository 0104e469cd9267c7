"""Closed-loop evaluation of planners in simulated worlds (`mapkit eval`).

Every method flies the same start–goal pairs in worlds generated with a seed the model never saw:
depth is rendered from the vehicle's pose, the method plans, the vehicle flies the plan for a replan
interval, and so on until the goal, a collision (exact distance to the world) or the time limit.

>>> from mapkit.evaluation import EvalConfig, evaluate
>>> evaluate("ws/runs/cpu", "eval_out", EvalConfig(worlds=("office",), pairs=5))  # doctest: +SKIP

Building blocks for other loops: :func:`run_episode` with any object that has ``name``,
``needs_depth``, ``replans`` and ``plan(Observation) -> MethodPlan``; :class:`Pieces` (world-frame
piecewise polynomials with exact snap effort); :func:`sample_pairs`.

Flight stacks and ablations: :func:`under_stack` (``full`` or ``none``), :func:`plan_runs` (every method
under every stack, each a :class:`Run` labelled ``NAME`` or ``NAME@STACK``), :func:`ablation` (every
run's outcomes and learned − untrained / straight-key-points with bootstrap intervals over pairs).

Reading results.json: :class:`EpisodeRecord` (one row of ``episodes``), :data:`Outcome`,
:data:`EVAL_FORMAT`; :func:`compare_effort` (two methods on the pairs both reached, also at equal
flight time: :func:`effort_at_time`); :func:`success_by_detour` (outcomes by how long the oracle's way
round was).
"""

from mapkit._formats import EVAL_FORMAT, OUTCOMES, EpisodeRecord, Outcome
from mapkit.evaluation._ablation import (
    Ablation,
    Interval,
    RunSummary,
    ablation,
    comparison_lines,
    paired_ratio,
    success_difference,
)
from mapkit.evaluation._layers import Corridor, Execution, Memory, SpeedProfile
from mapkit.evaluation._loop import Episode, LoopConfig, MethodPlan, Observation, level_pose, run_episode
from mapkit.evaluation._methods import (
    METHODS,
    LearnedMethod,
    OracleMethod,
    PlanInput,
    StraightMethod,
    make_methods,
)
from mapkit.evaluation._pairs import EvalError, Pair, sample_pairs
from mapkit.evaluation._paths import load_paths
from mapkit.evaluation._pieces import Pieces, hold, pieces_from_body
from mapkit.evaluation._report import (
    DETOUR_EDGES,
    DetourBin,
    EffortComparison,
    OutcomeCounts,
    compare_effort,
    effort_at_time,
    success_by_detour,
)
from mapkit.evaluation._route import Aim, FlightMap, Progress, RouteConfig
from mapkit.evaluation._run import (
    PLANS_FILE,
    WORLD_ORDER,
    CameraSpec,
    EvalConfig,
    EvalResult,
    evaluate,
    summarise,
    untrained_copy,
)
from mapkit.evaluation._stack import (
    STACKED_METHODS,
    UNTRAINED_SEEDS,
    Run,
    parse_stacks,
    parse_untrained_seeds,
    plan_runs,
    split_label,
    under_stack,
)

__all__ = [
    "METHODS", "WORLD_ORDER", "EVAL_FORMAT", "OUTCOMES",
    "EpisodeRecord", "Outcome",
    "CameraSpec", "EvalConfig", "EvalError", "EvalResult", "evaluate", "summarise",
    "Episode", "LoopConfig", "MethodPlan", "Observation", "level_pose", "run_episode",
    "Execution", "Corridor", "Memory", "SpeedProfile", "LearnedMethod", "OracleMethod", "PlanInput", "StraightMethod", "make_methods", "PLANS_FILE",
    "Aim", "FlightMap", "Progress", "RouteConfig",
    "Pair", "sample_pairs", "load_paths",
    "Pieces", "hold", "pieces_from_body",
    "EffortComparison", "compare_effort", "effort_at_time", "DETOUR_EDGES", "DetourBin", "OutcomeCounts",
    "success_by_detour",
    "Ablation", "Interval", "RunSummary", "ablation", "comparison_lines", "paired_ratio", "success_difference",
    "STACKED_METHODS", "UNTRAINED_SEEDS", "Run", "parse_stacks", "parse_untrained_seeds", "plan_runs", "split_label", "under_stack", "untrained_copy",
]
