"""`mapkit train`: the self-supervised planner trained on tuples.zarr + map.zarr, with resume and DDP."""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from mapkit._saved import load_saved
from mapkit._stores import Location, download_tree, remove_file, upload_file, upload_tree
from mapkit._version import __version__
from mapkit.train._config import TrainConfig, TrainConfigError
from mapkit.train._data import TrainDataError, TupleSamples, TupleStore
from mapkit.train._provenance import simulated_worlds, workspace_camera

if TYPE_CHECKING:
    from mapkit.planner import PlannerNet

METRIC_KEYS = ("total", "obstacle", "goal", "smoothness", "escape", "time", "score", "collision_rate",
               "winner_collision_rate", "score_accuracy")
log = logging.getLogger(__name__)

REACH_DISTANCE = 1.0
"""Metres: a validation plan "reaches" its goal when its end lies this close and it does not collide."""


@dataclass
class TrainSummary:
    run_dir: Path | str
    """The run folder: a local path, or its URL."""
    epochs_done: int
    steps: int
    seconds: float
    samples_per_second: float
    last: dict[str, Any] = field(default_factory=dict)
    baseline: dict[str, Any] = field(default_factory=dict)
    best_epoch: int | None = None
    """Epoch whose weights model.pt holds (best held-out blocked-goal reach), None before any."""
    blocked_goals: int | None = None
    """Training samples with a blocked goal (None: the stores do not record it)."""
    threads: int = 1
    """torch threads used."""


class _Step(nn.Module):
    """The network's forward behind one module, so DistributedDataParallel sees (and syncs) it."""

    def __init__(self, net: PlannerNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, depth: torch.Tensor, goal: torch.Tensor, image_index: torch.Tensor, camera: Any,
                velocity: torch.Tensor) -> Any:
        return self.net(self.net.preprocess(depth), goal, image_index, camera, velocity)


def set_threads(world_size: int = 1) -> int:
    """One torch thread per CPU core this process may use (its affinity), shared among the local
    DDP processes (torch's default may oversubscribe a shared machine)."""
    from mapkit.dataset import available_cpus

    n = max(1, available_cpus() // max(1, world_size))
    torch.set_num_threads(n)
    return n


def _device(name: str) -> torch.device:
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise TrainConfigError(f"--device {name}: torch sees no CUDA device on this machine; use --device cpu")
        index = int(name.split(":")[1]) if ":" in name else int(os.environ.get("LOCAL_RANK", 0))
        if index >= torch.cuda.device_count():
            raise TrainConfigError(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s)")
        return torch.device("cuda", index)
    if name != "cpu":
        raise TrainConfigError(f"--device {name!r}: expected cpu, cuda or cuda:N")
    return torch.device("cpu")


def _atomic_save(obj: Any, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _atomic_text(text: str, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def _distributed() -> tuple[int, int]:
    """(rank, world size) from torchrun's environment; initialises the process group once."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    import torch.distributed as dist

    if not dist.is_initialized():
        backend = "nccl" if torch.cuda.is_available() and os.environ.get("MAPKIT_DDP_BACKEND") != "gloo" else "gloo"
        dist.init_process_group(backend=backend)
    return dist.get_rank(), dist.get_world_size()


def _active_fraction(net: PlannerNet) -> tuple[list[Any], dict[int, torch.Tensor]]:
    """Hooks recording, per hidden ReLU of the key-point MLP, which units were ever positive."""
    seen: dict[int, torch.Tensor] = {}
    hooks = []
    relus = [m for m in net.keypoint_mlp if isinstance(m, (nn.ReLU, nn.LeakyReLU))]
    for i, relu in enumerate(relus):
        def hook(_m: nn.Module, _inp: Any, out: torch.Tensor, i: int = i) -> None:
            alive = (out > 0).any(dim=0)
            seen[i] = alive if i not in seen else seen[i] | alive
        hooks.append(relu.register_forward_hook(hook))
    return hooks, seen


def _end_speeds(planner: Any, count: int, rng: np.random.Generator | None, device: torch.device) -> torch.Tensor:
    """(count,) end speeds of the training plans: rest, or with ``tan_boundary`` half of them passing
    their end at cruise speed as in flight (random in training, alternating in validation)."""
    if not planner.tan_boundary:
        return torch.zeros(count, dtype=torch.float64, device=device)
    cruise = (rng.random(count) < 0.5) if rng is not None else (np.arange(count) % 2 == 1)
    return torch.from_numpy(cruise * planner.cruise_speed).to(device)


def _straight_output(net: PlannerNet, goal: torch.Tensor) -> Any:
    from mapkit.planner import PlannerOutput

    line = net.straight_line(goal)
    zero = torch.zeros(goal.shape[0], dtype=goal.dtype, device=goal.device)
    return PlannerOutput(keypoints=line, eta=zero + 0.5, eta_logit=zero)


def validate(net: PlannerNet, samples: TupleSamples, maps: list[Any], loss_config: Any, device: torch.device, *,
             straight: bool = False, max_batches: int | None = None, batch_size: int = 16,
             corridor: float | None = None) -> dict[str, float]:
    """Mean loss terms over a split (the chosen candidate's), with straight=True for key-points on
    the start–goal line; plus, over samples whose goal is blocked in the map, "blocked_collision"
    (plans that collide), "blocked_reach" (plans that end within REACH_DISTANCE of the goal without
    colliding) and "blocked_count", "active_units" (smallest fraction of the key-point MLP's
    hidden units active on some sample), and how the η gate would act on the chosen plans:
    "eta_catches" (share of colliding plans with η ≥ 0.5, i.e. rejected) and "eta_false_rejects"
    (share of free plans rejected)."""
    from mapkit.planner import candidate_loss

    sums: dict[str, float] = {}
    net.eval()
    hooks, seen = _active_fraction(net)
    try:
        with torch.no_grad():
            for b, (k, part) in enumerate(samples.batches(batch_size, shuffle=False)):
                if max_batches is not None and b >= max_batches:
                    break
                batch = samples.load(k, part, device)
                out = net(net.preprocess(batch["depth"]), batch["goal"], batch["image_index"], batch["camera"],
                          batch["velocity"])
                if straight:
                    out = _straight_output(net, batch["goal"])
                end_speed = _end_speeds(net.config, len(part), None, device)
                _, terms = candidate_loss(net, out, goal=batch["goal"], T_world_body=batch["T_world_body"],
                                          esdf_map=maps[k], start_velocity=batch["velocity"], end_speed=end_speed,
                                          corridor=corridor, config=loss_config)
                for key, value in _batch_sums(terms, batch["blocked"], None if straight else out.eta).items():
                    sums[key] = sums.get(key, 0.0) + value
    finally:
        for h in hooks:
            h.remove()
    net.train()
    total = {key: sums.get(key, 0.0) for key in (*METRIC_KEYS, "n", "blocked", "blocked_collision",
                                                  "blocked_reach", "collided", "caught", "free", "false_reject")}
    result = {k: total[k] / max(total["n"], 1) for k in METRIC_KEYS}
    blocked = max(total["blocked"], 1)
    result.update(blocked_count=total["blocked"], blocked_collision=total["blocked_collision"] / blocked,
                  blocked_reach=total["blocked_reach"] / blocked)
    if not straight:
        result.update(eta_catches=total["caught"] / max(total["collided"], 1.0),
                      eta_false_rejects=total["false_reject"] / max(total["free"], 1.0))
    if not straight and seen:
        result["active_units"] = min(float(v.float().mean()) for v in seen.values())
    return result


def _batch_sums(terms: dict[str, torch.Tensor], blocked: torch.Tensor, eta: torch.Tensor | None) -> dict[str, float]:
    """One validation batch's contribution to :func:`validate`'s sums (the η gate's with ``eta``)."""
    m = len(blocked)
    coll = terms["collided_chosen"]
    reach = (~coll) & (terms["goal_chosen"] < REACH_DISTANCE)
    sums = {key: float(terms[key]) * m for key in METRIC_KEYS}
    sums.update(n=m, blocked=int(blocked.sum()), blocked_collision=float(coll[blocked].sum()),
                blocked_reach=float(reach[blocked].sum()))
    if eta is not None:
        rejected = eta >= 0.5
        sums.update(collided=float(coll.sum()), caught=float((rejected & coll).sum()), free=float((~coll).sum()),
                    false_reject=float((rejected & ~coll).sum()))
    return sums


def _curves(metrics: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [m for m in metrics if "train" in m]
    if not epochs:
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    x = [m["epoch"] for m in epochs]
    for key in ("total", "obstacle", "goal", "smoothness", "escape", "time"):
        axes[0].plot(x, [m["train"][key] for m in epochs], marker="o", label=key)
    axes[0].set_xlabel("epoch")
    axes[0].set_ylabel("training loss term (unweighted)")
    axes[0].set_yscale("log")
    axes[0].legend(fontsize=8)
    base = next((m for m in metrics if m.get("epoch") == 0), None)
    vx = [m["epoch"] for m in metrics if "val" in m]
    for key, style in (("collision_rate", "-s"), ("blocked_collision", "-o"), ("blocked_reach", "-^"),
                       ("active_units", "-x")):
        ys = [m["val"].get(key) for m in metrics if "val" in m]
        if all(y is None for y in ys):
            continue
        line, = axes[1].plot(vx, [float("nan") if y is None else y for y in ys], style, label=f"val {key}")
        if base and key in base.get("straight", {}):
            axes[1].axhline(base["straight"][key], linestyle="--", color=line.get_color(), linewidth=0.8)
    axes[1].set_xlabel("epoch (0 = untrained; dashed: straight-line key-points on the same goals)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def _open_stores(workspaces: Sequence[str | Path | Location]) -> tuple[list[TupleStore], list[Any]]:
    """Tuple stores and their maps; a map changed since export is refused."""
    from mapkit.esdf import MAP, EsdfMap
    from mapkit.export import map_digest

    stores = [TupleStore.open(ws) for ws in workspaces]
    maps = []
    for s in stores:
        if not (s.workspace / MAP).exists():
            raise TrainDataError(f"{s.workspace / MAP} is missing (the tuples' distances and collision labels come from "
                                 f"it): rebuild it with `mapkit esdf -w {s.workspace}` using the options it had, or "
                                 f"copy it back, then `mapkit export -w {s.workspace} --overwrite`")
        if map_digest(s.workspace / MAP) != s.attrs["map"]["sha256"]:
            raise TrainDataError(f"{s.workspace / MAP} changed since `mapkit export`; re-run `mapkit export -w "
                                 f"{s.workspace} --overwrite` so the tuples match the map")
        maps.append(EsdfMap.open(s.workspace / MAP))
    return stores, maps


def _camera_or_none(workspace: str | Path) -> dict[str, Any] | None:
    """The first training workspace's camera (what evaluation renders), None when unreadable."""
    from mapkit.errors import MapkitError

    try:
        return workspace_camera(workspace)
    except (MapkitError, OSError):
        return None


_TAN_FIELDS = frozenset({"tan_boundary", "tan_boundary_scale", "tan_hidden", "accel", "min_segment_time", "min_total_time", "max_total_time"})
"""PlannerConfig fields that only change the time allocation (may differ from --init's with only = "tan")."""


def _init_worlds(init: str | None) -> set[tuple[str, int]]:
    """(kind, seed) of the simulated worlds the ``--init`` model trained on (its run's recorded
    ``training_worlds``): a fine-tuned model has seen them too, so `mapkit eval` must refuse them."""
    from mapkit.flight import resolve_model

    if not init:
        return set()
    path = resolve_model(init)
    run_config = (path if path.is_dir() else path.parent) / "config.json"
    try:
        recorded = json.loads(run_config.read_text()).get("training_worlds", [])
        return {(str(kind), int(seed)) for kind, seed in recorded}
    except (OSError, ValueError, TypeError, AttributeError) as exc:
        log.warning("--init %s: its training worlds are not known (%s: %s); `mapkit eval` cannot refuse them",
                    init, type(exc).__name__, exc)
        return set()


def _load_init(net: PlannerNet, init: str, *, tan_fresh: bool = False) -> None:
    """Weights of the model ``init`` (run directory, model.pt or "pretrained") into ``net``; with
    ``tan_fresh`` its TAN options may differ and the TAN keeps its new initial weights."""
    from mapkit.flight import resolve_model

    path = resolve_model(init)
    path = path / "model.pt" if path.is_dir() else path
    if not path.is_file():
        raise TrainConfigError(f"--init {init}: no model.pt there; pass a run directory, its model.pt or 'pretrained'")
    saved = load_saved(path, "mapkit planner", TrainConfigError, ("planner_config", "state_dict"))
    mine = net.config.to_dict()
    theirs = saved.get("planner_config", {})
    diff = sorted(k for k in mine if k in theirs and json.dumps(mine[k]) != json.dumps(theirs[k])
                  and not (tan_fresh and k in _TAN_FIELDS))
    if diff:
        k = diff[0]
        raise TrainConfigError(f"--init {init}: its planner has {k}={theirs[k]!r}, this run {mine[k]!r}; "
                               f"train with the same --preset and planner settings")
    state = saved["state_dict"]
    if tan_fresh:
        state = {k: v for k, v in state.items() if not k.startswith("tan.")} | {
            k: v for k, v in net.state_dict().items() if k.startswith("tan.")}
    net.load_state_dict(state)


def _selection_score(val: dict[str, float], only: str = "all") -> float:
    """Higher is better: held-out blocked-goal reach when there are blocked goals, else −loss; −U_T
    when only the TAN trains (the paths do not change)."""
    if only == "tan":
        return -val["time"]
    return val["blocked_reach"] if val.get("blocked_count", 0) > 0 else -val["total"]


def _metrics_upto(path: Path, epoch: int) -> list[dict[str, Any]]:
    """The rows of metrics.jsonl up to ``epoch`` (the checkpoint's), rewriting the file without the
    rest: a kill after an epoch's row but before its checkpoint must not leave that row twice."""
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    kept = [row for row in rows if int(row.get("epoch", 0)) <= epoch]
    if len(kept) != len(rows):
        _atomic_text("".join(json.dumps(row) + "\n" for row in kept), path)
    return kept


@dataclass
class _Session:
    """A training run in progress: what the steps of :func:`train` share."""

    config: TrainConfig
    run_dir: Path
    device: torch.device
    rank: int
    world: int
    """DDP world size (1 without torchrun)."""
    rng: np.random.Generator
    """Shuffling and end-speed sampling (seeded; its state goes into checkpoints)."""
    step: int = 0
    """Optimiser steps so far."""
    net: Any = None
    """The PlannerNet (set by :func:`_build_model`)."""
    step_module: Any = None
    """The net behind DistributedDataParallel when ``world`` > 1, else its plain wrapper."""
    optimizer: Any = None
    best_score: float = -math.inf
    best_epoch: int | None = None
    metrics: list[dict[str, Any]] = field(default_factory=list)
    writer: Any = None
    """TensorBoard SummaryWriter, None without the optional extra."""
    remote: Location | None = None
    """The run folder at a URL (``run_dir`` is then its local staging copy), None for a local run."""

    def log_row(self, entry: dict[str, Any]) -> None:
        """Append a row to metrics.jsonl (and to :attr:`metrics`)."""
        self.metrics.append(entry)
        with open(self.run_dir / "metrics.jsonl", "a") as f:
            f.write(json.dumps(entry) + "\n")
        self.publish("metrics.jsonl")

    def publish(self, *names: str) -> None:
        """A run at a URL: copy these files (or folders) of ``run_dir`` there, each file whole."""
        if self.remote is None:
            return
        for name in names:
            path = self.run_dir / name
            if path.is_dir():
                upload_tree(path, self.remote / name)
            elif path.exists():
                upload_file(path, self.remote / name)


@dataclass
class _Splits:
    """Training and validation samples with their maps."""

    train_set: TupleSamples
    maps: list[Any]
    val_set: TupleSamples
    val_maps: list[Any]


def _where(workspace: str | Path | Location) -> str:
    """A workspace as config.json records it: an absolute local path, or its URL."""
    loc = Location.of(workspace)
    return str(loc.local.resolve()) if loc.local is not None else loc.url


def _run_dir(workspaces: Sequence[str | Path], runs_dir: str | Path | None, name: str) -> tuple[Path, Location | None]:
    """runs_dir/NAME (default: first WS/runs/NAME) and, for a run folder at a URL, that location: the
    files are then written to a local staging folder holding a copy of what is there already (resume,
    the overwrite check), and each is copied to the URL after it is written."""
    where = runs_dir if runs_dir else Location.of(workspaces[0]) / "runs"
    loc = Location.of(where) / name
    if loc.local is not None:
        return loc.local, None
    loc.check_reachable()
    staging = Path(tempfile.mkdtemp(prefix=f".mapkit-run-{name}-"))
    if loc.exists():
        download_tree(loc, staging)
    return staging, loc


def _check_inputs(workspaces: Sequence[str | Path], val_workspaces: Sequence[str | Path], config: TrainConfig) -> None:
    """Raise when the config is out of range, no workspace is given, or a workspace is in both splits."""
    config.validate()
    if not workspaces:
        raise TrainDataError("no workspace given; pass -w WS (repeatable)")
    overlap = {_where(w) for w in workspaces} & {_where(w) for w in val_workspaces}
    if overlap:
        raise TrainDataError(f"{sorted(map(str, overlap))[0]} is both a training and a validation workspace; "
                             "hold out whole worlds")


def _resume_state(run_dir: Path, config: TrainConfig, *, resume: bool, overwrite: bool,
                  shown: str | None = None) -> dict[str, Any] | None:
    """The checkpoint to continue from (its config must match), None for a fresh run; refuses to
    start over an existing run without ``overwrite``. ``shown``: the run folder as messages name it
    (its URL when ``run_dir`` is a staging copy)."""
    checkpoint_path = run_dir / "checkpoint.pt"
    where = shown or str(run_dir)
    if resume:
        if not checkpoint_path.exists():
            raise TrainConfigError(f"--resume: {shown + '/checkpoint.pt' if shown else checkpoint_path} does not exist; "
                                   "start without --resume")
        theirs = TrainConfig.from_saved(json.loads((run_dir / "config.json").read_text())).to_dict()
        mine = config.to_dict()
        for key in ("planner", "loss", "batch_size", "corridor", "preset"):
            if theirs[key] != mine[key]:
                raise TrainConfigError(
                    f"--resume with an incompatible config: {key} is {mine[key]!r} but the run has "
                    f"{theirs[key]!r}; use the run's options or a new --name"
                )
        return load_saved(checkpoint_path, "mapkit training checkpoint", TrainConfigError,
                          ("epoch", "step", "model", "optimizer"))
    if run_dir.exists() and any(run_dir.iterdir()) and not overwrite:
        raise TrainConfigError(f"run {where} exists; pass --resume to continue it, --overwrite to restart, or a new --name")
    return None


def _splits(workspaces: Sequence[str | Path], val_workspaces: Sequence[str | Path], config: TrainConfig) -> _Splits:
    """Open the stores: held-out workspaces validate when given, else each store's own split."""
    stores, maps = _open_stores(workspaces)
    if val_workspaces:
        val_stores, val_maps = _open_stores(val_workspaces)
        train_set = TupleSamples(stores, "all", goals_together=config.goals_together)
        val_set = TupleSamples(val_stores, "all")
    else:
        train_set = TupleSamples(stores, "train", goals_together=config.goals_together)
        val_set, val_maps = TupleSamples(stores, "val"), maps
    if len(train_set) == 0:
        raise TrainDataError("no training samples: every tuple is in the validation split; lower val_fraction at export")
    return _Splits(train_set, maps, val_set, val_maps)


def _build_model(run: _Session, state: dict[str, Any] | None) -> None:
    """The net (DDP-wrapped when distributed), its optimiser, and the weights of --init or the checkpoint."""
    from mapkit.planner import PlannerNet

    config = run.config
    run.net = net = PlannerNet(config.planner).to(run.device)
    run.step_module = _Step(net)
    if run.world > 1:
        run.step_module = nn.parallel.DistributedDataParallel(
            run.step_module, device_ids=[run.device.index] if run.device.type == "cuda" else None)
    if config.only != "all":
        trained = ("tan.",) if config.only == "tan" else ("judge_mlp.", "eta_mlp.")
        for name, param in net.named_parameters():
            param.requires_grad_(name.startswith(trained))
    run.optimizer = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=config.lr)
    if state is None and config.init:
        _load_init(net, config.init, tan_fresh=config.only == "tan")
    if state is not None:
        net.load_state_dict(state["model"])
        run.optimizer.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["rng_torch"])
        run.rng.bit_generator.state = state["rng_numpy"]
        run.best_score, run.best_epoch = state.get("best_score", -math.inf), state.get("best_epoch")


def _start_run_dir(run: _Session, workspaces: Sequence[str | Path], val_workspaces: Sequence[str | Path], *,
                   resume: bool, start_epoch: int) -> None:
    """Rank 0: config.json, the metrics kept from before a resume, and TensorBoard when installed."""
    run_dir, config = run.run_dir, run.config
    run_dir.mkdir(parents=True, exist_ok=True)
    if not resume:
        for stale in ("metrics.jsonl", "checkpoint.pt", "model.pt", "training_curves.png"):
            (run_dir / stale).unlink(missing_ok=True)
            if run.remote is not None:
                remove_file(run.remote / stale)
    _atomic_text(json.dumps(config.to_dict() | {"planner_resolved": config.planner.to_dict(),
                                                "workspaces": [_where(w) for w in workspaces],
                                                "val_workspaces": [_where(w) for w in val_workspaces],
                                                "camera": _camera_or_none(workspaces[0]),
                                                "training_worlds": sorted(map(list, simulated_worlds(
                                                    [*workspaces, *val_workspaces]) | _init_worlds(config.init))),
                                                "mapkit_version": __version__}, indent=2), run_dir / "config.json")
    run.publish("config.json")
    if (run_dir / "metrics.jsonl").exists():
        run.metrics = _metrics_upto(run_dir / "metrics.jsonl", start_epoch - 1)
        run.publish("metrics.jsonl")
    run.writer = _tensorboard(run_dir)


def _tensorboard(run_dir: Path) -> Any:
    """A SummaryWriter into run_dir/tensorboard, or None (an optional extra; metrics.jsonl has every number)."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # optional extra
    except ImportError as exc:
        log.info("TensorBoard is not installed (%s); the metrics are in %s", exc, run_dir / "metrics.jsonl")
        return None
    try:
        return SummaryWriter(str(run_dir / "tensorboard"))
    except Exception as exc:  # noqa: BLE001 - any failure of the optional logger: warned, the run goes on
        log.warning("TensorBoard cannot write to %s (%s: %s); the metrics are in metrics.jsonl",
                    run_dir / "tensorboard", type(exc).__name__, exc)
        return None


def _validation(run: _Session, data: _Splits, *, straight: bool = False) -> dict[str, float]:
    """The validation metrics of the current weights (or of straight-line key-points)."""
    c = run.config
    return validate(run.net, data.val_set, data.val_maps, c.loss, run.device, straight=straight,
                    max_batches=c.val_batches, batch_size=c.batch_size, corridor=c.corridor)


def _train_step(run: _Session, data: _Splits, k: int, part: Any) -> dict[str, Any]:
    """One optimiser step on one batch; its loss terms."""
    from mapkit.planner import candidate_loss, time_allocation_loss

    config, net = run.config, run.net
    batch = data.train_set.load(k, part, run.device)
    with torch.set_grad_enabled(config.only != "tan"):
        out = run.step_module(batch["depth"], batch["goal"], batch["image_index"], batch["camera"], batch["velocity"])
    end_speed = _end_speeds(config.planner, len(part), run.rng, run.device)
    if config.only == "tan":
        loss, terms = time_allocation_loss(net, out.keypoints, start_velocity=batch["velocity"],
                                           end_speed=end_speed, config=config.loss)
        terms = {key: terms.get(key, torch.tensor(0.0)) for key in METRIC_KEYS}  # paths are not costed
    else:
        loss, terms = candidate_loss(net, out, goal=batch["goal"], T_world_body=batch["T_world_body"],
                                     esdf_map=data.maps[k], start_velocity=batch["velocity"], end_speed=end_speed,
                                     corridor=config.corridor, config=config.loss)
    if not torch.isfinite(loss):
        raise TrainConfigError(f"loss became {float(loss)} at step {run.step}; lower the learning rate (now {config.lr}; mapkit train --set lr=...)")
    run.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    nn.utils.clip_grad_norm_(net.parameters(), 10.0)
    run.optimizer.step()
    run.step += 1
    return terms


def _train_epoch(run: _Session, data: _Splits, epoch: int, progress: bool) -> tuple[dict[str, float], int, float]:
    """One pass over the training batches: (sums of each metric weighted by batch size, samples,
    seconds of steps)."""
    from tqdm import tqdm

    config = run.config
    # A frozen encoder stays in eval mode: batch norm would otherwise move its running statistics
    # (and so the key-points) even without gradients. The TAN and the judge have no such layers.
    run.net.train(config.only == "all")
    sums = {k: 0.0 for k in METRIC_KEYS}
    count = 0
    batches = list(data.train_set.batches(config.batch_size, shuffle=True, generator=run.rng, rank=run.rank,
                                          world_size=run.world))
    bar = tqdm(batches, desc=f"epoch {epoch}/{config.epochs}", unit="batch", disable=not progress or run.rank != 0,
               dynamic_ncols=True)
    t_steps = time.perf_counter()
    for k, part in bar:
        terms = _train_step(run, data, k, part)
        m = len(part)
        count += m
        for key in METRIC_KEYS:
            sums[key] += float(terms[key]) * m
        if run.rank == 0:
            bar.set_postfix({k: f"{sums[k] / count:.3g}" for k in ("total", "obstacle", "goal", "collision_rate")})
            if run.writer is not None:
                for key in METRIC_KEYS:
                    run.writer.add_scalar(f"train/{key}", float(terms[key]), run.step)
        if config.max_steps is not None and run.step >= config.max_steps:
            break
    bar.close()
    return sums, count, time.perf_counter() - t_steps


def _end_epoch(run: _Session, data: _Splits, epoch: int, sums: dict[str, float], count: int, steps_seconds: float,
               t_epoch: float) -> None:
    """Rank 0 after an epoch: validate, log the row, write the checkpoint, model.pt when better, curves."""
    val = _validation(run, data)
    score = _selection_score(val, run.config.only)
    improved = score > run.best_score
    if improved:
        run.best_score, run.best_epoch = score, epoch
    seconds = time.perf_counter() - t_epoch
    run.log_row({"epoch": epoch, "step": run.step, "train": {k: v / max(count, 1) for k, v in sums.items()}, "val": val,
             "seconds": seconds, "samples_per_second": count * run.world / steps_seconds, "best_epoch": run.best_epoch})
    if run.writer is not None:
        for key, value in val.items():
            run.writer.add_scalar(f"val/{key}", value, epoch)
    _write_checkpoint(run, epoch)
    if improved:
        _write_model(run, epoch, val)
    _curves(run.metrics, run.run_dir / "training_curves.png")
    run.publish("training_curves.png")


def _write_checkpoint(run: _Session, epoch: int) -> None:
    """checkpoint.pt: weights, optimiser, RNG states and the best so far (for --resume)."""
    _atomic_save({"model": run.net.state_dict(), "optimizer": run.optimizer.state_dict(), "epoch": epoch,
                  "step": run.step, "config": run.config.to_dict(), "rng_torch": torch.get_rng_state(),
                  "rng_numpy": run.rng.bit_generator.state, "best_score": run.best_score, "best_epoch": run.best_epoch},
                 run.run_dir / "checkpoint.pt")
    run.publish("checkpoint.pt")


def _write_model(run: _Session, epoch: int, val: dict[str, float]) -> None:
    """model.pt: the weights of the best epoch with their planner config."""
    _atomic_save({"state_dict": run.net.state_dict(), "planner_config": run.config.planner.to_dict(),
                  "loss_config": run.config.to_dict()["loss"], "mapkit_version": __version__, "epoch": epoch,
                  "selection": {"blocked_reach": val["blocked_reach"], "total": val["total"]}},
                 run.run_dir / "model.pt")
    run.publish("model.pt")


def train(workspaces: Sequence[str | Path], config: TrainConfig, *, runs_dir: str | Path | None = None,
          resume: bool = False, overwrite: bool = False, progress: bool = True,
          val_workspaces: Sequence[str | Path] = ()) -> TrainSummary:
    """Train the planner on the tuples of `workspaces`; writes runs_dir/NAME (default: first WS/runs).

    With ``val_workspaces`` (held-out worlds) every tuple of ``workspaces`` trains and every tuple of
    ``val_workspaces`` validates; otherwise each store's own train/val split is used. model.pt holds
    the epoch with the best validation blocked-goal reach (see :func:`validate`); checkpoint.pt the
    latest (for --resume)."""
    _check_inputs(workspaces, val_workspaces, config)
    device = _device(config.device)
    rank, world = _distributed()
    # torchrun's LOCAL_WORLD_SIZE: the processes on this machine, which share its cores
    local = int(os.environ.get("LOCAL_WORLD_SIZE", world))
    threads = set_threads(local) if device.type == "cpu" else torch.get_num_threads()
    run_dir, remote = _run_dir(workspaces, runs_dir, config.name)
    try:
        return _train(workspaces, val_workspaces, config, run_dir, remote, resume=resume, overwrite=overwrite,
                      progress=progress, device=device, rank=rank, world=world, threads=threads)
    finally:
        if remote is not None:
            try:
                shutil.rmtree(run_dir)  # the staging copy; the run is at `remote`
            except OSError as exc:
                log.warning("could not remove the staging copy %s of run %s (%s)", run_dir, remote.url, exc)


def _train(workspaces: Sequence[str | Path], val_workspaces: Sequence[str | Path], config: TrainConfig, run_dir: Path,
           remote: Location | None, *, resume: bool, overwrite: bool, progress: bool, device: torch.device, rank: int,
           world: int, threads: int) -> TrainSummary:
    """:func:`train` once the run folder is chosen (``run_dir`` local, or the staging copy of ``remote``)."""
    state = _resume_state(run_dir, config, resume=resume, overwrite=overwrite, shown=remote.url if remote else None)
    start_epoch = int(state["epoch"]) + 1 if state else 1
    torch.manual_seed(config.seed)
    run = _Session(config=config, run_dir=run_dir, device=device, rank=rank, world=world,
                   rng=np.random.default_rng(config.seed), step=int(state["step"]) if state else 0, remote=remote)
    data = _splits(workspaces, val_workspaces, config)
    _build_model(run, state)
    if rank == 0:
        _start_run_dir(run, workspaces, val_workspaces, resume=resume, start_epoch=start_epoch)
    if rank == 0 and not resume:
        run.log_row({"epoch": 0, "val": _validation(run, data), "straight": _validation(run, data, straight=True)})
    baseline = next((m for m in run.metrics if m.get("epoch") == 0), {})

    t_start = time.perf_counter()
    train_seconds = 0.0
    samples_seen = 0
    epoch = start_epoch - 1
    for epoch in range(start_epoch, config.epochs + 1):
        t_epoch = time.perf_counter()
        sums, count, steps_seconds = _train_epoch(run, data, epoch, progress)
        samples_seen += count
        train_seconds += steps_seconds
        if rank == 0:
            _end_epoch(run, data, epoch, sums, count, steps_seconds, t_epoch)
        if config.max_steps is not None and run.step >= config.max_steps:
            break
    if run.writer is not None:
        run.writer.close()
        run.publish("tensorboard")
    seconds = time.perf_counter() - t_start
    last: dict[str, Any] = next((m for m in reversed(run.metrics) if "train" in m), {})
    rate = samples_seen * world / train_seconds if train_seconds > 0 else math.nan
    return TrainSummary(run_dir if remote is None else remote.url, epoch, run.step, seconds, rate, last, baseline, run.best_epoch,
                        data.train_set.blocked_count(), threads)
