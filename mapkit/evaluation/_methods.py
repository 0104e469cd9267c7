"""The methods `mapkit eval` compares, all flying the same closed loop.

- ``learned``: the trained planner as deployed — key-points and η from the network; the total time
  from the speed profile (:func:`mapkit.planner.total_time`), every segment at least
  ``min_segment_time`` and the Time Allocation Net's split of the rest; corridor-bounded minimum
  snap with speed and acceleration limits (:class:`Execution`) from the reference's state at the
  takeover (to rest at the goal; through the local goal at cruise speed while the goal lies
  beyond the horizon). A plan with η ≥ 0.5 is flown anyway when the reference being flown has at
  least as many points near seen surfaces in the current depth image (the veto would keep the
  vehicle on a path the camera shows no safer).
- ``learned+uniform`` / ``learned+poly5`` / ``learned+gradient``: the same key-points, total time and
  execution, other splits (Table III of the paper; ``gradient`` is the TAN's supervision,
  Mellinger & Kumar descent under the same boundary conditions).
- ``iplanner-style``: the same network outputs, iPlanner's way: a cubic spline through the key-points
  timed by arc length at the cruise speed (no dynamics, no time allocation), clamped to the vehicle's
  velocity at the start and to the same end velocity as the others.
- ``straight``: no perception; one minimum-snap segment from the vehicle's state to the local goal,
  timed by the same speed profile (the optimum through any points of the straight line; pinning
  interior points at fixed times only adds snap).
- ``oracle``: search on the exact world (Dijkstra on a clearance grid + shortcuts) and one
  corridor-constrained minimum-snap trajectory to the goal; an upper reference, planned once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy.interpolate import CubicSpline

from mapkit.evaluation._loop import MethodPlan, Observation
from mapkit.evaluation._pieces import Pieces, pieces_from_body
from mapkit.planner import Allocation, CameraInput, PlannerConfig, plan_timing
from mapkit.planner._model import PlannerNet
from mapkit.sim import World
from mapkit.sim.search import FreeSpaceGraph
from mapkit.trajopt import allocate_times, min_snap

LEARNED_ALLOCATIONS: dict[str, Allocation] = {"learned": "tan", "learned+uniform": "uniform",
                                              "learned+poly5": "poly5", "learned+gradient": "gradient"}
METHODS = ("learned", "learned+uniform", "learned+poly5", "learned+gradient", "iplanner-style", "straight", "oracle")
"""Every method name, in report order."""
NEEDS_MODEL = frozenset({*LEARNED_ALLOCATIONS, "iplanner-style"})


@dataclass(frozen=True)
class Execution:
    """How a replanning method turns its timed key-points into the reference it flies."""

    corridor: float | None = 1.0
    """Widest half-width (m) of the flight corridor around the key-point segments: the trajectory may
    leave the interior key-points by up to this (per world axis) instead of passing through them,
    which absorbs the key-points' jitter from one plan to the next (most of a flight's effort).
    None: through the key-points."""
    check_corridor: bool = True
    """Check each corridor trajectory against the depth image it was planned from and halve the
    width (1, ½, ¼, ⅒ of ``corridor``, then through the key-points) while it has more points in view
    closer than the robot's size to a seen surface (or behind one) than the trajectory through the
    key-points: a wide corridor cuts the corners the key-points went around. Needs the camera."""
    v_max: float | None = 3.0
    """Per-axis speed limit, m/s (None: none)."""
    a_max: float | None = 4.0
    """Per-axis acceleration limit, m/s² (None: none)."""


def _tensors(wp: np.ndarray, start: np.ndarray, end_speed: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batch-of-one tensors: waypoints (1, K+1, 3), start derivatives (1, 3, 3), end speed (1,)."""
    return (torch.from_numpy(wp)[None], torch.from_numpy(np.ascontiguousarray(start[1:]))[None],
            torch.tensor([end_speed], dtype=torch.float64))


def _limited(wp: torch.Tensor, T: torch.Tensor, start: torch.Tensor, end: torch.Tensor, how: Execution,
             corridor: float | None):
    """Minimum snap in ``corridor`` (None: through the key-points) within the limits of ``how``. The
    limits rarely bind, so they join the QP only when the trajectory without them breaks one (on a
    dense grid). An infeasible QP never leaves the plan without a reference: with the limits it falls
    back to the corridor alone, with the corridor to the trajectory through the key-points."""
    with torch.no_grad():
        kw = {} if corridor is None else {"corridor": corridor}
        traj = min_snap(wp, T, start=start, end=end, on_infeasible="ignore", **kw)
        if not bool(traj.solved.all()):
            return min_snap(wp, T, start=start, end=end)
        over_v = how.v_max is not None and float(traj.max_velocity(per_axis=True, samples_per_segment=256).max()) > how.v_max
        over_a = how.a_max is not None and float(traj.max_acceleration(per_axis=True, samples_per_segment=256).max()) > how.a_max
        if not (over_v or over_a):
            return traj
        limited = min_snap(wp, T, start=start, end=end, on_infeasible="ignore", limits_everywhere=True,
                           v_max=how.v_max, a_max=how.a_max, **kw)
        return limited if bool(limited.solved.all()) else traj


def _samples(traj, count: int = 24) -> torch.Tensor:
    """(1, 1, count, 3) positions evenly spread in time over the trajectory (its start excluded)."""
    total = float(traj.durations.sum())
    t = torch.linspace(total / count, total, count, dtype=torch.float64)
    return traj.position(t).reshape(1, 1, count, 3)


class _Checker:
    """Counts a trajectory's points that come closer to a seen surface than the robot's size."""

    def __init__(self, x: torch.Tensor, camera: CameraInput, max_depth: float, pyramid: torch.Tensor | None) -> None:
        from mapkit.planner._depthcheck import nearest_depth_pyramid

        self.x, self.camera, self.max_depth = x, camera, max_depth
        self.pyramid = nearest_depth_pyramid(x) if pyramid is None else pyramid

    def __call__(self, traj) -> int:
        return self.points(_samples(traj))

    def points(self, pts: torch.Tensor) -> int:
        """Conflicts of points (1, 1, P, 3) in the body frame of the depth image."""
        from mapkit.planner import seen_conflicts

        return int(seen_conflicts(pts.to(self.x.dtype), self.x, self.camera, max_depth=self.max_depth,
                                  pyramid=self.pyramid)[0, 0])


def _execute(wp: torch.Tensor, T: torch.Tensor, start: torch.Tensor, end: torch.Tensor, how: Execution,
             check: "_Checker | None" = None):
    """The reference a plan flies: the widest corridor of ``how`` that ``check`` does not find
    closer to what the camera sees than the trajectory through the key-points."""
    if how.corridor is None:
        return _limited(wp, T, start, end, how, None)
    if check is None or not how.check_corridor:
        return _limited(wp, T, start, end, how, how.corridor)
    widest = _limited(wp, T, start, end, how, how.corridor)
    conflicts = check(widest)
    if conflicts == 0:  # the usual case, decided without the reference trajectory
        return widest
    with torch.no_grad():
        allowed = check(min_snap(wp, T, start=start, end=end))
    if conflicts <= allowed:
        return widest
    for scale in (0.5, 0.25, 0.1):
        traj = _limited(wp, T, start, end, how, how.corridor * scale)
        if check(traj) <= allowed:
            return traj
    return _limited(wp, T, start, end, how, None)


def _reference_no_safer(obs: Observation, plan, check: "_Checker") -> bool:
    """True when the reference being flown, over as long as the new plan from the takeover, has at
    least as many points closer to seen surfaces than the robot's size as the plan itself."""
    total = float(plan.durations.sum())
    t = obs.t + np.linspace(total / 24, total, 24)
    world = obs.reference.derivative(t, 0)
    R, p = obs.T_world_body[:3, :3], obs.T_world_body[:3, 3]
    body = torch.from_numpy((world - p) @ R).reshape(1, 1, 24, 3)
    return check.points(body) >= check(plan)


class LearnedMethod:
    """The network's key-points with a chosen time allocation (``tan`` is the deployed planner), or
    with iPlanner's cubic-spline interpolation (``spline=True``)."""

    needs_depth = True
    replans = True

    def __init__(self, name: str, net: PlannerNet, *, allocation: Allocation = "tan", spline: bool = False,
                 camera: CameraInput | None = None, execution: Execution = Execution()) -> None:
        self.name = name
        self.camera = camera
        self.net = net.eval()
        self.allocation = allocation
        self.spline = spline
        self.config = net.config
        self.execution = execution

    def _keypoints(self, obs: Observation, start: np.ndarray) -> tuple[np.ndarray, float, torch.Tensor, torch.Tensor | None]:
        with torch.inference_mode():
            d = torch.from_numpy(np.asarray(obs.depth, dtype=np.float32)[None])
            x = self.net.preprocess(d)
            g = torch.from_numpy(np.asarray(obs.local_goal_body, dtype=np.float32)[None])
            v = torch.from_numpy(np.asarray(start[1], dtype=np.float32)[None])
            out = self.net(x, g, camera=self.camera, velocity=v)
        return out.keypoints[0].double().numpy(), float(out.eta[0]), x, out.pyramid

    def plan(self, obs: Observation) -> MethodPlan:
        t0 = time.perf_counter()
        start = obs.start_body()
        kp, eta, x, pyramid = self._keypoints(obs, start)
        overrides = False
        wp = np.concatenate([start[:1], kp])
        wpt, st, es = _tensors(wp, start, self.config.cruise_speed if obs.goal_clipped else 0.0)
        t_alloc = time.perf_counter()
        with torch.inference_mode():
            timing = plan_timing(wpt, st, es, self.config, allocation=self.allocation, tan=self.net.tan)
        allocation_ms = 1e3 * (time.perf_counter() - t_alloc)
        if self.spline:
            coeffs, durations = _clamped_spline(wp, start[1], timing.end[0, 0].numpy(), float(timing.total[0]))
        else:
            check = None
            if self.camera is not None and self.execution.check_corridor:
                with torch.inference_mode():
                    check = _Checker(x, self.camera, self.config.max_depth, pyramid)
            with torch.inference_mode():
                traj = _execute(wpt, timing.durations, st, timing.end, self.execution, check)
            coeffs, durations = traj.coeffs[0].numpy(), timing.durations[0].numpy()
            if eta >= 0.5 and check is not None and obs.reference is not None:
                overrides = _reference_no_safer(obs, traj, check)
        latency = 1e3 * (time.perf_counter() - t0)
        pieces = pieces_from_body(coeffs, durations, obs.T_world_body, obs.t)
        kp_world = kp @ obs.T_world_body[:3, :3].T + obs.T_world_body[:3, 3]
        return MethodPlan(pieces=pieces, latency_ms=latency, eta=eta, keypoints_world=kp_world,
                          allocation_ms=None if self.spline else allocation_ms, overrides_eta=overrides)


def _clamped_spline(wp: np.ndarray, v0: np.ndarray, v1: np.ndarray, total: float) -> tuple[np.ndarray, np.ndarray]:
    """Cubic spline through ``wp`` (N, 3), knots at constant speed along the chords over ``total``
    seconds, velocity ``v0`` at the start and ``v1`` at the end → (M, 3, 4) normalised-time
    coefficients and (M,) durations."""
    chord = np.linalg.norm(np.diff(wp, axis=0), axis=1)
    keep = np.concatenate([[True], chord > 1e-6])
    wp, chord = wp[keep], np.linalg.norm(np.diff(wp[keep], axis=0), axis=1)
    if len(wp) < 2:  # every key-point on top of the vehicle: hold
        return np.zeros((1, 3, 4)) + np.concatenate([wp[0][:, None], np.zeros((3, 3))], axis=1)[None], np.array([1.0])
    knots = np.concatenate([[0.0], np.cumsum(chord)]) * (total / chord.sum())
    cs = CubicSpline(knots, wp, bc_type=((1, v0), (1, v1)))
    T = np.diff(knots)
    # scipy: c[m, i] multiplies (t - x_i)**(3 - m); normalised time s = (t - x_i) / T_i.
    coeffs = np.stack([cs.c[3 - k] * T[:, None] ** k for k in range(4)], axis=-1)  # (M, 3, 4)
    return coeffs, T


class StraightMethod:
    """One minimum-snap segment from the vehicle's state to the local goal, timed by the planner's
    speed profile; no camera."""

    name = "straight"
    needs_depth = False
    replans = True

    def __init__(self, config: PlannerConfig | None = None) -> None:
        self.config = config or PlannerConfig()

    def plan(self, obs: Observation) -> MethodPlan:
        t0 = time.perf_counter()
        start = obs.start_body()
        wp = np.stack([start[0], obs.local_goal_body])
        wpt, st, es = _tensors(wp, start, self.config.cruise_speed if obs.goal_clipped else 0.0)
        timing = plan_timing(wpt, st, es, self.config, allocation="uniform")
        with torch.no_grad():
            traj = min_snap(wpt, timing.durations, start=st, end=timing.end)
        latency = 1e3 * (time.perf_counter() - t0)
        return MethodPlan(pieces=pieces_from_body(traj.coeffs[0].numpy(), timing.durations[0].numpy(),
                                                  obs.T_world_body, obs.t), latency_ms=latency)


class OracleMethod:
    """Exact-map search + corridor minimum snap, planned once from the start to the goal."""

    name = "oracle"
    needs_depth = False
    replans = False

    def __init__(self, graph: FreeSpaceGraph, *, corridor: float = 0.1, v_max: float = 2.0, a_max: float = 2.0,
                 clearance: float = 0.35) -> None:
        self.graph = graph
        self.clearance = clearance
        self.corridor = corridor
        self.v_max, self.a_max = v_max, a_max

    def plan(self, obs: Observation) -> MethodPlan:
        t0 = time.perf_counter()
        poly = self.graph.path(obs.state_world[0], obs.goal_world)
        # The corridor bounds the deviation across each segment's line, not along it: at a sharp turn
        # the trajectory may run on past the corner. Shorter segments keep that overshoot small; the
        # first that keeps the clearance on the exact world is flown.
        for max_len in (3.0, 1.0, 0.5):
            wp_np = _split_long(poly, max_len)
            wp = torch.from_numpy(wp_np)[None]
            T = allocate_times(wp, "trapezoid", v_max=self.v_max, a_max=self.a_max)
            with torch.no_grad():
                traj = min_snap(wp, T, corridor=self.corridor, on_infeasible="ignore")
                t = torch.arange(0.0, float(T.sum()), 0.02, dtype=torch.float64)
                p = traj.position(t)[0].numpy()
            if bool(traj.solved.all()) and self.graph.world.signed_distance(p).min() >= self.clearance:
                break
        latency = 1e3 * (time.perf_counter() - t0)
        return MethodPlan(pieces=Pieces(t0=obs.t, durations=T[0].numpy(), coeffs=traj.coeffs[0].numpy()),
                          latency_ms=latency, keypoints_world=wp_np)


def _split_long(poly: np.ndarray, max_len: float) -> np.ndarray:
    """Insert points so no polyline segment is longer than ``max_len`` metres (keeps the corridor,
    which bounds the deviation from each segment's line, tight on long straight legs)."""
    out = [poly[0]]
    for a, b in zip(poly[:-1], poly[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / max_len)))
        out.extend(a + (b - a) * k / n for k in range(1, n + 1))
    return np.array(out)


def make_methods(names: list[str], net: PlannerNet | None, world: World, graph: FreeSpaceGraph | None, *,
                 oracle_corridor: float = 0.1, robot_radius: float = 0.3, camera: CameraInput | None = None,
                 execution: Execution = Execution()) -> list:
    """Instantiate the named methods (``net`` needed by the learned ones, ``graph`` by the oracle,
    ``camera`` by models that check their paths against the depth image; ``execution`` how the
    learned allocations fly their key-points)."""
    cfg = net.config if net is not None else None
    out = []
    for name in names:
        if name in LEARNED_ALLOCATIONS:
            out.append(LearnedMethod(name, net, allocation=LEARNED_ALLOCATIONS[name], camera=camera,
                                     execution=execution))
        elif name == "iplanner-style":
            out.append(LearnedMethod(name, net, spline=True, camera=camera))
        elif name == "straight":
            out.append(StraightMethod(cfg))
        elif name == "oracle":
            out.append(OracleMethod(graph, corridor=oracle_corridor, v_max=cfg.cruise_speed if cfg is not None else 2.0,
                                    clearance=robot_radius + 0.05))
        else:
            raise ValueError(f"unknown method {name!r}")
    return out
