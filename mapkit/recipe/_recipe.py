"""Recipes: how a shipped model is made, from nothing, as one declared and resumable chain of steps
(`mapkit train --recipe pretrained -o DIR`).

A recipe is a TOML file of ``[[step]]`` tables run in order; each step's ``kind`` names what it does
and its other keys are the fields of that kind's dataclass below (``options`` holds fields of the
stage's own config: :class:`~mapkit.dataset.DatasetConfig`, the training preset,
:class:`~mapkit.evaluation.EvalConfig`, :class:`TimingTuneConfig`, :class:`JudgeTuneConfig`). A step
refers to an earlier one by its ``name``; ``model`` at the top names the step whose model is the
result. Everything a step writes goes to ``DIR/steps/NAME``; ``DIR/recipe.json`` records the steps
done, so a run that stops resumes where it stopped (a dataset keeps its finished worlds, a training its
last epoch). The result is ``DIR/model.pt`` and ``DIR/config.json``, with the recipe beside them.
"""

from __future__ import annotations

import tomllib
from dataclasses import MISSING, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal

from mapkit.errors import MapkitError


class RecipeError(MapkitError):
    """A recipe that cannot be read or run; the message names the value and the fix."""


RECIPES = {"pretrained": "flight/pretrained/recipe.toml"}
"""Built-in recipes, by name: files under the mapkit package."""
STATE_FILE = "recipe.json"


@dataclass(frozen=True)
class DatasetStep:
    """Simulated worlds flown and run through ingest → fuse → esdf → export (:func:`~mapkit.dataset.build_dataset`)."""

    name: str
    worlds: int
    seed: int
    minutes: float = 0.0
    """Estimated minutes on 2 idle cores (the progress line's ETA)."""
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class TrainStep:
    """A training run on a dataset step's worlds, the last ``val_worlds`` held out; ``init`` starts
    from an earlier step's model (a fine-tune)."""

    name: str
    dataset: str
    val_worlds: int
    preset: str = "cpu"
    init: str | None = None
    planner: dict[str, Any] = field(default_factory=dict)
    loss: dict[str, Any] = field(default_factory=dict)
    minutes: float = 0.0
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ConfigureStep:
    """A model's planner config changed where it is deployed (the weights stay), e.g. the speed profile."""

    name: str
    model: str
    planner: dict[str, Any]
    minutes: float = 0.0


@dataclass(frozen=True)
class FlightsStep:
    """`mapkit eval` flights of a model (method ``learned``) on each seed, recording what the next
    tuning step learns from: ``record = "plans"`` (time allocation) or ``"judge"`` (the flown-path head)."""

    name: str
    model: str
    seeds: list[int]
    record: Literal["plans", "judge"]
    pairs: int = 60
    stack: Literal["full", "none"] = "full"
    minutes: float = 0.0
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class TuneTimingStep:
    """The Time Allocation Net tuned on recorded plans (:func:`tune_timing`)."""

    name: str
    model: str
    plans: list[str]
    val: list[str]
    minutes: float = 0.0
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class TuneJudgeStep:
    """The flown-path head fitted to recorded candidates (:func:`tune_judge`)."""

    name: str
    model: str
    records: list[str]
    val: list[str]
    minutes: float = 0.0
    options: dict[str, Any] = field(default_factory=dict)


Step = DatasetStep | TrainStep | ConfigureStep | FlightsStep | TuneTimingStep | TuneJudgeStep
STEP_KINDS: dict[str, type] = {"dataset": DatasetStep, "train": TrainStep, "configure": ConfigureStep,
                               "flights": FlightsStep, "tune_timing": TuneTimingStep, "tune_judge": TuneJudgeStep}


@dataclass(frozen=True)
class Recipe:
    """Steps run in order; ``model`` is the step whose model is the result."""

    name: str
    model: str
    steps: tuple[Step, ...]
    text: str = ""
    """The TOML it was read from (kept beside the result)."""

    def step(self, name: str) -> Step:
        for s in self.steps:
            if s.name == name:
                return s
        raise RecipeError(f"recipe {self.name!r}: no step named {name!r}; steps: {', '.join(s.name for s in self.steps)}")

    def miniature(self) -> Recipe:
        """The same chain at toy sizes (two short worlds, a few optimiser steps, one pair a seed): what
        the test suite runs so the recipe cannot rot."""
        return replace(self, name=f"{self.name}-miniature", steps=tuple(_tiny(s) for s in self.steps))


def load_recipe(recipe: str | Path) -> Recipe:
    """A built-in recipe by name (:data:`RECIPES`) or a recipe file."""
    path = Path(recipe)
    if str(recipe) in RECIPES:
        path = Path(__file__).resolve().parents[1] / RECIPES[str(recipe)]
    elif path.suffix != ".toml" or not path.is_file():
        raise RecipeError(f"--recipe {recipe}: not a recipe; use one of {', '.join(RECIPES)} or a .toml file")
    text = path.read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RecipeError(f"{path}: not TOML ({exc}); fix the file") from None
    return parse_recipe(data, text=text, source=str(path))


def parse_recipe(data: dict[str, Any], *, text: str = "", source: str = "recipe") -> Recipe:
    """A recipe from its parsed TOML (checked: known kinds and fields, names defined before use)."""
    _known(data, {"name", "model", "step"}, source)
    steps: list[Step] = []
    for i, table in enumerate(data.get("step", [])):
        kind = table.get("kind")
        if kind not in STEP_KINDS:
            raise RecipeError(f"{source}: step {i + 1} has kind {kind!r}; use one of {', '.join(STEP_KINDS)}")
        cls = STEP_KINDS[kind]
        body = {k: v for k, v in table.items() if k != "kind"}
        _known(body, {f.name for f in fields(cls)}, f"{source}: step {i + 1} ({kind})")
        try:
            steps.append(cls(**body))
        except TypeError:
            required = [f.name for f in fields(cls) if f.default is MISSING and f.default_factory is MISSING]
            raise RecipeError(f"{source}: step {i + 1} ({kind}) lacks a field; required: {', '.join(required)}") from None
    recipe = Recipe(name=str(data.get("name", Path(source).stem)), model=str(data.get("model", "")),
                    steps=tuple(steps), text=text)
    _check_references(recipe, source)
    return recipe


def _known(table: dict[str, Any], valid: set[str], where: str) -> None:
    unknown = sorted(set(table) - valid)
    if unknown:
        raise RecipeError(f"{where}: unknown field {unknown[0]!r}; valid fields: {', '.join(sorted(valid))}")


def _check_references(recipe: Recipe, source: str) -> None:
    """Every step's inputs name an earlier step of the right kind; names are unique."""
    seen: dict[str, Step] = {}
    for s in recipe.steps:
        if s.name in seen:
            raise RecipeError(f"{source}: two steps are named {s.name!r}; give each step its own name")
        for ref, kinds in _inputs(s):
            if ref not in seen or not isinstance(seen[ref], kinds):
                raise RecipeError(f"{source}: step {s.name!r} reads {ref!r}, which is not an earlier "
                                  f"{' or '.join(k.__name__ for k in kinds)}")
        seen[s.name] = s
    if recipe.model not in seen or not isinstance(seen[recipe.model], _MODEL_STEPS):
        raise RecipeError(f"{source}: model = {recipe.model!r} must name a step that makes a model")


_MODEL_STEPS = (TrainStep, ConfigureStep, TuneTimingStep, TuneJudgeStep)


def _inputs(s: Step) -> list[tuple[str, tuple[type, ...]]]:
    """(step name, kinds it may be) of every input of ``s``."""
    if isinstance(s, TrainStep):
        return [(s.dataset, (DatasetStep,))] + ([(s.init, _MODEL_STEPS)] if s.init else [])
    if isinstance(s, (ConfigureStep, FlightsStep)):
        return [(s.model, _MODEL_STEPS)]
    if isinstance(s, TuneTimingStep):
        return [(s.model, _MODEL_STEPS)] + [(n, (FlightsStep,)) for n in (*s.plans, *s.val)]
    if isinstance(s, TuneJudgeStep):
        return [(s.model, _MODEL_STEPS)] + [(n, (FlightsStep,)) for n in (*s.records, *s.val)]
    return []


def _tiny(s: Step) -> Step:
    """``s`` at toy sizes."""
    if isinstance(s, DatasetStep):
        return replace(s, worlds=2, minutes=0.1, options={**s.options, "duration": 4.0, "rate": 3.0, "workers": 1,
                                                          "kinds": ["forest", "office"]})
    if isinstance(s, TrainStep):
        return replace(s, val_worlds=1, minutes=0.1, options={**s.options, "epochs": 1, "max_steps": 2, "val_batches": 1})
    if isinstance(s, FlightsStep):
        return replace(s, seeds=s.seeds[:1], pairs=1, minutes=0.1,
                       options={**s.options, "worlds": ["forest"], "workers": 1})
    if isinstance(s, (TuneTimingStep, TuneJudgeStep)):
        return replace(s, minutes=0.1, options={**s.options, "steps": 4, "check_every": 2})
    return s
