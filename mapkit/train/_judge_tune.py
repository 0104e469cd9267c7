"""`mapkit lab tune-judge`: the flown-path head (``PlannerConfig.flown_samples``) fitted to flights.

The head reads :func:`mapkit.planner.flown_features` along each candidate's trajectory as flown; it
learns from flights recorded with ``EvalConfig.record_judge`` whether that stretch comes within the
robot's radius of the world (labels from the world, so it learns what the image hides). Everything
else keeps its weights.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from mapkit.errors import MapkitError
from mapkit.train._timing_tune import _write_run, with_new_head

if TYPE_CHECKING:
    from mapkit.planner import PlannerNet


class JudgeTuneError(MapkitError):
    """Bad input to `mapkit lab tune-judge`."""


@dataclass(frozen=True)
class JudgeTuneConfig:
    """How the flown-path head is fitted."""

    steps: int = 4000
    """Adam steps (about a minute on one core)."""
    lr: float = 1e-3
    """Adam's learning rate."""
    batch_size: int = 512
    """Candidates per step."""
    check_every: int = 250
    """Steps between validations; the weights with the lowest validation loss are kept."""
    seed: int = 0
    """Seed of a new head's initial weights and of the batch order."""
    positive_weight: float = 1.0
    """Weight of the colliding candidates in the cross-entropy (> 1 catches more, vetoes more)."""

    def validate(self) -> None:
        for name in ("steps", "batch_size", "check_every"):
            if getattr(self, name) < 1:
                raise JudgeTuneError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("lr", "positive_weight"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise JudgeTuneError(f"{name} must be > 0, got {value}")


@dataclass(frozen=True)
class JudgeRecords:
    """Labelled candidates (``judge.npz`` of ``EvalConfig.record_judge``)."""

    features: torch.Tensor
    """(R, N, F) float32 per point along each candidate's judged stretch (:func:`flown_features`)."""
    lengths: torch.Tensor
    """(R,) float32 metres of each candidate's trajectory within the horizon."""
    collides: torch.Tensor
    """(R,) bool: the stretch comes within ``robot_radius`` of the world."""
    horizon: float
    """Metres judged."""
    robot_radius: float
    """Metres the labels keep from the world."""
    history: float = 0.0
    """Seconds of earlier frames the clearances read (``EvalConfig.judge_history``); the fitted head
    reads as many (``flown_history``)."""

    def __len__(self) -> int:
        return int(self.collides.shape[0])


@dataclass(frozen=True)
class JudgeScore:
    """How a judge does on labelled candidates."""

    caught: float
    """Share of the colliding candidates it expects to collide (η >= 0.5)."""
    false_alarms: float
    """Share of the free candidates it expects to collide."""
    loss: float | None = None
    """Mean cross-entropy of its η (None for a rule)."""


@dataclass(frozen=True)
class JudgeTuneSummary:
    """What `mapkit lab tune-judge` did, on the validation candidates."""

    out_dir: Path
    train_rows: int
    val_rows: int
    colliding_share: float
    """Share of the validation candidates labelled colliding."""
    clearance_rule: JudgeScore
    """The rule "collides when a point comes within the robot's radius of a point of the depth image"."""
    before: JudgeScore | None
    """The model's own flown-path head (None: it had none)."""
    after: JudgeScore
    best_step: int
    """The step whose weights were kept."""
    history: float = 0.0
    """Seconds of earlier frames the records' clearances read (the fitted head's ``flown_history``)."""


def load_judge_records(folders: Sequence[Path]) -> JudgeRecords:
    """Every candidate recorded in the eval ``folders`` (each holding judge.npz)."""
    from mapkit._formats import JUDGE_FILE

    parts = []
    for folder in folders:
        path = Path(folder) / JUDGE_FILE
        if not path.is_file():
            raise JudgeTuneError(f"{folder} has no {JUDGE_FILE}; record it with the library's "
                                 "EvalConfig(methods=('learned',), record_judge=True), as the recipe's flights steps do")
        with np.load(path) as z:
            part = {k: z[k] for k in ("features", "lengths", "collides", "horizon", "robot_radius")}
            part["history"] = z["history"] if "history" in z.files else np.float64(0.0)  # recorded before histories
            parts.append((path, part))
    if not parts or sum(len(p["collides"]) for _, p in parts) == 0:
        raise JudgeTuneError(f"no recorded candidates in {', '.join(map(str, folders)) or '(no folder)'}")
    first_path, first = parts[0]
    for path, p in parts[1:]:
        same = (p["features"].shape[1:] == first["features"].shape[1:] and float(p["horizon"]) == float(first["horizon"])
                and float(p["robot_radius"]) == float(first["robot_radius"]))
        if len(p["collides"]) and not same:
            raise JudgeTuneError(f"{path} and {first_path} judge different stretches (points, horizon or radius): "
                                 "record them with the same model and robot radius")
        if len(p["collides"]) and float(p["history"]) != float(first["history"]):
            raise JudgeTuneError(f"{path} reads {float(p['history']):g} s of earlier frames, {first_path} "
                                 f"{float(first['history']):g} s: record both with the same judge_history")
    cat = {k: np.concatenate([p[k] for _, p in parts]) for k in ("features", "lengths", "collides")}
    return JudgeRecords(torch.from_numpy(cat["features"]).float(), torch.from_numpy(cat["lengths"]).float(),
                        torch.from_numpy(cat["collides"]).bool(), float(first["horizon"]), float(first["robot_radius"]),
                        float(first["history"]))


def _score(net: PlannerNet, records: JudgeRecords, pos_weight: float) -> JudgeScore:
    with torch.no_grad():
        logits = net.flown_logits(records.features, records.lengths)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(
            logits, records.collides.float(), pos_weight=torch.tensor(pos_weight))
    return _rates(logits >= 0, records.collides, float(loss))


def _rates(expects: torch.Tensor, collides: torch.Tensor, loss: float | None = None) -> JudgeScore:
    caught = float(expects[collides].float().mean()) if bool(collides.any()) else float("nan")
    false = float(expects[~collides].float().mean()) if bool((~collides).any()) else float("nan")
    return JudgeScore(caught=caught, false_alarms=false, loss=loss)


def clearance_rule(records: JudgeRecords) -> JudgeScore:
    """The depth image's own verdict: a candidate collides when one of its points comes within the
    robot's radius of a point of the image."""
    from mapkit.planner import CLEARANCE_CAP

    near = (records.features[..., 0] * CLEARANCE_CAP).amin(-1) < records.robot_radius
    return _rates(near, records.collides)


def fit_flown_head(net: PlannerNet, train: JudgeRecords, val: JudgeRecords, tune: JudgeTuneConfig, *,
                   progress: bool = True) -> tuple[JudgeScore, int]:
    """Fit ``net``'s flown-path head in place on ``train``; keep the weights with the lowest
    validation loss. Returns (their score on ``val``, their step)."""
    from tqdm import tqdm

    head = net.flown_mlp
    assert head is not None  # tune_judge gives the net a head first
    best, best_step, best_state = _score(net, val, tune.positive_weight).loss, 0, _copy(head)
    optimiser = torch.optim.Adam(head.parameters(), lr=tune.lr)
    generator = torch.Generator().manual_seed(tune.seed)
    weight = torch.tensor(tune.positive_weight)
    head.train()
    bar = tqdm(range(1, tune.steps + 1), desc="tune-judge", unit="step", disable=not progress, dynamic_ncols=True)
    for step in bar:
        index = torch.randint(0, len(train), (min(tune.batch_size, len(train)),), generator=generator)
        logits = net.flown_logits(train.features[index], train.lengths[index])
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, train.collides[index].float(),
                                                                    pos_weight=weight)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step % tune.check_every == 0 or step == tune.steps:
            now = _score(net, val, tune.positive_weight).loss
            assert now is not None and best is not None  # a head's score has a loss
            if now < best:
                best, best_step, best_state = now, step, _copy(head)
            bar.set_postfix(val=f"{now:.4f}", best=f"{best:.4f}")
    head.load_state_dict(best_state)
    head.eval()
    return _score(net, val, tune.positive_weight), best_step


def _copy(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in module.state_dict().items()}


def tune_judge(model: str | Path, records: Sequence[Path], val: Sequence[Path], out_dir: str | Path,
               config: JudgeTuneConfig | None = None, *, overwrite: bool = False,
               progress: bool = True) -> JudgeTuneSummary:
    """Fit the flown-path head of the model in ``model`` (a run directory, or "pretrained"; one is
    added when it has none) to the candidates recorded in the eval folders ``records``, choose the
    weights on ``val``, and write a run directory ``out_dir`` (model.pt and config.json, the latter with
    a ``judge_tune`` record of what was done)."""
    from mapkit.flight import Planner, resolve_model

    config = config or JudgeTuneConfig()
    config.validate()
    source = resolve_model(model)
    net = Planner.load(model).net
    train_set, val_set = load_judge_records(records), load_judge_records(val)
    if train_set.features.shape[1:] != val_set.features.shape[1:] or train_set.horizon != val_set.horizon:
        raise JudgeTuneError("the training and validation records judge different stretches: record both with one model")
    if train_set.history != val_set.history:
        raise JudgeTuneError(f"the training records read {train_set.history:g} s of earlier frames, the validation "
                             f"records {val_set.history:g} s: record both with the same judge_history")
    before = _score(net, val_set, config.positive_weight) if _fits(net, train_set) else None
    if before is None:
        shape = replace(net.config, flown_samples=int(train_set.features.shape[1]), flown_horizon=train_set.horizon)
        net = with_new_head(net, shape, "flown_mlp.", config.seed)
    net.config = replace(net.config, flown_history=train_set.history)  # the head reads what its records read
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a small head: one thread is as fast and leaves the other cores alone
    try:
        after, best_step = fit_flown_head(net, train_set, val_set, config, progress=progress)
    finally:
        torch.set_num_threads(threads)
    rule = clearance_rule(val_set)
    record = {"source": str(source), "records": [str(p) for p in records], "val": [str(p) for p in val],
              "train_rows": len(train_set), "val_rows": len(val_set), "config": asdict(config),
              "clearance_rule": asdict(rule), "val_before": None if before is None else asdict(before),
              "val_after": asdict(after), "best_step": best_step}
    _write_run(source, net, record, Path(out_dir), overwrite=overwrite, key="judge_tune",
               shape=("flown_samples", "flown_horizon", "flown_history"), error=JudgeTuneError)
    return JudgeTuneSummary(out_dir=Path(out_dir), train_rows=len(train_set), val_rows=len(val_set),
                            colliding_share=float(val_set.collides.float().mean()), clearance_rule=rule,
                            before=before, after=after, best_step=best_step, history=train_set.history)


def _fits(net: PlannerNet, records: JudgeRecords) -> bool:
    """Whether ``net`` has a flown-path head that reads the records' stretches; raises when it has
    one that reads others."""
    c = net.config
    if net.flown_mlp is None:
        return False
    if records.features.shape[1] != c.flown_samples or records.horizon != c.flown_horizon:
        raise JudgeTuneError(
            f"the records hold {records.features.shape[1]} points over {records.horizon} m per candidate; the model's "
            f"flown-path head reads {c.flown_samples} over {c.flown_horizon} m: record the flights with this model")
    return True

