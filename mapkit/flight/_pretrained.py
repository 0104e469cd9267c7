"""The planner shipped with mapkit: ``--model pretrained`` in `plan`, `eval` and `view`."""

from __future__ import annotations

import os
from pathlib import Path

PRETRAINED = "pretrained"
"""The model name that selects the shipped weights."""


def pretrained_dir() -> Path:
    """Directory of the shipped model (model.pt, config.json with the training camera and worlds,
    and REPRODUCE.md with the commands that made it)."""
    return Path(__file__).resolve().parent / "pretrained"


def resolve_model(model: str | os.PathLike[str]) -> Path:
    """A run directory for ``model``: the shipped model's directory for "pretrained", else the path."""
    if str(model) == PRETRAINED:
        return pretrained_dir()
    return Path(model)
