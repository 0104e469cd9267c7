"""Flying a trained planner: the pilot that every loop uses (`mapkit eval`'s simulated vehicles, your
own simulator or robot).

>>> from mapkit.flight import Pilot, VehicleState
>>> pilot = Pilot.load("pretrained")                     # the shipped model under the full flight stack
>>> step = pilot.step(t, VehicleState(position=p, velocity=v, yaw=yaw), goal_world,
...                   depth, K=K, T_world_body=T_world_body)            # doctest: +SKIP
>>> setpoint = step.reference.sample(t_now)   # position … snap, yaw, yaw rate for your controller  # doctest: +SKIP

Per camera frame :meth:`Pilot.step` returns a :class:`Reference` (world-frame piecewise polynomials,
C³ with the last at the switch) with a status (:data:`Status`); ``docs/flight.md`` says what to pass
and what to do on each status. The flight stack is typed layers (:class:`Execution`); single plans
(:class:`Planner`, ``mapkit plan``, the viewer) are the pilot's single-shot use.
"""

from mapkit.flight._camera import CENTRE_TOLERANCE, FOV_TOLERANCE, check_intrinsics, planning_frame
from mapkit.flight._config import PilotConfig, VehicleState
from mapkit.flight._errors import FlightError
from mapkit.flight._frame import GOAL_FRAMES, FramePlan, GoalFrame, goal_in_body, plan_from_frame
from mapkit.flight._layers import Corridor, Execution, Memory, SpeedProfile, under_stack
from mapkit.flight._learned import JudgeInput, LearnedMethod, PlanInput, open_direction
from mapkit.flight._pieces import Pieces, hold, pieces_from_body
from mapkit.flight._pilot import STATUSES, Pilot, PilotStep, Status, brake
from mapkit.flight._plan import Method, MethodPlan, Observation, level_pose
from mapkit.flight._pretrained import PRETRAINED, pretrained_dir, resolve_model
from mapkit.flight._recorded import RunCamera, recorded_camera
from mapkit.flight._reference import Reference, Setpoint
from mapkit.flight._route import Aim, FlightMap, Progress, RouteConfig
from mapkit.flight._single import SHIFT, WIDEN, Planner, PlanResult, write_plan_outputs

__all__ = [
    "CENTRE_TOLERANCE", "FOV_TOLERANCE", "GOAL_FRAMES", "PRETRAINED", "SHIFT", "STATUSES", "WIDEN",
    "Aim", "Corridor", "Execution", "FlightError", "FlightMap", "FramePlan", "GoalFrame", "JudgeInput", "LearnedMethod",
    "Memory", "Method", "MethodPlan", "Observation", "Pieces", "Pilot", "PilotConfig", "PilotStep", "PlanInput",
    "PlanResult", "Planner", "Progress", "Reference", "RouteConfig", "RunCamera", "Setpoint", "SpeedProfile", "Status",
    "VehicleState",
    "brake", "check_intrinsics", "goal_in_body", "hold", "level_pose", "open_direction", "pieces_from_body",
    "plan_from_frame", "planning_frame", "pretrained_dir", "recorded_camera", "resolve_model", "under_stack",
    "write_plan_outputs",
]
