"""Option values shared by the library's config dataclasses and the CLI's ``click.Choice`` lists, in
a module that imports nothing heavy: the CLI builds its options at import time, without torch."""

from __future__ import annotations

from typing import Literal, get_args

PresetName = Literal["cpu", "paper"]
"""Named training configurations (:data:`mapkit.train.PRESETS`)."""
PRESET_NAMES: tuple[PresetName, ...] = get_args(PresetName)

TrainedWeights = Literal["all", "tan", "judge"]
"""Which weights a run trains: all, only the Time Allocation Net, or only the judge (scores and η)."""
TRAINED_WEIGHTS: tuple[TrainedWeights, ...] = get_args(TrainedWeights)


GoalFrame = Literal["body", "world"]
"""The frame a planning goal is given in: the body frame of the frame planned from, or the world frame
(``mapkit plan --goal-frame``, :func:`mapkit.flight.plan_from_frame`)."""
GOAL_FRAMES: tuple[GoalFrame, ...] = get_args(GoalFrame)

TimingObjective = Literal["imitate"]
"""What `mapkit lab tune-timing` fits the Time Allocation Net to (``TimingTuneConfig.objective``)."""
TIMING_OBJECTIVES: tuple[TimingObjective, ...] = get_args(TimingObjective)

BoundaryScale = Literal["limits", "duration"]
"""How a Time Allocation Net makes its boundary inputs unitless
(:attr:`mapkit.trajopt.TimeAllocationNetConfig.boundary_scale`)."""
BOUNDARY_SCALES: tuple[BoundaryScale, ...] = get_args(BoundaryScale)

FlightStack = Literal["full", "none"]
"""The layers around a replanning learned method in `mapkit eval` (``EvalConfig.stacks``): ``full``, every
layer of :class:`mapkit.flight.Execution` as configured (memory, checked corridor, turn toward open
space, routing, follow); ``none``, the paper's protocol: the network's key-points through the corridor,
replanned every interval, nothing else."""
FLIGHT_STACKS: tuple[FlightStack, ...] = get_args(FlightStack)

VehicleKind = Literal["tracker", "rotorpy"]
"""What flies the pilot's references in `mapkit eval` (``EvalConfig.vehicle``): ``tracker``, a linear
4th-order tracker with a level body (exact, fast); ``rotorpy``, rotorpy's quadrotor (rotor dynamics,
drag) under its SE(3) controller, the camera tilting with the airframe."""
VEHICLES: tuple[VehicleKind, ...] = get_args(VehicleKind)

CANDIDATE_SHIFTS: tuple[float, ...] = (-0.6, -0.3, 0.3, 0.6)
"""Metres: the sideways shifts of the extra candidates a plan judges by default, single plans
(:data:`mapkit.flight.SHIFT`) and the full flight stack (``Execution.shift``) alike."""
