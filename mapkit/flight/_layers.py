"""The flight stack: the layers the pilot puts around the learned planner, as one typed config
(:class:`Execution`); a layer set to None is off. How each default was chosen: docs/results.md."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from mapkit._choices import CANDIDATE_SHIFTS, FLIGHT_STACKS, FlightStack
from mapkit.flight._route import RouteConfig


@dataclass(frozen=True)
class Corridor:
    """The flight corridor around the key-point segments, and its check against what was seen."""

    width: float | None = 1.0
    """Widest half-width (m) of the corridor: the trajectory may leave the interior key-points by up to
    this (per world axis) instead of passing through them, which absorbs the key-points' jitter from one
    plan to the next (most of a flight's effort). None: through the key-points."""
    check: bool = True
    """Check each corridor trajectory against the depth image it was planned from and halve the width
    (1, ½, ¼, ⅒ of ``width``, then through the key-points) while it has more points in view closer than
    the robot's size to a seen surface (or behind one) than the trajectory through the key-points."""
    check_memory: bool = True
    """With ``check`` and a :class:`Memory`: the check also counts the points of a trajectory's first
    ``Memory.blocked_within`` seconds that come closer than the robot's size to a remembered surface
    (the jamb of a doorway the camera no longer sees)."""
    unchecked_width: float = 0.3
    """Widest half-width (m) of the corridor when it flies without its check (``check`` off, a method
    without the camera, ``--stack none``): the narrower of this and ``width``."""

    def widest(self, checked: bool) -> float | None:
        """The widest half-width a plan may use (None: through the key-points)."""
        if checked or self.width is None:
            return self.width
        return min(self.width, self.unchecked_width)


@dataclass(frozen=True)
class Memory:
    """Surfaces seen in the last seconds of a flight, and what a plan that comes near them does instead."""

    seconds: float = 8.0
    """Seconds of depth images remembered (as world-frame points). A plan that comes near them is
    replaced by a clear candidate, else a plan toward open space, else the vehicle brakes and turns
    toward the side with fewer remembered surfaces within 3 m (:attr:`MethodPlan.turn_side`)."""
    blocked_within: float = 2.0
    """Seconds of each candidate that must keep clear of remembered surfaces for the way ahead to count
    as open (braking from cruise speed takes about 2.7 s)."""
    subgoal_time: float = 1.0
    """Seconds a blocked plan's way out is kept: when nothing leads on toward the goal, the network
    plans toward the most open direction of the depth image (:func:`open_direction`) until it gets
    within a metre of that point or this time passes."""


TURN_MIN_SPEED = 1.0
"""m/s: the slowest cruise speed ``SpeedProfile.turn_accel`` sets (the cruise speed itself when slower)."""


@dataclass(frozen=True)
class SpeedProfile:
    """How fast learned plans fly: the cruise speed (slowed for turns and stops) and the limits."""

    cruise: float | None = 1.2
    """m/s: the cruise speed of the profile that times learned plans (and the speed at which a plan
    passes a local goal beyond the horizon) while the flight makes its way: the oracle's pace. None: the
    model's ``cruise_speed``."""
    search_ratio: float = 1.4
    """Flown path over progress toward the goal above which a flight counts as searching for its way (a
    flight weaving between trees flies 1.05–1.15×); a searching flight flies at the model's own speed."""
    search_margin: float = 1.0
    """Metres of flown path allowed before the ratio counts (turning toward the way at the start)."""
    turn_accel: float | None = 1.5
    """m/s²: each plan's cruise speed (and its speed at a passed goal) is at most √(``turn_accel`` R), R
    the radius of the sharpest turn of its key-points (:func:`mapkit.planner.turn_speed`), and at least
    :data:`TURN_MIN_SPEED`; None: every plan at the cruise speed."""
    stop_decel: float | None = 0.75
    """m/s²: until a flight searches for its way, plans that end at rest (at the goal) slow down to it
    at this rate instead of the model's ``accel`` (None)."""
    v_max: float = 3.0
    """Speed limit of every plan (its norm), m/s. A plan that breaks it is flown slower, or re-solved
    with the limits in its QP; else it is not flown."""
    a_max: float = 4.0
    """Acceleration limit of every plan (its norm), m/s², kept the same way."""


@dataclass(frozen=True)
class Execution:
    """The flight stack, layer by layer: how a replanning method turns its timed key-points into the
    reference it flies (None turns a layer off)."""

    corridor: Corridor = field(default_factory=Corridor)
    """The flight corridor and its check (``Corridor(width=None)``: through the key-points)."""
    memory: Memory | None = field(default_factory=Memory)
    """The depth memory, its ways out and the turn toward open space; None: fly the network's choice."""
    route: RouteConfig | None = field(default_factory=RouteConfig)
    """With ``memory``: while a flight has stalled, the network's goal is a point on a route around every
    surface seen since the flight began (:class:`~mapkit.flight.FlightMap`). None: the local goal."""
    follow: float = 0.75
    """Fraction of the way each interior key-point of a plan moves toward where the reference being
    flown will be when the new plan reaches it (by at most ``corridor.width`` per axis; the start and
    the last key-point stay) before the plan is executed: receding-horizon plans otherwise restart from
    key-points that jitter from one plan to the next, and each correction costs snap. 0: unmoved."""
    speed: SpeedProfile = field(default_factory=SpeedProfile)
    """The speed profile and the limits of learned plans."""
    keep_choice: float | None = 3.0
    """Score margin (the judge's score logits) within which a replan keeps the candidate the last plan
    of the flight chose, while the judge still accepts it (η < 0.5), instead of switching to the
    best-scored one. None: the network's choice every plan."""
    flown_judge: bool = False
    """Gate and choose with the model's flown-path head where it has one (``PlannerConfig.flown_samples``);
    False: with the judge's η. ``under_stack(..., "none")`` turns it on."""
    widen: tuple[float, ...] = ()
    """Factors of widened candidates judged and chosen among with the trained ones
    (:meth:`~mapkit.planner.PlannerNet.widened`; () none): each trained candidate's detour from the straight
    line scaled. Single plans widen by :data:`mapkit.flight.WIDEN`; replanning flights look around instead."""
    shift: tuple[float, ...] = CANDIDATE_SHIFTS
    """Sideways shifts (m, left positive) of the network's candidates that every plan also judges and
    chooses among (:meth:`~mapkit.planner.PlannerNet.shifted`; () none): the trained candidates sit
    near anchors 1.2 m apart, and the memory's search for a clear candidate and the kept choice get
    neighbours a few decimetres to either side (about a third less effort at the same success)."""


def under_stack(execution: Execution, stack: FlightStack) -> Execution:
    """``execution`` as flown under ``stack``: ``full`` keeps every layer; ``none`` (the paper's protocol:
    the network alone) keeps the corridor's widths and the speed profile, turns every other layer and the
    corridor's check off, and gates with the model's flown-path head where it has one."""
    if stack == "full":
        return execution
    if stack == "none":
        return replace(execution, memory=None, route=None, follow=0.0, keep_choice=None, shift=(), widen=(), flown_judge=True,
                       corridor=replace(execution.corridor, check=False, check_memory=False))
    raise ValueError(f"unknown flight stack {stack!r}; use one of {', '.join(FLIGHT_STACKS)}")
