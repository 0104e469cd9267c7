"""Closed-loop evaluation of planners in simulated worlds (`mapkit eval`).

Every method flies the same start–goal pairs in worlds generated with a seed the model never saw:
depth is rendered from the vehicle's pose, the method plans, the vehicle flies the plan for a replan
interval, and so on until the goal, a collision (exact distance to the world) or the time limit.

>>> from mapkit.evaluation import EvalConfig, evaluate
>>> evaluate("ws/runs/cpu", "eval_out", EvalConfig(worlds=("office",), pairs=5))  # doctest: +SKIP

Every method flies through the same :class:`~mapkit.flight.Pilot` a user deploys. :func:`run_episode`
flies one pair with any planner (``name``, ``needs_depth``, ``replans``, ``plan(Observation) ->
MethodPlan``) or pilot; :func:`sample_pairs` draws start–goal pairs; :func:`plan_runs` and
:func:`ablation` fly and compare every method under every flight stack. Reading results.json:
:class:`EpisodeRecord`, :func:`compare_effort`, :func:`success_by_detour`.
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
from mapkit.evaluation._loop import Episode, Faults, LoopConfig, run_episode
from mapkit.evaluation._methods import METHODS, OracleMethod, StraightMethod, make_methods
from mapkit.evaluation._pairs import EvalError, Pair, sample_pairs
from mapkit.evaluation._paths import load_paths
from mapkit.evaluation._report import (
    DETOUR_EDGES,
    DetourBin,
    EffortComparison,
    OutcomeCounts,
    compare_effort,
    effort_at_time,
    success_by_detour,
)
from mapkit.evaluation._run import (
    PLANS_FILE,
    WORLD_ORDER,
    CameraSpec,
    EvalConfig,
    EvalResult,
    evaluate,
    judging_loop,
    summarise,
    untrained_copy,
)
from mapkit.evaluation._stack import (
    STACKED_METHODS,
    UNTRAINED_SEEDS,
    Run,
    parse_stacks,
    plan_runs,
    split_label,
)

__all__ = [
    "METHODS", "WORLD_ORDER", "EVAL_FORMAT", "OUTCOMES",
    "EpisodeRecord", "Outcome",
    "CameraSpec", "EvalConfig", "EvalError", "EvalResult", "evaluate", "judging_loop", "summarise",
    "Episode", "Faults", "LoopConfig", "run_episode",
    "OracleMethod", "StraightMethod", "make_methods", "PLANS_FILE",
    "Pair", "sample_pairs", "load_paths",
    "EffortComparison", "compare_effort", "effort_at_time", "DETOUR_EDGES", "DetourBin", "OutcomeCounts",
    "success_by_detour",
    "Ablation", "Interval", "RunSummary", "ablation", "comparison_lines", "paired_ratio", "success_difference",
    "STACKED_METHODS", "UNTRAINED_SEEDS", "Run", "parse_stacks", "plan_runs", "split_label", "untrained_copy",
]
