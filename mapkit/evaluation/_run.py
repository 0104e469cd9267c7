"""`mapkit eval`: every method on the same start–goal pairs in unseen simulated worlds."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import platform
import re
import sys
import threading
import uuid
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mapkit._choices import VEHICLES, FlightStack, VehicleKind
from mapkit._formats import EVAL_FORMAT, JUDGE_FILE, PLANS_FILE, EpisodeRecord
from mapkit._version import __version__
from mapkit.evaluation._ablation import Ablation, ablation
from mapkit.evaluation._loop import Episode, LoopConfig, check_interval, run_episode
from mapkit.evaluation._methods import METHODS, NEEDS_MODEL, make_methods
from mapkit.evaluation._pairs import EvalError, Pair, sample_pairs
from mapkit.evaluation._rotorpy import RotorpyVehicle
from mapkit.evaluation._stack import UNTRAINED_SEEDS, Run, check_stacks, plan_runs, split_label
from mapkit.flight import (
    Execution,
    FlightError,
    JudgeInput,
    LearnedMethod,
    Pilot,
    PlanInput,
    RouteConfig,
    under_stack,
)
from mapkit.flight._recorded import RunCamera
from mapkit.workspace import atomic_output, check_writable

if TYPE_CHECKING:
    from distributed import Client
    from tqdm import tqdm

    from mapkit._dask import ClusterInfo

log = logging.getLogger(__name__)

WORLD_ORDER = ("office", "garage", "forest")
"""The paper's table order; ``--world all`` runs these."""
PATH_RATE_HZ = 20.0
LOCAL_SCHEDULER = "local"
"""``EvalConfig.scheduler`` value that starts a Dask LocalCluster of ``workers`` processes here."""
DASK_RETRIES = 1
"""Dask re-runs a pair that raised once more (a model file briefly unreadable on shared storage)."""
_ADDRESS = re.compile(r"^([a-z][a-z0-9+]*://\S+|[^\s:/]+:\d+)$")


@dataclass
class EvalConfig:
    """What `mapkit eval` runs (every field ends up in results.json)."""

    worlds: tuple[str, ...] = WORLD_ORDER
    """World kinds, each generated with ``seed``."""
    pairs: int = 60
    """Start–goal pairs per world (the paper: 60)."""
    seed: int = 0
    """Seed of the worlds and the pairs; must differ from the seeds of the training worlds."""
    methods: tuple[str, ...] = METHODS
    """Methods to compare (see :data:`mapkit.evaluation.METHODS`)."""
    stacks: tuple[FlightStack, ...] = ("full",)
    """Flight stacks every learned method flies under (:func:`~mapkit.flight.under_stack`), each run
    labelled ``NAME@STACK`` under a stack other than ``full``; ``straight`` and ``oracle`` fly once."""
    min_distance: float = 8.0
    """Metres between start and goal, at least."""
    pair_clearance: float = 0.6
    """Metres from starts and goals to the nearest obstacle; also the oracle's search clearance."""
    oracle_corridor: float = 0.1
    """Half-width (m) of the oracle's flight corridor around its search path."""
    execution: Execution = field(default_factory=Execution)
    """How the learned allocations fly their key-points (corridor, speed and acceleration limits)."""
    workers: int = 1
    """Processes running pairs in parallel (with ``scheduler="local"``: the local Dask cluster's size; with a
    scheduler address it must stay 1). Results do not depend on it."""
    scheduler: str | None = None
    """None: ``workers`` processes here. A Dask scheduler address (``tcp://HOST:8786``): every pair is a task
    on that cluster (its workers read the model at the same path). ``"local"``: a Dask LocalCluster of
    ``workers`` processes here. Results do not depend on it."""
    loop: LoopConfig = field(default_factory=LoopConfig)
    """The closed loop (the pilot's options, goal radius, robot radius, time limit, tracker)."""
    vehicle: VehicleKind = "tracker"
    """What flies the references: the linear tracker (level body, exact and fast) or rotorpy's quadrotor
    under its SE(3) controller at 100 Hz (rotor dynamics and drag; the camera tilts with the airframe)."""
    gimbal: bool = False
    """With ``vehicle="rotorpy"``: render the camera level (on a gimbal) instead of at the airframe's attitude."""
    record_plans: bool = False
    """Also write plans.npz (:func:`write_plans`): the ``learned`` method's time allocation inputs, for
    ``mapkit lab tune-timing``. Results do not depend on it."""
    record_judge: bool = False
    """Also write judge.npz (:func:`write_judgements`): the ``learned`` method's candidates as a flown-path
    head reads them, labelled by collision, for ``mapkit lab tune-judge``. Results do not depend on it."""
    judge_history: float | None = None
    """With ``record_judge``: seconds of earlier frames the recorded clearances read; None: the model's
    ``flown_history``. Results do not depend on it."""

    def validate(self) -> None:
        """Raise :class:`EvalError` naming the first setting out of range."""
        unknown = [w for w in self.worlds if w not in WORLD_ORDER]
        if unknown or not self.worlds:
            raise EvalError(f"unknown world {unknown[0] if unknown else '(none)'!r}; "
                            f"use one of {', '.join(WORLD_ORDER)} or all")
        bad = [m for m in self.methods if m not in METHODS]
        if bad or not self.methods:
            raise EvalError(f"unknown method {bad[0] if bad else '(none)'!r}; use some of {', '.join(METHODS)}")
        check_stacks(self.stacks)
        if self.vehicle not in VEHICLES:
            raise EvalError(f"--vehicle {self.vehicle!r}: use one of {', '.join(VEHICLES)}")
        if self.gimbal and self.vehicle != "rotorpy":
            raise EvalError("gimbal levels the camera of the rotorpy quadrotor; the tracker's camera is always "
                            "level: pass --vehicle rotorpy too, or drop gimbal=true")
        if self.pairs < 1:
            raise EvalError(f"--pairs must be >= 1, got {self.pairs}")
        if self.workers < 1:
            raise EvalError(f"--workers must be >= 1, got {self.workers}")
        if self.judge_history is not None:
            if not self.record_judge:
                raise EvalError("judge_history sets what record_judge records; set record_judge too")
            if not (math.isfinite(self.judge_history) and self.judge_history >= 0):
                raise EvalError(f"judge_history must be >= 0 seconds, got {self.judge_history}")
        self._validate_scheduler()
        if not (math.isfinite(self.min_distance) and self.min_distance > 0):
            raise EvalError(f"min_distance must be > 0 metres, got {self.min_distance}")
        _validate_loop(self.loop)
        _validate_execution(self.execution)
        if not self.pair_clearance > self.loop.robot_radius:
            raise EvalError(f"pair clearance {self.pair_clearance} m must exceed the robot radius {self.loop.robot_radius} m")

    def _validate_scheduler(self) -> None:
        if self.scheduler is None or self.scheduler == LOCAL_SCHEDULER:
            return
        if not _ADDRESS.match(self.scheduler):
            raise EvalError(f"--scheduler {self.scheduler!r} is not a Dask scheduler address; use tcp://HOST:8786 "
                            f"(what `dask scheduler` prints) or {LOCAL_SCHEDULER} for a cluster on this machine")
        if self.workers != 1:
            raise EvalError(f"--workers {self.workers} does nothing with --scheduler {self.scheduler}: that cluster's "
                            f"workers run the pairs; drop --workers, or use --scheduler {LOCAL_SCHEDULER} --workers "
                            f"{self.workers}")


@dataclass
class CameraSpec:
    """The depth camera rendered in the loop: the training data's camera when it can be read."""

    width: int
    height: int
    K: list[list[float]]
    T_body_camera: list[list[float]]
    source: str


@dataclass
class EvalResult:
    """What :func:`evaluate` wrote and its summary."""

    out_dir: Path
    summary: dict[str, Any]
    files: list[Path]
    ablation: Ablation | None = None
    """Every run and learned against its untrained / straight-key-point twins (:func:`ablation`)."""


# ------------------------------------------------------------------------------------ set-up
def _sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _run_config(run_dir: Path) -> dict:
    path = run_dir / "config.json"
    if not path.exists():
        return {}
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise EvalError(f"{path} is not readable JSON ({exc}); is {run_dir} a mapkit run directory?") from None


def _training_camera(run_cfg: dict) -> CameraSpec | None:
    """The camera recorded in the run's config (``camera``), else that of the first readable training
    workspace's frames.zarr."""
    from mapkit.errors import MapkitError
    from mapkit.train import workspace_camera

    saved = run_cfg.get("camera")
    if isinstance(saved, dict):
        try:
            return CameraSpec(**saved)
        except TypeError as exc:  # another version's fields: read the workspaces instead
            log.info("the run's recorded camera does not fit this version (%s); reading its workspaces", exc)
    for ws in run_cfg.get("workspaces", []):
        try:
            return CameraSpec(**workspace_camera(ws))
        except (MapkitError, OSError):  # a moved or deleted workspace: try the next one
            continue
    return None


def _training_worlds(run_cfg: dict) -> set[tuple[str, int]]:
    """(kind, seed) of simulated worlds the run trained or validated on: recorded in its config, and
    found through its workspaces' recordings."""
    from mapkit.train import simulated_worlds

    out: set[tuple[str, int]] = {(str(k), int(s)) for k, s in run_cfg.get("training_worlds", [])}
    # A moved or deleted workspace (the shipped model's) is logged, not fatal; it can hide a training
    # world only from an older run that did not record them (a warning then).
    level = logging.DEBUG if "training_worlds" in run_cfg else logging.WARNING
    return out | simulated_worlds([*run_cfg.get("workspaces", []), *run_cfg.get("val_workspaces", [])],
                                  unreadable_level=level)


def _default_camera() -> CameraSpec:
    from mapkit.sim import CameraModel, camera_extrinsics

    cam = CameraModel(width=160, height=120)
    Tbl, Tlo = camera_extrinsics()
    return CameraSpec(width=160, height=120, K=cam.K.tolist(), T_body_camera=(Tbl @ Tlo).tolist(),
                      source="default: D435 scaled to 160x120 (training workspaces not readable)")


# --------------------------------------------------------------------------------- workers
@dataclass(frozen=True)
class _WorkerSetup:
    """What every worker process needs, sent once to each (picklable)."""

    model: str | None
    """Run directory of the model (absolute, or "pretrained": each worker's own shipped copy), None when
    no method needs one."""
    model_sha256: str | None
    """model.pt's hash where the evaluation started: a Dask worker refuses another file at that path."""
    camera: CameraSpec
    runs: tuple[Run, ...]
    """Every method under every stack (:func:`~mapkit.evaluation.plan_runs`)."""
    config: EvalConfig
    """The evaluation, its loop with the model's robot radius and cruise speed."""


@dataclass(frozen=True)
class _WorldBundle:
    """A world with what flying in it needs: the camera, its rays and the methods' pilots."""

    world: Any
    camera: Any
    rays: np.ndarray
    pilots: list[Pilot]
    """One pilot per run, each flying its method (the same object a user deploys)."""
    vehicle: RotorpyVehicle | None = None
    """rotorpy's quadrotor (``--vehicle rotorpy``), reset for every flight; None: the linear tracker."""


@dataclass(frozen=True)
class _WorkerState:
    """One process's set-up, its model and the worlds built so far (``worlds`` fills lazily)."""

    setup: _WorkerSetup
    net: Any
    untrained: dict[int, Any] = field(default_factory=dict)
    """Seed → the model's architecture at those initial weights (the ``untrained`` runs)."""
    worlds: dict[str, _WorldBundle] = field(default_factory=dict)


@dataclass
class _EpisodeRun:
    """One episode as a worker returns it: the results.json row and what goes elsewhere."""

    record: EpisodeRecord
    latencies_ms: list[float]
    """Wall-clock planning and time allocation latencies (latency.json)."""
    allocation_ms: list[float]
    path: np.ndarray
    """(N, 4) float32 [t, x, y, z] at PATH_RATE_HZ (trajectories.npz)."""
    plans: list[PlanInput] = field(default_factory=list)
    """With ``record_plans``, the learned method's plan inputs (plans.npz)."""
    judgements: list[Judgement] = field(default_factory=list)
    """With ``record_judge``, the learned method's labelled candidates (judge.npz)."""


@dataclass(frozen=True)
class Judgement:
    """One plan's candidates as the flown-path head reads them (:class:`JudgeInput`), labelled."""

    features: np.ndarray
    """(M, N, F) float32, :attr:`JudgeInput.features`."""
    lengths: np.ndarray
    """(M,) float32 metres, :attr:`JudgeInput.lengths`."""
    collides: np.ndarray
    """(M,) bool: the candidate's judged stretch comes within the robot's radius of the world."""

    @classmethod
    def label(cls, judged: JudgeInput, world: Any, robot_radius: float) -> Judgement:
        pts = judged.points_world.astype(np.float64)
        distance = np.asarray(world.signed_distance(pts.reshape(-1, 3))).reshape(pts.shape[:2])
        return cls(features=judged.features, lengths=judged.lengths, collides=distance.min(axis=1) < robot_radius)


_WORKER: _WorkerState | None = None
"""This process's state; a module global because ProcessPoolExecutor's initializer can only set one."""


def _init_worker(setup: _WorkerSetup) -> None:
    """Per process: one torch thread and the model prepared for inference (identical results whatever
    --workers is)."""
    import torch

    global _WORKER
    torch.set_num_threads(1)
    net = None
    untrained = {}
    if setup.model is not None:
        from mapkit.flight import Planner

        net = Planner.load(setup.model).net.prepare_inference()
        if any(run.method == "untrained" for run in setup.runs):
            untrained = {seed: untrained_copy(net, seed).prepare_inference() for seed in UNTRAINED_SEEDS}
    _WORKER = _WorkerState(setup=setup, net=net, untrained=untrained)


def untrained_copy(net: Any, seed: int) -> Any:
    """A new :class:`~mapkit.planner.PlannerNet` of ``net``'s configuration at the initial weights that
    ``seed`` gives (the same in every process; the global torch generator is left as it was)."""
    import torch

    from mapkit.planner import PlannerNet

    with torch.random.fork_rng():
        torch.manual_seed(seed)
        return PlannerNet(net.config).eval()


def _worker() -> _WorkerState:
    """This process's state; set by :func:`_init_worker`."""
    if _WORKER is None:
        raise RuntimeError("evaluation worker used before _init_worker")
    return _WORKER


def _world_bundle(kind: str) -> _WorldBundle:
    """The world ``kind`` of this process, built on first use."""
    from mapkit.planner import CameraInput
    from mapkit.sim import CameraModel, FreeSpaceGraph, make_world

    state = _worker()
    setup, config = state.setup, state.setup.config
    if kind not in state.worlds:
        world = make_world(kind, seed=config.seed)
        graph = FreeSpaceGraph(world, clearance=config.pair_clearance)
        cam = setup.camera
        K = np.asarray(cam.K)
        camera = CameraModel(width=cam.width, height=cam.height, fx=float(K[0, 0]), fy=float(K[1, 1]))
        u = (np.arange(camera.width) - K[0, 2]) / K[0, 0]
        v = (np.arange(camera.height) - K[1, 2]) / K[1, 1]
        uu, vv = np.meshgrid(u, v, indexing="xy")
        rays = np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)], axis=1)
        calibration = CameraInput.from_calibration(K, cam.width, cam.height, np.asarray(cam.T_body_camera))
        methods = [_run_method(state, run, world, graph, calibration) for run in setup.runs]
        recorded = RunCamera(cam.width, cam.height, K, np.asarray(cam.T_body_camera), "the evaluation's camera")
        pilots = [Pilot(method, camera=recorded, config=config.loop.pilot) for method in methods]
        vehicle = RotorpyVehicle() if config.vehicle == "rotorpy" else None
        state.worlds[kind] = _WorldBundle(world=world, camera=camera, rays=rays, pilots=pilots,
                                          vehicle=vehicle)
    return state.worlds[kind]


def _run_method(state: _WorkerState, run: Run, world: Any, graph: Any, calibration: Any) -> Any:
    """The method ``run`` flies in ``world``, named by its label; the trained network's runs (under any
    stack) record their plans and judgements when asked to."""
    config = state.setup.config
    execution = config.execution if run.stack is None else under_stack(config.execution, run.stack)
    seed = UNTRAINED_SEEDS[0] if run.init_seed is None else run.init_seed
    (method,) = make_methods([run.method], state.net, world, graph, oracle_corridor=config.oracle_corridor,
                             robot_radius=config.loop.robot_radius, camera=calibration,
                             execution=dataclasses.replace(execution), untrained=state.untrained.get(seed))
    method.name = run.label
    if isinstance(method, LearnedMethod) and run.method == "learned":
        method.plan_log = [] if config.record_plans else None
        method.judge_log = [] if config.record_judge else None
        method.record_history = config.judge_history
    return method


def _path_at_rate(samples: np.ndarray, control_rate: float) -> np.ndarray:
    """Every n-th row of the control-rate samples (PATH_RATE_HZ), the last one always kept, float32."""
    step = max(1, int(round(control_rate / PATH_RATE_HZ)))
    path = samples[::step]
    if len(samples) and (len(samples) - 1) % step:
        path = np.concatenate([path, samples[-1:]])
    return path.astype(np.float32)


def _run_pair(kind: str, pair: dict) -> list[_EpisodeRun]:
    """Every method flown from one start–goal pair (``pair``: :meth:`Pair.to_dict`)."""
    from mapkit.sim import render_depth

    b = _world_bundle(kind)
    setup = _worker().setup
    world, camera, rays = b.world, b.camera, b.rays
    T_bc = np.asarray(setup.camera.T_body_camera)
    loop = dataclasses.replace(setup.config.loop)

    def render(T_world_body: np.ndarray) -> np.ndarray:
        return render_depth(world, T_world_body @ T_bc, camera, rays=rays)

    start, goal = np.asarray(pair["start"]), np.asarray(pair["goal"])
    out = []
    for pilot in b.pilots:
        method = pilot.planner
        ep = run_episode(world, start, goal, pilot, loop, render=render, vehicle=b.vehicle, gimbal=setup.config.gimbal)
        record = _record(kind, pair, method.name, ep)
        plans = getattr(method, "plan_log", None) or []
        judged = getattr(method, "judge_log", None) or []
        out.append(_EpisodeRun(record=record, latencies_ms=ep.latencies_ms, allocation_ms=ep.allocation_ms,
                               path=_path_at_rate(ep.samples, loop.control_rate), plans=list(plans),
                               judgements=[Judgement.label(j, world, loop.robot_radius) for j in judged]))
        plans.clear()
        judged.clear()
    return out


_EPISODE_FIELDS = [f.name for f in dataclasses.fields(Episode) if f.name in EpisodeRecord.__dataclass_fields__]
"""The fields an :class:`Episode` hands its results.json row as they are."""


def _record(kind: str, pair: dict, label: str, ep: Episode) -> EpisodeRecord:
    """The results.json row of run ``label``'s flight ``ep`` from ``pair``."""
    fields: dict[str, Any] = {name: getattr(ep, name) for name in _EPISODE_FIELDS}
    # inf in a world without obstacles: JSON has no infinity, so "none in reach"
    fields["min_distance"] = ep.min_distance if math.isfinite(ep.min_distance) else None
    return EpisodeRecord(world=kind, pair=pair["pair"], method=label, start=pair["start"], goal=pair["goal"],
                         distance=pair["distance"], line_of_sight=pair["line_of_sight"],
                         path_length_ratio=ep.path_length / pair["distance"], stack=split_label(label).stack, **fields)


def _call(args: tuple[str, dict]) -> tuple[str, int, list[_EpisodeRun]]:
    """One pool task: (world kind, pair index, its episodes)."""
    kind, pair = args
    return kind, pair["pair"], _run_pair(kind, pair)


# -------------------------------------------------------------------------------- summaries
def _stats(values: list[float], extreme: str | None = None) -> dict[str, float | None]:
    """Mean, std and median of ``values`` (None when empty), and their ``"min"`` or ``"max"`` when asked."""
    out: dict[str, float | None] = {"mean": None, "std": None, "median": None}
    if values:
        a = np.asarray(values, dtype=np.float64)
        out = {"mean": float(a.mean()), "std": float(a.std()), "median": float(np.median(a))}
    if extreme is not None:
        out[extreme] = float(min(values) if extreme == "min" else max(values)) if values else None
    return out


def _present(values: list[float | None]) -> list[float]:
    """The values a file recorded (None: a field older results lack)."""
    return [v for v in values if v is not None]


_SUCCESS_STATS = ("control_effort", "plan_effort", "time_s", "peak_speed", "peak_acceleration", "peak_jerk",
                  "path_length_ratio")
"""Episode fields :func:`summarise` gives statistics of over the successful flights (results.json's order)."""
_FLIGHT_STATS = ("climb", "tracking_error_mean", "tracking_error_max", "reference_peak_speed",
                 "reference_peak_acceleration")
"""Episode fields :func:`summarise` gives statistics and the largest value of over every flight."""


def summarise(episodes: list[EpisodeRecord], worlds: list[str], methods: list[str]) -> dict:
    """Per method: per world and ``overall`` rates and metric statistics (effort, flight time and path ratio over
    successful episodes; clearance over all)."""
    out: dict[str, dict] = {}
    for m in methods:
        out[m] = {}
        for w in [*worlds, "overall"]:
            eps = [e for e in episodes if e.method == m and (w == "overall" or e.world == w)]
            n = len(eps)
            ok = [e for e in eps if e.outcome == "success"]
            dists = _present([e.min_distance for e in eps])
            hidden = [e for e in eps if not e.line_of_sight]
            out[m][w] = {
                "episodes": n,
                "success_rate": len(ok) / n if n else None,
                "collision_rate": sum(e.outcome == "collision" for e in eps) / n if n else None,
                "timeout_rate": sum(e.outcome == "timeout" for e in eps) / n if n else None,
                **{key: _stats(_present([getattr(e, key) for e in ok])) for key in _SUCCESS_STATS},
                "min_distance": _stats(dists, "min"),
                "hidden_goal_episodes": len(hidden),
                "hidden_goal_success_rate": (sum(e.outcome == "success" for e in hidden) / len(hidden)
                                             if hidden else None),
                "rejected_plan_rate": (sum(e.rejected_plans or 0 for e in eps) / max(1, sum(e.plans or 0 for e in eps))
                                       if eps else None),
                **{key: _stats(_present([getattr(e, key) for e in eps]), "max") for key in _FLIGHT_STATS},
            }
    return out


def latency_summary(latencies: dict[tuple[str, str], list[float]], worlds: list[str], methods: list[str]) -> dict:
    out: dict[str, dict] = {}
    for m in methods:
        out[m] = {}
        for w in [*worlds, "overall"]:
            vals = [v for (wk, mk), vs in latencies.items() if mk == m and (w == "overall" or wk == w) for v in vs]
            out[m][w] = {"plans": len(vals), **{f"{k}_ms": v for k, v in _stats(vals).items()},
                         "p90_ms": float(np.percentile(vals, 90)) if vals else None}
    return out


def _versions() -> dict[str, str]:
    import scipy
    import torch

    return {"mapkit": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "torch": torch.__version__}


# ------------------------------------------------------------------------------------ main
@dataclass
class _ModelContext:
    """What the model (or its absence) decides about an evaluation."""

    camera: CameraSpec
    loop: LoopConfig
    """The loop with the model's robot radius and cruise speed."""
    trained_worlds: set[tuple[str, int]]
    """(kind, seed) of the worlds the model trained or validated on."""
    model_info: dict[str, Any] | None
    """results.json's ``model`` (None without a model)."""
    flown_horizon: float = 1.5
    """The model's ``flown_horizon`` and ``flown_history`` (judge.npz)."""
    flown_history: float = 0.0


def _model_context(model: str | os.PathLike[str] | None, config: EvalConfig) -> _ModelContext:
    """Load the model (a missing or foreign one is a one-line error) and read its training camera,
    robot radius, cruise speed and training worlds; the defaults without a model."""
    from mapkit.flight import Planner, resolve_model

    context = _ModelContext(camera=_default_camera(), loop=dataclasses.replace(config.loop), trained_worlds=set(),
                            model_info=None)
    need_model = [m for m in config.methods if m in NEEDS_MODEL]
    if need_model and model is None:
        raise EvalError(f"methods {need_model} need a model: pass --model RUN_DIR (a run of `mapkit train`) or "
                        f"--model pretrained (untrained copies its architecture, straight-keypoints its timing)")
    if model is None:
        return context
    run_dir = resolve_model(model)
    net = Planner.load(run_dir).net  # a missing or foreign model.pt is a one-line error here
    run_cfg = _run_config(run_dir)
    cam = _training_camera(run_cfg)
    h, w = net.config.input_size
    if cam is not None:
        context.camera = cam  # the network resizes its images as in training, so any input size fits
    elif h > context.camera.height or w > context.camera.width:
        raise EvalError(
            f"model {run_dir} expects depth resized to {h}x{w}, its run records no training camera and its "
            f"workspaces are not readable, and the default camera renders only "
            f"{context.camera.height}x{context.camera.width}; put the run's training workspaces back where "
            f"its config.json names them, or evaluate a model trained on a recorded camera"
        )
    else:
        log.warning("the run's training workspaces are not readable; rendering %s", context.camera.source)
    loss = run_cfg.get("loss", {}) or {}
    cruise = config.execution.speed.cruise  # the time limit follows the pace the flights are asked for
    context.loop = dataclasses.replace(context.loop, robot_radius=float(loss.get("robot_radius", context.loop.robot_radius)),
                                       cruise_speed=float(net.config.cruise_speed if cruise is None else cruise))
    context.trained_worlds = _training_worlds(run_cfg)
    context.flown_horizon = net.config.flown_horizon
    context.flown_history = net.config.flown_history
    context.model_info = {"path": str(run_dir.resolve()), "sha256": _sha256(run_dir / "model.pt"),
                          "planner_config": net.config.to_dict(),
                          "training_worlds": sorted(map(list, context.trained_worlds))}
    return context


def judging_loop(model: str | os.PathLike[str], config: EvalConfig | None = None) -> LoopConfig:
    """The loop settings `mapkit eval` judges ``model``'s flights by under ``config`` (default: the
    command's defaults): the model's robot radius, and the time limit at the pace the flights are asked
    for. For flights judged elsewhere (over DDS, on another simulator) to be compared with eval's."""
    return _model_context(model, config or EvalConfig()).loop


def _refuse_training_seed(config: EvalConfig, trained_worlds: set[tuple[str, int]]) -> None:
    """Raise :class:`EvalError` when ``config.seed`` makes a world the model trained on."""
    clash = [k for k in config.worlds if (k, config.seed) in trained_worlds]
    if clash:
        raise EvalError(f"--seed {config.seed} made the training world(s) {', '.join(clash)} of this model; "
                        f"pass another --seed so the evaluation worlds are unseen")


def _worlds_and_pairs(config: EvalConfig) -> tuple[dict[str, Any], dict[str, list[Pair]]]:
    """The evaluation worlds and their pairs (deterministic in the seed), sampled here so every
    method and worker gets the same."""
    from mapkit.sim import FreeSpaceGraph, make_world

    worlds = {k: make_world(k, seed=config.seed) for k in config.worlds}
    pairs: dict[str, list[Pair]] = {}
    for kind, world in worlds.items():
        graph = FreeSpaceGraph(world, clearance=config.pair_clearance)
        pairs[kind] = sample_pairs(graph, config.pairs, seed=config.seed, min_distance=config.min_distance)
    return worlds, pairs


_Results = dict[tuple[str, int], list[_EpisodeRun]]
"""(world, pair index) → its episodes, one per run."""


def _fly_all(setup: _WorkerSetup, tasks: list[tuple[str, dict]], workers: int, progress: bool,
             cluster: tuple[Client, ClusterInfo] | None = None) -> tuple[_Results, int]:
    """Run every (world, pair) task: on the Dask ``cluster`` when given, else in this process or in
    ``workers`` spawned ones; with the number of processes (or Dask workers) that ran them."""
    from tqdm import tqdm

    bar = tqdm(total=len(tasks), unit="pair", desc="eval", dynamic_ncols=True, disable=not progress)
    try:
        if cluster is not None:
            return _fly_on_dask(setup, tasks, cluster, bar), cluster[1].workers
        if workers == 1:
            return _fly_here(setup, tasks, bar), 1
        return _fly_in_pool(setup, tasks, workers, bar), workers
    finally:
        bar.close()


def _fly_here(setup: _WorkerSetup, tasks: list[tuple[str, dict]],
              bar: tqdm) -> _Results:
    """Every task in this process (its torch thread count restored after)."""
    import torch

    global _WORKER
    results: _Results = {}
    threads = torch.get_num_threads()
    try:
        _init_worker(setup)
        for task in tasks:
            kind, idx, runs = _call(task)
            results[(kind, idx)] = runs
            bar.update(1)
    finally:
        torch.set_num_threads(threads)
        _WORKER = None
    return results


def _fly_in_pool(setup: _WorkerSetup, tasks: list[tuple[str, dict]], workers: int,
                 bar: tqdm) -> _Results:
    """Every task in ``workers`` spawned processes, each set up once by :func:`_init_worker`."""
    results: _Results = {}
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"),
                             initializer=_init_worker, initargs=(setup,)) as pool:
        for kind, idx, runs in pool.map(_call, tasks):
            results[(kind, idx)] = runs
            bar.update(1)
    return results


# ------------------------------------------------------------------------------------ Dask
_DASK_LOCK = threading.Lock()
"""One pair at a time per worker process: a world's methods keep state during a flight, so threads
of one multi-threaded Dask worker must not share them."""


def _dask_task(setup: _WorkerSetup, task: tuple[str, dict]) -> tuple[str, int, list[_EpisodeRun]]:
    """One Dask task: a (world, pair) flown on this worker process. The process is set up (model,
    one torch thread) on its first task of an evaluation and keeps the model and worlds for the next
    ones; a task of another evaluation (another setup) sets it up again."""
    with _DASK_LOCK:
        if _WORKER is None or _WORKER.setup != setup:
            _check_worker_model(setup)
            _init_worker(setup)
        return _call(task)


def _check_worker_model(setup: _WorkerSetup) -> None:
    """Raise :class:`EvalError` when this (possibly remote) worker reads another model.pt than the one
    the evaluation started with."""
    from mapkit.flight import resolve_model

    if setup.model is None or setup.model_sha256 is None:
        return
    path = resolve_model(setup.model) / "model.pt"
    if path.exists() and _sha256(path) != setup.model_sha256:
        raise EvalError(f"Dask worker {platform.node()} reads another {path} than the one evaluated "
                        f"(sha256 {setup.model_sha256[:12]}…); put the run directory on storage every worker "
                        "shares, at the same path")


def _release_dask_worker(setup: _WorkerSetup) -> None:
    """Drop this worker process's model and worlds when they are ``setup``'s (the evaluation ended)."""
    global _WORKER
    with _DASK_LOCK:
        if _WORKER is not None and _WORKER.setup == setup:
            _WORKER = None


@contextmanager
def _dask_cluster(config: EvalConfig) -> Iterator[tuple[Client, ClusterInfo] | None]:
    """The Dask client of ``config.scheduler`` (None without one). ``local`` is always a LocalCluster
    of ``config.workers`` processes here, whatever DASK_SCHEDULER_ADDRESS says."""
    if config.scheduler is None:
        yield None
        return
    import dask

    from mapkit._dask import dask_client

    if config.scheduler == LOCAL_SCHEDULER:
        with dask.config.set({"scheduler-address": None}), dask_client(None, workers=config.workers) as cluster:
            yield cluster
    else:
        with dask_client(config.scheduler) as cluster:
            yield cluster


def _fly_on_dask(setup: _WorkerSetup, tasks: list[tuple[str, dict]], cluster: tuple[Client, ClusterInfo],
                 bar: tqdm) -> _Results:
    """Every task as a Dask task on ``cluster``; results in completion order (the caller orders them)."""
    from distributed import as_completed
    from distributed.scheduler import KilledWorker

    client, info = cluster
    if not bar.disable:  # beside the bar, on stderr: the command's stdout stays its table
        bar.write(f"dask: {info.workers} worker(s) at {info.address}"
                  + (f", dashboard {info.dashboard}" if info.dashboard else ""), file=sys.stderr)
    run_id = uuid.uuid4().hex[:8]
    futures = {client.submit(_dask_task, setup, task, key=f"mapkit-eval-{run_id}-{task[0]}-{task[1]['pair']:03d}",
                             retries=DASK_RETRIES): task for task in tasks}
    results: _Results = {}
    for future in as_completed(futures):
        kind, pair = futures[future][0], futures[future][1]["pair"]
        try:
            _, idx, runs = future.result()
        except KilledWorker:
            raise EvalError(f"pair {pair} of {kind}: the Dask workers running it died more than "
                            "distributed.scheduler.allowed-failures times; see the workers' logs (out of memory?) "
                            "or run it here without --scheduler") from None
        results[(kind, idx)] = runs
        bar.update(1)
    if not info.local:  # a long-lived cluster: free the model and worlds its workers hold
        client.run(_release_dask_worker, setup)
    return results


@dataclass
class _Collected:
    """The episodes in results.json order, with their latencies and paths split off."""

    episodes: list[EpisodeRecord] = field(default_factory=list)
    latencies: dict[tuple[str, str], list[float]] = field(default_factory=dict)
    """(world, method) → planning (and time allocation) latencies, ms."""
    allocations: dict[tuple[str, str], list[float]] = field(default_factory=dict)
    paths: dict[str, np.ndarray] = field(default_factory=dict)
    """``"{world}/{pair:03d}/{method}"`` → (N, 4) float32 executed path."""
    plans: list[tuple[str, int, PlanInput]] = field(default_factory=list)
    """(world, pair, plan input) of every recorded plan, in results.json order."""
    judgements: list[tuple[str, int, Judgement]] = field(default_factory=list)
    """(world, pair, labelled candidates) of every recorded plan, in results.json order."""


def _collect(config: EvalConfig, pairs: dict[str, list[Pair]], results: _Results) -> _Collected:
    """Order the episodes by world, pair and method and split off latencies and paths."""
    out = _Collected()
    for kind in config.worlds:
        for p in pairs[kind]:
            for run in results[(kind, p.index)]:
                method = run.record.method
                out.latencies.setdefault((kind, method), []).extend(run.latencies_ms)
                out.allocations.setdefault((kind, method), []).extend(run.allocation_ms)
                out.paths[f"{kind}/{p.index:03d}/{method}"] = run.path
                out.plans.extend((kind, p.index, plan) for plan in run.plans)
                out.judgements.extend((kind, p.index, j) for j in run.judgements)
                out.episodes.append(run.record)
    return out


def _results_doc(config: EvalConfig, context: _ModelContext, pairs: dict[str, list[Pair]],
                 summary: dict, episodes: list[EpisodeRecord]) -> dict[str, Any]:
    """results.json's content (key order is the file's)."""
    doc: dict[str, Any] = {
        "format": EVAL_FORMAT,
        "versions": _versions(),
        "model": context.model_info,
        "seed": config.seed,
        "config": dataclasses.asdict(config),
        "camera": dataclasses.asdict(context.camera),
        "worlds": {k: {"seed": config.seed, "world_json": f"worlds/{k}.world.json",
                       "pairs": [p.to_dict() for p in pairs[k]]} for k in config.worlds},
        "methods": run_labels(config),
        "summary": summary,
        "episodes": [e.to_dict() for e in episodes],
    }
    for key in ("workers", "scheduler", "record_plans", "record_judge", "judge_history"):  # no result depends on them
        del doc["config"][key]
    return doc


def run_labels(config: EvalConfig) -> list[str]:
    """results.json's ``methods``: the label of every run, in report order."""
    return [run.label for run in plan_runs(config.methods, config.stacks, UNTRAINED_SEEDS)]


def write_plans(path: Path, plans: list[tuple[str, int, PlanInput]]) -> None:
    """plans.npz: ``waypoints`` (P, K+1, 3), ``start`` (P, 3, 3), ``end_speed`` (P,), ``cruise_speed``
    (P,), ``decel`` (P,), ``world`` (P,) and ``pair`` (P,) of every recorded plan (body frame, metres
    and seconds)."""
    if plans:
        waypoints = np.stack([p.waypoints for _, _, p in plans])
        start = np.stack([p.start for _, _, p in plans])
    else:
        waypoints, start = np.zeros((0, 0, 3)), np.zeros((0, 3, 3))
    def per_plan(name: str) -> np.ndarray:
        return np.array([getattr(p, name) for _, _, p in plans], np.float64)
    np.savez_compressed(path, waypoints=waypoints.astype(np.float64), start=start.astype(np.float64),
                        end_speed=per_plan("end_speed"), cruise_speed=per_plan("cruise_speed"), decel=per_plan("decel"),
                        world=np.array([w for w, _, _ in plans], dtype=str),
                        pair=np.array([i for _, i, _ in plans], np.int64))


def write_judgements(path: Path, judgements: list[tuple[str, int, Judgement]], horizon: float,
                     robot_radius: float, history: float = 0.0) -> None:
    """judge.npz, one row per candidate of every recorded plan: ``features`` (R, N, F), ``lengths``
    (R,) metres, ``collides`` (R,) bool, ``plan`` (R,) the plan's index in the file, ``world`` (R,),
    ``pair`` (R,), ``horizon`` (the metres judged), ``robot_radius`` (the labels' metres) and
    ``history`` (seconds of earlier frames the clearances read)."""
    from mapkit.planner import FLOWN_FEATURES

    n = judgements[0][2].features.shape[1] if judgements else 0
    def stacked(name: str, empty: tuple[int, ...], dtype: Any) -> np.ndarray:
        parts = [getattr(j, name) for _, _, j in judgements]
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(empty, dtype)
    counts = [len(j.collides) for _, _, j in judgements]
    np.savez_compressed(path, features=stacked("features", (0, n, FLOWN_FEATURES), np.float32),
                        lengths=stacked("lengths", (0,), np.float32), collides=stacked("collides", (0,), bool),
                        plan=np.repeat(np.arange(len(judgements), dtype=np.int64), counts),
                        world=np.repeat(np.array([w for w, _, _ in judgements], dtype=str), counts),
                        pair=np.repeat(np.array([p for _, p, _ in judgements], np.int64), counts),
                        horizon=np.float64(horizon), robot_radius=np.float64(robot_radius),
                        history=np.float64(history))


def _write_outputs(out_dir: Path, config: EvalConfig, context: _ModelContext, doc: dict[str, Any], lat: dict,
                   alloc: dict, worlds: dict[str, Any], collected: _Collected, workers: int, overwrite: bool) -> None:
    """Write the eval folder as one unit: worlds, results.json, latency.json, trajectories.npz, the
    recorded plans and judgements when asked for, and the report."""
    from mapkit.evaluation._report import write_report

    with atomic_output(out_dir, overwrite=overwrite) as tmp:
        tmp.mkdir(parents=True)
        (tmp / "worlds").mkdir()
        for kind, world in worlds.items():
            world.to_json(tmp / "worlds" / f"{kind}.world.json")
        (tmp / "results.json").write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")
        (tmp / "latency.json").write_text(json.dumps(
            {"format": EVAL_FORMAT, "device": platform.processor() or platform.machine(), "torch_threads": 1,
             "workers": workers, "latency": lat, "allocation": alloc}, indent=1) + "\n")
        np.savez_compressed(tmp / "trajectories.npz", **collected.paths)  # type: ignore[arg-type]  # numpy's stub: a key might be allow_pickle
        if config.record_plans:
            write_plans(tmp / PLANS_FILE, collected.plans)
        if config.record_judge:
            history = context.flown_history if config.judge_history is None else config.judge_history
            write_judgements(tmp / JUDGE_FILE, collected.judgements, context.flown_horizon, config.loop.robot_radius,
                             history)
        write_report(tmp, doc, lat, worlds, alloc)


def _model_for_workers(model: str | os.PathLike[str] | None, config: EvalConfig) -> str | None:
    """The model as workers load it: "pretrained" stays a name (every installation ships it), a run
    directory becomes absolute (workers start elsewhere); None when no method needs it."""
    from mapkit.flight import PRETRAINED

    if model is None or not any(m in NEEDS_MODEL for m in config.methods):
        return None
    return PRETRAINED if str(model) == PRETRAINED else str(Path(model).resolve())


def evaluate(
    model: str | os.PathLike[str] | None,
    out_dir: str | os.PathLike[str],
    config: EvalConfig | None = None,
    *,
    overwrite: bool = False,
    progress: bool = True,
) -> EvalResult:
    """Fly every method of ``config`` from the same start–goal pairs in unseen simulated worlds and
    write ``out_dir``: results.json (every outcome and number; identical for the same inputs on CPU),
    latency.json (wall-clock planning times), trajectories.npz (executed paths,
    ``"{world}/{pair:03d}/{method}"`` → (N, 4) [t, x, y, z]), worlds/*.world.json, report.md and PNGs.

    Args:
        model: run directory with model.pt (None only when no method needs a model).
        out_dir: output folder (refused if it exists, unless ``overwrite``).
        config: what to run; ``config.scheduler`` runs the pairs as Dask tasks (results.json and
            trajectories.npz are the same as without it).

    Raises:
        EvalError: bad settings or model; SchedulerError: the scheduler cannot be reached.
    """
    config = config or EvalConfig()
    out_dir = Path(out_dir)
    config.validate()
    check_writable(out_dir, overwrite=overwrite)
    # Connect first: an unreachable scheduler is refused before the model and worlds are built.
    with _dask_cluster(config) as cluster:
        context = _model_context(model, config)
        _refuse_training_seed(config, context.trained_worlds)
        config = dataclasses.replace(config, loop=context.loop)
        worlds, pairs = _worlds_and_pairs(config)

        setup = _WorkerSetup(model=_model_for_workers(model, config),
                             model_sha256=context.model_info["sha256"] if context.model_info else None,
                             camera=context.camera, config=config,
                             runs=tuple(plan_runs(config.methods, config.stacks, UNTRAINED_SEEDS)))
        tasks = [(k, p.to_dict()) for k in config.worlds for p in pairs[k]]
        results, workers = _fly_all(setup, tasks, config.workers, progress, cluster)
    collected = _collect(config, pairs, results)

    worlds_list, methods = list(config.worlds), run_labels(config)
    summary = summarise(collected.episodes, worlds_list, methods)
    lat = latency_summary(collected.latencies, worlds_list, methods)
    alloc = latency_summary(collected.allocations, worlds_list, methods)
    doc = _results_doc(config, context, pairs, summary, collected.episodes)
    _write_outputs(out_dir, config, context, doc, lat, alloc, worlds, collected, workers, overwrite)
    files = sorted(p for p in out_dir.rglob("*") if p.is_file())
    return EvalResult(out_dir=out_dir, summary={"success": summary, "latency": lat, "allocation": alloc}, files=files,
                      ablation=ablation(collected.episodes, methods))


def _validate_loop(loop: LoopConfig) -> None:
    """One line naming the loop's first bad setting (its key under ``loop``)."""
    pilot = loop.pilot
    if not (math.isfinite(pilot.horizon) and pilot.horizon > 0):
        raise EvalError(f"loop.pilot.horizon must be > 0 metres (the local goal's distance), got {pilot.horizon}")
    check_interval(pilot.replan_interval, loop.depth_rate)
    try:
        pilot.validate()
    except FlightError as exc:
        raise EvalError(str(exc).replace("PilotConfig.", "loop.pilot.")) from None
    faults, interval = loop.faults, pilot.replan_interval
    for name, value, ok, where in (("fault drop", faults.drop, 0.0 <= faults.drop < 1.0, "[0, 1)"),
                                   ("fault delay", faults.delay, 0.0 <= faults.delay < interval,
                                    f"[0, replan interval {interval} s)"),
                                   ("fault pose_noise", faults.pose_noise, 0.0 <= faults.pose_noise <= 1.0,
                                    "[0, 1] metres")):
        if not ok:
            raise EvalError(f"{name} {value:g} must be in {where}")


def _validate_execution(ex: Execution) -> None:
    """One line naming the flight stack's first bad setting (its key under ``execution``)."""
    pace, memory, route = ex.speed, ex.memory, ex.route
    for key, value in (("corridor.width", ex.corridor.width), ("corridor.unchecked_width", ex.corridor.unchecked_width),
                       ("speed.v_max", pace.v_max), ("speed.a_max", pace.a_max),
                       ("memory.seconds", None if memory is None else memory.seconds),
                       ("speed.turn_accel", pace.turn_accel), ("speed.stop_decel", pace.stop_decel),
                       ("keep_choice", ex.keep_choice)):
        if value is not None and not (math.isfinite(value) and value > 0):
            off = "" if key in ("corridor.unchecked_width", "speed.v_max", "speed.a_max") else ' ("none" turns it off)'
            raise EvalError(f"execution.{key} must be a positive number{off}, got {value}")
    for name in ("blocked_within", "subgoal_time") if memory is not None else ():
        value = getattr(memory, name)
        if not (math.isfinite(value) and value > 0):
            raise EvalError(f"execution.memory.{name} must be a positive number of seconds, got {value}")
    if route is not None:
        _validate_route(route)
    if pace.cruise is not None and not (math.isfinite(pace.cruise) and pace.cruise > 0):
        raise EvalError(f"execution.speed.cruise must be a positive speed in m/s (or \"none\": the model's cruise "
                        f"speed), got {pace.cruise}")
    if not (math.isfinite(pace.search_ratio) and pace.search_ratio >= 1):
        raise EvalError(f"SpeedProfile.search_ratio must be >= 1 (flown path over progress), got {pace.search_ratio}")
    if not (math.isfinite(pace.search_margin) and pace.search_margin >= 0):
        raise EvalError(f"SpeedProfile.search_margin must be >= 0 metres, got {pace.search_margin}")
    if not all(math.isfinite(s) for s in ex.shift):
        raise EvalError(f"Execution.shift must be finite metres, got {ex.shift}")
    if not (math.isfinite(ex.follow) and 0 <= ex.follow <= 1):
        raise EvalError(f"execution.follow must be in [0, 1] (the fraction of the way toward the reference), got {ex.follow}")


def _validate_route(route: RouteConfig) -> None:
    """One line naming the flight map's first bad setting."""
    if not (math.isfinite(route.after) and route.after > 0):
        raise EvalError(f"execution.route.after must be a positive number of seconds (execution.route = \"none\" turns "
                        f"the flight map off), got {route.after}")
    positive = ("progress", "cell", "extent", "height", "inflate", "horizon")
    for name in positive + ("descend", "detour", "sight"):
        value = getattr(route, name)
        if not (math.isfinite(value) and (value > 0 if name in positive else value >= 0)):
            raise EvalError(f"RouteConfig.{name} must be {'> 0' if name in positive else '>= 0'} metres, got {value}")
    if not math.isfinite(route.ground):
        raise EvalError(f"RouteConfig.ground must be a finite world height in metres, got {route.ground}")
    if not route.wary > route.inflate:
        raise EvalError(f"RouteConfig.wary ({route.wary} m) must exceed RouteConfig.inflate ({route.inflate} m)")
