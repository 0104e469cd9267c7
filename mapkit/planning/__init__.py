"""Using a trained planner: `Planner.load(run_dir).plan(depth, goal)` and the outputs of `mapkit plan`;
``Planner.load("pretrained")`` loads the model shipped with mapkit."""

from mapkit.planning._planner import Planner, PlanningError, PlanResult, write_plan_outputs
from mapkit.planning._pretrained import PRETRAINED, pretrained_dir, resolve_model

__all__ = ["PRETRAINED", "PlanResult", "Planner", "PlanningError", "pretrained_dir", "resolve_model", "write_plan_outputs"]
