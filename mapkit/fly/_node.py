"""`mapkit fly`: the pilot live on a robot's ROS 2 graph.

Three threads: Cyclone's, which hands each message to a callback that only checks and stores it; the
planner's, which calls :meth:`Pilot.step` for the newest depth frame (and between frames, so the pilot
notices frames stopping); the stream's, which samples the reference at the setpoint rate and publishes
it. The pilot's clock is this machine's (seconds since the epoch, as ROS time); a message's header stamp
is used where it agrees with the receive time within ``max_stamp_skew``.

Safety: no setpoint before odometry; until a goal, a hold where the vehicle was first seen; a goal
outside the geofence is refused; depth lost → the pilot brakes and holds; odometry lost → braking from
the reference, then holding. After a plan's end the reference holds its end at rest.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapkit.errors import MapkitError
from mapkit.flight import Pilot, PilotStep, Reference, VehicleState
from mapkit.fly import _inputs, _outputs
from mapkit.fly._config import DEPTH_TYPES, ODOMETRY_TYPES, FlyConfig
from mapkit.fly._dds import Link
from mapkit.fly._inputs import DepthFrame, Odometry
from mapkit.fly._stream import SetpointStream, StreamedReference
from mapkit.geometry import interpolate_transform, matrix_from_quat_xyzw, quat_xyzw_from_matrix
from mapkit.ingest._decode import tf_samples
from mapkit.ingest._tf import NoPose, TfTree

log = logging.getLogger("mapkit.fly")
LOG_INTERVAL = 5.0
"""Seconds between two log lines of one kind (a bad stream logs once, then a count)."""
IDLE_STEP = 0.1
"""Seconds between the planner's calls without a frame (the pilot notices frames stopping)."""
JUMP_SPEED = 10.0
"""m/s: odometry that moves faster than this between two messages has jumped (see FlyNode._jumped)."""
ODOMETRY_HISTORY = 2.0
"""Seconds of odometry kept to find the body's pose at a frame's stamp."""
LEAD_QUANTILE, LEAD_MARGIN = 0.5, 0.003
"""A plan leads the node's clock by this quantile of the last plans' hand-over times plus this many
seconds: about half take over at their time, the others as they arrive, a few ms later (a median 9 ms
in the office on 2 cores). That moves the setpoints too little to matter: at a takeover position is
continuous to jerk and yaw to its rate, so 10 ms late moves the acceleration by ~0.01 m/s² and the
yaw rate by ≤ 0.1 rad/s. A later quantile would delay every plan to spare a few of them that."""
LEAD_HISTORY, LEAD_MIN_PLANS = 20, 5
"""Hand-over times kept, and how many before they replace ``FlyConfig.plan_lead``."""


class RateLimitedLog:
    """One warning per kind every :data:`LOG_INTERVAL` seconds, with how many were held back."""

    def __init__(self) -> None:
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def warn(self, kind: str, text: str) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + 1
        now = time.monotonic()
        if now - self._last.get(kind, -LOG_INTERVAL) < LOG_INTERVAL:
            self._held[kind] = self._held.get(kind, 0) + 1
            return
        held = self._held.pop(kind, 0)
        self._last[kind] = now
        log.warning("%s%s", text, f" ({held} more like it since the last line)" if held else "")


@dataclass(frozen=True)
class TimedStep:
    """One frame flown, with when (time.perf_counter()) each stage of it happened."""

    received: float
    """The depth message arrived."""
    called: float
    """The pilot was called with it."""
    handed: float
    """The pilot's answer was handed to the setpoint stream."""
    takeover: float
    """The answer takes over: the later of the time it was made for and ``handed``."""
    step: PilotStep


@dataclass
class _Pending:
    msg: Any
    received_ns: int
    received_perf: float
    """time.perf_counter() at arrival (for latency)."""


class FlyNode:
    """The pilot on DDS: subscribes to depth, camera info, odometry, tf and goals; publishes setpoints,
    the plan's path and the status. :meth:`start`, then :meth:`close` (Ctrl-C)."""

    def __init__(self, pilot: Pilot, config: FlyConfig, link: Link) -> None:
        config.validate()
        self.pilot, self.config, self.link = pilot, config, link
        self.log = RateLimitedLog()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._running = False
        self._threads: list[threading.Thread] = []
        self._frame: _Pending | None = None
        self._odometry: deque[Odometry] = deque()
        self._K: np.ndarray | None = None
        self._tf = TfTree()
        self._goal: np.ndarray | None = None
        self._jump = False
        self._origin: np.ndarray | None = None  # the first odometry: the geofence's centre
        self._reference: Reference | None = None
        ctx = mp.get_context("spawn")
        self._sim_ns = ctx.Value("q", 0, lock=False)  # shared with the stream process
        self._t0_ns = ctx.Value("q", -1, lock=False)  # the pilot's clock starts at the first time it is read
        self._stream: SetpointStream | None = None
        self._last_frame_ns: int | None = None
        self._state = {"state": "waiting", "reason": "no odometry yet"}
        self.frames_dropped = 0
        self.late_plans = 0
        """References handed to the stream after the time they were made for (the setpoints moved on to
        them there)."""
        self.late_by: deque[float] = deque(maxlen=1000)
        """Seconds each late reference arrived after its time."""
        self._handovers: deque[float] = deque(maxlen=LEAD_HISTORY)
        self._last_t = -np.inf  # the last time a step was made for (the pilot's stamps never go back)
        self.steps: deque[TimedStep] = deque(maxlen=1000)
        """The last frames flown, each with its timing."""

    # -- wiring ---------------------------------------------------------------------------------------------
    def start(self) -> None:
        """Subscribe, make the publishers, and start the planner and the setpoint stream."""
        t, c = self.config.topics, self.config
        sensor = t.sensor_qos
        on_error = self._on_error
        self.link.reader(t.depth, DEPTH_TYPES[t.depth_type], self._on_depth, qos=sensor, on_error=on_error)
        self.link.reader(t.camera_info, "sensor_msgs/msg/CameraInfo", self._on_info, qos=sensor, on_error=on_error)
        self.link.reader(t.odometry_topic, ODOMETRY_TYPES[t.odometry_type], self._on_odometry, qos=sensor,
                         on_error=on_error)
        self.link.reader(t.tf, "tf2_msgs/msg/TFMessage", self._on_tf, qos="reliable", on_error=on_error)
        self.link.reader(t.tf_static, "tf2_msgs/msg/TFMessage", self._on_tf_static, qos="latched", on_error=on_error)
        self.link.reader(t.goal, "geometry_msgs/msg/PoseStamped", self._on_goal, qos="reliable", on_error=on_error)
        if c.sim_time:
            self.link.reader(t.clock, "rosgraph_msgs/msg/Clock", self._on_clock, qos="reliable", on_error=on_error)
        self._publish_path = self.link.writer(t.path, "nav_msgs/msg/Path")
        self._publish_status = self.link.writer(t.status, "std_msgs/msg/String")
        if not c.dry_run:
            self._stream = SetpointStream(c, self._sim_ns, self._t0_ns)
        self._running = True
        thread = threading.Thread(target=self._plan_loop, name="mapkit-fly-planner", daemon=True)
        thread.start()
        self._threads.append(thread)

    def close(self) -> None:
        """Stop the planner and the setpoint stream (PX4 leaves offboard on its own failsafe)."""
        self._running = False
        self._wake.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
        self._threads.clear()
        if self._stream is not None:
            self._stream.close()

    @property
    def setpoint_times(self) -> list[float]:
        """time.perf_counter() of each setpoint the stream published (known once it is closed)."""
        return [] if self._stream is None else self._stream.times

    @property
    def stream_priority(self) -> str:
        """What the setpoint stream ran at: ``real time``, ``nice`` or ``default`` (known once it is closed)."""
        return "" if self._stream is None else self._stream.priority

    @property
    def status(self) -> dict[str, Any]:
        """What the node is doing, as published on the status topic."""
        with self._lock:
            out: dict[str, Any] = dict(self._state)
            now = self.now_ns()
            out["goal"] = None if self._goal is None else [round(float(v), 3) for v in self._goal]
            out["odometry_age"] = None if not self._odometry else round((now - self._odometry[-1].stamp_ns) * 1e-9, 3)
            out["depth_age"] = None if self._last_frame_ns is None else round((now - self._last_frame_ns) * 1e-9, 3)
        out["dry_run"] = self.config.dry_run
        out["frames_dropped"] = self.frames_dropped
        out["late_plans"] = self.late_plans
        out["problems"] = dict(self.log.counts)
        return out

    @property
    def plan_lead(self) -> float:
        """Seconds ahead of the node's clock the next plan is made for: ``FlyConfig.plan_lead`` at first,
        then the median (:data:`LEAD_QUANTILE`) of the last plans' hand-over times (the pilot's step and the send to the
        stream) plus :data:`LEAD_MARGIN`, at most half the pilot's replan interval."""
        if len(self._handovers) < LEAD_MIN_PLANS:
            return self.config.plan_lead
        lead = float(np.quantile(np.asarray(self._handovers), LEAD_QUANTILE)) + LEAD_MARGIN
        return min(lead, 0.5 * self.pilot.config.replan_interval)

    def _set_state(self, state: str, reason: str, **extra: Any) -> None:
        with self._lock:
            self._state = {"state": state, "reason": reason, **extra}

    def now_ns(self) -> int:
        """This node's clock: the machine's (ROS time), or the simulator's /clock with ``sim_time``."""
        return int(self._sim_ns.value) if self.config.sim_time else time.time_ns()

    def set_goal(self, goal: np.ndarray) -> str:
        """Fly to `goal` (world frame) if it is inside the geofence; returns why not ('' when taken)."""
        refusal = self._outside_fence(goal)
        if refusal:
            log.warning("goal %s refused: %s", np.round(goal, 2).tolist(), refusal)
            with self._lock:
                self._state = {**self._state, "refused_goal": np.round(goal, 3).tolist(), "refused_because": refusal}
            return refusal
        log.info("goal %s accepted", np.round(goal, 2).tolist())
        with self._lock:
            self._goal = np.asarray(goal, dtype=np.float64)
        self._wake.set()
        return ""

    # -- inputs (Cyclone's thread) -----------------------------------------------------------------------------
    def _on_clock(self, msg: Any, received_ns: int) -> None:
        self._sim_ns.value = max(self._sim_ns.value, int(msg.clock.sec) * 1_000_000_000 + int(msg.clock.nanosec))

    def _on_error(self, topic: str, exc: Exception) -> None:
        self.log.warn(f"bad message on {topic}", f"{topic}: {exc}")

    def _on_depth(self, msg: Any, received_ns: int) -> None:
        received_ns = self.now_ns()
        if received_ns == 0:
            return  # no simulator time yet
        with self._lock:
            if self._frame is not None:
                self.frames_dropped += 1  # the planner was busy: only the newest frame counts
            self._frame = _Pending(msg, received_ns, time.perf_counter())
        self._wake.set()

    def _on_info(self, msg: Any, received_ns: int) -> None:
        K, _, _ = _inputs.intrinsics(msg, self.config.topics.camera_info)
        with self._lock:
            self._K = K

    def _on_odometry(self, msg: Any, received_ns: int) -> None:
        received_ns, c = self.now_ns(), self.config
        if received_ns == 0:
            return  # no simulator time yet
        if c.topics.odometry_type == "px4":
            odo = _inputs.px4_odometry(msg, received_ns)
        else:
            odo = _inputs.nav_odometry(msg, c.frames.world)
            stamp, agrees = _inputs.stamp_of(odo.stamp_ns, received_ns, c.max_stamp_skew)
            if not agrees:
                self.log.warn("odometry clock", f"odometry stamps are {(odo.stamp_ns - received_ns) * 1e-9:+.2f} s "
                              "from this machine's clock; using receive times (synchronise the clocks)")
                odo = Odometry(stamp, odo.R_world_body, odo.position, odo.velocity)
        with self._lock:
            if self._odometry and odo.stamp_ns <= self._odometry[-1].stamp_ns:
                return  # reordered or repeated: the newer one is already here
            if self._odometry and self._jumped(self._odometry[-1], odo):
                self._odometry.clear()
                self._goal, self._jump = None, True
            self._odometry.append(odo)
            while odo.stamp_ns - self._odometry[0].stamp_ns > ODOMETRY_HISTORY * 1e9:
                self._odometry.popleft()
            if self._origin is None:
                self._origin = odo.position.copy()

    def _jumped(self, last: Odometry, odo: Odometry) -> bool:
        """True when odometry moved farther than any flight could between two messages (an estimator
        reset, a vehicle carried): the goal is dropped, and the node holds until it is sent again."""
        gap = float(np.linalg.norm(odo.position - last.position))
        dt = (odo.stamp_ns - last.stamp_ns) * 1e-9
        if gap <= self.pilot.config.resync_distance + 2 * JUMP_SPEED * dt:
            return False
        log.warning("odometry jumped %.2f m in %.3f s: goal dropped, holding here; send the goal again", gap, dt)
        return True

    def _on_tf(self, msg: Any, received_ns: int, static: bool = False) -> None:
        with self._lock:
            for stamp, parent, child, translation, q in tf_samples(msg):
                if static:
                    T = np.eye(4)
                    T[:3, :3] = matrix_from_quat_xyzw(q)
                    T[:3, 3] = translation
                    self._tf.set_static(parent, child, T)
                else:
                    self._tf.add_dynamic(parent, child, stamp, translation, q, "tf")

    def _on_tf_static(self, msg: Any, received_ns: int) -> None:
        self._on_tf(msg, received_ns, static=True)

    def _on_goal(self, msg: Any, received_ns: int) -> None:
        self.set_goal(_inputs.goal_position(msg, self.config.frames.world))

    def _outside_fence(self, goal: np.ndarray) -> str:
        """Why `goal` is outside the geofence ('' inside)."""
        c = self.config
        with self._lock:
            origin = self._origin
        if origin is None:
            return "no odometry yet: the geofence is centred on the first odometry"
        horizontal = float(np.hypot(*(goal - origin)[:2]))
        if horizontal > c.fence_radius:
            return f"{horizontal:.1f} m from the start, beyond the fence radius {c.fence_radius} m"
        if abs(goal[2] - origin[2]) > c.fence_height:
            return f"{goal[2] - origin[2]:+.1f} m from the start's height, beyond ±{c.fence_height} m"
        return ""

    # -- the planner ------------------------------------------------------------------------------------------
    def _seconds(self, stamp_ns: int) -> float:
        """The pilot's clock: seconds since the node was made (small numbers keep polynomial times exact)."""
        if self._t0_ns.value < 0:
            self._t0_ns.value = stamp_ns
        return (stamp_ns - self._t0_ns.value) * 1e-9

    def _plan_loop(self) -> None:
        last_status = 0.0
        while self._running:
            self._wake.wait(IDLE_STEP)
            self._wake.clear()
            if not self._running:
                break
            try:
                self._plan_once()
            except MapkitError as exc:  # an input the pilot refuses: logged, the next frame may do
                self.log.warn(f"pilot: {type(exc).__name__}", f"frame not flown: {exc}")
            except Exception:  # a bug must not end the planner silently: logged, and the status says so
                log.exception("the planner failed on this frame")
                self._set_state("error", "the planner failed on a frame (see the log); braking from the reference")
            if time.monotonic() - last_status >= 0.2:
                last_status = time.monotonic()
                self._publish_status(_outputs.status(self.status))

    def _plan_once(self) -> None:
        c = self.config
        now_ns = self.now_ns()
        with self._lock:
            pending, self._frame = self._frame, None
            goal, K = self._goal, self._K
            odo = self._odometry[-1] if self._odometry else None
        if now_ns == 0:
            return self._set_state("waiting", f"no simulator time yet on {c.topics.clock}")
        if odo is None:
            return self._set_state("waiting", f"no odometry yet on {c.topics.odometry_topic}")
        now = self._seconds(now_ns)
        plan_t = self._last_t = max(now + self.plan_lead, self._last_t)  # taken over once the stream has it
        call = (time.perf_counter(), plan_t - now)
        if self._jump:
            self._jump = False
            self.pilot.reset()
            with self._lock:
                self._reference = None
        if goal is None:
            self._hold_here(odo, now)
            return self._set_state("holding", f"waiting for a goal on {c.topics.goal}")
        age = (now_ns - odo.stamp_ns) * 1e-9
        if age > c.odometry_timeout:
            if self.pilot.reference is None:
                return self._set_state("waiting", f"no odometry for {age:.2f} s")
            return self._adopt(self.pilot.stop(plan_t, f"no odometry for {age:.2f} s (odometry_timeout "
                                                       f"{c.odometry_timeout} s): braking, then holding"), plan_t, None,
                               call)
        state = VehicleState(position=odo.position, velocity=odo.velocity, yaw=odo.yaw)
        inputs = None if pending is None else self._frame_inputs(pending)
        if inputs is None:
            return self._adopt(self.pilot.step(plan_t, state, goal), plan_t, None, call)
        depth, T_world_body, T_body_camera = inputs
        step = self.pilot.step(plan_t, state, goal, depth, K=K, T_world_body=T_world_body,
                               T_body_camera=T_body_camera)
        self._adopt(step, plan_t, pending, call)

    def _hold_here(self, odo: Odometry, now: float) -> None:
        """Before a goal: hold where the vehicle is (again, when it is moved farther than the pilot's
        ``resync_distance`` from the hold: carried, or another pilot flew it)."""
        with self._lock:
            ref = self._reference
            far = ref is None or float(np.linalg.norm(ref.derivative(now, 0)[0] - odo.position)) > \
                self.pilot.config.resync_distance
            if far:
                self._reference = Reference.holding(odo.position, odo.yaw, now)
        if far:
            self._send(self._reference, now)

    def _send(self, reference: Reference | None, start: float) -> None:
        """Hand the stream process the reference to fly from ``start`` on (the node's clock)."""
        if self._stream is not None and reference is not None:
            self._stream.send(StreamedReference.of(reference, start))

    def _adopt(self, step: PilotStep, start: float, frame: _Pending | None, call: tuple[float, float]) -> None:
        """Fly the pilot's answer, made for ``start`` (the node's clock plus :attr:`plan_lead`); ``call`` is
        time.perf_counter() when the pilot was called, and how far ahead of the clock ``start`` was."""
        with self._lock:
            changed = step.reference is not self._reference
            self._reference = step.reference
            self._state = {"state": step.status, "reason": step.reason}
        if changed:
            self._send(step.reference, start)
            late = self._seconds(self.now_ns()) - start
            if late > 0:
                self.late_plans += 1
                self.late_by.append(late)
        handed = time.perf_counter()
        if step.replanned:
            self._handovers.append(handed - call[0])
        if frame is not None:
            self.steps.append(TimedStep(frame.received_perf, call[0], handed, max(handed, call[0] + call[1]), step))
        if changed:
            self._publish_path(_outputs.path(step.reference, start, self.now_ns(), self.config.frames.world))

    def _frame_inputs(self, pending: _Pending) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(depth, T_world_body, T_body_camera) of a depth message; None (logged) when it cannot be flown."""
        c = self.config
        try:
            frame = _inputs.depth_frame(pending.msg, DEPTH_TYPES[c.topics.depth_type], c.topics.depth)
        except MapkitError as exc:
            self.log.warn("depth message", str(exc))
            return None
        stamp_ns, agrees = _inputs.stamp_of(frame.stamp_ns, pending.received_ns, c.max_stamp_skew)
        if not agrees:
            self.log.warn("depth clock", f"depth stamps are {(frame.stamp_ns - pending.received_ns) * 1e-9:+.2f} s "
                          "from this machine's clock; using receive times (synchronise the clocks)")
        self._last_frame_ns = pending.received_ns
        T_world_body = self._body_at(stamp_ns)
        if T_world_body is None:
            self.log.warn("no pose", "a depth frame has no odometry at its stamp (odometry late or stopped): skipped")
            return None
        T_body_camera = self._mount(frame, stamp_ns)
        return None if T_body_camera is None else (frame.depth, T_world_body, T_body_camera)

    def _body_at(self, stamp_ns: int) -> np.ndarray | None:
        """The body's pose at `stamp_ns` from the odometry history (interpolated; the newest if the frame
        is newer by less than the odometry timeout)."""
        with self._lock:
            history = list(self._odometry)
        if not history or stamp_ns < history[0].stamp_ns:
            return None
        after = next((i for i, o in enumerate(history) if o.stamp_ns >= stamp_ns), None)
        if after is None:
            late = (stamp_ns - history[-1].stamp_ns) * 1e-9
            return history[-1].T_world_body if late <= self.config.odometry_timeout else None
        b = history[after]
        if after == 0 or b.stamp_ns == stamp_ns:
            return b.T_world_body
        a = history[after - 1]
        s = (stamp_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
        return interpolate_transform(a.position, quat_xyzw_from_matrix(a.R_world_body), b.position,
                                     quat_xyzw_from_matrix(b.R_world_body), s)

    def _mount(self, frame: DepthFrame, stamp_ns: int) -> np.ndarray | None:
        """T_body_camera from tf (body frame → the image's optical frame); None (logged) when they do not connect."""
        body = self.config.frames.body
        try:
            with self._lock:
                return self._tf.lookup(body, frame.frame_id, stamp_ns, max_gap_ns=int(0.5e9))
        except (MapkitError, NoPose) as exc:
            self.log.warn("tf", f"no transform from {body!r} to the depth frame {frame.frame_id!r} ({exc}); "
                          "publish the camera mount on /tf_static")
            return None
