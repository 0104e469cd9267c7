"""Using a trained planner: `Planner.load(run_dir).plan(depth, goal)` and the outputs of `mapkit plan`."""

from mapkit.planning._planner import Planner, PlanningError, PlanResult, write_plan_outputs

__all__ = ["PlanResult", "Planner", "PlanningError", "write_plan_outputs"]
