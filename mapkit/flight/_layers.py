"""The flight stack: the layers the pilot puts around the learned planner, as one typed config
(:class:`Execution`) composed of named layers: the flight corridor and its check
(:class:`Corridor`), the depth memory and its ways out (:class:`Memory`), the flight map's routing
(:class:`~mapkit.flight.RouteConfig`), following the reference being flown (``follow``), keeping
the last plan's candidate (``keep_choice``) and the speed profile that times the plans
(:class:`SpeedProfile`). A layer set to None is off. How each default was chosen, with the flights
that chose it: docs/results.md."""

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
    the robot's size to a seen surface (or behind one) than the trajectory through the key-points: a
    wide corridor cuts the corners the key-points went around. Needs the camera."""
    check_memory: bool = True
    """With ``check`` and a :class:`Memory`: the check also counts the points of a trajectory's first
    ``Memory.blocked_within`` seconds that come closer than the robot's size to a remembered surface
    (the jamb of a doorway the camera no longer sees)."""
    unchecked_width: float | None = 0.3
    """Widest half-width (m) of the corridor when it flies without its check (``check`` off, a method
    without the camera, ``--stack none``): the narrower of this and ``width``. Unchecked, a wide
    corridor grazes what the key-points went around (in the forest, trees beside the vehicle that the
    camera no longer sees); narrower, the plan loses the smoothing the corridor buys. None: through
    the key-points."""

    def widest(self, checked: bool) -> float | None:
        """The widest half-width a plan may use: ``width`` when ``checked``, else the narrower of
        ``width`` and ``unchecked_width`` (None: through the key-points)."""
        if checked or self.width is None:
            return self.width
        return None if self.unchecked_width is None else min(self.width, self.unchecked_width)


@dataclass(frozen=True)
class Memory:
    """Surfaces seen in the last seconds of a flight, and what a plan that comes near them does instead."""

    seconds: float = 8.0
    """Seconds of depth images remembered (as world-frame points). A plan whose first ``blocked_within``
    seconds come closer than the robot's size to a remembered surface is replaced by the best-scored
    candidate that keeps clear; when none does, by a plan toward open space (``subgoal_time``); when
    that is blocked too, the vehicle brakes to rest and turns to look elsewhere
    (:attr:`MethodPlan.blocked`), turned by up to 60° when that keeps the brake clear."""
    blocked_within: float = 2.0
    """Seconds of each candidate that must keep clear of remembered surfaces for the way ahead to count
    as open (braking from cruise speed takes about 2.7 s)."""
    subgoal_time: float = 1.0
    """Seconds a blocked plan's way out is kept: when nothing leads on toward the goal, the network
    plans toward the most open direction of the depth image (:func:`open_direction`) until it gets
    within a metre of that point or this time passes."""
    turn_toward_open: bool = True
    """A blocked vehicle that hovers and turns to look elsewhere (:attr:`~mapkit.flight.PilotConfig.look_turn_deg` at a
    time) turns toward the side with fewer remembered surfaces within 3 m
    (:attr:`MethodPlan.turn_side`) instead of always counter-clockwise (which turned it into the
    corner it stood in)."""


TURN_MIN_SPEED = 1.0
"""m/s: the slowest cruise speed ``SpeedProfile.turn_accel`` sets (the cruise speed itself when slower)."""


@dataclass(frozen=True)
class SpeedProfile:
    """How fast learned plans fly: the cruise speed (slowed for turns and for stops; the model's own
    cruise speed once a flight searches for its way) and the speed and acceleration limits."""

    cruise: float | None = 1.2
    """m/s: the cruise speed of the profile that times learned plans (and the speed at which a plan
    passes a local goal beyond the horizon) while the flight makes its way: the oracle's pace. None: the
    model's ``cruise_speed``. The network still reads the velocity scaled by the model's own cruise
    speed. The same path flown in 1/k of the time costs k⁷ the snap. The time limit follows this speed
    (``mapkit.evaluation.LoopConfig.cruise_speed``)."""
    search_ratio: float = 1.4
    """Flown path over progress toward the goal above which a flight counts as searching for its way (a
    flight weaving between trees flies 1.05–1.15×); a searching flight stalls for good unless it hurries."""
    search_margin: float = 1.0
    """Metres of flown path allowed before the ratio counts (turning toward the way at the start)."""
    turn_accel: float | None = 1.5
    """m/s²: each plan's cruise speed (and its speed at a passed goal) is at most √(``turn_accel`` R), R
    the radius of the sharpest turn of its key-points (:func:`mapkit.planner.turn_speed`), and at least
    :data:`TURN_MIN_SPEED`; None: every plan at the cruise speed. A turn's snap grows with the seventh power
    of its speed, and a straight path has none."""
    stop_decel: float | None = 0.75
    """m/s²: until a flight searches for its way, plans that end at rest (at the goal) slow down to it
    at this rate instead of the model's ``accel`` (None)."""
    v_max: float | None = 3.0
    """Speed limit of every plan (its norm), m/s (None: none). A plan that breaks it is flown slower, or
    re-solved with the limits in its QP; one that still breaks it is not flown (the pilot keeps its
    last reference)."""
    a_max: float | None = 4.0
    """Acceleration limit of every plan (its norm), m/s² (None: none), kept the same way."""


@dataclass(frozen=True)
class Execution:
    """How a replanning method turns its timed key-points into the reference it flies: the flight
    stack, layer by layer (None turns a layer off; :func:`~mapkit.flight.under_stack` turns off
    every layer but the corridor and the speed profile)."""

    corridor: Corridor = field(default_factory=Corridor)
    """The flight corridor and its check (``Corridor(width=None)``: through the key-points)."""
    memory: Memory | None = field(default_factory=Memory)
    """The depth memory, its ways out and the turn toward open space; None: fly the network's choice."""
    route: RouteConfig | None = field(default_factory=RouteConfig)
    """With ``memory``: while a flight has not come 0.5 m closer to its goal for ``route.after`` seconds,
    the network's goal is a point on a route around every surface seen since the flight began
    (:class:`~mapkit.flight.FlightMap`, a 3-D grid; unseen space counts as free), as long as that
    route is a detour, and a hovering vehicle faces that point. None: the local goal on the straight line."""
    follow: float = 0.75
    """Fraction of the way each interior key-point of a plan moves toward where the reference being
    flown will be when the new plan reaches it (by at most ``corridor.width`` per axis; the start and
    the last key-point stay) before the plan is executed: receding-horizon plans otherwise restart from
    key-points that jitter from one plan to the next, and each correction costs snap. The memory's other
    candidates are not moved. 0, or no corridor: the network's key-points."""
    speed: SpeedProfile = field(default_factory=SpeedProfile)
    """The speed profile and the limits of learned plans."""
    keep_choice: float | None = 3.0
    """Score margin (the judge's score logits) within which a replan keeps the candidate the last plan
    of the flight chose, while the judge still accepts it (η < 0.5), instead of switching to the
    best-scored one. Candidates that stay apart (left and right detours metres apart) otherwise swap
    from plan to plan and each swap costs snap. None: the network's choice every plan."""
    flown_judge: bool = False
    """Gate and choose with the model's flown-path head where it has one (``PlannerConfig.flown_samples``:
    each candidate's trajectory as flown, judged against the depth image); False: with the judge's η, which
    the rest of the stack was built around. ``under_stack(..., "none")`` turns it on: without the stack the
    head is the network's own answer. With the full stack the head flies no better, at twice the effort
    and several times the latency: it solves the corridor problem of every candidate and its shifted
    copies."""
    widen: tuple[float, ...] = ()
    """Factors of widened candidates judged and chosen among with the trained ones
    (:meth:`~mapkit.planner.PlannerNet.widened`; () none): each trained candidate's detour from the straight
    line scaled. Single plans (:meth:`mapkit.flight.Planner.plan`) widen by
    :data:`mapkit.flight.WIDEN`: with nothing flown before, a box beside the line may need a wider
    detour than training gave the candidates. Replanning flights do not: they hover and look around
    instead (widening there flew fewer office pairs, docs/results.md)."""
    shift: tuple[float, ...] = CANDIDATE_SHIFTS
    """Sideways shifts (m, left positive) of the network's candidates that every plan also judges and
    chooses among (:meth:`~mapkit.planner.PlannerNet.shifted`; () none): the trained candidates sit
    near anchors 1.2 m apart, and the memory's search for a clear candidate and the kept choice get
    neighbours a few decimetres to either side (about a third less effort at the same success).
    ``under_stack(..., "none")`` turns it off."""


def under_stack(execution: Execution, stack: FlightStack) -> Execution:
    """``execution`` as flown under ``stack``: ``full`` keeps every layer as configured; ``none`` keeps
    the corridor's widths and the speed profile and turns off the depth memory (with its ways out and
    the turn toward open space), the corridor's check (so the corridor flies at its
    ``unchecked_width``), the flight map's routing, following the reference, keeping the last
    plan's candidate and the shifted candidates, and gates with the model's flown-path head where it has
    one (the paper's protocol: the network alone, its key-points through a narrow corridor, replanned
    every interval)."""
    if stack == "full":
        return execution
    if stack == "none":
        return replace(execution, memory=None, route=None, follow=0.0, keep_choice=None, shift=(), widen=(), flown_judge=True,
                       corridor=replace(execution.corridor, check=False, check_memory=False))
    raise ValueError(f"unknown flight stack {stack!r}; use one of {', '.join(FLIGHT_STACKS)}")
