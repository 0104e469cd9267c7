"""Names shared by the writer and the readers of mapkit's result files, in one light module (no
torch, no open3d) so the evaluation runner, ``mapkit.viz`` and the viewer agree without importing
each other."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal, get_args

EVAL_FORMAT = "mapkit-eval/1"
"""``format`` of a `mapkit eval` folder's results.json and latency.json."""
PLANS_FILE = "plans.npz"
JUDGE_FILE = "judge.npz"
"""``EvalConfig.record_plans``: the learned method's time allocation inputs (``mapkit lab tune-timing``
reads them)."""

Outcome = Literal["success", "collision", "timeout"]
"""How a closed-loop flight ended."""
OUTCOMES: tuple[Outcome, ...] = get_args(Outcome)

EPISODE_KEYS = ("world", "pair", "method", "outcome", "start", "goal")
"""Keys every row of results.json's ``episodes`` has; the measured ones may be missing in files
written by hand or by older versions."""


@dataclass(frozen=True)
class EpisodeRecord:
    """One flight of one method from one start–goal pair: a row of results.json's ``episodes``
    (fields in the file's key order). Measured fields are None only in files that lack them."""

    world: str
    """World kind the flight ran in."""
    pair: int
    """Index of the start–goal pair in that world."""
    method: str
    """Method that planned the flight."""
    outcome: Outcome
    """How the flight ended."""
    start: list[float]
    """(3,) world-frame start, metres."""
    goal: list[float]
    """(3,) world-frame goal, metres."""
    distance: float | None = None
    """Straight-line start–goal distance, metres."""
    line_of_sight: bool | None = None
    """True when the straight segment start→goal touches no obstacle."""
    time_s: float | None = None
    """Flight time at the end, seconds."""
    path_length: float | None = None
    """Metres flown."""
    path_length_ratio: float | None = None
    """``path_length`` / ``distance``."""
    control_effort: float | None = None
    """∫‖snap‖² dt of the executed trajectory, m²/s⁷."""
    min_distance: float | None = None
    """Smallest exact distance from the body centre to the world, metres; None also when no
    obstacle was in reach (JSON has no infinity)."""
    collision_point: list[float] | None = None
    """World point of the first sample closer than the robot radius."""
    collision_time: float | None = None
    """Flight time of that sample, seconds."""
    plans: int | None = None
    """Plans made."""
    rejected_plans: int | None = None
    """Plans not executed because η >= 0.5."""
    plan_effort: float | None = None
    """Mean per-plan ∫‖snap‖² dt, m²/s⁷ (None for references of degree < 4)."""
    peak_speed: float | None = None
    """Largest speed of the flown vehicle, m/s."""
    peak_acceleration: float | None = None
    """Largest acceleration norm, m/s²."""
    peak_jerk: float | None = None
    """Largest jerk norm, m/s³."""
    climb: float | None = None
    """Metres the flight rose above the higher of its start and goal (0 when it never did)."""
    tracking_error_mean: float | None = None
    """Mean distance from the vehicle to its reference over the flight, metres."""
    tracking_error_max: float | None = None
    """Largest distance from the vehicle to its reference, metres."""
    reference_peak_speed: float | None = None
    """Largest speed of the references the pilot handed the vehicle, m/s."""
    reference_peak_acceleration: float | None = None
    """Largest acceleration norm of those references, m/s²."""
    stack: str | None = None
    """The flight stack the method flew under (``full``, ``none``); None for methods no stack changes
    (``straight``, ``oracle``) and in files written before stacks. ``method`` is the run's label:
    ``NAME@STACK`` under a stack other than ``full``."""

    def to_dict(self) -> dict[str, Any]:
        """The results.json row: every field in declaration order (the file's key order)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, row: dict[str, Any]) -> EpisodeRecord:
        """A results.json row; keys this version does not know are ignored, missing measured ones are None.
        Raises KeyError naming a missing one of :data:`EPISODE_KEYS`."""
        missing = [k for k in EPISODE_KEYS if k not in row]
        if missing:
            raise KeyError(missing[0])
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in row.items() if k in names})
