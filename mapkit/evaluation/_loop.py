"""The closed loop: render depth from the current pose, plan, fly the plan for a replan interval,
repeat until the goal, a collision or the time limit.

Vehicle model. The executed trajectory is the reference tracked by a linear 4th-order controller
with feed-forward up to snap: per axis the tracking error e = r − x obeys
``e⁽⁴⁾ = −(k3 e⁽³⁾ + k2 ë + k1 ė + k0 e)`` with all four poles at −ω (critically damped). A plan
starts from the vehicle's full state (position … jerk), so a minimum-snap reference (C³ within
itself) is flown exactly and its effort is the reference's exact ∫‖snap‖². A reference with jumps
(a cubic spline's jerk at its knots, a start acceleration that is not the vehicle's) is smoothed by
the tracker, and its snap is then finite and comparable. Written here because no library
simulates this loop; the vehicle's body is level and its yaw follows its velocity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Literal, Protocol

import numpy as np
from scipy.linalg import expm

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
    """m/s of the planners' total-time rule; sets the time limit."""
    tracking_bandwidth: float = 5.0
    """ω, rad/s: all four poles of the tracking error at −ω."""
    respect_eta: bool = True
    """Do not execute plans with collision probability η >= 0.5 (keep flying the previous one;
    when hovering, turn 60° to look elsewhere)."""
    on_reject: Literal["continue", "brake"] = "continue"
    """What the vehicle does with a rejected plan (η >= 0.5) while it still flies: "continue" keeps
    flying the previous plan; "brake" replaces it with one minimum-snap segment to rest straight
    ahead (about 1.5 m/s² on average), then hovers and turns to look elsewhere as above."""
    look_turn_deg: float = 60.0
    """Degrees the vehicle turns when hovering and a plan is rejected."""
    final_approach: float = 1.0
    """Metres: closer to the goal than this, a replanning method's plan is replaced by one
    minimum-snap segment to rest at the goal (key-points spaced a few centimetres apart with
    sub-second segments are a degenerate input for every key-point planner, and their snap would
    dominate the effort of the whole flight). 0 disables it."""


@dataclass
class Observation:
    """What a method gets at a planning instant."""

    t: float
    """Episode time, seconds."""
    T_world_body: np.ndarray
    """(4, 4) level body pose."""
    state_world: np.ndarray
    """(4, 3) position, velocity, acceleration, jerk of the vehicle, world frame."""
    goal_world: np.ndarray
    """(3,) the real goal."""
    local_goal_body: np.ndarray
    """(3,) the goal in the body frame, clipped to the horizon."""
    depth: np.ndarray | None
    """(H, W) metres, NaN invalid, rendered at the body pose (None for methods without a camera)."""
    goal_clipped: bool = False
    """True when the real goal lies beyond the horizon: the plan should not stop at the local goal
    but pass it at cruise speed (a receding-horizon plan that ends at rest brakes every interval)."""


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


class Method(Protocol):
    """A planner under evaluation."""

    name: str
    needs_depth: bool
    replans: bool

    def plan(self, obs: Observation) -> MethodPlan: ...


@dataclass
class Episode:
    """One flight from start to goal."""

    outcome: str
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
    tracker = _Tracker(config.tracking_bandwidth, dt)
    distance = float(np.linalg.norm(goal - start))
    t_limit = max(config.timeout_min, config.timeout_factor * distance / config.cruise_speed)

    x = np.zeros((4, 3))  # vehicle position, velocity, acceleration, jerk
    x[0] = start
    E = np.zeros((4, 3))  # tracking error e = r − x and its derivatives
    ref = hold(start, 0.0)
    jumps = _jumps(ref)
    t = 0.0
    look = 0.0
    plans = rejected = 0
    latencies: list[float] = []
    rows = [np.array([0.0, *start])]
    path_length = 0.0
    effort = 0.0
    min_dist = float(world.signed_distance(start[None])[0])
    outcome, coll_point, coll_time = "timeout", None, None
    if min_dist < config.robot_radius:
        outcome, coll_point, coll_time = "collision", start.tolist(), 0.0
    planned_once = False
    braking = False
    while outcome == "timeout" and t < t_limit - 1e-9:
        if method.replans or not planned_once:
            planned_once = True
            v_h = float(np.hypot(x[1, 0], x[1, 1]))
            to_goal = goal - x[0]
            yaw = math.atan2(x[1, 1], x[1, 0]) if v_h > 0.5 else math.atan2(to_goal[1], to_goal[0]) + look
            T_wb = level_pose(x[0], yaw)
            g_body = T_wb[:3, :3].T @ to_goal
            n = float(np.linalg.norm(g_body))
            local = g_body * min(1.0, config.horizon / n) if n > 0 else g_body
            depth = render(T_wb) if method.needs_depth else None
            obs = Observation(t=t, T_world_body=T_wb, state_world=x.copy(), goal_world=goal,
                              local_goal_body=local, depth=depth, goal_clipped=n > config.horizon)
            if method.replans and float(np.linalg.norm(to_goal)) < config.final_approach:
                mp = _final_approach(obs, config)
            else:
                mp = method.plan(obs)
            plans += 1
            latencies.append(mp.latency_ms)
            if config.respect_eta and mp.eta is not None and mp.eta >= 0.5:
                rejected += 1
                if t >= ref.t_end - 1e-9:
                    look += math.radians(config.look_turn_deg)
                elif config.on_reject == "brake" and not braking:
                    braking = True
                    ref = _brake(obs).pieces
                    jumps = _jumps(ref)
                    E = ref.state(t) - x
                    E[np.abs(E) < _JUMP_TOL] = 0.0
            else:
                braking = False
                ref = mp.pieces
                jumps = _jumps(ref)
                look = 0.0
                E = ref.state(t) - x  # e = r − x: a plan from the vehicle's state gives zero error
                E[np.abs(E) < _JUMP_TOL] = 0.0
        elif t >= ref.t_end and not E.any():
            t = t_limit  # an open-loop method at rest short of the goal never gets there
            break
        # Fly one interval on the control grid.
        tg = t + dt * np.arange(1, steps + 1)
        r = np.stack([ref.derivative(tg, q) for q in range(5)])  # (5, N, 3)
        ev = [(tk, jk) for tk, jk in jumps if t < tk <= tg[-1] + 1e-12]
        if E.any() or ev:
            Es = np.empty((steps, 4, 3))
            cur, tau0 = E, t
            for i, ti in enumerate(tg):
                for tk, jk in ev:
                    if tau0 < tk <= ti:
                        cur = tracker.phi(tk - tau0) @ cur + jk
                        tau0 = tk
                cur = tracker.phi(ti - tau0) @ cur
                tau0 = ti
                Es[i] = cur
            Ek = np.einsum("k,nka->na", tracker.k, Es)  # x⁽⁴⁾ − r⁽⁴⁾
        else:
            Es = None
        pos = r[0] - (Es[:, 0] if Es is not None else 0.0)
        d = world.signed_distance(pos)
        hit = np.flatnonzero(d < config.robot_radius)
        near = np.flatnonzero(np.linalg.norm(pos - goal, axis=1) <= config.goal_radius)
        stop = steps
        if len(hit) and (not len(near) or hit[0] <= near[0]):
            stop = int(hit[0]) + 1
            outcome, coll_point, coll_time = "collision", pos[hit[0]].tolist(), float(tg[hit[0]])
        elif len(near):
            stop = int(near[0]) + 1
            outcome = "success"
        over = np.flatnonzero(tg >= t_limit - 1e-9)
        if outcome == "timeout" and len(over):
            stop = int(over[0]) + 1
        t_end = float(tg[stop - 1])
        effort += ref.snap_effort(t, t_end)
        if Es is not None:
            cross = 2.0 * (r[4][:stop] * Ek[:stop]).sum(-1) + (Ek[:stop] ** 2).sum(-1)
            # The error's snap at t (start of the interval) completes the trapezoid.
            e0 = np.einsum("k,ka->a", tracker.k, E)
            r0 = ref.derivative(np.array([t]), 4)[0]
            f0 = float(2.0 * r0 @ e0 + e0 @ e0)
            effort += float(np.trapezoid(np.concatenate([[f0], cross]), np.concatenate([[t], tg[:stop]])))
        prev = rows[-1][1:]
        seg = np.concatenate([prev[None], pos[:stop]])
        path_length += float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
        min_dist = min(min_dist, float(d[:stop].min()))
        rows.extend(np.column_stack([tg[:stop], pos[:stop]]))
        # Vehicle state at the end of the flown part.
        x = r[:4, stop - 1] - (Es[stop - 1] if Es is not None else 0.0)
        E = Es[stop - 1] if Es is not None else np.zeros((4, 3))
        t = t_end
    return Episode(
        outcome=outcome, time_s=float(min(t, t_limit)), path_length=path_length, control_effort=effort,
        min_distance=min_dist, collision_point=coll_point, collision_time=coll_time, plans=plans,
        rejected_plans=rejected, latencies_ms=latencies, samples=np.array(rows),
    )


def _final_approach(obs: Observation, config: LoopConfig) -> MethodPlan:
    """One minimum-snap segment from the vehicle's state to rest at the goal, at half the current
    speed on average (at least a quarter of the cruise speed)."""
    import time

    import torch

    from mapkit.trajopt import min_snap

    t0 = time.perf_counter()
    R, p = obs.T_world_body[:3, :3], obs.T_world_body[:3, 3]
    goal = R.T @ (obs.goal_world - p)
    speed = max(0.5 * float(np.linalg.norm(obs.state_world[1])), 0.25 * config.cruise_speed)
    T = max(float(np.linalg.norm(goal)) / speed, 0.2)
    wp = torch.from_numpy(np.stack([np.zeros(3), goal]))[None]
    with torch.no_grad():
        traj = min_snap(wp, torch.tensor([[T]], dtype=torch.float64),
                        start=torch.from_numpy(obs.state_world[1:4] @ R)[None])
    from mapkit.evaluation._pieces import pieces_from_body

    return MethodPlan(pieces=pieces_from_body(traj.coeffs[0].numpy(), np.array([T]), obs.T_world_body, obs.t),
                      latency_ms=1e3 * (time.perf_counter() - t0))


def _brake(obs: Observation, deceleration: float = 1.5) -> MethodPlan:
    """One minimum-snap segment from the vehicle's state to rest along its velocity: over
    T = max(0.5, 2 v / a) seconds to v T / 2 metres ahead (the distance of a constant deceleration a)."""
    import torch

    from mapkit.evaluation._pieces import pieces_from_body
    from mapkit.trajopt import min_snap

    R = obs.T_world_body[:3, :3]
    start = obs.state_world[1:4] @ R  # body-frame velocity, acceleration, jerk
    speed = float(np.linalg.norm(start[0]))
    T = max(0.5, 2.0 * speed / deceleration)
    stop = 0.5 * T * start[0]
    wp = torch.from_numpy(np.stack([np.zeros(3), stop]))[None]
    with torch.no_grad():
        traj = min_snap(wp, torch.tensor([[T]], dtype=torch.float64), start=torch.from_numpy(start)[None])
    return MethodPlan(pieces=pieces_from_body(traj.coeffs[0].numpy(), np.array([T]), obs.T_world_body, obs.t),
                      latency_ms=0.0)


def _jumps(ref: Pieces) -> list[tuple[float, np.ndarray]]:
    """Knot times where the reference's position … jerk jump, with the jump (4, 3)."""
    times, before, after = ref.limits_at_knots()
    out = []
    for tk, b, a in zip(times, before, after):
        j = a - b
        j[np.abs(j) < _JUMP_TOL] = 0.0
        if j.any():
            out.append((float(tk), j))
    return out
