"""Running a recipe (:mod:`mapkit.recipe._recipe`): each step's library call, writing into
``DIR/steps/NAME``; ``DIR/recipe.json`` records the steps done, so a stopped run resumes."""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapkit._version import __version__
from mapkit.recipe._recipe import (
    STATE_FILE,
    STEP_KINDS,
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


@dataclass
class RecipeSummary:
    out_dir: Path
    steps_run: list[str]
    steps_skipped: list[str]
    seconds: float


def run_recipe(recipe: Recipe, out_dir: str | Path, *, force: bool = False, progress: bool = True) -> RecipeSummary:
    """Run ``recipe`` into ``out_dir``, resuming the steps a previous run finished there. A run made by
    another mapkit version is refused unless ``force``."""
    out = Path(out_dir)
    state = _open_state(out, recipe, force)
    t0, run, skipped = time.perf_counter(), [], []
    for i, s in enumerate(recipe.steps):
        if s.name in state["done"]:
            skipped.append(s.name)
            continue
        if progress:
            _say(f"recipe {recipe.name}: step {i + 1}/{len(recipe.steps)} {_kind(s)} {s.name!r} "
                 f"(about {s.minutes:g} min); {_eta(recipe, state, i, time.perf_counter() - t0)}")
        started = time.perf_counter()
        run_step(s, out, recipe, progress=progress)
        state["done"][s.name] = {"seconds": round(time.perf_counter() - started, 1)}
        _write_state(out, state)
        run.append(s.name)
    _publish(out, recipe)
    summary = RecipeSummary(out, run, skipped, time.perf_counter() - t0)
    if progress:
        _say(f"recipe {recipe.name}: {len(run)} steps run, {len(skipped)} already done, "
             f"{summary.seconds / 60:.1f} min; wrote {out / 'model.pt'}, config.json and recipe.toml")
    return summary


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def _kind(s: Step) -> str:
    return next(k for k, cls in STEP_KINDS.items() if isinstance(s, cls))


def _eta(recipe: Recipe, state: dict[str, Any], index: int, elapsed: float) -> str:
    """The time left: the remaining steps' estimates, scaled by how the finished steps compared with
    theirs (this machine's pace)."""
    left = sum(s.minutes for s in recipe.steps[index:] if s.name not in state["done"])
    done = [(s.minutes, state["done"][s.name]["seconds"]) for s in recipe.steps if s.name in state["done"]]
    estimated, taken = sum(m for m, _ in done), sum(t for _, t in done) / 60
    pace = taken / estimated if estimated > 0 and taken > 0 else 1.0
    return f"elapsed {elapsed / 60:.0f} min, ETA {left * pace:.0f} min"


def _open_state(out: Path, recipe: Recipe, force: bool) -> dict[str, Any]:
    path = out / STATE_FILE
    if not path.is_file():
        out.mkdir(parents=True, exist_ok=True)
        state = {"recipe": recipe.name, "mapkit": __version__, "done": {}}
        (out / "recipe.toml").write_text(recipe.text)
        _write_state(out, state)
        return state
    state = json.loads(path.read_text())
    if state.get("recipe") != recipe.name:
        raise RecipeError(f"-o {out} holds recipe {state.get('recipe')!r}, not {recipe.name!r}; use another folder")
    if state.get("mapkit") != __version__ and not force:
        raise RecipeError(f"-o {out} was started by mapkit {state.get('mapkit')}, this is {__version__}: its steps may "
                          "differ; use a new folder, or --force to resume anyway")
    state["mapkit"] = __version__
    return state


def _write_state(out: Path, state: dict[str, Any]) -> None:
    tmp = out / (STATE_FILE + ".tmp")
    tmp.write_text(json.dumps(state, indent=1))
    tmp.replace(out / STATE_FILE)


def _publish(out: Path, recipe: Recipe) -> None:
    """The result model beside the recipe: DIR/model.pt and DIR/config.json."""
    src = out / "steps" / recipe.model
    for name in ("model.pt", "config.json"):
        shutil.copyfile(src / name, out / name)
