"""Recipes: a model made from nothing by one declared, resumable chain of steps (datasets, training,
flights that record what the tuning steps learn from, time allocation and judge tuning):
`mapkit train --recipe pretrained -o DIR`. After ``mapkit.evaluation`` in the pipeline: a recipe
flies its models."""

from mapkit.recipe._recipe import (
    RECIPES,
    ConfigureStep,
    DatasetStep,
    FlightsStep,
    Recipe,
    RecipeError,
    TrainStep,
    TuneJudgeStep,
    TuneTimingStep,
    load_recipe,
    parse_recipe,
)
from mapkit.recipe._run import RecipeSummary, run_recipe

__all__ = ["RECIPES", "ConfigureStep", "DatasetStep", "FlightsStep", "Recipe", "RecipeError", "RecipeSummary",
           "TrainStep", "TuneJudgeStep", "TuneTimingStep", "load_recipe", "parse_recipe", "run_recipe"]
