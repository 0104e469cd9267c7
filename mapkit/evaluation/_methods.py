"""The methods `mapkit eval` compares, all flying the same closed loop.

- ``learned``: the trained planner as deployed — key-points and η from the network, the Time
  Allocation Net's split of the total time, minimum snap from the vehicle's state (to rest at the
  goal; through the local goal at cruise speed while the goal lies beyond the horizon).
- ``learned+uniform`` / ``learned+poly5`` / ``learned+gradient``: the same key-points and total time,
  other time allocations (Table III of the paper).
- ``iplanner-style``: the same network outputs, iPlanner's way: a cubic spline through the key-points
  timed by arc length at the cruise speed (no dynamics, no time allocation), clamped to the vehicle's
  velocity at the start and to the same end velocity as the others.
- ``straight``: no perception; one minimum-snap segment from the vehicle's state to the local goal (the optimum through any points of the straight line; pinning interior points at fixed
  times only adds snap).
- ``oracle``: search on the exact world (Dijkstra on a clearance grid + shortcuts) and one
  corridor-constrained minimum-snap trajectory to the goal; an upper reference, planned once.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from scipy.interpolate import CubicSpline

from mapkit.evaluation._loop import MethodPlan, Observation
from mapkit.evaluation._pieces import Pieces, pieces_from_body
from mapkit.planner import CameraInput
from mapkit.planner._model import PlannerNet
from mapkit.sim import World
from mapkit.sim.search import FreeSpaceGraph
from mapkit.trajopt import allocate_times, min_snap

LEARNED_ALLOCATIONS = {"learned": "tan", "learned+uniform": "uniform", "learned+poly5": "poly5",
                       "learned+gradient": "gradient"}
METHODS = ("learned", "learned+uniform", "learned+poly5", "learned+gradient", "iplanner-style", "straight", "oracle")
"""Every method name, in report order."""
_MIN_SEGMENT_S = 0.4
NEEDS_MODEL = frozenset({*LEARNED_ALLOCATIONS, "iplanner-style"})


def _start_body(obs: Observation) -> np.ndarray:
    """(3, 3) velocity, acceleration, jerk of the vehicle in the body frame."""
    R = obs.T_world_body[:3, :3]
    return obs.state_world[1:4] @ R


def _total_time(waypoints: np.ndarray, obs: Observation, *, cruise_speed: float, min_total_time: float,
                max_total_time: float) -> float:
    """Seconds for the whole plan. Beyond the horizon the planner's own rule (path length / cruise
    speed). On the approach (rest at the goal) the average speed is half the current speed, kept
    within [cruise / 2, cruise], and each segment gets at least 0.4 s on average: a plan asking for the cruise average while it must stop makes
    the vehicle speed up every interval (only the start of each plan is flown) and brake hard at
    the end."""
    length = float(np.linalg.norm(np.diff(waypoints, axis=0), axis=1).sum())
    if obs.goal_clipped:
        return float(np.clip(length / cruise_speed, min_total_time, max_total_time))
    v0 = float(np.linalg.norm(obs.state_world[1]))
    speed = float(np.clip(0.5 * v0, 0.5 * cruise_speed, cruise_speed))
    # Close to the goal the key-points crowd together; at least 0.4 s per segment keeps their
    # pinned passing times from demanding snap that grows like 1 / T⁷.
    floor = max(min_total_time, _MIN_SEGMENT_S * (len(waypoints) - 1))
    return float(np.clip(length / speed, floor, max_total_time))


def _end_body(obs: Observation, waypoints: np.ndarray, speed: float) -> np.ndarray:
    """(3, 3) end velocity, acceleration, jerk: rest at the real goal; beyond the horizon, cruise
    speed along the last segment (the next plan takes over long before the end)."""
    end = np.zeros((3, 3))
    if obs.goal_clipped:
        last = waypoints[-1] - waypoints[-2]
        n = float(np.linalg.norm(last))
        if n > 1e-6:
            end[0] = speed * last / n
    return end


class LearnedMethod:
    """The network's key-points with a chosen time allocation (``tan`` is the deployed planner), or
    with iPlanner's cubic-spline interpolation (``spline=True``)."""

    needs_depth = True
    replans = True

    def __init__(self, name: str, net: PlannerNet, *, allocation: str = "tan", spline: bool = False,
                 camera: CameraInput | None = None) -> None:
        self.name = name
        self.camera = camera
        self.net = net.eval()
        self.allocation = allocation
        self.spline = spline
        self.config = net.config

    def _keypoints(self, obs: Observation) -> tuple[np.ndarray, float]:
        with torch.inference_mode():
            d = torch.from_numpy(np.asarray(obs.depth, dtype=np.float32)[None])
            x = self.net.preprocess(d)
            g = torch.from_numpy(np.asarray(obs.local_goal_body, dtype=np.float32)[None])
            v = torch.from_numpy(np.asarray(_start_body(obs)[0], dtype=np.float32)[None])
            out = self.net(x, g, camera=self.camera, velocity=v)
        return out.keypoints[0].double().numpy(), float(out.eta[0])

    def plan(self, obs: Observation) -> MethodPlan:
        t0 = time.perf_counter()
        kp, eta = self._keypoints(obs)
        wp = np.concatenate([np.zeros((1, 3)), kp])
        start = _start_body(obs)
        c = self.config
        end = _end_body(obs, wp, c.cruise_speed)
        total_s = _total_time(wp, obs, cruise_speed=c.cruise_speed, min_total_time=c.min_total_time,
                              max_total_time=c.max_total_time)
        if self.spline:
            coeffs, durations = _clamped_spline(wp, start[0], end[0], total_s)
        else:
            wpt = torch.from_numpy(wp)[None]
            en = torch.from_numpy(end)[None]
            total = torch.tensor([total_s], dtype=torch.float64)
            st = torch.from_numpy(start)[None]
            if self.allocation == "tan":
                with torch.inference_mode():
                    shares = self.net.tan.shares(wpt.to(next(self.net.tan.parameters()).dtype)).double()
                shares = shares.clamp_min(1e-4)
                T = shares / shares.sum(-1, keepdim=True) * total[:, None]
            elif self.allocation == "gradient":
                T = allocate_times(wpt, "gradient", total_time=total, start=st, end=en, max_iters=30)
            else:
                T = allocate_times(wpt, self.allocation, total_time=total)
            with torch.no_grad():
                traj = min_snap(wpt, T.reshape(1, -1), start=st, end=en)
            coeffs, durations = traj.coeffs[0].numpy(), T[0].numpy()
        latency = 1e3 * (time.perf_counter() - t0)
        pieces = pieces_from_body(coeffs, durations, obs.T_world_body, obs.t)
        kp_world = kp @ obs.T_world_body[:3, :3].T + obs.T_world_body[:3, 3]
        return MethodPlan(pieces=pieces, latency_ms=latency, eta=eta, keypoints_world=kp_world)


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
    """One minimum-snap segment from the vehicle's state to the local goal; no camera."""

    name = "straight"
    needs_depth = False
    replans = True

    def __init__(self, *, num_keypoints: int = 1, cruise_speed: float = 2.0, min_total_time: float = 1.0,
                 max_total_time: float = 15.0) -> None:
        self.K = num_keypoints
        self.rule = dict(cruise_speed=cruise_speed, min_total_time=min_total_time, max_total_time=max_total_time)

    def plan(self, obs: Observation) -> MethodPlan:
        t0 = time.perf_counter()
        frac = np.arange(0, self.K + 1)[:, None] / self.K
        wp = torch.from_numpy(frac * obs.local_goal_body[None])[None]
        total = _total_time(wp[0].numpy(), obs, **self.rule)
        T = torch.full((1, self.K), total / self.K, dtype=torch.float64)
        end = torch.from_numpy(_end_body(obs, wp[0].numpy(), self.rule["cruise_speed"]))[None]
        with torch.no_grad():
            traj = min_snap(wp, T, start=torch.from_numpy(_start_body(obs))[None], end=end)
        latency = 1e3 * (time.perf_counter() - t0)
        return MethodPlan(pieces=pieces_from_body(traj.coeffs[0].numpy(), T[0].numpy(), obs.T_world_body, obs.t),
                          latency_ms=latency)


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
                 oracle_corridor: float = 0.1, robot_radius: float = 0.3, camera: CameraInput | None = None) -> list:
    """Instantiate the named methods (``net`` needed by the learned ones, ``graph`` by the oracle,
    ``camera`` by models that check their paths against the depth image)."""
    cfg = net.config if net is not None else None
    out = []
    for name in names:
        if name in LEARNED_ALLOCATIONS:
            out.append(LearnedMethod(name, net, allocation=LEARNED_ALLOCATIONS[name], camera=camera))
        elif name == "iplanner-style":
            out.append(LearnedMethod(name, net, spline=True, camera=camera))
        elif name == "straight":
            kw = {} if cfg is None else dict(cruise_speed=cfg.cruise_speed, min_total_time=cfg.min_total_time,
                                             max_total_time=cfg.max_total_time)
            out.append(StraightMethod(**kw))
        elif name == "oracle":
            out.append(OracleMethod(graph, corridor=oracle_corridor, v_max=cfg.cruise_speed if cfg is not None else 2.0,
                                    clearance=robot_radius + 0.05))
        else:
            raise ValueError(f"unknown method {name!r}")
    return out
