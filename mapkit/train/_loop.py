"""`mapkit train`: the self-supervised planner trained on tuples.zarr + map.zarr, with resume and DDP."""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from mapkit._version import __version__
from mapkit.train._config import TrainConfig, TrainConfigError
from mapkit.train._data import TrainDataError, TupleSamples, TupleStore

METRIC_KEYS = ("total", "obstacle", "goal", "smoothness", "escape", "time", "collision_rate")


@dataclass
class TrainSummary:
    run_dir: Path
    epochs_done: int
    steps: int
    seconds: float
    samples_per_second: float
    last: dict[str, Any] = field(default_factory=dict)
    baseline: dict[str, Any] = field(default_factory=dict)


class _Step(nn.Module):
    """net.plan behind a forward(), so DistributedDataParallel sees (and syncs) the whole step."""

    def __init__(self, net: nn.Module, corridor: float | None = None) -> None:
        super().__init__()
        self.net = net
        self.corridor = corridor

    def forward(self, depth: torch.Tensor, goal: torch.Tensor, velocity: torch.Tensor) -> Any:
        return self.net.plan(depth, goal, start_velocity=velocity, corridor=self.corridor)


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


def evaluate(net: nn.Module, samples: TupleSamples, maps: list[Any], loss_config: Any, device: torch.device, *,
             straight: bool = False, max_batches: int | None = None, batch_size: int = 16,
             corridor: float | None = None) -> dict[str, float]:
    """Mean loss terms over a split; with straight=True for key-points on the start–goal line."""
    from mapkit.planner import planner_loss

    totals = {k: 0.0 for k in METRIC_KEYS}
    n = 0
    net.eval()
    with torch.no_grad():
        for b, (k, part) in enumerate(samples.batches(batch_size, shuffle=False)):
            if max_batches is not None and b >= max_batches:
                break
            batch = samples.load(k, part, device)
            x = net.preprocess(batch["depth"])
            out = net(x, batch["goal"])
            keypoints = net.straight_line(batch["goal"]) if straight else out.keypoints
            plan = net.trajectory(keypoints, start_velocity=batch["velocity"], corridor=corridor)
            _, terms = planner_loss(plan, goal=batch["goal"], T_world_body=batch["T_world_body"], esdf_map=maps[k],
                                    eta=out.eta, eta_logit=out.eta_logit, config=loss_config)
            m = len(part)
            for key in METRIC_KEYS:
                totals[key] += float(terms[key]) * m
            n += m
    net.train()
    return {k: v / max(n, 1) for k, v in totals.items()}


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
    for key, style in (("obstacle", "-o"), ("collision_rate", "-s")):
        axes[1].plot(vx, [m["val"][key] for m in metrics if "val" in m], style, label=f"val {key}")
        if base and "straight" in base:
            axes[1].axhline(base["straight"][key], linestyle="--", color="grey", linewidth=0.8)
    axes[1].set_xlabel("epoch (0 = untrained; dashed: straight-line key-points)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def train(workspaces: Sequence[str | Path], config: TrainConfig, *, runs_dir: str | Path | None = None,
          resume: bool = False, overwrite: bool = False, progress: bool = True) -> TrainSummary:
    """Train the planner on the tuples of `workspaces`; writes runs_dir/NAME (default: first WS/runs)."""
    from tqdm import tqdm

    from mapkit.esdf import MAP, EsdfMap
    from mapkit.export import map_digest
    from mapkit.planner import LossConfig, PlannerConfig, PlannerNet

    config.validate()
    if not workspaces:
        raise TrainDataError("no workspace given; pass -w WS (repeatable)")
    device = _device(config.device)
    rank, world = _distributed()
    run_dir = Path(runs_dir) if runs_dir else Path(workspaces[0]) / "runs"
    run_dir = run_dir / config.name
    checkpoint_path = run_dir / "checkpoint.pt"
    start_epoch, step, state = 1, 0, None
    if resume:
        if not checkpoint_path.exists():
            raise TrainConfigError(f"--resume: {checkpoint_path} does not exist; start without --resume")
        saved_all = json.loads((run_dir / "config.json").read_text())
        saved = TrainConfig.from_dict({k: v for k, v in saved_all.items() if k in TrainConfig.__dataclass_fields__})
        for key in ("planner", "loss", "batch_size", "corridor", "preset"):
            if getattr(saved, key) != getattr(config, key):
                raise TrainConfigError(
                    f"--resume with an incompatible config: {key} is {getattr(config, key)!r} but the run has "
                    f"{getattr(saved, key)!r}; use the run's options or a new --name"
                )
        state = torch.load(checkpoint_path, map_location="cpu", weights_only=False)
        start_epoch, step = int(state["epoch"]) + 1, int(state["step"])
    elif run_dir.exists() and any(run_dir.iterdir()) and not overwrite:
        raise TrainConfigError(f"run {run_dir} exists; pass --resume to continue it, --overwrite to restart, or a new --name")

    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    stores = [TupleStore.open(ws) for ws in workspaces]
    maps = []
    for s in stores:
        digest = map_digest(s.workspace / MAP) if (s.workspace / MAP).exists() else None
        if digest != s.attrs["map"]["sha256"]:
            raise TrainDataError(f"{s.workspace / MAP} changed since `mapkit export` (or is missing); re-run `mapkit export --overwrite`")
        maps.append(EsdfMap.open(s.workspace / MAP))
    train_set, val_set = TupleSamples(stores, "train"), TupleSamples(stores, "val")
    if len(train_set) == 0:
        raise TrainDataError("no training samples: every tuple is in the validation split; lower --val-fraction at export")

    planner_cfg = PlannerConfig.from_dict(config.planner) if config.planner else PlannerConfig()
    loss_cfg = LossConfig(**config.loss)
    net = PlannerNet(planner_cfg).to(device)
    step_module: nn.Module = _Step(net, config.corridor)
    if world > 1:
        step_module = nn.parallel.DistributedDataParallel(step_module, device_ids=[device.index] if device.type == "cuda" else None)
    optimizer = torch.optim.Adam(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    if state is not None:
        net.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["rng_torch"])
        rng.bit_generator.state = state["rng_numpy"]

    writer = None
    metrics: list[dict[str, Any]] = []
    if rank == 0:
        run_dir.mkdir(parents=True, exist_ok=True)
        if not resume:
            for stale in ("metrics.jsonl", "checkpoint.pt", "model.pt", "training_curves.png"):
                (run_dir / stale).unlink(missing_ok=True)
        _atomic_text(json.dumps(config.to_dict() | {"planner_resolved": planner_cfg.to_dict(),
                                                    "workspaces": [str(Path(w).resolve()) for w in workspaces],
                                                    "mapkit_version": __version__}, indent=2), run_dir / "config.json")
        if (run_dir / "metrics.jsonl").exists():
            metrics = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]
        try:
            from torch.utils.tensorboard import SummaryWriter  # optional extra

            writer = SummaryWriter(str(run_dir / "tensorboard"))
        except Exception:
            writer = None

    def log(entry: dict[str, Any]) -> None:
        metrics.append(entry)
        with open(run_dir / "metrics.jsonl", "a") as f:
            f.write(json.dumps(entry) + "\n")

    if rank == 0 and not resume:
        base = {
            "epoch": 0,
            "val": evaluate(net, val_set, maps, loss_cfg, device, max_batches=config.val_batches, batch_size=config.batch_size,
                            corridor=config.corridor),
            "straight": evaluate(net, val_set, maps, loss_cfg, device, straight=True, max_batches=config.val_batches,
                                 batch_size=config.batch_size, corridor=config.corridor),
        }
        log(base)
    baseline = next((m for m in metrics if m.get("epoch") == 0), {})

    t_start = time.perf_counter()
    train_seconds = 0.0
    samples_seen = 0
    epoch = start_epoch - 1
    from mapkit.planner import planner_loss

    for epoch in range(start_epoch, config.epochs + 1):
        sums = {k: 0.0 for k in METRIC_KEYS}
        count = 0
        t_epoch = time.perf_counter()
        batches = list(train_set.batches(config.batch_size, shuffle=True, generator=rng, rank=rank, world_size=world))
        bar = tqdm(batches, desc=f"epoch {epoch}/{config.epochs}", unit="batch", disable=not progress or rank != 0, dynamic_ncols=True)
        t_steps = time.perf_counter()
        for k, part in bar:
            batch = train_set.load(k, part, device)
            plan = step_module(batch["depth"], batch["goal"], batch["velocity"])
            loss, terms = planner_loss(plan, goal=batch["goal"], T_world_body=batch["T_world_body"], esdf_map=maps[k],
                                       config=loss_cfg)
            if not torch.isfinite(loss):
                raise TrainConfigError(f"loss became {float(loss)} at step {step}; lower --lr (now {config.lr})")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            step += 1
            m = len(part)
            samples_seen += m
            count += m
            for key in METRIC_KEYS:
                sums[key] += float(terms[key]) * m
            if rank == 0:
                bar.set_postfix({k: f"{sums[k] / count:.3g}" for k in ("total", "obstacle", "goal", "collision_rate")})
                if writer is not None:
                    for key in METRIC_KEYS:
                        writer.add_scalar(f"train/{key}", float(terms[key]), step)
            if config.max_steps is not None and step >= config.max_steps:
                break
        bar.close()
        steps_seconds = time.perf_counter() - t_steps
        train_seconds += steps_seconds
        if rank == 0:
            val = evaluate(net, val_set, maps, loss_cfg, device, max_batches=config.val_batches, batch_size=config.batch_size,
                           corridor=config.corridor)
            seconds = time.perf_counter() - t_epoch
            log({"epoch": epoch, "step": step, "train": {k: v / max(count, 1) for k, v in sums.items()}, "val": val,
                 "seconds": seconds, "samples_per_second": count * world / steps_seconds})
            if writer is not None:
                for key, value in val.items():
                    writer.add_scalar(f"val/{key}", value, epoch)
            _atomic_save({"model": net.state_dict(), "optimizer": optimizer.state_dict(), "epoch": epoch, "step": step,
                          "config": config.to_dict(), "rng_torch": torch.get_rng_state(), "rng_numpy": rng.bit_generator.state},
                         checkpoint_path)
            _atomic_save({"state_dict": net.state_dict(), "planner_config": planner_cfg.to_dict(),
                          "loss_config": config.loss, "mapkit_version": __version__}, run_dir / "model.pt")
            _curves(metrics, run_dir / "training_curves.png")
        if config.max_steps is not None and step >= config.max_steps:
            break
    if writer is not None:
        writer.close()
    seconds = time.perf_counter() - t_start
    last = next((m for m in reversed(metrics) if "train" in m), {})
    rate = samples_seen * world / train_seconds if train_seconds > 0 else math.nan
    return TrainSummary(run_dir, epoch, step, seconds, rate, last, baseline)
