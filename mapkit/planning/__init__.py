"""Using a trained planner: `Planner.load(run_dir).plan(depth, goal)` and the outputs of `mapkit plan`;
``Planner.load("pretrained")`` loads the model shipped with mapkit.

Not to be confused with :mod:`mapkit.planner`, which *defines* the network, its configuration and
its training loss on batched tensors. This package wraps one trained network for single frames:
loading a run's model.pt, planning from one depth frame (with its camera calibration when the net
needs it), clipping far goals to the planner's range, and writing the plan's files (`mapkit plan`,
the viewer).
"""

from mapkit.flight._pretrained import PRETRAINED, pretrained_dir, resolve_model
from mapkit.flight._recorded import RunCamera, recorded_camera
from mapkit.planning._frame import GOAL_FRAMES, FramePlan, GoalFrame, goal_in_body, plan_from_frame
from mapkit.planning._planner import SHIFT, WIDEN, Planner, PlanningError, PlanResult, write_plan_outputs

__all__ = ["GOAL_FRAMES", "SHIFT", "WIDEN", "FramePlan", "GoalFrame", "PRETRAINED", "PlanResult", "Planner", "PlanningError",
           "RunCamera", "goal_in_body", "plan_from_frame", "pretrained_dir", "recorded_camera", "resolve_model",
           "write_plan_outputs"]
