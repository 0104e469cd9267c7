"""The learned planner under the flight stack (:class:`~mapkit.flight.Execution`): the network's
key-points and η, timed by the speed profile and the Time Allocation Net, executed as corridor-bounded
minimum snap within the limits from the reference's state at the takeover, with the depth memory,
the flight map and the other layers around it. ``allocation`` picks other splits (Table III of the
paper), ``spline=True`` flies iPlanner's cubic spline, ``keypoints="straight"`` the straight line.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, fields, replace
from typing import Any, Literal

import numpy as np
import torch
from scipy.interpolate import CubicSpline
from scipy.spatial import cKDTree

from mapkit.flight._layers import TURN_MIN_SPEED, Execution, SpeedProfile
from mapkit.flight._pieces import pieces_from_body
from mapkit.flight._plan import MethodPlan, Observation
from mapkit.flight._route import FlightMap, Progress, depth_points
from mapkit.planner import Allocation, CameraInput, ImageFeatures, PlannerConfig, Timing, plan_timing, turn_speed
from mapkit.planner._errors import PlannerError
from mapkit.planner._model import PlannerNet, PlannerOutput
from mapkit.trajopt import Trajectory, min_snap

_FULL_STACK = Execution()
KeypointSource = Literal["network", "straight"]
ROBOT_RADIUS = 0.3
"""Metres: the robot's radius (the evaluation's collision radius)."""
ROBOT_CLEARANCE = 0.35
"""Metres a plan's first ``Memory.blocked_within`` seconds must keep from every remembered surface."""


@dataclass
class _Search:
    """Whether a flight searches for its way (stalled, or flown much farther than it came); it stays so."""

    searching: bool = False
    start_distance: float | None = None
    flown: float = 0.0
    last: np.ndarray | None = None

    def update(self, position: np.ndarray, distance: float, ratio: float, margin: float) -> bool:
        """Record the vehicle's position and distance to the goal at a plan; True once searching."""
        if self.last is None:
            self.start_distance = distance
        else:
            self.flown += float(np.linalg.norm(position - self.last))
        self.last = np.array(position, dtype=np.float64)
        assert self.start_distance is not None
        self.searching = self.searching or self.flown > ratio * (self.start_distance - distance) + margin
        return self.searching


def _at_speed(config: PlannerConfig, speed: float | None) -> PlannerConfig:
    """``config`` whose speed profile cruises at ``speed`` m/s (None: its own cruise speed)."""
    return config if speed is None else replace(config, cruise_speed=float(speed))


def _tensors(wp: np.ndarray, start: np.ndarray, end_speed: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batch-of-one tensors: waypoints (1, K+1, 3), start derivatives (1, 3, 3), end speed (1,)."""
    return (torch.from_numpy(wp)[None], torch.from_numpy(np.ascontiguousarray(start[1:]))[None],
            torch.tensor([end_speed], dtype=torch.float64))


def _limited(wp: torch.Tensor, T: torch.Tensor, start: torch.Tensor, end: torch.Tensor, how: Execution,
             corridor: float | None) -> Trajectory:
    """Minimum snap in ``corridor`` (None, or infeasible: through the key-points) within ``how``'s limits
    (norms, dense grid): else flown slower (durations stretched by the excess, a few rounds, at most
    :data:`MAX_STRETCH`), else with the limits in the QP (:func:`_bounded`), else the closest."""
    with torch.no_grad():
        kw: dict[str, Any] = {} if corridor is None else {"corridor": corridor}
        traj = min_snap(wp, T, start=start, end=end, on_infeasible="ignore", **kw)
        if not bool(traj.solved.all()):
            kw = {}
            traj = min_snap(wp, T, start=start, end=end)
        limits = how.speed
        tried, stretch = [(_excess(traj, limits), 1.0, traj)], 1.0
        while tried[-1][0] > 1.0 + 1e-6 and stretch < MAX_STRETCH and tried[-1][0] <= min(x[0] for x in tried):
            stretch = min(MAX_STRETCH, stretch * min(max(1.05 * tried[-1][0], 1.1), 2.0))
            slower = min_snap(wp, T * stretch, start=start, end=_slowed(end, stretch), on_infeasible="ignore", **kw)
            if kw and not _solved(slower):  # a narrow corridor can refuse a slower flight
                kw = {}
                slower = min_snap(wp, T * stretch, start=start, end=_slowed(end, stretch), on_infeasible="ignore")
            if not _solved(slower):
                break
            tried.append((_excess(slower, limits), stretch, slower))
        excess, best, traj = min(tried, key=lambda x: x[0])
        if excess <= 1.0 + 1e-6:
            return traj
        return _bounded(wp, T * best, start, _slowed(end, best), limits, [kw, {}] if kw else [kw], traj)


def _slowed(end: torch.Tensor, stretch: float) -> torch.Tensor:
    """End derivatives (B, 3) or (B, D, 3) of the same path flown ``stretch`` times slower."""
    if end.dim() == 2:
        return end / stretch
    powers = stretch ** torch.arange(1, end.shape[1] + 1, dtype=end.dtype)
    return end / powers[None, :, None]


MAX_STRETCH = 8.0
"""The most a plan's durations are stretched to keep the limits."""


def _bounded(wp: torch.Tensor, T: torch.Tensor, start: torch.Tensor, end: torch.Tensor, limits: SpeedProfile,
             corridors: list[dict[str, Any]], closest: Trajectory) -> Trajectory:
    """The first QP with per-axis bounds limit / √3, then limit, in each of ``corridors``, that keeps the
    limits (norms); else the closest of those and ``closest``."""
    out = [closest]
    for scale, kw in itertools.product((1.0 / math.sqrt(3.0), 1.0), corridors):
        traj = min_snap(wp, T, start=start, end=end, on_infeasible="ignore", limits_everywhere=True,
                        v_max=limits.v_max * scale, a_max=limits.a_max * scale, **kw)
        if not _solved(traj):
            continue
        if _within(traj, limits):
            return traj
        out.append(traj)
    return min(out, key=lambda t: _excess(t, limits))


def _solved(traj: Trajectory) -> bool:
    return bool(traj.solved.all()) and bool(torch.isfinite(traj.coeffs).all())


def _excess(traj: Trajectory, limits: SpeedProfile) -> float:
    """How much slower ``traj`` must fly to keep ``limits``: the largest of v / v_max and √(a / a_max)."""
    v = float(traj.max_velocity(samples_per_segment=256).max())
    a = float(traj.max_acceleration(samples_per_segment=256).max())
    return max(v / limits.v_max, (a / limits.a_max) ** 0.5)


def _within(traj: Trajectory, limits: SpeedProfile) -> bool:
    """True when the speed and the acceleration (norms, 256 samples a segment) keep ``limits``."""
    return _excess(traj, limits) <= 1.0 + 1e-6


def follow_reference(wp: torch.Tensor, durations: torch.Tensor, obs: Observation, fraction: float,
                     limit: float) -> torch.Tensor:
    """Waypoints (1, K+1, 3) (body frame of ``obs``) with every interior key-point reached before the
    reference ends moved ``fraction`` of the way toward it, by at most ``limit`` metres per axis."""
    ref = obs.reference
    if ref is None or fraction <= 0:
        return wp
    times = obs.t + np.cumsum(durations[0].detach().cpu().numpy())[:-1]
    inside = np.flatnonzero(times <= ref.t_end - 1e-9)
    if not len(inside):
        return wp
    R, p = obs.T_world_body[:3, :3], obs.T_world_body[:3, 3]
    toward = torch.from_numpy((ref.derivative(times[inside], 0) - p) @ R).to(wp.dtype)
    out = wp.clone()
    idx = torch.from_numpy(inside + 1)
    out[0, idx] += fraction * (toward - out[0, idx]).clamp(-limit, limit)
    return out


def _samples(traj, count: int = 24, within: float | None = None) -> torch.Tensor:
    """(1, B, count, 3) positions evenly spread over each trajectory or its first ``within`` seconds."""
    total = traj.durations.sum(-1).reshape(-1, 1)
    if within is not None:
        total = total.clamp(max=within)
    t = total * torch.linspace(1.0 / count, 1.0, count, dtype=torch.float64)
    return traj.position(t).reshape(1, -1, count, 3)


class _Checker:
    """Counts a trajectory's points closer to a seen surface than the robot's size: in its depth image,
    and with ``recall`` (the memory, the pose, seconds) among the remembered surfaces."""

    def __init__(self, x: torch.Tensor, camera: CameraInput, max_depth: float, pyramid: torch.Tensor | None,
                 recall: tuple[_Memory, np.ndarray, float] | None = None) -> None:
        from mapkit.planner._depthcheck import nearest_depth_pyramid

        self.x, self.camera, self.max_depth = x, camera, max_depth
        self.pyramid = nearest_depth_pyramid(x) if pyramid is None else pyramid
        self.recall = recall

    def __call__(self, traj) -> int:
        n = self.points(_samples(traj))
        if self.recall is not None and self.recall[0].frames:
            memory, T_world_body, within = self.recall
            n += int(memory.conflicts(_samples(traj, within=within)[0], T_world_body)[0])
        return n

    def points(self, pts: torch.Tensor) -> int:
        """Conflicts of points (1, 1, P, 3) in the body frame of the depth image."""
        from mapkit.planner import seen_conflicts

        return int(seen_conflicts(pts.to(self.x.dtype), self.x, self.camera, max_depth=self.max_depth,
                                  pyramid=self.pyramid)[0][0])


def _execute(wp: torch.Tensor, T: torch.Tensor, start: torch.Tensor, end: torch.Tensor, how: Execution,
             check: _Checker | None = None) -> Trajectory:
    """The reference a plan flies: the widest corridor that ``check`` finds no closer to what the camera
    sees than the trajectory through the key-points."""
    width = how.corridor.widest(check is not None and how.corridor.check)
    if width is None or check is None or not how.corridor.check:
        return _limited(wp, T, start, end, how, width)
    widest = _limited(wp, T, start, end, how, width)
    conflicts = check(widest)
    if conflicts == 0:  # the usual case, decided without the reference trajectory
        return widest
    with torch.no_grad():
        allowed = check(min_snap(wp, T, start=start, end=end))
    if conflicts <= allowed:
        return widest
    for scale in (0.5, 0.25, 0.1):
        traj = _limited(wp, T, start, end, how, width * scale)
        if check(traj) <= allowed:
            return traj
    return _limited(wp, T, start, end, how, None)


def open_direction(depth: np.ndarray, camera: CameraInput, goal_body: np.ndarray, max_depth: float,
                   min_free: float = 2.5) -> np.ndarray | None:
    """A point (3,) in the body frame toward the image column with the most free depth in the middle
    fifth of the rows (a doorway), up to 5 m and 1 m short of what is seen there, one metre of free
    depth traded per radian off ``goal_body``'s bearing; None when no column is free for ``min_free`` m."""
    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    band = depth[int(0.4 * H):int(0.6 * H) + 1]
    free = np.where(np.isfinite(band) & (band > 0), band, max_depth).min(axis=0)
    fx, _, cx, _ = (float(v) for v in camera.intrinsics[0])
    bearing = -np.arctan(((np.arange(W) + 0.5) / W - cx) / fx)  # image x grows to the body's right (−y)
    goal_bearing = math.atan2(float(goal_body[1]), float(goal_body[0]))
    score = np.where(free >= min_free, np.minimum(free, 6.0) - np.abs(bearing - goal_bearing), -np.inf)
    j = int(np.argmax(score))
    if not np.isfinite(score[j]):
        return None
    reach = min(free[j] - 1.0, 5.0)
    return np.array([reach * math.cos(bearing[j]), reach * math.sin(bearing[j]), 0.0])


def _pick(timing: Timing, m: int) -> Timing:
    """Row ``m`` of a batched timing, as a batch of one."""
    return Timing(**{f.name: getattr(timing, f.name)[m:m + 1] for f in fields(timing)})


class _Memory:
    """Surfaces the camera saw during the last ``seconds`` of one flight, world frame: one k-d tree per
    depth image (every second pixel), built once when the image arrives."""

    stride = 2

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.frames: list[tuple[float, cKDTree]] = []
        self._nearest_cache: tuple[tuple, float] | None = None
        self._near_cache: dict[tuple[bytes, float], dict[cKDTree, np.ndarray]] = {}

    def forget(self) -> None:
        """A new flight starts with nothing remembered."""
        self.frames = []
        self._nearest_cache = None
        self._near_cache = {}

    def points(self, obs: Observation, camera: CameraInput) -> np.ndarray:
        """(N, 3) world points of the observation's depth image (every second pixel) seen by ``camera``."""
        fx, fy, cx, cy = (float(v) for v in camera.intrinsics[0])
        ray = (fx, fy, cx, cy)
        T_body_camera = np.linalg.inv(camera.T_camera_body[0].double().numpy())
        return depth_points(np.asarray(obs.depth), ray, obs.T_world_body @ T_body_camera, self.stride)

    def add(self, obs: Observation) -> None:
        """Remember the observation's depth image (seen by its camera)."""
        assert obs.camera is not None  # an observation to remember carries its camera
        self.add_points(obs.t, self.points(obs, obs.camera))

    def add_points(self, t: float, world: np.ndarray) -> None:
        """Remember an image's world points (:meth:`points`) seen at ``t``."""
        self.frames = [(seen, tree) for seen, tree in self.frames if t - seen <= self.seconds]
        if len(world):
            self.frames.append((t, cKDTree(world, balanced_tree=False, compact_nodes=False)))

    def clearest(self, T_world_body: np.ndarray, start: np.ndarray, deceleration: float = 3.0) -> np.ndarray | None:
        """Body-frame unit vector closest to the velocity (turned by up to 60°, level) along which a
        brake to rest keeps clear of remembered surfaces; None when straight on is clear or none is."""
        v = start[1]
        speed = float(np.linalg.norm(v[:2]))
        if speed < 0.3:
            return None
        reach = float(np.linalg.norm(v)) ** 2 / deceleration + 0.3
        heading = math.atan2(v[1], v[0])
        steps = np.linspace(0.2, 1.0, 8)[None, :, None] * reach
        for turn in (0.0, 20.0, -20.0, 40.0, -40.0, 60.0, -60.0):
            a = heading + math.radians(turn)
            d = np.array([math.cos(a), math.sin(a), 0.0])
            if self.conflicts(torch.from_numpy(d[None, None, :] * steps), T_world_body)[0] == 0:
                return None if turn == 0.0 else d
        return None

    def open_side(self, T_world_body: np.ndarray, radius: float = 3.0) -> float | None:
        """+1 (left) or −1 (right): the side with fewer remembered surface points within ``radius``
        metres near the body's height, which a blocked vehicle turns toward; None on a tie."""
        p, R = T_world_body[:3, 3], T_world_body[:3, :3]
        left = right = 0
        for _, tree in self.frames:
            near = tree.query_ball_point(p, radius)
            if not near:
                continue
            body = (tree.data[near] - p) @ R
            level = np.abs(body[:, 2]) < 0.5
            left += int((level & (body[:, 1] > 0.3)).sum())
            right += int((level & (body[:, 1] < -0.3)).sum())
        return None if left == right else (1.0 if left < right else -1.0)

    def _nearest(self, position: np.ndarray) -> float:
        """Metres to the nearest remembered surface up to :data:`ROBOT_CLEARANCE` (inf beyond), cached."""
        key = (position.tobytes(), len(self.frames), self.frames[-1][0] if self.frames else None)
        if self._nearest_cache is None or self._nearest_cache[0] != key:
            now = min((tree.query(position, distance_upper_bound=ROBOT_CLEARANCE)[0] for _, tree in self.frames),
                      default=np.inf)
            self._nearest_cache = (key, float(now))
        return self._nearest_cache[1]

    def conflicts(self, paths_body: torch.Tensor, T_world_body: np.ndarray) -> np.ndarray:
        """(M,) points of each path (M, P, 3) (body frame) closer than :data:`ROBOT_CLEARANCE` to a
        remembered surface, or than the vehicle is now when it is nearer already."""
        pts = paths_body.double().numpy() @ T_world_body[:3, :3].T + T_world_body[:3, 3]
        flat = pts.reshape(-1, 3)
        radius = min(ROBOT_CLEARANCE, max(self._nearest(T_world_body[:3, 3]) - 0.02, ROBOT_RADIUS))
        # frames already asked about this path answer from the last few queries' results
        key = (flat.tobytes(), radius)
        known = self._near_cache.get(key, {})
        per_frame = {}
        near = np.zeros(len(flat), dtype=bool)
        for _, tree in self.frames:
            hit = known.get(tree)
            if hit is None:
                hit = np.isfinite(tree.query(flat, distance_upper_bound=radius)[0])
            per_frame[tree] = hit
            near |= hit
        self._near_cache.pop(key, None)
        self._near_cache[key] = per_frame
        while len(self._near_cache) > 4:
            del self._near_cache[next(iter(self._near_cache))]
        return near.reshape(pts.shape[:2]).sum(axis=1)


def _reference_no_safer(obs: Observation, plan, check: _Checker) -> bool:
    """True when the reference being flown has at least as many conflicts as the plan, over as long."""
    assert obs.reference is not None  # the caller checks
    total = float(plan.durations.sum())
    t = obs.t + np.linspace(total / 24, total, 24)
    world = obs.reference.derivative(t, 0)
    R, p = obs.T_world_body[:3, :3], obs.T_world_body[:3, 3]
    body = torch.from_numpy((world - p) @ R).reshape(1, 1, 24, 3)
    return check.points(body) >= check.points(_samples(plan))


@dataclass(frozen=True)
class PlanInput:
    """What a plan's time allocation was given in flight (``mapkit tune-timing`` learns from these)."""

    waypoints: np.ndarray
    """(K+1, 3) body frame metres: the start, then the network's key-points (before following the reference)."""
    start: np.ndarray
    """(3, 3) velocity, acceleration and jerk rows at the start, body frame."""
    end_speed: float
    """m/s at the last key-point (0: rest at the goal)."""
    cruise_speed: float
    """m/s: the cruise speed of the plan's speed profile (slowed for its turns, :attr:`SpeedProfile.turn_accel`)."""
    decel: float
    """m/s²: the rate at which the plan's speed profile slows down to the end speed."""


@dataclass(frozen=True)
class JudgeInput:
    """What the flown-path head read about every candidate of one plan (``mapkit tune-judge`` learns from these)."""

    features: np.ndarray
    """(M, N, FLOWN_FEATURES) float32 (:func:`mapkit.planner.flown_features`)."""
    lengths: np.ndarray
    """(M,) float32 metres of each candidate's trajectory within ``flown_horizon``."""
    points_world: np.ndarray
    """(M, LABEL_POINTS, 3) float32 world-frame points along the same stretch, where the label is read."""


LABEL_POINTS = 48
"""Points along a candidate's judged stretch where its recorded label reads the world."""
RECORD_SAMPLES = 16
"""Points per candidate recorded for a model without a flown-path head."""


@dataclass
class _Attempt:
    """One network pass toward a goal, timed and executed (minimum snap, or iPlanner's spline)."""

    kp: np.ndarray
    eta: float
    timing: Timing
    allocation_ms: float
    traj: Trajectory | None = None
    check: _Checker | None = None
    blocked: bool = False
    out: PlannerOutput | None = None
    end_speed: float = 0.0


class LearnedMethod:
    """The network's key-points with a chosen time allocation (``tan`` is the deployed planner), or
    with iPlanner's cubic-spline interpolation (``spline=True``)."""

    needs_depth = True
    replans = True

    def __init__(self, name: str, net: PlannerNet, *, allocation: Allocation = "tan", spline: bool = False,
                 camera: CameraInput | None = None, execution: Execution = _FULL_STACK,
                 keypoints: KeypointSource = "network") -> None:
        self.name = name
        self.keypoint_source = keypoints
        self.camera = camera
        self.net = net.eval()
        self.allocation = allocation
        self.spline = spline
        self.config = net.config
        self.execution = execution
        self._timing_config = _at_speed(net.config, execution.speed.cruise)
        self._search = _Search()
        self.plan_log: list[PlanInput] | None = None
        self.judge_log: list[JudgeInput] | None = None
        self._subgoal: tuple[np.ndarray, float] | None = None  # (world point, until)
        self._flight: tuple[np.ndarray, float] | None = None  # (goal, time) of the last plan
        self._image: tuple[Observation, ImageFeatures] | None = None  # the last frame's encoding
        self._memory = None if execution.memory is None else _Memory(execution.memory.seconds)
        self._cam = camera  # the camera of the frame being planned (Observation.camera, else ``camera``)
        self._route = None if execution.route is None or self._memory is None else FlightMap(execution.route)
        self._progress = Progress()
        self._chosen: int | None = None  # the candidate the last plan of this flight flew
        self._recent: list[tuple[float, torch.Tensor]] = []  # (t, world points) of this flight's frames, for the head
        self.record_history: float | None = None

    def _keypoints(self, obs: Observation, start: np.ndarray, goal: np.ndarray, end_speed: float = 0.0):
        """The network's pass toward ``goal``; a second pass on the same frame reuses its image encoding."""
        if self.keypoint_source == "straight":
            return self._straight_keypoints(obs, goal)
        with torch.inference_mode():
            image = self._image[1] if self._image is not None and self._image[0] is obs else None
            if image is None:
                x = self.net.preprocess(torch.from_numpy(np.asarray(obs.depth, dtype=np.float32)[None]))
            else:
                x = image.x
            g = torch.from_numpy(np.asarray(goal, dtype=np.float32)[None])
            v = torch.from_numpy(np.asarray(start[1], dtype=np.float32)[None])
            out = self.net(x, g, camera=self._cam, velocity=v, image=image, widen=self.execution.widen,
                           shift=self.execution.shift)
            self._image = None if out.image is None else (obs, out.image)
            out = self._flown_judged(x, out, obs, start, end_speed)
            return x, self._kept(out)

    def _flown_judged(self, x: torch.Tensor, out: PlannerOutput, obs: Observation, start: np.ndarray,
                      end_speed: float) -> PlannerOutput:
        """``out`` judged by the net's flown-path head and/or recorded for ``--record-judge``."""
        net = self.net
        head = net.flown_mlp is not None and self.execution.flown_judge
        # iPlanner-style flies a spline, not the corridor's trajectory: it keeps the judge's η
        if (not head and self.judge_log is None) or out.candidates is None or self.spline:
            return out
        if self._cam is None:
            raise PlannerError("the flown-path judge reads the depth image: the flight needs the camera's calibration")
        flown = self._flown_trajectories(out.candidates[0], start, end_speed)
        history = self.config.flown_history
        record = history if self.record_history is None else self.record_history
        self._remember_frame(x, obs, max(history, record if self.judge_log is not None else 0.0))
        if self.judge_log is not None:
            self.judge_log.append(self._judge_input(flown, x, obs, self._recent_points(obs, record)))
        return net.judge_flown(out, flown, x, self._cam, recent=self._recent_points(obs, history)) if head else out

    def _remember_frame(self, x: torch.Tensor, obs: Observation, seconds: float) -> None:
        """Keep the frame's world points among this flight's recent ones for ``seconds``."""
        from mapkit.planner import input_points

        assert self._cam is not None  # checked by _flown_judged
        self._recent = [(t, p) for t, p in self._recent if obs.t - t <= seconds + 1e-6]
        if seconds <= 0 or (self._recent and self._recent[-1][0] == obs.t):
            return
        body = input_points(x, self._cam, max_depth=self.config.max_depth)[0].double()
        body = body[body[:, 0] < 1e5]  # pixels without a return
        T = torch.from_numpy(obs.T_world_body)
        self._recent.append((obs.t, body @ T[:3, :3].T + T[:3, 3]))

    def _recent_points(self, obs: Observation, seconds: float) -> torch.Tensor | None:
        """(1, P, 3) body-frame points of this flight's frames of the last ``seconds``, or None."""
        earlier = [p for t, p in self._recent if 0 < obs.t - t <= seconds + 1e-6]
        if not earlier:
            return None
        T = torch.from_numpy(obs.T_world_body)
        return ((torch.cat(earlier) - T[:3, 3]) @ T[:3, :3])[None]

    def _flown_trajectories(self, candidates: torch.Tensor, start: np.ndarray, end_speed: float) -> Trajectory:
        """Every candidate (M, K, 3) timed like a plan in the unchecked corridor (no speed limits)."""
        M = candidates.shape[0]
        wp = torch.cat([torch.from_numpy(start[:1]).expand(M, 1, 3), candidates.double()], dim=1)
        st = torch.from_numpy(np.ascontiguousarray(start[1:])).expand(M, 3, 3)
        es = torch.full((M,), float(end_speed), dtype=torch.float64)
        width = self.execution.corridor.widest(False)
        timing = self._timed(wp, st, es)
        return min_snap(wp, timing.durations, start=st, end=timing.end, corridor=width, on_infeasible="ignore")

    def _judge_input(self, flown: Trajectory, x: torch.Tensor, obs: Observation,
                     recent: torch.Tensor | None) -> JudgeInput:
        """What the flown-path head reads about the candidates ``flown``, and their stretches in the world."""
        from mapkit.planner import arclength_points, flown_features

        c = self.config
        assert self._cam is not None  # checked by _flown_judged
        points, lengths = arclength_points(flown, horizon=c.flown_horizon, count=c.flown_samples or RECORD_SAMPLES)
        features = flown_features(points[None], x, self._cam, max_depth=c.max_depth, recent=recent)[0]
        dense, _ = arclength_points(flown, horizon=c.flown_horizon, count=LABEL_POINTS)
        R, p = obs.T_world_body[:3, :3], obs.T_world_body[:3, 3]
        return JudgeInput(features=features.numpy().astype(np.float32), lengths=lengths.numpy().astype(np.float32),
                          points_world=(dense.numpy() @ R.T + p).astype(np.float32))

    def _kept(self, out: PlannerOutput) -> PlannerOutput:
        """``out`` choosing the last plan's candidate while accepted and within ``keep_choice`` of the best."""
        margin, prev = self.execution.keep_choice, self._chosen
        if (margin is None or prev is None or out.scores is None or out.candidates is None
                or out.candidate_eta_logits is None or out.chosen is None or prev >= out.candidates.shape[1]):
            return out
        best = int(out.chosen[0])
        if (best == prev or float(out.candidate_eta_logits[0, prev]) >= 0.0
                or float(out.scores[0, prev]) < float(out.scores[0, best]) - margin):
            return out
        logit = out.candidate_eta_logits[:, prev]
        return replace(out, keypoints=out.candidates[:, prev], eta=torch.sigmoid(logit), eta_logit=logit,
                       chosen=torch.full_like(out.chosen, prev))

    def _straight_keypoints(self, obs: Observation, goal: np.ndarray) -> tuple[torch.Tensor, PlannerOutput]:
        """The preprocessed depth and one candidate on the straight line to ``goal``, η = 0."""
        with torch.inference_mode():
            x = self.net.preprocess(torch.from_numpy(np.asarray(obs.depth, dtype=np.float32)[None]))
            line = self.net.straight_line(torch.from_numpy(np.asarray(goal, dtype=np.float32)[None]))
        logit = torch.full((1,), -30.0)
        return x, PlannerOutput(keypoints=line, eta=torch.sigmoid(logit), eta_logit=logit,
                                candidates=line[:, None], candidate_eta_logits=logit[:, None])

    def _timed(self, wp: torch.Tensor, start: torch.Tensor, end_speed: torch.Tensor) -> Timing:
        """Segment times of plans (B, K+1, 3) under the speed profile (:class:`SpeedProfile`)."""
        config, how = self._timing_config, self.execution.speed
        cruise = decel = None
        if how.turn_accel is not None:
            slowest = min(TURN_MIN_SPEED, config.cruise_speed)
            cruise = turn_speed(wp, how.turn_accel).clamp(slowest, config.cruise_speed)
            end_speed = torch.minimum(end_speed, cruise)
        if how.stop_decel is not None and not self._search.searching:
            decel = torch.where(end_speed > 0, config.accel, how.stop_decel).to(wp.dtype)
        return plan_timing(wp, start, end_speed, config, allocation=self.allocation, tan=self.net.tan,
                           cruise_speed=cruise, decel=decel)

    def _attempt(self, obs: Observation, start: np.ndarray, goal: np.ndarray, end_speed: float) -> _Attempt:
        """Key-points to ``goal`` (body frame), timed, moved toward the reference and executed."""
        x, out = self._keypoints(obs, start, goal, end_speed)
        kp = out.keypoints[0].double().numpy()
        wp = np.concatenate([start[:1], kp])
        wpt, st, es = _tensors(wp, start, end_speed)
        t_alloc = time.perf_counter()
        with torch.inference_mode():
            timing = self._timed(wpt, st, es)
        attempt = _Attempt(kp, float(out.eta[0]), timing, 1e3 * (time.perf_counter() - t_alloc))
        if self.plan_log is not None:
            self.plan_log.append(PlanInput(waypoints=wp, start=np.array(start[1:]), end_speed=float(timing.end[0, 0].norm()),
                                           cruise_speed=float(timing.cruise_speed[0]), decel=float(timing.decel[0])))
        attempt.out, attempt.end_speed = out, end_speed
        if self.spline:
            attempt.traj = _spline_trajectory(wp, start, timing)
            return attempt
        how = self.execution
        if self._cam is not None and how.corridor.check:
            recall = None
            if how.corridor.check_memory and self._memory is not None and how.memory is not None:
                recall = (self._memory, obs.T_world_body, how.memory.blocked_within)
            attempt.check = _Checker(x, self._cam, self.config.max_depth, out.pyramid, recall)
        width = how.corridor.widest(attempt.check is not None)
        if width is not None:
            wpt = follow_reference(wpt, timing.durations, obs, how.follow, width)
        with torch.inference_mode():
            attempt.traj = _execute(wpt, timing.durations, st, timing.end, how, attempt.check)
        return attempt

    def _remembered(self, obs: Observation, start: np.ndarray, attempt: _Attempt) -> _Attempt:
        """The plan if it keeps clear of the memory, else the best-scored clear candidate, else ``blocked``."""
        memory, how = self._memory, self.execution
        assert memory is not None and how.memory is not None  # called only with a memory
        within = how.memory.blocked_within
        T = obs.T_world_body
        if attempt.traj is None or memory.conflicts(_samples(attempt.traj, within=within)[0], T)[0] == 0:
            return attempt
        out = attempt.out
        # a network pass: a model with a memory judges several candidates
        assert out is not None and out.candidates is not None and out.candidate_eta_logits is not None
        M = out.candidates.shape[1]
        wp = torch.cat([torch.from_numpy(start[:1]).expand(M, 1, 3), out.candidates[0].double()], dim=1)
        st = torch.from_numpy(np.ascontiguousarray(start[1:]))[None].expand(M, 3, 3)
        es = torch.full((M,), attempt.end_speed, dtype=torch.float64)
        with torch.inference_mode():
            timing = self._timed(wp, st, es)
            paths = min_snap(wp, timing.durations, start=st, end=timing.end)
        clear = memory.conflicts(_samples(paths, within=within)[0], T) == 0
        if not clear.any():
            attempt.blocked = True
            return attempt
        scores = out.scores[0].numpy() if out.scores is not None else np.zeros(M)
        m = int(np.argmax(np.where(clear, scores, -np.inf)))
        with torch.inference_mode():
            if self.spline:
                traj = _spline_trajectory(wp[m].numpy(), start, _pick(timing, m))
            else:
                traj = _execute(wp[m:m + 1], timing.durations[m:m + 1], st[:1], timing.end[m:m + 1], how, attempt.check)
        eta = float(torch.sigmoid(out.candidate_eta_logits[0, m]))
        return _Attempt(out.candidates[0, m].double().numpy(), eta, _pick(timing, m), attempt.allocation_ms,
                        traj, attempt.check, False, out, attempt.end_speed)

    def _subgoal_in_force(self, obs: Observation) -> np.ndarray | None:
        """The way-out point (world) still being flown to, if any; a new flight starts over first."""
        if self._flight is None or obs.t <= self._flight[1] or not np.array_equal(self._flight[0], obs.goal_world):
            self._subgoal = None
            self._chosen = None
            self._progress = Progress()
            self._search = _Search()
            self._recent = []
            if self._memory is not None:
                self._memory.forget()
            if self._route is not None:
                self._route.forget()
        self._flight = (np.array(obs.goal_world), obs.t)
        if self._subgoal is not None:
            point, until = self._subgoal
            if obs.t > until or np.linalg.norm(point - obs.T_world_body[:3, 3]) < 1.0:
                self._subgoal = None
        return None if self._subgoal is None else self._subgoal[0]

    def _aim(self, obs: Observation, points: np.ndarray | None, wanted: bool) -> np.ndarray | None:
        """The flight map's aim point (world) when ``wanted`` and stalled; the map is updated either way."""
        if self._route is None or points is None:
            return None
        p = obs.T_world_body[:3, 3]
        self._route.add(points, p)
        stalled = self._progress.update(obs.t, float(np.linalg.norm(np.asarray(obs.goal_world) - p)), self._route.config)
        self._search.searching = self._search.searching or stalled
        aim = self._route.aim(p, np.asarray(obs.goal_world)) if stalled and wanted else None
        if aim is None:
            return None
        # the height that passes the route's next closed column; else halfway to the local goal's height
        z = p[2] + 0.5 * float(obs.local_goal_body[2]) if aim.height is None else aim.height
        return np.array([aim.xy[0], aim.xy[1], z])

    def _speed_config(self, obs: Observation) -> PlannerConfig:
        """The planner config at the profile's cruise speed, or the model's own once searching."""
        how = self.execution.speed
        p = obs.T_world_body[:3, 3]
        searching = self._search.update(p, float(np.linalg.norm(np.asarray(obs.goal_world) - p)),
                                        how.search_ratio, how.search_margin)
        return _at_speed(self.config, None if searching else how.cruise)

    def plan(self, obs: Observation) -> MethodPlan:
        t0 = time.perf_counter()
        self._cam = self.camera if obs.camera is None else obs.camera
        start = obs.start_body()
        sub = self._subgoal_in_force(obs)
        points = None if self._memory is None or self._cam is None else self._memory.points(obs, self._cam)
        aim = self._aim(obs, points, sub is None)
        self._timing_config = self._speed_config(obs)
        goal_body = np.asarray(obs.local_goal_body, dtype=np.float64)
        end_speed = self._timing_config.cruise_speed if obs.goal_clipped else 0.0
        if aim is not None:
            goal_body = obs.T_world_body[:3, :3].T @ (aim - obs.T_world_body[:3, 3])
            end_speed = self._timing_config.cruise_speed
        if sub is None:
            attempt = self._attempt(obs, start, goal_body, end_speed)
        else:
            attempt = self._attempt(obs, start, obs.T_world_body[:3, :3].T @ (sub - obs.T_world_body[:3, 3]),
                                    self._timing_config.cruise_speed)
        if self._memory is not None and points is not None:  # the memory needs the camera
            self._memory.add_points(obs.t, points)
            attempt = self._remembered(obs, start, attempt)
            if attempt.blocked and sub is None and self._cam is not None:
                body = open_direction(np.asarray(obs.depth), self._cam, goal_body, self.config.max_depth)
                if body is not None:
                    point = obs.T_world_body[:3, :3] @ body + obs.T_world_body[:3, 3]
                    assert self.execution.memory is not None  # a memory found it blocked
                    self._subgoal = (point, obs.t + self.execution.memory.subgoal_time)
                    attempt = self._remembered(obs, start, self._attempt(obs, start, body, self._timing_config.cruise_speed))
        assert attempt.traj is not None  # every attempt is executed (a spline, or minimum snap)
        self._chosen = _candidate_index(attempt)
        # the trajectory's own durations: a spline's knots follow its chords, a plan slowed to keep the limits
        durations = attempt.traj.durations[0].numpy()
        coeffs = attempt.traj.coeffs[0].numpy()
        overrides = False
        if attempt.eta >= 0.5 and attempt.check is not None and obs.reference is not None:
            with torch.inference_mode():
                overrides = _reference_no_safer(obs, attempt.traj, attempt.check)
        brake = side = None
        if attempt.blocked and self._memory is not None:
            brake = self._memory.clearest(obs.T_world_body, start)
            side = self._memory.open_side(obs.T_world_body)
        latency = 1e3 * (time.perf_counter() - t0)
        pieces = pieces_from_body(coeffs, durations, obs.T_world_body, obs.t)
        kp_world = attempt.kp @ obs.T_world_body[:3, :3].T + obs.T_world_body[:3, 3]
        return MethodPlan(pieces=pieces, latency_ms=latency, eta=attempt.eta, keypoints_world=kp_world,
                          allocation_ms=None if self.spline else attempt.allocation_ms, overrides_eta=overrides,
                          within_limits=self.spline or _within(attempt.traj, self.execution.speed),
                          blocked=attempt.blocked, brake_direction=brake, turn_side=side, look_at=aim,
                          candidate=self._chosen)


def _candidate_index(attempt: _Attempt) -> int | None:
    """Which of the network's candidates ``attempt`` flies (None: no candidates, or none of them)."""
    out = attempt.out
    if out is None or out.candidates is None:
        return None
    gaps = (out.candidates[0].double() - torch.from_numpy(attempt.kp)[None]).abs().amax(dim=(1, 2))
    m = int(gaps.argmin())
    return m if float(gaps[m]) < 1e-6 else None


def _spline_trajectory(wp: np.ndarray, start: np.ndarray, timing: Timing) -> Trajectory:
    """iPlanner's reference: :func:`_clamped_spline` through ``wp`` (K+1, 3) as a batch-of-one trajectory."""
    coeffs, durations = _clamped_spline(wp, start[1], timing.end[0, 0].numpy(), float(timing.total[0]))
    return Trajectory(torch.from_numpy(coeffs)[None], torch.from_numpy(durations)[None])


def _clamped_spline(wp: np.ndarray, v0: np.ndarray, v1: np.ndarray, total: float) -> tuple[np.ndarray, np.ndarray]:
    """Cubic spline through ``wp`` (N, 3) at constant chord speed over ``total`` s, end velocities ``v0``,
    ``v1`` → (M, 3, 4) normalised-time coefficients and (M,) durations."""
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

