"""The pilot: a stateful receding-horizon planner for any vehicle loop (docs/flight.md)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from mapkit._choices import FlightStack
from mapkit.flight._camera import check_intrinsics, frame_camera, planning_frame, rigid
from mapkit.flight._config import PilotConfig, VehicleState, finite_vector
from mapkit.flight._errors import FlightError
from mapkit.flight._layers import Execution, under_stack
from mapkit.flight._pieces import Pieces, hold
from mapkit.flight._plan import Method, MethodPlan, Observation, level_pose
from mapkit.flight._recorded import RunCamera
from mapkit.flight._reference import YAW_TAIL, Reference, YawFollower
from mapkit.planner import CameraInput
from mapkit.trajopt import min_snap

Status = Literal["cruising", "braking", "blocked", "reached"]
"""``cruising``: flying a plan toward the goal. ``braking``: braking to rest (no way ahead, a stale or
inconsistent input). ``blocked``: at rest with no plan accepted, turning to look elsewhere (or waiting
for frames). ``reached``: within ``goal_radius`` of the goal; the pilot no longer replans."""
STATUSES: tuple[Status, ...] = ("cruising", "braking", "blocked", "reached")
BRAKE_PEAK = 1.3
"""A brake's acceleration peaks at no more than this times its ``brake_deceleration``."""
FACE_MIN_DISTANCE = 0.3
"""Metres: a vehicle at rest this close (horizontally) to what it would face keeps its heading (a goal
at the vehicle, "stay here", has no direction)."""
LOOK_DONE_DEG = 15.0
"""Degrees: a hovering vehicle turns to look elsewhere again once it faces this close to its last aim."""


@dataclass
class PilotStep:
    """The pilot's answer to one call."""

    reference: Reference
    """The reference to fly from now on."""
    status: Status
    """What the vehicle is doing (:data:`Status`)."""
    reason: str
    """One line saying why."""
    replanned: bool = False
    """A plan was made in this call."""
    taken: bool = False
    """... and it is flown (not vetoed, not blocked)."""
    eta: float | None = None
    """The plan's collision probability (None: no plan, or the planner has none)."""
    candidate: int | None = None
    """Which of the network's candidates the plan flies (None: no plan, or none of them)."""
    latency_ms: float = 0.0
    """Wall-clock time of this call."""
    plan: MethodPlan | None = None
    """The planner's whole answer when it planned."""


@dataclass
class _Frame:
    """One depth frame, checked, with the level frame the network plans in."""

    depth: np.ndarray
    T_world_plan: np.ndarray
    camera: CameraInput | None
    offset: float  # metres from the frame's position to the vehicle's state


class Pilot:
    """A trained planner and its flight stack, flown frame by frame.

    >>> pilot = Pilot.load("pretrained")                                       # doctest: +SKIP
    >>> step = pilot.step(t, state, goal_world, depth, K=K, T_world_camera=T)  # doctest: +SKIP
    >>> setpoint = step.reference.sample(t_now)                               # doctest: +SKIP

    Plans start from the reference's own state at the takeover, so every new reference is C³ with the
    last at the switch.
    """

    def __init__(self, planner: Method, *, camera: RunCamera | None = None, config: PilotConfig | None = None) -> None:
        self.config = config or PilotConfig()
        self.config.validate()
        self.planner = planner
        self.camera = camera
        """The camera the model was trained with: the default K and T_body_camera of frames."""
        self.reset()

    @classmethod
    def load(cls, model: str | Path = "pretrained", *, stack: FlightStack | Execution = "full",
             config: PilotConfig | None = None) -> Pilot:
        """The pilot of a trained model (``"pretrained"``: the shipped one; or a run directory) under
        ``stack``: ``"full"`` (every layer), ``"none"`` (the network alone through a narrow corridor, the
        paper's protocol) or an :class:`Execution` with layers of your own. It plans on the CPU."""
        from mapkit.flight._learned import LearnedMethod
        from mapkit.flight._recorded import load_network

        net, cam = load_network(model)
        net = net.prepare_inference()  # a frozen encoder for single images: ~2 ms faster a plan
        execution = stack if isinstance(stack, Execution) else under_stack(Execution(), stack)
        camera = None if cam is None else CameraInput.from_calibration(cam.K, cam.width, cam.height, cam.T_body_camera)
        return cls(LearnedMethod("learned", net, camera=camera, execution=execution), camera=cam, config=config)

    def reset(self) -> None:
        """Forget the flight: the next call starts a new one (from the vehicle's state)."""
        self._ref: Reference | None = None
        self._goal: np.ndarray | None = None
        self._stamp: float | None = None
        self._started = 0.0  # the flight's first stamp
        self._last_frame: float | None = None
        self._seen_depth = False  # a frame with a valid pixel arrived in this flight
        self._last_plan: float | None = None
        self._status: Status = "blocked"
        self._reason = "no frame yet"
        self._braking = False
        self._look = 0.0
        self._turn = 1.0
        self._look_at: np.ndarray | None = None

    @property
    def reference(self) -> Reference | None:
        """The reference being flown (None before the first call)."""
        return self._ref

    def step(self, stamp: float, state: VehicleState, goal_world: np.ndarray, depth: np.ndarray | None = None, *,
             K: np.ndarray | None = None, T_world_camera: np.ndarray | None = None,
             T_world_body: np.ndarray | None = None, T_body_camera: np.ndarray | None = None) -> PilotStep:
        """One call per camera frame (or without ``depth``, between frames, to learn that frames stopped).

        Args:
            stamp: seconds, never decreasing (the reference's times are on this clock).
            state: the vehicle's estimate now, world frame.
            goal_world: (3,) metres, world frame; a new goal starts a new flight.
            depth: (H, W) float metres along the optical axis, NaN (or 0, inf) invalid.
            K: (3, 3) pixels of this image (default: the model's recorded camera, for its image size).
            T_world_camera: (4, 4) optical camera → world at this frame; or give ``T_world_body`` (the
                body's pose at this frame, any attitude) and ``T_body_camera`` (default: the recorded mount).
        """
        t0 = time.perf_counter()
        stamp = self._check_stamp(stamp)
        goal = finite_vector(goal_world, "goal_world")
        if self._goal is None or not np.array_equal(goal, self._goal):
            self._new_flight(goal)
        if self._ref is None:  # the first call: from the vehicle's own state
            self._started = stamp
            self._ref = self._with_yaw(self._from_state(state, stamp), stamp, state.yaw, 0.0)
        self._resync(stamp, state)
        out = self._decide(stamp, state, goal, depth, K, T_world_camera, T_world_body, T_body_camera)
        out.latency_ms = 1e3 * (time.perf_counter() - t0)
        self._status, self._reason = out.status, out.reason
        return out

    def stop(self, stamp: float, reason: str) -> PilotStep:
        """Brake to rest from the reference, then hold (``braking``, then ``blocked``): for an input the
        caller lost, such as odometry. The next :meth:`step` goes on from there."""
        if self._ref is None:
            raise FlightError("stop() before the first step(): there is no reference to brake from")
        out = self._brake_for(self._check_stamp(stamp), reason)
        self._status, self._reason = out.status, out.reason
        return out

    def _decide(self, stamp: float, state: VehicleState, goal: np.ndarray, depth: np.ndarray | None,
                K: np.ndarray | None, T_world_camera: np.ndarray | None, T_world_body: np.ndarray | None,
                T_body_camera: np.ndarray | None) -> PilotStep:
        """Hold at the goal, brake for a stale or inconsistent input, keep the reference, or plan."""
        c = self.config
        if float(np.linalg.norm(goal - state.position)) <= c.goal_radius:
            return self._answer("reached", f"within {c.goal_radius} m of the goal")
        frame = None
        image = None if depth is None else _depth(depth, empty_ok=self._seen_depth)
        if image is not None:
            frame = self._frame(image, K, T_world_camera, T_world_body, T_body_camera, state)
            self._last_frame = stamp
            self._seen_depth = True
        elif self.planner.needs_depth:  # no frame, or one that sees nothing within range mid-flight
            return self._without_frame(stamp)
        if frame is not None and frame.offset > c.pose_tolerance:
            return self._brake_for(stamp, f"the frame's pose is {frame.offset:.2f} m from the vehicle's state "
                                          f"(pose_tolerance {c.pose_tolerance} m): braking")
        if self._last_plan is not None and (stamp - self._last_plan < c.replan_interval - 1e-6
                                            or not self.planner.replans):
            return self._answer(self._status, self._reason)
        if frame is None:
            T = level_pose(state.position, state.yaw) if T_world_body is None else rigid(T_world_body, "T_world_body")
            frame = _Frame(np.zeros((0, 0)), planning_frame(state.position, T, T), None, 0.0)
        return self._plan(stamp, goal, frame, image is not None)

    def _check_stamp(self, stamp: float) -> float:
        stamp = float(stamp)
        if not math.isfinite(stamp):
            raise FlightError(f"stamp {stamp} is not finite: pass seconds on one clock")
        if self._stamp is not None and stamp < self._stamp:
            raise FlightError(f"stamp {stamp} s is before the last call's {self._stamp} s: stamps must never go "
                              "backwards (call reset() to start a new flight on a new clock)")
        self._stamp = stamp
        return stamp

    def _new_flight(self, goal: np.ndarray) -> None:
        """A new goal starts a new flight; the reference being flown is kept."""
        ref, stamp, seen = self._ref, self._stamp, self._seen_depth
        self.reset()
        self._ref, self._stamp, self._goal, self._seen_depth = ref, stamp, goal, seen
        self._started = 0.0 if stamp is None else stamp

    def _from_state(self, state: VehicleState, stamp: float) -> Pieces:
        """Hold where the vehicle hovers, else brake to rest from its position and velocity."""
        if float(np.linalg.norm(state.velocity)) < 0.05:
            return hold(state.position, stamp)
        return brake(state.derivatives() * [[1.0], [1.0], [0.0], [0.0]], stamp, self.config.brake_deceleration)

    def _resync(self, stamp: float, state: VehicleState) -> None:
        """A vehicle far from its reference brakes from its own state."""
        assert self._ref is not None  # set by step
        gap = float(np.linalg.norm(self._ref.derivative(stamp, 0)[0] - state.position))
        if gap > self.config.resync_distance:
            self._ref = self._with_yaw(self._from_state(state, stamp), stamp, state.yaw, 0.0)
            self._braking = True

    def _frame(self, depth: np.ndarray, K: np.ndarray | None, T_world_camera: np.ndarray | None,
               T_world_body: np.ndarray | None, T_body_camera: np.ndarray | None, state: VehicleState) -> _Frame:
        """The checked frame (:class:`FlightError` names the first bad input and its fix)."""
        image = depth  # checked by _depth
        height, width = image.shape
        rec = self.camera
        if K is None:
            if rec is None or (rec.height, rec.width) != (height, width):
                raise FlightError(f"depth is {width}x{height} and no K was given: pass the image's K (3x3 pixels)"
                                  + ("" if rec is None else f"; the model's recorded camera is {rec.width}x{rec.height}"))
            K = rec.K
        K = check_intrinsics(K, width, height, rec)
        body = None if T_world_body is None else rigid(T_world_body, "T_world_body")
        if T_world_camera is not None:
            T_wc = rigid(T_world_camera, "T_world_camera")
        elif body is not None:
            mount = T_body_camera if T_body_camera is not None else (None if rec is None else rec.T_body_camera)
            if mount is None:
                raise FlightError("T_world_body was given without T_body_camera, and the model records no camera "
                                  "mount: pass T_body_camera (optical camera → body FLU)")
            T_wc = body @ rigid(mount, "T_body_camera")
        else:
            raise FlightError("a frame needs the camera's pose: pass T_world_camera, or T_world_body (with "
                              "T_body_camera unless the model's recorded mount is right)")
        position = state.position if body is None else body[:3, 3]
        offset = float(np.linalg.norm((T_wc[:3, 3] if body is None else body[:3, 3]) - state.position))
        T_world_plan = planning_frame(position, T_wc, body)
        return _Frame(image, T_world_plan, frame_camera(K, width, height, T_world_plan, T_wc), offset)

    def _without_frame(self, stamp: float) -> PilotStep:
        """A call without a usable frame: brake once usable frames have stopped for ``frame_timeout``."""
        quiet = stamp - (self._last_frame if self._last_frame is not None else self._started)
        if quiet <= self.config.frame_timeout:
            return self._answer(self._status, self._reason)
        return self._brake_for(stamp, f"no depth frame with a valid pixel for {quiet:.2f} s (frame_timeout "
                                      f"{self.config.frame_timeout} s): braking to rest and holding")

    def _brake_for(self, stamp: float, reason: str) -> PilotStep:
        """Brake to rest from the reference's state (once), then hold."""
        assert self._ref is not None  # set by step
        if not self._braking:
            self._braking = True
            self._adopt(brake(self._ref.state(stamp), stamp, self.config.brake_deceleration), stamp)
        return self._answer("braking" if stamp < self._ref.t_end else "blocked", reason)

    def _plan(self, stamp: float, goal: np.ndarray, frame: _Frame, with_depth: bool) -> PilotStep:
        """Plan from the reference's state at the takeover, and take the plan or react to its rejection."""
        assert self._ref is not None  # set by step
        c = self.config
        self._last_plan = stamp
        T = frame.T_world_plan
        t_take = stamp + c.plan_latency
        to_goal = goal - T[:3, 3]
        g_body = T[:3, :3].T @ to_goal
        n = float(np.linalg.norm(g_body))
        local = g_body * min(1.0, c.horizon / n) if n > 0 else g_body
        obs = Observation(t=t_take, T_world_body=T, state_world=self._ref.state(t_take), goal_world=goal,
                          local_goal_body=local, depth=frame.depth if with_depth else None, goal_clipped=n > c.horizon,
                          reference=self._ref.pieces, camera=frame.camera)
        return self._react(stamp, obs, self.planner.plan(obs))

    def _react(self, stamp: float, obs: Observation, mp: MethodPlan) -> PilotStep:
        """Take the plan, or keep the reference, brake, or turn to look elsewhere when it is rejected."""
        assert self._ref is not None  # set by step
        c = self.config
        self._look_at = mp.look_at
        vetoed = mp.eta is not None and mp.eta >= 0.5 and not mp.overrides_eta
        if not (vetoed or mp.blocked or not mp.within_limits):
            self._braking = False
            self._look = 0.0
            self._adopt(mp.pieces, stamp)
            return self._answer("cruising", "flying the new plan", taken=True, plan=mp)
        why = ("no way ahead" if mp.blocked else f"plan vetoed (η = {mp.eta:.2f})" if vetoed
               else "the plan breaks the speed or acceleration limits")
        if self._at_rest(stamp):  # a new look around, the way the planner asks
            if self._look == 0.0 and mp.turn_side:
                self._turn = float(np.sign(mp.turn_side))
            if self._faces_aim(stamp):
                self._look += self._turn * math.radians(c.look_turn_deg)
            self._adopt(self._ref.pieces, stamp)
            return self._answer("blocked", f"{why}: hovering, turning {c.look_turn_deg:.0f}° to look elsewhere", plan=mp)
        if mp.blocked and not self._braking:
            self._braking = True
            direction = None if mp.brake_direction is None else obs.T_world_body[:3, :3] @ mp.brake_direction
            self._adopt(brake(self._ref.state(stamp), stamp, c.brake_deceleration, direction), stamp)
        if self._braking:
            return self._answer("braking", f"{why}: braking to rest", plan=mp)
        return self._answer("cruising", f"{why}: flying the last plan", plan=mp)

    def _at_rest(self, stamp: float) -> bool:
        """True when the reference stays at rest from ``stamp`` on (it has ended, or only holds)."""
        assert self._ref is not None  # set by step
        if stamp >= self._ref.t_end - 1e-9:
            return True
        t = np.linspace(stamp, self._ref.t_end, 16)
        return float(np.abs(self._ref.derivative(t, 1)).max()) < 1e-3

    def _faces_aim(self, stamp: float) -> bool:
        """True when the hovering reference faces within :data:`LOOK_DONE_DEG` of its last look turn's aim."""
        assert self._ref is not None and self._goal is not None  # set by step
        facing = self._look_at if self._look_at is not None else self._goal
        to = facing - self._ref.derivative(stamp, 0)[0]
        gap = float(self._ref.yaw(stamp)[0]) - (math.atan2(to[1], to[0]) + self._look)
        return abs((gap + math.pi) % (2 * math.pi) - math.pi) < math.radians(LOOK_DONE_DEG)

    def _adopt(self, pieces: Pieces, stamp: float) -> None:
        """Fly ``pieces`` from its start (the reference until then), the yaw profile recomputed from now."""
        assert self._ref is not None  # set by step
        spliced = pieces if pieces is self._ref.pieces else self._ref.pieces.splice(pieces, stamp)
        self._ref = self._with_yaw(spliced, stamp, float(self._ref.yaw(stamp)[0]), float(self._ref.yaw_rate(stamp)[0]))

    def _with_yaw(self, pieces: Pieces, stamp: float, yaw_now: float, rate_now: float) -> Reference:
        """``pieces`` with a yaw profile from ``yaw_now``, ``rate_now`` at ``stamp``: along the way ahead while
        moving, else toward the point of interest (or the goal) plus the look-around turn."""
        c = self.config
        facing = self._look_at if self._look_at is not None else self._goal
        assert facing is not None  # the goal is set by step
        look, L = self._look, c.look_ahead

        def target(t: np.ndarray) -> np.ndarray:
            p, v = pieces.derivative(t, 0), pieces.derivative(t, 1)
            moving = np.hypot(v[:, 0], v[:, 1]) > 0.5
            ahead = pieces.derivative(np.minimum(t + L, pieces.t_end), 0) - p if L > 0 else v
            far = np.hypot(ahead[:, 0], ahead[:, 1]) > 0.3
            heading = np.where(far, np.arctan2(ahead[:, 1], ahead[:, 0]), np.arctan2(v[:, 1], v[:, 0]))
            to = facing - p
            here = np.hypot(to[:, 0], to[:, 1]) < FACE_MIN_DISTANCE  # no direction to face: keep the heading
            at_rest = np.where(here, yaw_now, np.arctan2(to[:, 1], to[:, 0]) + look)
            return np.where(moving, heading, at_rest)

        until = max(stamp, pieces.t_end) + YAW_TAIL
        return Reference(pieces, YawFollower(target, stamp, yaw_now, rate_now, c.max_yaw_rate, c.max_yaw_accel, until))

    def _answer(self, status: Status, reason: str, *, taken: bool = False, plan: MethodPlan | None = None) -> PilotStep:
        """This call's answer: the reference now, and the plan made (if one was)."""
        assert self._ref is not None  # set by step
        return PilotStep(reference=self._ref, status=status, reason=reason, replanned=plan is not None, taken=taken,
                         eta=None if plan is None else plan.eta, candidate=None if plan is None else plan.candidate,
                         plan=plan)


def _depth(depth: np.ndarray, *, empty_ok: bool) -> np.ndarray | None:
    """The depth image checked: 2-D float metres with a valid pixel; without one, None when ``empty_ok``."""
    image = np.asarray(depth)
    if image.ndim != 2 or min(image.shape) < 2:
        raise FlightError(f"depth must be one (H, W) image, got shape {image.shape}")
    if not np.issubdtype(image.dtype, np.floating):
        raise FlightError(f"depth has dtype {image.dtype}; pass float metres (16UC1 millimetres: "
                          "depth.astype(np.float32) / 1000 with 0 set to NaN)")
    if not np.any(np.isfinite(image) & (image > 0)):
        if empty_ok:
            return None
        raise FlightError("depth has no valid pixel (all NaN, 0 or inf): skip the frame, or check the camera's "
                          "encoding and units")
    return image


def brake(state_world: np.ndarray, t0: float, deceleration: float, direction: np.ndarray | None = None) -> Pieces:
    """One minimum-snap segment from ``state_world`` (4, 3: position … jerk) to rest v² / a metres along
    its velocity (or ``direction``, a world unit vector) over max(0.5, 2 v / a) s, longer while its
    acceleration would peak above :data:`BRAKE_PEAK` × ``deceleration``."""
    speed = float(np.linalg.norm(state_world[1]))
    way = state_world[1] if direction is None else speed * np.asarray(direction, dtype=np.float64)
    allowed = max(BRAKE_PEAK * deceleration, float(np.linalg.norm(state_world[2])))
    T = max(0.5, 2.0 * speed / deceleration)
    for _ in range(8):
        pieces = _segment(state_world, state_world[0] + 0.5 * T * way, T, t0)
        peak = float(np.linalg.norm(pieces.derivative(t0 + np.linspace(0.0, T, 65), 2), axis=1).max())
        if peak <= allowed * (1 + 1e-6):
            break
        T *= max(1.1, math.sqrt(peak / allowed))
    return pieces


def _segment(state_world: np.ndarray, end: np.ndarray, T: float, t0: float) -> Pieces:
    """One world-frame minimum-snap segment from ``state_world`` to rest at ``end`` over ``T`` seconds."""
    wp = torch.from_numpy(np.stack([state_world[0], end]))[None]
    with torch.no_grad():
        traj = min_snap(wp, torch.tensor([[T]], dtype=torch.float64),
                        start=torch.from_numpy(np.ascontiguousarray(state_world[1:]))[None])
    return Pieces(t0=float(t0), durations=np.array([T]), coeffs=traj.coeffs[0].numpy())
