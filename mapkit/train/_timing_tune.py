"""`mapkit tune-timing`: the Time Allocation Net fine-tuned on the plans the planner makes in flight.

Training fits the TAN to the gradient-descent split of the key-points the network makes on training
tuples. In the closed loop the network sees other inputs (its own flights, mid-manoeuvre start
states), and there the shipped TAN's split cost 4.7× the snap of the gradient-descent split per plan
(median; 1.28× over the sum of all plans; 1494 plans of dev seed 7). Here the TAN alone learns from
plans recorded in flight (``mapkit eval --record-plans``) by minimising the minimum-snap cost of the
trajectory through the key-points under its own split: no labels, the same cost the gradient-descent
allocation minimises, in the same conditions (start state, end speed, total-time rule, minimum
segment time) the planner uses it in. Everything but the TAN keeps its weights.

On the shipped model it lowers the executed effort (×0.73–0.82) but costs office success (87.7 →
83.8 % over five held-out seeds), so the shipped model keeps its TAN (docs/train.md).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from mapkit.errors import MapkitError
from mapkit.workspace import atomic_output

if TYPE_CHECKING:
    from mapkit.planner import PlannerConfig, PlannerNet
    from mapkit.trajopt import TimeAllocationNet


class TimingTuneError(MapkitError):
    """Bad input to `mapkit tune-timing`."""


@dataclass(frozen=True)
class TimingTuneConfig:
    """How the TAN is fine-tuned."""

    steps: int = 4000
    """Adam steps (a few minutes on one core)."""
    lr: float = 1e-3
    """Adam's learning rate."""
    batch_size: int = 256
    """Plans per step."""
    check_every: int = 250
    """Steps between validations; the weights with the lowest validation cost are kept."""
    seed: int = 0
    """Seed of the batch order (and of a new TAN's initial weights)."""
    boundary_inputs: bool = False
    """Replace the TAN by a new one that also reads the start velocity and acceleration and the end
    speed (``PlannerConfig.tan_boundary``), trained from scratch on the plans. A TAN without them
    cannot tell a plan started at cruise speed from one started at rest."""

    def validate(self) -> None:
        for name in ("steps", "batch_size", "check_every"):
            if getattr(self, name) < 1:
                raise TimingTuneError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise TimingTuneError(f"--lr must be > 0, got {self.lr}")


@dataclass(frozen=True)
class PlanInputs:
    """Recorded plans (``plans.npz`` of ``mapkit eval --record-plans``), as float64 tensors."""

    waypoints: torch.Tensor
    """(P, K+1, 3) body frame metres: the start and the network's key-points."""
    start: torch.Tensor
    """(P, 3, 3) velocity, acceleration, jerk at the start."""
    end_speed: torch.Tensor
    """(P,) m/s."""
    cruise_speed: torch.Tensor | None = None
    """(P,) m/s: each plan's cruise speed in flight (slowed for its turns); NaN or None: the model's."""
    decel: torch.Tensor | None = None
    """(P,) m/s²: each plan's rate of slowing down to its end speed; NaN or None: the model's ``accel``."""

    def __len__(self) -> int:
        return int(self.waypoints.shape[0])

    def take(self, index: torch.Tensor) -> PlanInputs:
        def rows(v: torch.Tensor | None) -> torch.Tensor | None:
            return None if v is None else v[index]
        return PlanInputs(self.waypoints[index], self.start[index], self.end_speed[index],
                          rows(self.cruise_speed), rows(self.decel))

    def profile(self, config: PlannerConfig) -> tuple[torch.Tensor, torch.Tensor]:
        """(cruise speed, deceleration) of each plan, the model's where the recording has none."""
        def filled(value: torch.Tensor | None, default: float) -> torch.Tensor:
            if value is None:
                return torch.full_like(self.end_speed, default)
            return torch.where(torch.isnan(value), torch.full_like(value, default), value)
        return filled(self.cruise_speed, config.cruise_speed), filled(self.decel, config.accel)


@dataclass(frozen=True)
class TimingTuneSummary:
    """What `mapkit tune-timing` did. Costs are the snap of the trajectory through each plan's key-points,
    as a ratio to the gradient-descent allocation's on the same plan."""

    out_dir: Path
    train_plans: int
    val_plans: int
    before: tuple[float, float]
    """Validation (median per-plan ratio, ratio of the summed costs) with the TAN as it was."""
    after: tuple[float, float]
    """The same with the kept weights."""
    best_step: int
    """The step whose weights were kept (0: none improved on the TAN as it was)."""


def load_plan_inputs(folders: Sequence[Path], *, num_segments: int) -> PlanInputs:
    """Every plan recorded in the eval ``folders`` (each holding plans.npz) for a TAN of ``num_segments``."""
    from mapkit.evaluation import PLANS_FILE

    parts: list[dict[str, np.ndarray]] = []
    for folder in folders:
        path = Path(folder) / PLANS_FILE
        if not path.is_file():
            raise TimingTuneError(f"{folder} has no {PLANS_FILE}; make it with `mapkit eval --methods learned "
                                  "--record-plans -o FOLDER` (any seed that is not a held-out one)")
        with np.load(path) as z:
            part = {k: z[k] for k in ("waypoints", "start", "end_speed")}
            # plans recorded before 2026-12-03 have no speed profile: NaN, the model's own
            part.update({k: z[k] if k in z else np.full(len(part["end_speed"]), np.nan) for k in ("cruise_speed", "decel")})
        if len(part["end_speed"]) and part["waypoints"].shape[1] != num_segments + 1:
            raise TimingTuneError(f"{path} holds plans of {part['waypoints'].shape[1] - 1} segments; the model's TAN "
                                  f"allocates {num_segments}: record the plans with the same model")
        parts.append(part)
    if not parts or sum(len(p["end_speed"]) for p in parts) == 0:
        raise TimingTuneError(f"no recorded plans in {', '.join(map(str, folders)) or '(no folder)'}")
    cat = {k: torch.from_numpy(np.concatenate([p[k] for p in parts if len(p["end_speed"])])).double()
           for k in ("waypoints", "start", "end_speed", "cruise_speed", "decel")}
    return PlanInputs(cat["waypoints"], cat["start"], cat["end_speed"], cat["cruise_speed"], cat["decel"])


def plan_costs(tan: TimeAllocationNet | None, config: PlannerConfig, plans: PlanInputs) -> torch.Tensor:
    """(P,) snap cost of each plan's minimum-snap trajectory through its key-points, timed by ``tan``
    (None: the gradient-descent allocation, 30 iterations), as the planner times it in flight (each
    plan at its recorded cruise speed and deceleration)."""
    from mapkit.planner import plan_timing
    from mapkit.trajopt import min_snap

    cruise_speed, decel = plans.profile(config)
    timing = plan_timing(plans.waypoints, plans.start, plans.end_speed, config,
                         allocation="tan" if tan is not None else "gradient", tan=tan, gradient_iters=30,
                         cruise_speed=cruise_speed, decel=decel)
    durations = timing.durations if tan is None else _durations(timing.shares, timing.total, config)
    return min_snap(plans.waypoints, durations, start=plans.start, end=timing.end).snap_cost()


def _durations(shares: torch.Tensor, total: torch.Tensor, config: PlannerConfig) -> torch.Tensor:
    """Durations from the TAN's shares with their gradient (plan_timing detaches them for flight)."""
    from mapkit.planner._timing import durations_from_shares

    return durations_from_shares(shares, total, config.min_segment_time)


def _ratios(tan: TimeAllocationNet, config: PlannerConfig, plans: PlanInputs, reference: torch.Tensor) -> tuple[float, float]:
    """(median per-plan ratio, ratio of the sums) of the TAN's costs to ``reference``."""
    with torch.no_grad():
        cost = plan_costs(tan, config, plans)
    return float((cost / reference).median()), float(cost.sum() / reference.sum())


def tune_tan(tan: TimeAllocationNet, config: PlannerConfig, train: PlanInputs, val: PlanInputs,
             tune: TimingTuneConfig, *, progress: bool = True) -> tuple[tuple[float, float], tuple[float, float], int]:
    """Fine-tune ``tan`` in place on ``train`` (mean log cost ratio to the gradient-descent split; the
    log weighs a cheap plan's waste like an expensive one's) and keep the weights that give the lowest
    summed cost on ``val``. Returns the validation ratios before and after, and the kept step."""
    from tqdm import tqdm

    with torch.no_grad():
        ref_train = plan_costs(None, config, train)
        ref_val = plan_costs(None, config, val)
    before = _ratios(tan, config, val, ref_val)
    best, best_step, best_state = before, 0, {k: v.clone() for k, v in tan.state_dict().items()}
    optimiser = torch.optim.Adam(tan.parameters(), lr=tune.lr)
    generator = torch.Generator().manual_seed(tune.seed)
    tan.train()
    bar = tqdm(range(1, tune.steps + 1), desc="tune-timing", unit="step", disable=not progress, dynamic_ncols=True)
    for step in bar:
        index = torch.randint(0, len(train), (min(tune.batch_size, len(train)),), generator=generator)
        cost = plan_costs(tan, config, train.take(index))
        loss = torch.log(cost.clamp_min(1e-12) / ref_train[index].clamp_min(1e-12)).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step % tune.check_every == 0 or step == tune.steps:
            now = _ratios(tan, config, val, ref_val)
            if now[1] < best[1]:
                best, best_step, best_state = now, step, {k: v.clone() for k, v in tan.state_dict().items()}
            bar.set_postfix(val_sum_ratio=f"{now[1]:.3f}", best=f"{best[1]:.3f}")
    tan.load_state_dict(best_state)
    tan.eval()
    return before, best, best_step


def tune_timing(model: str | Path, plans: Sequence[Path], val: Sequence[Path], out_dir: str | Path,
                config: TimingTuneConfig | None = None, *, overwrite: bool = False,
                progress: bool = True) -> TimingTuneSummary:
    """Fine-tune the TAN of the model in ``model`` (a run directory, or "pretrained") on the plans
    recorded in the eval folders ``plans``, choose the weights on ``val``, and write a run directory
    ``out_dir`` (model.pt and config.json, the latter with a ``timing_tune`` record of what was done)."""
    config = config or TimingTuneConfig()
    config.validate()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small batches: one thread is as fast and leaves the other cores alone
    try:
        return _tune_and_write(model, plans, val, Path(out_dir), config, overwrite=overwrite, progress=progress)
    finally:
        torch.set_num_threads(threads)


def _tune_and_write(model: str | Path, plans: Sequence[Path], val: Sequence[Path], out: Path,
                    config: TimingTuneConfig, *, overwrite: bool, progress: bool) -> TimingTuneSummary:
    """The body of :func:`tune_timing`."""
    from mapkit.planning import Planner, resolve_model

    source = resolve_model(model)
    net = Planner.load(model).net
    M = net.tan.config.num_segments
    train_set, val_set = load_plan_inputs(plans, num_segments=M), load_plan_inputs(val, num_segments=M)
    if config.boundary_inputs and not net.config.tan_boundary:
        with torch.no_grad():  # "before" is the model's own TAN, not the new one's random start
            before = _ratios(net.tan, net.config, val_set, plan_costs(None, net.config, val_set))
        net = _with_boundary_tan(net, seed=config.seed)
        _, after, best_step = tune_tan(net.tan, net.config, train_set, val_set, config, progress=progress)
    else:
        before, after, best_step = tune_tan(net.tan, net.config, train_set, val_set, config, progress=progress)
    record = {"source": str(source), "plans": [str(p) for p in plans], "val": [str(p) for p in val],
              "train_plans": len(train_set), "val_plans": len(val_set), "config": asdict(config),
              "val_before": {"median_ratio": before[0], "sum_ratio": before[1]},
              "val_after": {"median_ratio": after[0], "sum_ratio": after[1]}, "best_step": best_step}
    _write_run(source, net, record, out, overwrite=overwrite)
    return TimingTuneSummary(out_dir=out, train_plans=len(train_set), val_plans=len(val_set), before=before,
                             after=after, best_step=best_step)


def _with_boundary_tan(net: PlannerNet, *, seed: int) -> PlannerNet:
    """The same network with a new, untrained TAN that reads the boundary conditions."""
    from dataclasses import replace

    from mapkit.planner import PlannerNet

    torch.manual_seed(seed)
    out = PlannerNet(replace(net.config, tan_boundary=True))
    kept = {k: v for k, v in net.state_dict().items() if not k.startswith("tan.")}
    missing, unexpected = out.load_state_dict(kept, strict=False)
    assert not unexpected and all(k.startswith("tan.") for k in missing)  # only the TAN is new
    return out.eval()


def _write_run(source: Path, net: PlannerNet, record: dict, out: Path, *, overwrite: bool) -> None:
    """``out``: the source's model.pt with the new weights (and planner config) and a ``timing_tune``
    note, its config.json with the same note; any REPRODUCE.md is left out (it describes the source)."""
    from mapkit._saved import load_saved

    saved = load_saved(source / "model.pt", "mapkit planner", TimingTuneError, ("planner_config", "state_dict"))
    saved = {**saved, "state_dict": net.state_dict(), "planner_config": net.config.to_dict(),
             "timing_tune": json.loads(json.dumps(record))}
    run_config = json.loads((source / "config.json").read_text()) if (source / "config.json").is_file() else {}
    run_config["timing_tune"] = record
    with atomic_output(out, overwrite=overwrite) as tmp:
        tmp.mkdir(parents=True)
        torch.save(saved, tmp / "model.pt")
        (tmp / "config.json").write_text(json.dumps(run_config, indent=1) + "\n")
