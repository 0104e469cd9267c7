"""`mapkit lab tune-timing`: the Time Allocation Net fine-tuned on the plans the planner makes in flight
(``EvalConfig.record_plans``), whose inputs differ from the training tuples', in the conditions the
planner times them in, to imitate each segment's duration in the gradient-descent split. Everything but
the TAN keeps its weights.
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

from mapkit._choices import BOUNDARY_SCALES, TIMING_OBJECTIVES, BoundaryScale, TimingObjective
from mapkit.errors import MapkitError
from mapkit.workspace import atomic_output

if TYPE_CHECKING:
    from mapkit.planner import PlannerConfig, PlannerNet
    from mapkit.trajopt import TimeAllocationNet


class TimingTuneError(MapkitError):
    """Bad input to `mapkit lab tune-timing`."""


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
    speed (``PlannerConfig.tan_boundary``), trained from scratch on the plans."""
    boundary_scale: BoundaryScale = "limits"
    """With ``boundary_inputs``: how the new TAN makes them unitless (``PlannerConfig.tan_boundary_scale``)."""
    tan_hidden: tuple[int, ...] | None = None
    """Hidden widths of a new TAN trained from scratch on the plans (None: the model's TAN, or with
    ``boundary_inputs`` a new one of its width)."""
    lr_decay: bool = True
    """Cosine decay of the learning rate to 1 % of ``lr`` over ``steps`` (off: constant)."""
    objective: TimingObjective = "imitate"
    """The only one left, ``imitate``: the weighted mean squared log ratio of each segment's duration to
    the gradient-descent split's (``first_weight`` on the first segment, 1 on the others). Also what
    chooses the weights kept."""
    first_weight: float = 4.0
    """The weight of the first segment, the one a replanning flight executes."""

    def validate(self) -> None:
        for name in ("steps", "batch_size", "check_every"):
            if getattr(self, name) < 1:
                raise TimingTuneError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise TimingTuneError(f"lr must be > 0, got {self.lr}")
        if self.objective not in TIMING_OBJECTIVES:
            raise TimingTuneError(f"objective must be one of {', '.join(TIMING_OBJECTIVES)}, got {self.objective!r}")
        if self.boundary_scale not in BOUNDARY_SCALES:
            raise TimingTuneError(f"boundary_scale must be one of {', '.join(BOUNDARY_SCALES)}, got {self.boundary_scale!r}")
        if self.boundary_scale != "limits" and not self.boundary_inputs:
            raise TimingTuneError(f"boundary_scale {self.boundary_scale} scales the boundary inputs: set boundary_inputs too")
        if self.tan_hidden is not None and (not self.tan_hidden or min(self.tan_hidden) < 1):
            raise TimingTuneError(f"tan_hidden must be widths >= 1 (e.g. 256,256,256), got {self.tan_hidden}")
        if not (math.isfinite(self.first_weight) and self.first_weight > 0):
            raise TimingTuneError(f"first_weight must be > 0, got {self.first_weight}")


@dataclass(frozen=True)
class PlanInputs:
    """Recorded plans (``plans.npz`` of ``EvalConfig.record_plans``), as float64 tensors."""

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
    """What `mapkit lab tune-timing` did (snap costs as ratios to the gradient-descent split's)."""

    out_dir: Path
    train_plans: int
    val_plans: int
    before: tuple[float, float]
    """Validation (median per-plan ratio, ratio of the summed costs) with the TAN as it was."""
    after: tuple[float, float]
    """The same with the kept weights."""
    best_step: int
    """The step whose weights were kept (0: none improved on the TAN as it was)."""
    objective: tuple[float, float]
    """The validation score of the config's objective before and after (:attr:`TuneOutcome.objective`)."""


def load_plan_inputs(folders: Sequence[Path], *, num_segments: int) -> PlanInputs:
    """Every plan recorded in the eval ``folders`` (each holding plans.npz) for a TAN of ``num_segments``."""
    from mapkit._formats import PLANS_FILE

    parts: list[dict[str, np.ndarray]] = []
    for folder in folders:
        path = Path(folder) / PLANS_FILE
        if not path.is_file():
            raise TimingTuneError(f"{folder} has no {PLANS_FILE}; record it with the library's "
                                  "EvalConfig(methods=('learned',), record_plans=True), as the recipe's flights steps do")
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
    (None: gradient descent) as the planner times it in flight."""
    from mapkit.trajopt import min_snap

    durations, end = _timed(tan, config, plans)
    return min_snap(plans.waypoints, durations, start=plans.start, end=end).snap_cost()


def _timed(tan: TimeAllocationNet | None, config: PlannerConfig, plans: PlanInputs) -> tuple[torch.Tensor, torch.Tensor]:
    """Durations (P, M) of each plan as the planner times it in flight (a TAN's keep their gradient;
    None: gradient descent) and the end states (P, 4, 3) its trajectory ends in."""
    from mapkit.planner import plan_timing
    from mapkit.planner._timing import durations_from_shares

    cruise_speed, decel = plans.profile(config)
    timing = plan_timing(plans.waypoints, plans.start, plans.end_speed, config,
                         allocation="tan" if tan is not None else "gradient", tan=tan, gradient_iters=30,
                         cruise_speed=cruise_speed, decel=decel)
    if tan is None:
        return timing.durations, timing.end
    # plan_timing detaches the TAN's durations for flight; here they keep the shares' gradient
    return durations_from_shares(timing.shares, timing.total, config.min_segment_time), timing.end


@dataclass(frozen=True)
class _Reference:
    """The gradient-descent split of a set of plans."""

    cost: torch.Tensor
    """(P,) snap cost of each plan."""
    durations: torch.Tensor
    """(P, M) seconds."""

    @classmethod
    def of(cls, config: PlannerConfig, plans: PlanInputs) -> _Reference:
        from mapkit.trajopt import min_snap

        with torch.no_grad():  # one gradient descent (the slow part) for both
            durations, end = _timed(None, config, plans)
            cost = min_snap(plans.waypoints, durations, start=plans.start, end=end).snap_cost()
        return cls(cost, durations)

    def take(self, index: torch.Tensor) -> _Reference:
        return _Reference(self.cost[index], self.durations[index])


def _objective(tan: TimeAllocationNet, config: PlannerConfig, plans: PlanInputs, reference: _Reference,
               tune: TimingTuneConfig) -> torch.Tensor:
    """(P,) the value of ``tune.objective`` for each plan (lower is better)."""
    durations, _ = _timed(tan, config, plans)
    weights = torch.ones(durations.shape[1], dtype=durations.dtype)
    weights[0] = tune.first_weight
    error = torch.log(durations.clamp_min(1e-9) / reference.durations.clamp_min(1e-9))
    return (error**2 * weights).sum(-1) / weights.sum()


@dataclass(frozen=True)
class TuneOutcome:
    """What :func:`tune_tan` did, on the validation plans (fields as :class:`TimingTuneSummary`'s;
    ``objective``: the mean weighted squared log ratio)."""

    before: tuple[float, float]
    after: tuple[float, float]
    best_step: int
    objective: tuple[float, float]


def _snap_ratios(tan: TimeAllocationNet, config: PlannerConfig, plans: PlanInputs, reference: _Reference) -> tuple[float, float]:
    """(median per-plan ratio, ratio of the sums) of the TAN's snap costs to the reference's."""
    with torch.no_grad():
        cost = plan_costs(tan, config, plans)
    return float((cost / reference.cost).median()), float(cost.sum() / reference.cost.sum())


def _score(tan: TimeAllocationNet, config: PlannerConfig, plans: PlanInputs, reference: _Reference,
           tune: TimingTuneConfig) -> float:
    """The validation score that chooses the weights kept (lower is better)."""
    with torch.no_grad():
        return float(_objective(tan, config, plans, reference, tune).mean())


def tune_tan(tan: TimeAllocationNet, config: PlannerConfig, train: PlanInputs, val: PlanInputs,
             tune: TimingTuneConfig, *, progress: bool = True) -> TuneOutcome:
    """Fine-tune ``tan`` in place on ``train`` (``tune.objective`` against the gradient-descent split)
    and keep the weights that score lowest on ``val``."""
    from tqdm import tqdm

    ref_train, ref_val = _Reference.of(config, train), _Reference.of(config, val)
    before = _score(tan, config, val, ref_val, tune)
    best, best_step, best_state = before, 0, {k: v.clone() for k, v in tan.state_dict().items()}
    snap_before = _snap_ratios(tan, config, val, ref_val)
    optimiser = torch.optim.Adam(tan.parameters(), lr=tune.lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, tune.steps, eta_min=tune.lr / 100) if tune.lr_decay else None
    generator = torch.Generator().manual_seed(tune.seed)
    tan.train()
    bar = tqdm(range(1, tune.steps + 1), desc="tune-timing", unit="step", disable=not progress, dynamic_ncols=True)
    for step in bar:
        index = torch.randint(0, len(train), (min(tune.batch_size, len(train)),), generator=generator)
        loss = _objective(tan, config, train.take(index), ref_train.take(index), tune).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if schedule is not None:
            schedule.step()
        if step % tune.check_every == 0 or step == tune.steps:
            now = _score(tan, config, val, ref_val, tune)
            if now < best:
                best, best_step, best_state = now, step, {k: v.clone() for k, v in tan.state_dict().items()}
            bar.set_postfix(val=f"{now:.3f}", best=f"{best:.3f}")
    tan.load_state_dict(best_state)
    tan.eval()
    return TuneOutcome(before=snap_before, after=_snap_ratios(tan, config, val, ref_val), best_step=best_step,
                       objective=(before, best))


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
    from mapkit.flight import Planner, resolve_model

    source = resolve_model(model)
    net = Planner.load(model).net
    M = net.tan.config.num_segments
    train_set, val_set = load_plan_inputs(plans, num_segments=M), load_plan_inputs(val, num_segments=M)
    own: tuple[tuple[float, float], float] | None = None
    if _needs_new_tan(net.config, config):
        # "before" is the model's own TAN, not the new one's random start
        reference = _Reference.of(net.config, val_set)
        own = (_snap_ratios(net.tan, net.config, val_set, reference),
               _score(net.tan, net.config, val_set, reference, config))
        net = _with_new_tan(net, config)
    outcome = tune_tan(net.tan, net.config, train_set, val_set, config, progress=progress)
    before, score_before = own or (outcome.before, outcome.objective[0])
    after, score_after = outcome.after, outcome.objective[1]
    record = {"source": str(source), "plans": [str(p) for p in plans], "val": [str(p) for p in val],
              "train_plans": len(train_set), "val_plans": len(val_set), "config": asdict(config),
              "val_before": {"median_ratio": before[0], "sum_ratio": before[1], "objective": score_before},
              "val_after": {"median_ratio": after[0], "sum_ratio": after[1], "objective": score_after},
              "best_step": outcome.best_step}
    _write_run(source, net, record, out, overwrite=overwrite)
    return TimingTuneSummary(out_dir=out, train_plans=len(train_set), val_plans=len(val_set), before=before,
                             after=after, best_step=outcome.best_step, objective=(score_before, score_after))


def _needs_new_tan(planner: PlannerConfig, tune: TimingTuneConfig) -> bool:
    """Whether the model's TAN cannot take the tuning: other inputs, another scale or another width."""
    other_inputs = tune.boundary_inputs and (not planner.tan_boundary or planner.tan_boundary_scale != tune.boundary_scale)
    return other_inputs or (tune.tan_hidden is not None and tuple(tune.tan_hidden) != tuple(planner.tan_hidden))


def _with_new_tan(net: PlannerNet, tune: TimingTuneConfig) -> PlannerNet:
    """The same network with a new, untrained TAN: reading the boundary conditions (on the tuning's
    scale) if asked or if the model's did, of the tuning's width if given."""
    from dataclasses import replace

    boundary = tune.boundary_inputs or net.config.tan_boundary
    scale = tune.boundary_scale if tune.boundary_inputs else net.config.tan_boundary_scale
    hidden = tuple(tune.tan_hidden) if tune.tan_hidden is not None else tuple(net.config.tan_hidden)
    config = replace(net.config, tan_boundary=boundary, tan_boundary_scale=scale, tan_hidden=hidden)
    return with_new_head(net, config, "tan.", tune.seed)


def with_new_head(net: PlannerNet, config: PlannerConfig, head: str, seed: int) -> PlannerNet:
    """A net of ``config`` with ``net``'s weights but a new ``head`` (its state-dict prefix), seeded by ``seed``."""
    from mapkit.planner import PlannerNet

    torch.manual_seed(seed)
    out = PlannerNet(config)
    kept = {k: v for k, v in net.state_dict().items() if not k.startswith(head)}
    missing, unexpected = out.load_state_dict(kept, strict=False)
    assert not unexpected and all(k.startswith(head) for k in missing)  # only the head is new
    return out.eval()


TAN_SHAPE = ("tan_boundary", "tan_boundary_scale", "tan_hidden")
"""The planner fields a new TAN may change."""


def _write_run(source: Path, net: PlannerNet, record: dict, out: Path, *, overwrite: bool,
               key: str = "timing_tune", shape: tuple[str, ...] = TAN_SHAPE,
               error: type[MapkitError] = TimingTuneError) -> None:
    """``out``: the source's model.pt and config.json with the new weights and planner config and a
    ``key`` note (``timing_tune``, ``judge_tune``). ``shape``: the planner fields the tuning may have changed."""
    from mapkit._saved import load_saved

    saved = load_saved(source / "model.pt", "mapkit planner", error, ("planner_config", "state_dict"))
    saved = {**saved, "state_dict": net.state_dict(), "planner_config": net.config.to_dict(),
             key: json.loads(json.dumps(record))}
    run_config = json.loads((source / "config.json").read_text()) if (source / "config.json").is_file() else {}
    run_config[key] = record
    _note_shape(run_config, net.config, shape)
    with atomic_output(out, overwrite=overwrite) as tmp:
        tmp.mkdir(parents=True)
        torch.save(saved, tmp / "model.pt")
        (tmp / "config.json").write_text(json.dumps(run_config, indent=2) + "\n")


def _note_shape(run_config: dict, planner: PlannerConfig, fields: tuple[str, ...]) -> None:
    """config.json's ``planner`` and ``planner_resolved`` with a new head's shape ``fields``, so the run's
    config builds a net its weights fit."""
    shape = {k: list(v) if isinstance(v, tuple) else v for k, v in ((k, getattr(planner, k)) for k in fields)}
    resolved = run_config.get("planner_resolved")
    if isinstance(resolved, dict) and all(resolved.get(k) == v for k, v in shape.items()):
        return  # the head kept its shape
    for key in ("planner", "planner_resolved"):
        if isinstance(run_config.get(key), dict):
            run_config[key].update(shape)
