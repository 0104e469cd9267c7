"""What each kind of recipe step does (:mod:`mapkit.train._recipe`): the library call of its stage,
writing into ``DIR/steps/NAME``, resuming what a stopped run left there."""

from __future__ import annotations

import json
import os
from dataclasses import fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapkit.train._recipe import (
    ConfigureStep,
    DatasetStep,
    FlightsStep,
    Recipe,
    RecipeError,
    Step,
    TrainStep,
    TuneTimingStep,
)

if TYPE_CHECKING:
    from mapkit.evaluation import EvalConfig


def run_step(s: Step, out: Path, recipe: Recipe, *, progress: bool = True) -> None:
    """Run one step of ``recipe`` into ``out/steps/NAME``."""
    here = out / "steps" / s.name
    if isinstance(s, DatasetStep):
        _dataset(s, here, progress)
    elif isinstance(s, TrainStep):
        _train(s, out, progress)
    elif isinstance(s, ConfigureStep):
        _configure(s, out / "steps" / s.model, here)
    elif isinstance(s, FlightsStep):
        _flights(s, out / "steps" / s.model, here, progress)
    elif isinstance(s, TuneTimingStep):
        from mapkit.train._timing_tune import TimingTuneConfig, tune_timing

        config = _config(TimingTuneConfig, s.options, s.name)
        tune_timing(out / "steps" / s.model, _flown(out, recipe, s.plans), _flown(out, recipe, s.val), here, config,
                    overwrite=True, progress=progress)
    else:
        from mapkit.train._judge_tune import JudgeTuneConfig, tune_judge

        config = _config(JudgeTuneConfig, s.options, s.name)
        tune_judge(out / "steps" / s.model, _flown(out, recipe, s.records), _flown(out, recipe, s.val), here, config,
                   overwrite=True, progress=progress)


def _config(cls: type, options: dict[str, Any], step: str) -> Any:
    """``cls(**options)``, TOML lists as tuples; an unknown field names the valid ones."""
    valid = {f.name for f in fields(cls)}
    unknown = sorted(set(options) - valid)
    if unknown:
        raise RecipeError(f"step {step!r}: {cls.__name__} has no field {unknown[0]!r}; valid: {', '.join(sorted(valid))}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in options.items()})


def _flown(out: Path, recipe: Recipe, names: list[str]) -> list[Path]:
    """The eval folders of flights steps ``names``, one per seed."""
    folders = []
    for name in names:
        step = recipe.step(name)
        assert isinstance(step, FlightsStep)  # checked when the recipe was read
        folders += [out / "steps" / name / f"seed_{seed}" for seed in step.seeds]
    return folders


def _dataset(s: DatasetStep, root: Path, progress: bool) -> None:
    from mapkit.dataset import DatasetConfig, build_dataset, parse_cameras
    from mapkit.export import ExportConfig

    options = dict(s.options)
    if "export" in options:
        options["export"] = _config(ExportConfig, options["export"], s.name)
    if isinstance(options.get("cameras"), str):
        options["cameras"] = parse_cameras(options["cameras"])
    config = _config(DatasetConfig, {"worlds": s.worlds, "seed": s.seed, **options}, s.name)
    summary = build_dataset(root, config, progress=progress)
    if summary.failed:
        name, reason = next(iter(summary.failed.items()))
        raise RecipeError(f"step {s.name!r}: world {name} failed ({reason}); run the recipe again to retry it")


def _train(s: TrainStep, out: Path, progress: bool) -> None:
    from mapkit.dataset import split_worlds
    from mapkit.train import preset, train

    runs = out / "steps"
    init = None if s.init is None else str(runs / s.init)
    config = preset(s.preset, **{**s.options, "name": s.name, "init": init, "planner": s.planner, "loss": s.loss})
    train_ws, val_ws = split_worlds(runs / s.dataset, s.val_worlds)
    resume = (runs / s.name / "checkpoint.pt").is_file()
    train(train_ws, config, runs_dir=runs, resume=resume, overwrite=not resume, progress=progress,
          val_workspaces=val_ws)


def _configure(s: ConfigureStep, src: Path, dst: Path) -> None:
    """``src``'s model with planner config fields replaced, its config.json noting the change."""
    import torch

    from mapkit.planner import PlannerConfig

    saved = torch.load(src / "model.pt", map_location="cpu", weights_only=True)
    unknown = sorted(set(s.planner) - set(saved["planner_config"]))
    if unknown:
        raise RecipeError(f"step {s.name!r}: the planner config has no field {unknown[0]!r}")
    saved["planner_config"] = {**saved["planner_config"], **s.planner}
    PlannerConfig.from_dict(saved["planner_config"])  # checks the values
    dst.mkdir(parents=True, exist_ok=True)
    torch.save(saved, dst / "model.pt")
    run = json.loads((src / "config.json").read_text())
    run["configured"] = {"from": s.model, "planner": s.planner}
    (dst / "config.json").write_text(json.dumps(run, indent=1))


def _flights(s: FlightsStep, model: Path, here: Path, progress: bool) -> None:
    from mapkit.evaluation import EvalConfig, evaluate

    options = {"workers": os.cpu_count() or 1, **s.options}
    base: EvalConfig = _config(EvalConfig, options, s.name)
    base = replace(base, methods=("learned",), stacks=(s.stack,), pairs=s.pairs, record_plans=s.record == "plans",
                   record_judge=s.record == "judge")
    for seed in s.seeds:
        folder = here / f"seed_{seed}"
        if not (folder / "results.json").is_file():
            evaluate(model, folder, replace(base, seed=seed), overwrite=True, progress=progress)
