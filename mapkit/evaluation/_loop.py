"""The closed loop: render depth from the current pose, give it to the pilot
(:class:`~mapkit.flight.Pilot`), fly its reference for a replan interval, repeat until the goal, a
collision or the time limit.

The default vehicle tracks the reference with a linear 4th-order controller (feed-forward up to snap,
all four poles of the per-axis error e = r − x at −ω), level body, the reference's yaw: a minimum-snap
reference from the vehicle's state is flown exactly, and a reference with jumps is smoothed.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

from mapkit._formats import Outcome
from mapkit.evaluation._pairs import EvalError
from mapkit.evaluation._rotorpy import RotorpyVehicle
from mapkit.flight import Method, Pieces, Pilot, PilotConfig, PilotStep, Reference, VehicleState, hold, level_pose
from mapkit.flight._recorded import RunCamera
from mapkit.geometry import transform_from_pose
from mapkit.sim import World

_JUMP_TOL = 1e-6  # smaller reference jumps (m, m/s, m/s², m/s³) are float noise, not events


@dataclass(frozen=True)
class Faults:
    """Faults injected into the frames the pilot gets (``mapkit eval --faults DROP,DELAY,NOISE``), drawn
    per flight from ``seed`` and the pair (the same for every method)."""

    drop: float = 0.0
    """Fraction of frames lost: the pilot is called without depth (it brakes after its frame timeout)."""
    delay: float = 0.0
    """Seconds by which depth lags: the frame is rendered (and posed) where the body was this long ago."""
    pose_noise: float = 0.0
    """Metres, the standard deviation of noise per axis on the state's position and the frame's pose (one draw for both)."""
    seed: int = 0
    """Seed of the faults' generator."""

    @property
    def any(self) -> bool:
        return bool(self.drop or self.delay or self.pose_noise)


@dataclass
class LoopConfig:
    """How an episode is flown and judged."""

    pilot: PilotConfig = field(default_factory=PilotConfig)
    """How the pilot plans (depth is rendered once per replan interval)."""
    depth_rate: float = 30.0
    """Hz of the depth camera; the replan interval must be a whole number of frames."""
    control_rate: float = 200.0
    """Hz at which the executed trajectory is sampled for collisions, the goal and the effort."""
    goal_radius: float = 0.5
    """Metres: success when the body centre comes this close to the goal."""
    robot_radius: float = 0.3
    """Metres: collision when the exact distance from the body centre to the world drops below."""
    timeout_factor: float = 4.0
    """Time limit = max(``timeout_min``, factor × straight distance / cruise speed)."""
    timeout_min: float = 20.0
    """Seconds, the smallest time limit."""
    cruise_speed: float = 2.0
    """m/s of the time limit; ``mapkit eval`` sets it to ``execution.speed.cruise``, or the model's cruise speed."""
    tracking_bandwidth: float = 5.0
    """ω, rad/s: all four poles of the tracking error at −ω."""
    faults: Faults = field(default_factory=Faults)
    """Faults injected into the frames (none by default)."""

    def time_limit(self, distance: float) -> float:
        """Seconds a flight over a straight ``distance`` (metres) gets before it is a timeout."""
        return max(self.timeout_min, self.timeout_factor * float(distance) / self.cruise_speed)


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
    """Mean over executed plans of each plan's whole ∫‖snap‖² dt (the paper's), m²/s⁷; None below degree 4."""
    peak_speed: float = 0.0
    """Largest speed of the flown vehicle, m/s (acceleration m/s², jerk m/s³ likewise)."""
    peak_acceleration: float = 0.0
    peak_jerk: float = 0.0
    samples: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    """(N, 4) rows [t, x, y, z] of the executed path at ``control_rate``."""
    climb: float = 0.0
    """Metres the flight rose above the higher of its start and goal (0 when it never did)."""
    tracking_error_mean: float = 0.0
    """Mean distance from the vehicle to its reference over the flight, metres (and the largest)."""
    tracking_error_max: float = 0.0
    reference_peak_speed: float = 0.0
    """Largest speed (m/s) and acceleration (m/s²) of the references the pilot handed the vehicle."""
    reference_peak_acceleration: float = 0.0


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
    reference: Reference | None = None
    """The pilot's last reference (its yaw is the vehicle's)."""
    yaw0: float = 0.0
    """The vehicle's yaw before the pilot's first reference: toward the goal."""
    attitudes: tuple[np.ndarray, np.ndarray] | None = None
    """rotorpy: the last interval's sample times and attitudes (xyzw), for a delayed frame's pose."""
    t: float = 0.0
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
    tracking: list[float] = field(default_factory=list)
    """|r − x| at every control step, metres."""
    ref_peaks: np.ndarray = field(default_factory=lambda: np.zeros(2))
    outcome: Outcome = "timeout"
    coll_point: list[float] | None = None
    coll_time: float | None = None

    @property
    def yaw(self) -> float:
        """The vehicle's yaw now: the reference's."""
        return self.yaw0 if self.reference is None else float(self.reference.yaw(self.t)[0])

    def adopt(self, ref: Pieces) -> None:
        """Fly ``ref`` (the pilot's reference, spliced onto the last at the switch)."""
        self.ref = ref
        self.jumps = _jumps(self.ref)
        # e = r − x: zero for a plan from the reference's state, else a jump the tracker absorbs
        self.E = self.ref.state(self.t) - self.x
        self.E[np.abs(self.E) < _JUMP_TOL] = 0.0


def run_episode(
    world: World,
    start: np.ndarray,
    goal: np.ndarray,
    method: Method | Pilot,
    config: LoopConfig,
    *,
    render: Callable[[np.ndarray], np.ndarray] | None = None,
    camera: RunCamera | None = None,
    vehicle: RotorpyVehicle | None = None,
    gimbal: bool = False,
) -> Episode:
    """Fly ``method`` (a planner, flown by a :class:`~mapkit.flight.Pilot` with ``config.pilot``, or a
    pilot) from ``start`` to ``goal`` in ``world``.

    Args:
        world: exact ground truth (collisions use its signed distance).
        start, goal: (3,) world points.
        method: the planner, or the pilot flying one (reset first: every episode is a new flight).
        config: loop settings.
        render: T_world_body (4, 4) → depth (H, W); needed when the planner needs depth.
        camera: the camera ``render`` renders (its K and mount); default: the pilot's.
        vehicle: fly rotorpy's quadrotor (:class:`RotorpyVehicle`) instead of the linear tracker; its camera
            is rendered at the airframe's true attitude (tilting with it) unless ``gimbal``.

    Raises:
        EvalError: the replan interval is not a whole number of depth frames.
    """
    start = np.asarray(start, dtype=np.float64).reshape(3)
    goal = np.asarray(goal, dtype=np.float64).reshape(3)
    pilot = method if isinstance(method, Pilot) else Pilot(method, camera=camera, config=config.pilot)
    pilot.reset()
    interval = pilot.config.replan_interval
    check_interval(interval, config.depth_rate)
    dt = 1.0 / config.control_rate
    steps = int(round(interval / dt))
    tracker = _Tracker(config.tracking_bandwidth, dt)
    t_limit = config.time_limit(float(np.linalg.norm(goal - start)))
    f = _take_off(world, start, goal, config, vehicle)
    mount = camera or pilot.camera
    T_body_camera = None if mount is None else mount.T_body_camera
    faults = config.faults
    rng = np.random.default_rng([faults.seed, zlib.crc32(start.tobytes() + goal.tobytes())])
    while f.outcome == "timeout" and f.t < t_limit - 1e-9:
        if pilot.planner.replans or not f.plans:
            T_wb, state = _pose(f, vehicle, gimbal)
            frame = _faulty_frame(f, faults, rng, T_wb, state, vehicle, gimbal)
            _replan(f, goal, pilot, render, T_body_camera, None if camera is None else camera.K, frame, state)
        elif f.t >= f.ref.t_end and not f.E.any():
            f.t = t_limit  # an open-loop method at rest short of the goal never gets there
            break
        if vehicle is None:
            _fly(f, world, goal, config, tracker, steps, t_limit)
        else:
            _fly_rotorpy(f, world, goal, config, vehicle, min(f.t + interval, t_limit), t_limit)
    return _episode(f, start, goal, t_limit)


def check_interval(interval: float, depth_rate: float) -> None:
    """Raise :class:`EvalError` unless ``interval`` seconds are a whole number of frames at ``depth_rate`` Hz."""
    frames = interval * depth_rate
    if not (math.isfinite(frames) and frames >= 1 - 1e-9 and abs(frames - round(frames)) < 1e-6):
        raise EvalError(f"loop.pilot.replan_interval {interval} s is not a whole number of depth frames at "
                        f"{depth_rate:g} Hz; use a multiple of {1 / depth_rate:.4g} s")


def _take_off(world: World, start: np.ndarray, goal: np.ndarray, config: LoopConfig,
              vehicle: RotorpyVehicle | None) -> _Flight:
    """The flight at rest at ``start``, facing ``goal`` (a collision already when ``start`` is too close to the world)."""
    x = np.zeros((4, 3))
    x[0] = start
    ref = hold(start, 0.0)
    f = _Flight(x=x, E=np.zeros((4, 3)), ref=ref, jumps=_jumps(ref), rows=[np.array([0.0, *start])],
                min_dist=float(world.signed_distance(start[None])[0]),
                yaw0=math.atan2(goal[1] - start[1], goal[0] - start[0]))
    if f.min_dist < config.robot_radius:
        f.outcome, f.coll_point, f.coll_time = "collision", start.tolist(), 0.0
    if vehicle is not None:
        vehicle.reset(start, f.yaw0)
    return f


def _episode(f: _Flight, start: np.ndarray, goal: np.ndarray, t_limit: float) -> Episode:
    """The :class:`Episode` a finished flight adds up to."""
    executed = f.plans - f.rejected
    return Episode(
        outcome=f.outcome, time_s=float(min(f.t, t_limit)), path_length=f.path_length, control_effort=f.effort,
        min_distance=f.min_dist, collision_point=f.coll_point, collision_time=f.coll_time, plans=f.plans,
        rejected_plans=f.rejected, latencies_ms=f.latencies, allocation_ms=f.allocations,
        plan_effort=float(np.mean(f.plan_efforts)) if executed and f.plan_efforts else None,
        peak_speed=float(f.peaks[0]), peak_acceleration=float(f.peaks[1]), peak_jerk=float(f.peaks[2]),
        samples=np.array(f.rows), climb=max(0.0, float(np.max(np.asarray(f.rows)[:, 3])) - max(start[2], goal[2])),
        tracking_error_mean=float(np.mean(f.tracking)) if f.tracking else 0.0,
        tracking_error_max=float(np.max(f.tracking)) if f.tracking else 0.0,
        reference_peak_speed=float(f.ref_peaks[0]), reference_peak_acceleration=float(f.ref_peaks[1]),
    )


def _pose(f: _Flight, vehicle: RotorpyVehicle | None, gimbal: bool) -> tuple[np.ndarray, VehicleState]:
    """The body's pose (the camera's mount) and the vehicle's state now: the tracker's level body with
    the reference's yaw, or the rotorpy airframe at its true attitude (level on a gimbal)."""
    if vehicle is None:
        yaw = f.yaw
        return level_pose(f.x[0], yaw), VehicleState(position=f.x[0], velocity=f.x[1], acceleration=f.x[2], yaw=yaw)
    state = VehicleState(position=vehicle.position, velocity=vehicle.velocity, acceleration=vehicle.acceleration,
                         yaw=vehicle.yaw)
    return (level_pose(vehicle.position, vehicle.yaw) if gimbal else vehicle.T_world_body), state


def _faulty_frame(f: _Flight, faults: Faults, rng: np.random.Generator, T_wb: np.ndarray, state: VehicleState,
                  vehicle: RotorpyVehicle | None, gimbal: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """(where the frame is rendered, the pose the pilot is given) after the faults (``state`` gets the
    same noise); None for a dropped frame."""
    if not faults.any:
        return T_wb, T_wb
    noise = rng.normal(0.0, faults.pose_noise, 3) if faults.pose_noise else np.zeros(3)
    dropped = bool(faults.drop) and rng.random() < faults.drop
    state.position = state.position + noise
    if dropped:
        return None
    seen = _past_pose(f, vehicle, gimbal, f.t - faults.delay) if faults.delay else T_wb
    given = seen.copy()
    given[:3, 3] += noise
    return seen, given


def _past_pose(f: _Flight, vehicle: RotorpyVehicle | None, gimbal: bool, t: float) -> np.ndarray:
    """The body's pose at an earlier time ``t`` (the start before the flight), from the last second of samples."""
    rows = np.asarray(f.rows[-200:])
    position = np.array([np.interp(t, rows[:, 0], rows[:, k]) for k in (1, 2, 3)])
    if vehicle is not None and not gimbal and f.attitudes is not None:
        times, quaternions = f.attitudes
        return transform_from_pose(position, quaternions[int(np.argmin(np.abs(times - t)))])
    if vehicle is not None and f.attitudes is None:  # before the first interval: where it started
        return level_pose(position, vehicle.yaw)
    return level_pose(position, f.yaw0 if f.reference is None else float(f.reference.yaw(max(t, 0.0))[0]))


def _replan(f: _Flight, goal: np.ndarray, pilot: Pilot, render: Callable[[np.ndarray], np.ndarray] | None,
            T_body_camera: np.ndarray | None, K: np.ndarray | None, frame: tuple[np.ndarray, np.ndarray] | None,
            state: VehicleState) -> None:
    """Render the frame where the body was seen, give it to the pilot (none when dropped), fly its answer."""
    depth, T_given = None, None
    if pilot.planner.needs_depth and frame is not None:
        if render is None:
            raise ValueError(f"{getattr(pilot.planner, 'name', 'the planner')} needs depth: pass render=")
        depth, T_given = render(frame[0]), frame[1]
    elif not pilot.planner.needs_depth:
        T_given = _pose(f, None, False)[0] if frame is None else frame[1]
    step = pilot.step(f.t, state, goal, depth, K=K, T_world_body=T_given,
                      T_body_camera=T_body_camera if depth is not None else None)
    _record(f, step)
    f.reference = step.reference
    if step.reference.pieces is not f.ref:
        f.adopt(step.reference.pieces)


def _record(f: _Flight, step: PilotStep) -> None:
    """Count the pilot's plan, its latency, its rejection or its effort, and the reference's peaks."""
    if step.plan is None:
        return
    mp = step.plan
    f.plans += 1
    f.latencies.append(mp.latency_ms)
    if mp.allocation_ms is not None:
        f.allocations.append(mp.allocation_ms)
    if not step.taken:
        f.rejected += 1
    elif mp.pieces.degree >= 4:  # a cubic spline's snap is zero between knots and impulsive at them
        f.plan_efforts.append(mp.pieces.snap_effort(mp.pieces.t0, mp.pieces.t_end))
    if step.reference.pieces is not f.ref:
        f.ref_peaks = np.maximum(f.ref_peaks, step.reference.peaks(f.t))


def _fly(f: _Flight, world: World, goal: np.ndarray, config: LoopConfig, tracker: _Tracker, steps: int,
         t_limit: float) -> None:
    """Fly one replanning interval on the control grid: track the reference, judge the samples, add up
    effort and peaks."""
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
    stop = _judge(f, world, goal, config, tg, states[:, 0], t_limit)
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
    f.peaks = np.maximum(f.peaks, np.linalg.norm(states[:stop, 1:4], axis=-1).max(axis=0))
    f.tracking.extend(np.linalg.norm(Es[:stop, 0], axis=1).tolist() if Es is not None else [0.0] * stop)
    f.x = states[stop - 1]
    f.E = Es[stop - 1] if Es is not None else np.zeros((4, 3))
    f.t = t_end


def _fly_rotorpy(f: _Flight, world: World, goal: np.ndarray, config: LoopConfig, vehicle: RotorpyVehicle,
                 t1: float, t_limit: float) -> None:
    """Fly rotorpy's quadrotor on the pilot's reference until ``t1``. Effort is the reference's exact
    ∫‖snap‖² dt (rotorpy's state has no snap); the peaks are the airframe's (jerk by differences)."""
    assert f.reference is not None  # a reference is given before every interval
    t0 = f.t
    trace = vehicle.fly(f.reference.sample, t0, t1)
    stop = _judge(f, world, goal, config, trace.t, trace.position, t_limit)
    t_end = float(trace.t[stop - 1])
    f.effort += f.ref.snap_effort(t0, t_end)
    dt = np.diff(np.concatenate([[t0], trace.t[:stop]]))
    jerk = np.diff(np.vstack([f.x[2][None], trace.acceleration[:stop]]), axis=0) / dt[:, None]
    peaks = [np.linalg.norm(a, axis=1).max() for a in (trace.velocity[:stop], trace.acceleration[:stop], jerk)]
    f.peaks = np.maximum(f.peaks, peaks)
    f.tracking.extend(np.linalg.norm(trace.position[:stop] - trace.reference[:stop], axis=1).tolist())
    f.attitudes = (trace.t, trace.quaternion_xyzw)
    f.x = np.stack([trace.position[stop - 1], trace.velocity[stop - 1], trace.acceleration[stop - 1], jerk[-1]])
    f.t = t_end


def _judge(f: _Flight, world: World, goal: np.ndarray, config: LoopConfig, tg: np.ndarray, pos: np.ndarray,
           t_limit: float) -> int:
    """Judge the samples ``pos`` (N, 3) at times ``tg`` (N,): the first collision, arrival or the time limit
    ends the flight. Adds the path, clearance and rows up to there; returns how many samples were flown."""
    d = world.signed_distance(pos)
    hit = np.flatnonzero(d < config.robot_radius)
    near = np.flatnonzero(np.linalg.norm(pos - goal, axis=1) <= config.goal_radius)
    stop = len(tg)
    if len(hit) and (not len(near) or hit[0] <= near[0]):
        stop = int(hit[0]) + 1
        f.outcome, f.coll_point, f.coll_time = "collision", pos[hit[0]].tolist(), float(tg[hit[0]])
    elif len(near):
        stop = int(near[0]) + 1
        f.outcome = "success"
    over = np.flatnonzero(tg >= t_limit - 1e-9)
    if f.outcome == "timeout" and len(over):
        stop = int(over[0]) + 1
    seg = np.concatenate([f.rows[-1][1:][None], pos[:stop]])
    f.path_length += float(np.linalg.norm(np.diff(seg, axis=0), axis=1).sum())
    f.min_dist = min(f.min_dist, float(d[:stop].min()))
    f.rows.extend(np.column_stack([tg[:stop], pos[:stop]]))
    return stop


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
