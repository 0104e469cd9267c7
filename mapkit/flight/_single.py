"""A trained planner ready to use: `Planner.load(run_dir)` and `mapkit plan` from a recorded frame."""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from mapkit._choices import CANDIDATE_SHIFTS
from mapkit.flight._errors import FlightError
from mapkit.flight._recorded import RUN_CONFIG, RunCamera, load_network
from mapkit.geometry import quat_xyzw_from_matrix

if TYPE_CHECKING:
    from mapkit.flight._pilot import Pilot, PilotStep


@dataclass
class PlanResult:
    """One plan, body frame at planning time unless named otherwise."""

    keypoints: np.ndarray
    """(K, 3) metres."""
    eta: float
    """Collision probability; the plan is not to be executed when eta >= 0.5."""
    durations: np.ndarray
    """(K,) seconds per segment."""
    samples_t: np.ndarray
    """(N,) seconds."""
    samples_body: np.ndarray
    """(N, 3) trajectory positions."""
    control_effort: float
    """∫‖snap‖² dt, m²/s⁷."""
    latency_ms: float
    """Depth → trajectory, wall clock."""
    goal_body: np.ndarray
    """(3,) the goal planned to: the one asked for, or the local goal on its way (``goal_clipped``)."""
    widened: bool = False
    """True when the chosen candidate is a widened one (:data:`WIDEN`)."""
    shifted: bool = False
    """True when the chosen candidate is a shifted one (:data:`SHIFT`)."""
    goal_clipped: bool = False
    """True when the goal asked for lay beyond :data:`LOCAL_GOAL_RANGE` and the plan went that far toward it."""
    camera_from_run: bool = False
    """True when the depth image was checked with the camera the run recorded (no ``K`` / ``T_body_camera``)."""

    @property
    def execute(self) -> bool:
        return self.eta < 0.5

    @property
    def variant(self) -> str | None:
        """``"widened"``, ``"shifted"``, ``"widened and shifted"`` or None (a trained candidate)."""
        names = [name for name, on in (("widened", self.widened), ("shifted", self.shifted)) if on]
        return " and ".join(names) or None


LOCAL_GOAL_RANGE = 6.0
"""Metres: the farthest goal a plan goes to directly (``mapkit eval``'s local-goal horizon)."""


WIDEN = (1.5, 2.5)
"""Factors of the widened candidates a single plan adds (:meth:`PlannerNet.widened`): each trained
candidate's detour from the straight line scaled, judged and chosen among like the trained ones
(docs/results.md). ``mapkit eval``'s closed loop does not widen."""


SHIFT = CANDIDATE_SHIFTS
"""Sideways shifts (metres at the middle of the path, left positive) of the shifted candidates a plan
adds (:meth:`PlannerNet.shifted`): every candidate, trained or widened, also moved by each, judged and
chosen among like the trained ones (docs/results.md)."""


class Planner:
    """A trained PlannerNet with its config, on a device, in inference mode. A process that plans many
    frames on the CPU calls ``planner.net.prepare_inference()`` once: a frozen encoder, ~2 ms faster."""

    def __init__(self, net: Any, device: torch.device, *, camera: RunCamera | None = None) -> None:
        self.net = net.eval().to(device)
        self.device = device
        self.camera = camera
        """The depth camera the run recorded, used when :meth:`plan` is given no calibration (None: none)."""
        self._said_camera = False
        self._cpu_net: Any = None  # the network the single-shot pilot flies (a CPU copy when on a GPU)

    @property
    def needs_camera(self) -> bool:
        """True when the model needs the camera's calibration to plan (``depth_check``)."""
        c = self.net.config
        return bool(c.depth_check and c.num_candidates > 1)

    @classmethod
    def load(cls, run_dir: str | Path, *, device: str = "cpu") -> Planner:
        """Load runs/NAME/model.pt (state dict + planner config; nothing pickled but tensors);
        ``run_dir="pretrained"`` loads the model shipped with mapkit."""

        if device.startswith("cuda") and not torch.cuda.is_available():
            raise FlightError(f"--device {device}: torch sees no CUDA device; use --device cpu")
        try:
            net, camera = load_network(run_dir)
        except FlightError as exc:
            raise FlightError(str(exc)) from None
        return cls(net, torch.device(device), camera=camera)

    def plan(self, depth: np.ndarray, goal_body: np.ndarray, *, velocity_body: np.ndarray | None = None,
             rate_hz: float = 50.0, corridor: float | None = None, K: np.ndarray | None = None,
             T_body_camera: np.ndarray | None = None, widen: tuple[float, ...] = WIDEN,
             shift: tuple[float, ...] = SHIFT) -> PlanResult:
        """Depth (H, W) metres (NaN invalid) + goal (3,) body frame [+ velocity (3,)] → PlanResult, in the
        body frame of the frame: the pilot's single-shot use (one frame under the full flight stack).

        `corridor`: widest half-width (m) of the flight corridor (None: the stack's, :class:`Corridor`).
        `K` (3, 3) and `T_body_camera` (4, 4) (optical camera → body): the depth camera's calibration;
        without them the run's recorded camera is used (a warning, :attr:`PlanResult.camera_from_run`)
        and depth must have its size. Another field of view is refused (docs/flight.md).
        `widen`, `shift`: the widened and shifted candidates (:data:`WIDEN`, :data:`SHIFT`; () none)."""
        from mapkit.flight._config import VehicleState

        asked = np.asarray(goal_body, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(asked)):
            raise FlightError(f"goal {asked.tolist()} is not finite")
        vel = np.zeros(3) if velocity_body is None else np.asarray(velocity_body, np.float64).reshape(3)
        K, T_body_camera, from_run = self._calibration(np.asarray(depth).shape, K, T_body_camera)
        pilot = self._single_shot(widen, shift, corridor)
        try:
            step = pilot.step(0.0, VehicleState(np.zeros(3), vel), asked, np.asarray(depth), K=K,
                              T_world_body=np.eye(4), T_body_camera=T_body_camera)
        except FlightError as exc:
            raise FlightError(str(exc)) from None
        return _result(step, asked, rate_hz, from_run, self.net.config.num_candidates, len(widen))

    def _single_shot(self, widen: tuple[float, ...], shift: tuple[float, ...], corridor: float | None) -> Pilot:
        """A pilot of this network (on the CPU) for one frame, whose body frame is its world."""
        import copy
        from dataclasses import replace

        from mapkit.flight._config import PilotConfig
        from mapkit.flight._layers import Corridor, Execution
        from mapkit.flight._learned import LearnedMethod
        from mapkit.flight._pilot import Pilot
        from mapkit.planner import CameraInput

        stack = Execution(widen=widen, shift=shift)
        if corridor is not None:
            stack = replace(stack, corridor=Corridor(width=corridor))
        cam = self.camera
        camera = None if cam is None else CameraInput.from_calibration(cam.K, cam.width, cam.height, cam.T_body_camera)
        config = PilotConfig(horizon=LOCAL_GOAL_RANGE, goal_radius=1e-3, plan_latency=0.0)  # from the frame itself
        if self._cpu_net is None:
            self._cpu_net = self.net if self.device.type == "cpu" else copy.deepcopy(self.net).cpu()
        return Pilot(LearnedMethod("learned", self._cpu_net, camera=camera, execution=stack), camera=cam, config=config)

    def _calibration(self, shape: tuple[int, ...], K: np.ndarray | None, T_body_camera: np.ndarray | None
                     ) -> tuple[np.ndarray | None, np.ndarray | None, bool]:
        """(K, T_body_camera, from the run's camera) for a depth image of `shape`: those given, else the
        run's for a model that needs them; raises when there are none (or the size differs)."""
        if (K is not None and T_body_camera is not None) or not self.needs_camera:
            return K, T_body_camera, False
        fix = "pass the camera's K and T_body_camera"
        if K is not None or T_body_camera is not None:
            raise FlightError(f"this model checks its paths against the depth image: {fix} (both, or neither "
                                "to use the camera its run recorded)")
        cam = self.camera
        if cam is None:
            raise FlightError(f"this model checks its paths against the depth image: {fix} (its run records no "
                                f"camera to use instead: no `camera` in its {RUN_CONFIG})")
        if tuple(shape[-2:]) != (cam.height, cam.width):
            raise FlightError(f"depth is {shape[-1]}x{shape[-2]} pixels but the camera this model's run recorded "
                                f"({_source_name(cam.source)}) is {cam.width}x{cam.height}: {fix}")
        if not self._said_camera:
            self._said_camera = True
            warnings.warn(f"no K / T_body_camera given: checking the depth image with the camera the model's run "
                          f"recorded ({cam.width}x{cam.height}, from {_source_name(cam.source)}); pass K and "
                          "T_body_camera for another camera", stacklevel=3)
        return cam.K, cam.T_body_camera, True


def _source_name(source: str) -> str:
    """Where a run read its camera as messages show it: the last two parts (the training machine's path)."""
    parts = PurePath(source).parts[-2:]
    return "/".join(parts) if parts else f"the run's {RUN_CONFIG}"


def check_output_folder(out_dir: Path) -> None:
    """Raise :class:`FlightError` when ``out_dir`` (or a parent) is an existing file."""
    for path in (out_dir, *out_dir.parents):
        if path.exists() and not path.is_dir():
            raise FlightError(f"-o {out_dir}: {path} is a file; -o takes a folder (the plan is written as "
                                "plan_NNNNNN.json, .tum and .mcap inside it)")


def write_plan_outputs(result: PlanResult, T_world_body: np.ndarray, stamp_ns: int, out_dir: Path, *,
                       world_frame: str = "world", stem: str = "plan") -> list[Path]:
    """plan.json, plan.tum (t x y z qx qy qz qw, world frame) and plan.mcap (nav_msgs/Path)."""
    from mapkit.bags import BagRecorder

    check_output_folder(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    R, p0 = T_world_body[:3, :3], T_world_body[:3, 3]
    world = result.samples_body @ R.T + p0
    q = quat_xyzw_from_matrix(R)  # the body's attitude at planning time (the planner plans positions)
    # int64 nanoseconds end to end: epoch seconds in a float lose the nanoseconds (float32: whole minutes)
    t_ns = int(stamp_ns) + np.round(np.asarray(result.samples_t, dtype=np.float64) * 1e9).astype(np.int64)
    json_path = out_dir / f"{stem}.json"
    json_path.write_text(json.dumps({
        "frame": world_frame, "stamp_ns": int(stamp_ns), "eta": result.eta, "execute": result.execute,
        "keypoints_body": result.keypoints.tolist(), "durations": result.durations.tolist(),
        "control_effort_m2_s7": result.control_effort, "latency_ms": result.latency_ms,
        "t": np.asarray(result.samples_t, dtype=np.float64).tolist(), "stamps_ns": t_ns.tolist(),
        "goal_body": result.goal_body.tolist(), "goal_clipped": result.goal_clipped,
        "positions_world": world.tolist(),
    }, indent=1))
    tum_path = out_dir / f"{stem}.tum"
    tum_path.write_text("".join(f"{t // 10**9}.{t % 10**9:09d} {x:.6f} {y:.6f} {z:.6f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n"
                                for t, (x, y, z) in zip(t_ns.tolist(), world, strict=True)))
    mcap_path = out_dir / f"{stem}.mcap"
    with BagRecorder(mcap_path, "mcap", overwrite=True) as bag:
        Path_ = bag.typestore.types["nav_msgs/msg/Path"]
        PoseStamped = bag.typestore.types["geometry_msgs/msg/PoseStamped"]
        poses = []
        for t, pos in zip(t_ns.tolist(), world, strict=True):
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = pos
            poses.append(PoseStamped(header=bag.header(t, world_frame), pose=bag.pose_message(T)))
        bag.write_raw("/planner/path", "nav_msgs/msg/Path", Path_(header=bag.header(int(stamp_ns), world_frame), poses=poses), int(stamp_ns))
    return [json_path, tum_path, mcap_path]


def _result(step: PilotStep, asked: np.ndarray, rate_hz: float, from_run: bool, trained: int, widened: int) -> PlanResult:
    """The pilot's plan (in the body frame of the frame) as a :class:`PlanResult`, sampled at ``rate_hz``."""
    mp = step.plan
    assert mp is not None  # a single shot always plans
    pieces = mp.pieces
    total = float(pieces.durations.sum())
    t = np.linspace(0.0, total, max(2, int(total * rate_hz) + 1))  # float64: stamps are built from it
    distance = float(np.linalg.norm(asked))
    clipped = distance > LOCAL_GOAL_RANGE
    candidate = mp.candidate
    unshifted = trained * (1 + (widened if trained > 1 else 0))
    return PlanResult(
        keypoints=np.asarray(mp.keypoints_world, dtype=np.float32), eta=float(mp.eta if mp.eta is not None else 0.0),
        durations=pieces.durations.astype(np.float32), samples_t=t,
        samples_body=pieces.derivative(pieces.t0 + t, 0).astype(np.float32),
        control_effort=pieces.snap_effort(pieces.t0, pieces.t_end), latency_ms=step.latency_ms,
        goal_body=asked * (LOCAL_GOAL_RANGE / distance) if clipped else asked, goal_clipped=clipped,
        widened=candidate is not None and candidate % unshifted >= trained,
        shifted=candidate is not None and candidate >= unshifted, camera_from_run=from_run,
    )
