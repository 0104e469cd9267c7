"""The learned planner's network and loss (torch modules and functions on batched tensors): depth
image + goal → key-points + collision probability η → Time Allocation Net → differentiable
minimum-snap trajectory, and the self-supervised loss that trains it.

Flying a trained network (loading a run's model.pt or the shipped one, the pilot, single plans) is
:mod:`mapkit.flight`.

Model (the paper's upper level): :class:`PlannerNet` — a ResNet-18 depth encoder (:class:`ResNet18`,
written here; :func:`load_torchvision_state_dict` loads torchvision's ImageNet weights), a linear goal
embedding concatenated over the feature map, two conv layers and three-layer MLPs predicting K
key-points (as offsets from the straight origin → goal line) and η; :meth:`PlannerNet.trajectory`
turns key-points into a :class:`mapkit.trajopt.Trajectory` through the net's TAN and
:func:`mapkit.trajopt.min_snap`. Everything is in the body frame (FLU, robot at the origin).

Loss: :func:`candidate_loss`, winner-takes-all over the candidates of γ1 U_O (:func:`obstacle_cost` on
the ESDF) + γ2 U_G (:func:`goal_cost`) + γ3 U_S (:func:`smoothness_cost`) + γ4 U_E (η's BCE against
:func:`collision_labels`) + γ5 U_T (:func:`time_cost` against :func:`time_targets`).

>>> import torch
>>> from mapkit.planner import PlannerNet, planner_preset
>>> net = PlannerNet(planner_preset("cpu")).eval()
>>> depth = torch.full((1, 120, 200), 6.0); depth[:, :10] = float("nan")
>>> with torch.inference_mode():
...     p = net.plan(depth, torch.tensor([[8.0, 0.0, 0.0]]), start_velocity=torch.zeros(1, 3))
>>> p.keypoints.shape, p.eta.shape, p.trajectory.num_segments
(torch.Size([1, 5, 3]), torch.Size([1]), 5)
"""

from mapkit.planner._config import PLANNER_PRESETS, PlannerConfig, planner_preset
from mapkit.planner._depthcheck import CameraInput, depth_margins, image_points, point_margins, seen_conflicts
from mapkit.planner._errors import PlannerError
from mapkit.planner._flown import (
    CLEARANCE_CAP,
    FLOWN_FEATURES,
    arclength_points,
    flown_clearance,
    flown_features,
    input_points,
)
from mapkit.planner._loss import (
    LossConfig,
    body_to_world,
    candidate_loss,
    collision_labels,
    escape_cost,
    goal_cost,
    obstacle_cost,
    obstacle_penalty,
    sample_trajectory,
    smoothness_cost,
    time_allocation_loss,
    time_cost,
    time_targets,
)
from mapkit.planner._model import (
    ImageFeatures,
    Plan,
    PlannerNet,
    PlannerOutput,
    preprocess_depth,
)
from mapkit.planner._resnet import ResNet18, load_torchvision_state_dict
from mapkit.planner._timing import Allocation, Timing, plan_timing, total_time, turn_speed

__all__ = [
    "Allocation",
    "CameraInput",
    "depth_margins",
    "image_points",
    "point_margins",
    "arclength_points",
    "flown_clearance",
    "flown_features",
    "input_points",
    "FLOWN_FEATURES",
    "CLEARANCE_CAP",
    "seen_conflicts",
    "PLANNER_PRESETS",
    "ImageFeatures",
    "LossConfig",
    "Plan",
    "PlannerConfig",
    "PlannerError",
    "PlannerNet",
    "PlannerOutput",
    "ResNet18",
    "body_to_world",
    "collision_labels",
    "escape_cost",
    "goal_cost",
    "load_torchvision_state_dict",
    "obstacle_cost",
    "obstacle_penalty",
    "candidate_loss",
    "planner_preset",
    "preprocess_depth",
    "sample_trajectory",
    "smoothness_cost",
    "time_cost",
    "time_allocation_loss",
    "time_targets",
    "total_time",
    "turn_speed",
    "plan_timing",
    "Timing",
]
