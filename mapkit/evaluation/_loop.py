"""The closed loop: render depth from the current pose, plan, fly the plan for a replan interval,
repeat until the goal, a collision or the time limit.

Vehicle model. The executed trajectory is the reference tracked by a linear 4th-order controller
with feed-forward up to snap: per axis the tracking error e = r − x obeys
``e⁽⁴⁾ = −(k3 e⁽³⁾ + k2 ë + k1 ė + k0 e)`` with all four poles at −ω (critically damped). A plan
starts from the vehicle's full state (position … jerk), so a minimum-snap reference (C³ within
itself) is flown exactly and its effort is the reference's exact ∫‖snap‖². A reference with jumps
(a cubic spline's jerk at its knots, a start acceleration that is not the vehicle's) is smoothed by
the tracker, and its snap is then finite and comparable. Written here because no library
simulates this loop; the vehicle's body is level and it heads toward where its reference goes
(:attr:`LoopConfig.look_ahead`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from scipy.linalg import expm

from mapkit._choices import OnReject
from mapkit._formats import Outcome
from mapkit.evaluation._pieces import Pieces, hold
from mapkit.sim import World

_JUMP_TOL = 1e-6  # smaller reference jumps (m, m/s, m/s², m/s³) are float noise, not events


@dataclass
class LoopConfig:
    """How an episode is flown and judged."""

    replan_interval: float = 0.5
    """Seconds a plan is flown before the next one (planning uses the latest depth frame)."""
    depth_rate: float = 30.0
    """Hz of the depth camera; the replan interval must be a whole number of frames."""
    control_rate: float = 200.0
    """Hz at which the executed trajectory is sampled for collisions, the goal and the effort."""
    goal_radius: float = 0.5
    """Metres: success when the body centre comes this close to the goal."""
    robot_radius: float = 0.3
    """Metres: collision when the exact distance from the body centre to the world drops below."""
    horizon: float = 6.0
    """Metres: planners that see only the camera get the goal clipped to this distance (a local
    goal along the direction to the real goal); the depth range is 10 m."""
    timeout_factor: float = 4.0
    """Time limit = max(``timeout_min``, factor × straight distance / cruise speed)."""
    timeout_min: float = 20.0
    """Seconds, the smallest time limit."""
    cruise_speed: float = 2.0
    """m/s of the planners' total-time rule; sets the time limit. ``mapkit eval`` sets it to the
    learned model's cruise speed, or to ``--speed`` when given (the pace the flights are asked for)."""
    tracking_bandwidth: float = 5.0
    """ω, rad/s: all four poles of the tracking error at −ω."""
    respect_eta: bool = True
    """Do not execute plans with collision probability η >= 0.5 (keep flying the previous one;
    when hovering, turn 60° to look elsewhere), unless the method overrides the veto
    (:attr:`MethodPlan.overrides_eta`: its own check found the previous reference no safer)."""
    on_reject: OnReject = "continue"
    """What the vehicle does with a rejected plan (η >= 0.5) while it still flies: "continue" keeps
    flying the previous plan; "brake" replaces it with one minimum-snap segment to rest straight
    ahead (about 1.5 m/s² on average), then hovers and turns to look elsewhere as above."""
    brake_deceleration: float = 3.0
    """m/s², about the peak deceleration of a brake to rest (a rejected plan with ``on_reject="brake"``,
    or a method that finds no way ahead): it stops v² / this metres ahead. Learned planner, office and
    garage, seeds 7 / 13 (120 pairs each): 1.5 → 80.8 / 75.0 %, 3 → 82.5 / 85.0 %, 4 → 81.7 / 85.0 %."""
    look_ahead: float = 1.5
    """Seconds: while moving, the vehicle (and its camera) heads toward where the reference will be this
    much later instead of along its velocity, as a pilot looks into a turn: a vehicle turning through a
    doorway sees the wall beside it before it gets there. 0: along the velocity. Learned planner,
    office on dev seeds 7 / 13 (60 pairs each): 0 → 71.7 / 75.0 %, 0.5 → 71.7 % (seed 7), 1.0 → 80.0 / 85.0 %,
    1.5 → 83.3 / 85.0 %, 2.0 → 80.0 % (seed 7); garage / forest at 1.5: 93.3 / 100 and 96.7 / 98.3 %
    (0: 96.7 / 98.3 and 98.3 / 98.3 %)."""
    look_turn_deg: float = 60.0
    """Degrees the vehicle turns when hovering and a plan is rejected. Learned planner, office on dev
    seeds 7 / 13 / 31 / 37 (60 pairs each, 2026-11-30): 30° 90.0 / 88.3 / 78.3 / 61.7 %, 60° 90.0 / 85.0
    / 80.0 / 63.3 %, 90° 88.3 / 88.3 / 81.7 / 61.7 %. With ``Memory.turn_toward_open`` (same seeds, same
    day): 60° 90.0 / 88.3 / 83.3 / 65.0 %, 90° 91.7 / 88.3 / 85.0 / 66.7 % (199 against 196 of 240
    flights), but on held-out seeds 11 / 17 / 19 / 23 / 29 / 41 / 43 (all worlds) 90° reached 93.2 % on
    average against 93.7 % (office 76.7 / 83.3 / 93.3 / 78.3 / 61.7 / 85.0 / 88.3 % against 81.7 / 83.3 /
    93.3 / 78.3 / 70.0 / 85.0 / 90.0 %): 60° stays."""
    plan_latency: float = 0.02
    """Seconds from the depth frame to the new plan taking over (rounded up to control steps; the
    measured planning latency is about 9 ms): the vehicle flies the previous reference meanwhile,
    and the plan starts from that reference's position … jerk at the takeover, so the flown
    reference stays C³ across every replan."""
    final_approach: float = 0.0
    """Metres: closer to the goal than this, a replanning method's plan is replaced by one
    minimum-snap segment to rest at the goal. 0 (the default) disables it: with every segment at
    least ``min_segment_time`` long and the corridor, the planner's own plans to rest cost less (it
    was needed while key-points crowded into a metre were pinned at sub-second intervals)."""


@dataclass
class Observation:
    """What a method gets at a planning instant."""

    t: float
    """Episode time the plan takes over (the depth frame is ``plan_latency`` older), seconds."""
    T_world_body: np.ndarray
    """(4, 4) level body pose at the depth frame: the frame the network plans in."""
    state_world: np.ndarray
    """(4, 3) position, velocity, acceleration, jerk the plan starts from at ``t`` (the reference's),
    world frame."""
    goal_world: np.ndarray
    """(3,) the real goal."""
    local_goal_body: np.ndarray
    """(3,) the goal in the body frame, clipped to the horizon."""
    depth: np.ndarray | None
    """(H, W) metres, NaN invalid, rendered at the body pose (None for methods without a camera)."""
    goal_clipped: bool = False
    """True when the real goal lies beyond the horizon: the plan should not stop at the local goal
    but pass it at cruise speed (a receding-horizon plan that ends at rest brakes every interval)."""
    reference: Pieces | None = None
    """The reference being flown (what a rejected plan leaves the vehicle on)."""

    def start_body(self) -> np.ndarray:
        """(4, 3) the start state in the body frame of the depth frame (position a few centimetres
        ahead of the origin when the vehicle moves during the planning latency)."""
        R, p = self.T_world_body[:3, :3], self.T_world_body[:3, 3]
        out = self.state_world @ R
        out[0] = R.T @ (self.state_world[0] - p)
        return out


@dataclass
class MethodPlan:
    """A method's answer."""

    pieces: Pieces
    """World-frame reference starting at the observation's time."""
    latency_ms: float
    """Wall-clock planning time (observation → trajectory)."""
    eta: float | None = None
    """Predicted collision probability, for methods that have one."""
    keypoints_world: np.ndarray | None = None
    """(K, 3) the key-points the trajectory passes, world frame (for plots)."""
    allocation_ms: float | None = None
    """Wall-clock time of the time allocation alone (TAN vs gradient descent)."""
    overrides_eta: bool = False
    """The method asks to fly this plan although η >= 0.5: its own check found the reference being
    flown no safer (a rejected plan leaves the vehicle on it)."""
    brake_direction: np.ndarray | None = None
    """(3,) unit vector, body frame at the observation: where a blocked method brakes to (None: along
    the velocity)."""
    turn_side: float | None = None
    """+1 (counter-clockwise) or −1: the way a blocked vehicle that hovers should turn to look
    elsewhere, read when it starts turning (None: the way it turned last, at first counter-clockwise)."""
    look_at: np.ndarray | None = None
    """(3,) world point a hovering vehicle faces at the next observation (None: the goal)."""
    blocked: bool = False
    """The method found no way ahead it can fly (every path it could take runs into what the camera
    sees): the loop brakes to rest and then turns to look elsewhere, whatever η says."""


class Method(Protocol):
    """A planner under evaluation."""

    name: str
    needs_depth: bool
    replans: bool

    def plan(self, obs: Observation) -> MethodPlan: ...


@dataclass
class Episode:
    """One flight from start to goal."""

    outcome: Outcome
    """``success``, ``collision`` or ``timeout``."""
    time_s: float
    """Episode time at the end."""
    path_length: float
    """Metres flown."""
    control_effort: float
    """∫‖snap‖² dt of the executed trajectory, m²/s⁷."""
    min_distance: float
    """Smallest exact distance from the body centre to the world along the flight, metres."""
    collision_point: list[float] | None
    """World point of the first sample closer than the robot radius."""
    collision_time: float | None
    plans: int
    """Plans made."""
    rejected_plans: int
    """Plans not executed because η >= 0.5."""
    latencies_ms: list[float] = field(default_factory=list)
    allocation_ms: list[float] = field(default_factory=list)
    """Time allocation latency of each plan, when the method reports it."""
    plan_effort: float | None = None
    """Mean over executed plans of each plan's whole ∫‖snap‖² dt (the paper's per-plan effort), m²/s⁷;
    None for references of degree < 4 (a cubic spline's snap is impulsive at its knots)."""
    peak_speed: float = 0.0
    """Largest speed of the flown vehicle, m/s."""
    peak_acceleration: float = 0.0
    """Largest acceleration norm, m/s²."""
    peak_jerk: float = 0.0
    """Largest jerk norm, m/s³."""
    samples: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    """(N, 4) rows [t, x, y, z] of the executed path at ``control_rate``."""


def level_pose(position: np.ndarray, yaw: float) -> np.ndarray:
    """(4, 4) T_world_body of a level body at ``position`` heading ``yaw`` (radians from +x)."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = position
    return T


class _Tracker:
    """Exact propagation of the 4th-order tracking error (same dynamics on every axis)."""

    def __init__(self, omega: float, dt: float) -> None:
        w = float(omega)
        self.k = np.array([w ** 4, 4 * w ** 3, 6 * w ** 2, 4 * w])  # (s + ω)⁴ = s⁴ + k3 s³ + k2 s² + k1 s + k0
        A = np.zeros((4, 4))
        A[0, 1] = A[1, 2] = A[2, 3] = 1.0
        A[3] = -self.k
        self.A = A
        self.dt = dt
        self.phi_dt = expm(A * dt)

    def phi(self, tau: float) -> np.ndarray:
        return self.phi_dt if abs(tau - self.dt) < 1e-12 else expm(self.A * tau)


@dataclass
class _Flight:
    """What changes while an episode is flown."""

    x: np.ndarray
    """(4, 3) vehicle position … jerk."""
    E: np.ndarray
    """(4, 3) tracking error e = r − x and its derivatives."""
    ref: Pieces
    jumps: list[tuple[float, np.ndarray]]
    t: float = 0.0
    look: float = 0.0
    braking: bool = False
    turn: float = 1.0
    """+1 or −1: the way the hovering vehicle turns (:attr:`MethodPlan.turn_side`)."""
    look_at: np.ndarray | None = None
    """Where the hovering vehicle faces (:attr:`MethodPlan.look_at`); None: the goal."""
    plans: int = 0
    rejected: int = 0
    latencies: list[float] = field(default_factory=list)
    allocations: list[float] = field(default_factory=list)
    plan_efforts: list[float] = field(default_factory=list)
    rows: list[np.ndarray] = field(default_factory=list)
    path_length: float = 0.0
    effort: float = 0.0
    min_dist: float = math.inf
    peaks: np.ndarray = field(default_factory=lambda: np.zeros(3))
    outcome: Outcome = "timeout"
    coll_point: list[float] | None = None
    coll_time: float | None = None

    def take(self, plan: Pieces) -> None:
        """Fly ``plan`` from its start (the reference until then)."""
        self.ref = self.ref.splice(plan, self.t)
        self.jumps = _jumps(self.ref)
        # e = r − x: zero for a plan from the reference's state; a plan that starts now somewhere
        # else (a scripted reference) is a jump the tracker absorbs.
        self.E = self.ref.state(self.t) - self.x
        self.E[np.abs(self.E) < _JUMP_TOL] = 0.0


def run_episode(
    world: World,
    start: np.ndarray,
    goal: np.ndarray,
    method: Method,
    config: LoopConfig,
    *,
    render: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Episode:
    """Fly ``method`` from ``start`` to ``goal`` in ``world``.

    Args:
        world: exact ground truth (collisions use its signed distance).
        start, goal: (3,) world points.
        method: the planner.
        config: loop settings.
        render: T_world_body (4, 4) → depth (H, W); needed when ``method.needs_depth``.
    """
    start = np.asarray(start, dtype=np.float64).reshape(3)
    goal = np.asarray(goal, dtype=np.float64).reshape(3)
    frames = config.replan_interval * config.depth_rate
    if abs(frames - round(frames)) > 1e-6 or frames < 1:
        raise ValueError(f"replan_interval {config.replan_interval} s is not a whole number of depth frames "
                         f"at {config.depth_rate} Hz")
    dt = 1.0 / config.control_rate
    steps = int(round(config.replan_interval / dt))
    lag = dt * math.ceil(config.plan_latency / dt - 1e-9)
    if not 0 <= lag < config.replan_interval:
        raise ValueError(f"plan_latency {config.plan_latency} s must be in [0, replan_interval)")
    tracker = _Tracker(config.tracking_bandwidth, dt)
    t_limit = max(config.timeout_min, config.timeout_factor * float(np.linalg.norm(goal - start)) / config.cruise_speed)
    x = np.zeros((4, 3))
    x[0] = start
    ref = hold(start, 0.0)
    f = _Flight(x=x, E=np.zeros((4, 3)), ref=ref, jumps=_jumps(ref), rows=[np.array([0.0, *start])],
                min_dist=float(world.signed_distance(start[None])[0]))
    if f.min_dist < config.robot_radius:
        f.outcome, f.coll_point, f.coll_time = "collision", start.tolist(), 0.0
    planned_once = False
    while f.outcome == "timeout" and f.t < t_limit - 1e-9:
        if method.replans or not planned_once:
            planned_once = True
            _replan(f, world, goal, method, config, render, lag if method.replans else 0.0)
        elif f.t >= f.ref.t_end and not f.E.any():
            f.t = t_limit  # an open-loop method at rest short of the goal never gets there
            break
        _fly(f, world, goal, config, tracker, steps, t_limit)
    executed = f.plans - f.rejected
    return Episode(
        outcome=f.outcome, time_s=float(min(f.t, t_limit)), path_length=f.path_length, control_effort=f.effort,
        min_distance=f.min_dist, collision_point=f.coll_point, collision_time=f.coll_time, plans=f.plans,
        rejected_plans=f.rejected, latencies_ms=f.latencies, allocation_ms=f.allocations,
        plan_effort=float(np.mean(f.plan_efforts)) if executed and f.plan_efforts else None,
        peak_speed=float(f.peaks[0]), peak_acceleration=float(f.peaks[1]), peak_jerk=float(f.peaks[2]),
        samples=np.array(f.rows),
    )


def _replan(f: _Flight, world: World, goal: np.ndarray, method: Method, config: LoopConfig,
            render: Callable[[np.ndarray], np.ndarray] | None, lag: float) -> None:
    """Observe at ``f.t``, plan from the reference's state at ``f.t + lag``, and take the plan (or
    react to its rejection)."""
    v_h = float(np.hypot(f.x[1, 0], f.x[1, 1]))
    to_goal = goal - f.x[0]
    heading = f.x[1]
    if config.look_ahead > 0:
        ahead = f.ref.derivative(np.array([min(f.t + config.look_ahead, f.ref.t_end)]), 0)[0] - f.x[0]
        heading = ahead if math.hypot(ahead[0], ahead[1]) > 0.3 else heading
    facing = to_goal if f.look_at is None else f.look_at - f.x[0]
    yaw = math.atan2(heading[1], heading[0]) if v_h > 0.5 else math.atan2(facing[1], facing[0]) + f.look
    T_wb = level_pose(f.x[0], yaw)
    g_body = T_wb[:3, :3].T @ to_goal
    n = float(np.linalg.norm(g_body))
    local = g_body * min(1.0, config.horizon / n) if n > 0 else g_body
    depth = None
    if method.needs_depth:
        assert render is not None  # given whenever the method needs depth
        depth = render(T_wb)
    t_take = f.t + lag
    obs = Observation(t=t_take, T_world_body=T_wb, state_world=f.ref.state(t_take), goal_world=goal,
                      local_goal_body=local, depth=depth, goal_clipped=n > config.horizon, reference=f.ref)
    if method.replans and float(np.linalg.norm(to_goal)) < config.final_approach:
        mp = _final_approach(obs, config)
    else:
        mp = method.plan(obs)
    f.look_at = mp.look_at
    f.plans += 1
    f.latencies.append(mp.latency_ms)
    if mp.allocation_ms is not None:
        f.allocations.append(mp.allocation_ms)
    vetoed = config.respect_eta and mp.eta is not None and mp.eta >= 0.5 and not mp.overrides_eta
    if vetoed or mp.blocked:
        f.rejected += 1
        if f.t >= f.ref.t_end - 1e-9:
            if f.look == 0.0 and mp.turn_side:  # a new look around, the way the method asks
                f.turn = float(np.sign(mp.turn_side))
            f.look += f.turn * math.radians(config.look_turn_deg)
        elif (mp.blocked or config.on_reject == "brake") and not f.braking:
            f.braking = True
            f.take(_brake(obs, config.brake_deceleration, mp.brake_direction).pieces)
        return
    f.braking = False
    f.look = 0.0
    if mp.pieces.degree >= 4:  # a cubic spline's snap is zero between knots and impulsive at them
        f.plan_efforts.append(mp.pieces.snap_effort(mp.pieces.t0, mp.pieces.t_end))
    f.take(mp.pieces)


def _fly(f: _Flight, world: World, goal: np.ndarray, config: LoopConfig, tracker: _Tracker, steps: int,
         t_limit: float) -> None:
    """Fly one replanning interval on the control grid: track the reference, judge collisions and
    the goal, add up effort, path length and the peaks of speed, acceleration and jerk."""
    t, dt = f.t, tracker.dt
    tg = t + dt * np.arange(1, steps + 1)
    r = np.stack([f.ref.derivative(tg, q) for q in range(5)])  # (5, N, 3)
    ev = [(tk, jk) for tk, jk in f.jumps if t < tk <= tg[-1] + 1e-12]
    Es = None
    if f.E.any() or ev:
        Es = np.empty((steps, 4, 3))
        cur, tau0 = f.E, t
        for i, ti in enumerate(tg):
            for tk, jk in ev:
                if tau0 < tk <= ti:
                    cur = tracker.phi(tk - tau0) @ cur + jk
                    tau0 = tk
            cur = tracker.phi(ti - tau0) @ cur
            tau0 = ti
            Es[i] = cur
    states = r[:4].transpose(1, 0, 2) - (Es if Es is not None else 0.0)  # (N, 4, 3) vehicle
    pos = states[:, 0]
    d = world.signed_distance(pos)
    hit = np.flatnonzero(d < config.robot_radius)
    near = np.flatnonzero(np.linalg.norm(pos - goal, axis=1) <= config.goal_radius)
    stop = steps
    if len(hit) and (not len(near) or hit[0] <= near[0]):
        stop = int(hit[0]) + 1
        f.outcome, f.coll_point, f.coll_time = "collision", pos[hit[0]].tolist(), float(tg[hit[0]])
    elif len(near):
        stop = int(near[0]) + 1
        f.outcome = "success"
    over = np.flatnonzero(tg >= t_limit - 1e-9)
    if f.outcome == "timeout" and len(over):
        stop = int(over[0]) + 1
    t_end = float(tg[stop - 1])
    f.effort += f.ref.snap_effort(t, t_end)
    if Es is not None:
        Ek = np.einsum("k,nka->na", tracker.k, Es)  # x⁽⁴⁾ − r⁽⁴⁾
        cross = 2.0 * (r[4][:stop] * Ek[:stop]).sum(-1) + (Ek[:stop] ** 2).sum(-1)
        # The error's snap at t (start of the interval) completes the trapezoid.
        e0 = np.einsum("k,ka->a", tracker.k, f.E)
        r0 = f.ref.derivative(np.array([t]), 4)[0]
        f0 = float(2.0 * r0 @ e0 + e0 @ e0)
        f.effort += float(np.trapezoid(np.concatenate([[f0], cross]), np.concatenate([[t], tg[:stop]])))
    seg = np.concatenate([f.rows[-1][1:][None], pos[:stop]])
    f.path_length += float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
    f.min_dist = min(f.min_dist, float(d[:stop].min()))
    f.peaks = np.maximum(f.peaks, np.linalg.norm(states[:stop, 1:4], axis=-1).max(axis=0))
    f.rows.extend(np.column_stack([tg[:stop], pos[:stop]]))
    f.x = states[stop - 1]
    f.E = Es[stop - 1] if Es is not None else np.zeros((4, 3))
    f.t = t_end


def _final_approach(obs: Observation, config: LoopConfig) -> MethodPlan:
    """One minimum-snap segment from the vehicle's state to rest at the goal, at half the current
    speed on average (at least a quarter of the cruise speed)."""
    import time

    import torch

    from mapkit.trajopt import min_snap

    t0 = time.perf_counter()
    R, p = obs.T_world_body[:3, :3], obs.T_world_body[:3, 3]
    goal = R.T @ (obs.goal_world - p)
    start = obs.start_body()
    speed = max(0.5 * float(np.linalg.norm(start[1])), 0.25 * config.cruise_speed)
    T = max(float(np.linalg.norm(goal - start[0])) / speed, 0.2)
    wp = torch.from_numpy(np.stack([start[0], goal]))[None]
    with torch.no_grad():
        traj = min_snap(wp, torch.tensor([[T]], dtype=torch.float64), start=torch.from_numpy(start[1:])[None])
    from mapkit.evaluation._pieces import pieces_from_body

    return MethodPlan(pieces=pieces_from_body(traj.coeffs[0].numpy(), np.array([T]), obs.T_world_body, obs.t),
                      latency_ms=1e3 * (time.perf_counter() - t0))


def _brake(obs: Observation, deceleration: float, direction: np.ndarray | None = None) -> MethodPlan:
    """One minimum-snap segment from the vehicle's state to rest along its velocity: over
    T = max(0.5, 2 v / a) seconds to v T / 2 = v² / a metres ahead (half of ``deceleration`` on average;
    the smooth profile peaks near it)."""
    import torch

    from mapkit.evaluation._pieces import pieces_from_body
    from mapkit.trajopt import min_snap

    state = obs.start_body()
    start = state[1:]  # body-frame velocity, acceleration, jerk
    speed = float(np.linalg.norm(start[0]))
    T = max(0.5, 2.0 * speed / deceleration)
    stop = state[0] + 0.5 * T * (start[0] if direction is None else speed * direction)
    wp = torch.from_numpy(np.stack([state[0], stop]))[None]
    with torch.no_grad():
        traj = min_snap(wp, torch.tensor([[T]], dtype=torch.float64), start=torch.from_numpy(start)[None])
    return MethodPlan(pieces=pieces_from_body(traj.coeffs[0].numpy(), np.array([T]), obs.T_world_body, obs.t),
                      latency_ms=0.0)


def _jumps(ref: Pieces) -> list[tuple[float, np.ndarray]]:
    """Knot times where the reference's position … jerk jump, with the jump (4, 3)."""
    times, before, after = ref.limits_at_knots()
    out = []
    for tk, b, a in zip(times, before, after, strict=True):
        j = a - b
        j[np.abs(j) < _JUMP_TOL] = 0.0
        if j.any():
            out.append((float(tk), j))
    return out
