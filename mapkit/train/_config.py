"""Typed training configuration and its named presets."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any

from mapkit._choices import TRAINED_WEIGHTS, PresetName, TrainedWeights
from mapkit.errors import MapkitError
from mapkit.planner import LossConfig, PlannerConfig
from mapkit.planner._config import REMOVED_FIELDS as REMOVED_PLANNER_FIELDS
from mapkit.planner._config import drop_removed_fields
from mapkit.planner._loss import REMOVED_FIELDS as REMOVED_LOSS_FIELDS


class TrainConfigError(MapkitError):
    """A training option or preset that cannot be used."""


REMOVED_FIELDS: dict[str, Any] = {"weight_decay": 0.0, "grad_clip": 10.0}
"""Removed TrainConfig options a saved run's config.json may still name, with the value that trains as now."""


@dataclass
class TrainConfig:
    """Everything a run needs; saved as runs/NAME/config.json. Each field is a setting of `mapkit train`
    (`mapkit config train`; nested fields as planner.FIELD / loss.FIELD)."""

    name: str = "run"
    """Run directory name under --runs-dir."""
    preset: PresetName = "cpu"
    """The preset this config started from ('paper' or 'cpu')."""
    epochs: int = 24
    """Passes over the training samples."""
    batch_size: int = 16
    """Samples per optimiser step (per process under torchrun)."""
    lr: float = 1e-4
    """Adam learning rate."""
    seed: int = 0
    """Seeds weights, shuffling and sampling; CPU runs are reproducible."""
    device: str = "cpu"
    """'cpu', 'cuda' or 'cuda:N'."""
    max_steps: int | None = None
    """Stop after this many optimiser steps in total (smoke tests, quick looks)."""
    val_batches: int | None = None
    """Limit validation to this many batches (None: all)."""
    goals_together: bool = False
    """Batches hold whole tuples (every goal of a depth image): the encoder runs once per image."""
    corridor: float | None = None
    """Flight-corridor half-width (m) for min_snap during training; None = through the key-points."""
    init: str | None = None
    """Start from the weights of this model (a run directory, its model.pt, or "pretrained") instead of
    random ones (fine-tuning); its planner configuration must equal this run's."""
    only: TrainedWeights = "all"
    """Which weights train. "tan": only the Time Allocation Net, on the key-points of the frozen
    ``init`` model (its TAN options may differ from the init model's; the best epoch is chosen by the
    held-out U_T). "judge": only the candidates' judge (scores and η; a one-path net's η head)."""
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    """The planner network's configuration (mapkit.planner)."""
    loss: LossConfig = field(default_factory=LossConfig)
    """The training loss's weights and parameters (mapkit.planner)."""
    _planner_keys: tuple[str, ...] = field(default=(), repr=False, compare=False)
    """PlannerConfig fields given by name (preset, planner settings, config.json), in order: config.json
    lists them even at their default value."""
    _loss_keys: tuple[str, ...] = field(default=(), repr=False, compare=False)
    """LossConfig fields given by name, likewise."""

    def to_dict(self) -> dict[str, Any]:
        """config.json's form: ``planner`` / ``loss`` as the fields given by name, then any other
        field that differs from its default (JSON types)."""
        data: dict[str, Any] = {f.name: getattr(self, f.name) for f in _option_fields()}
        data["planner"] = _named_fields(self.planner, self._planner_keys)
        data["loss"] = _named_fields(self.loss, self._loss_keys)
        return json.loads(json.dumps(data))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TrainConfig:
        """Build a config from :meth:`to_dict`'s form (config.json, a preset with overrides);
        ``planner`` / ``loss`` may be dicts of fields or config objects. Unknown options and
        ill-typed nested fields raise :class:`TrainConfigError` naming them."""
        known = {f.name for f in _option_fields()}
        unknown = sorted(set(data) - known)
        if unknown:
            raise TrainConfigError(f"unknown training options {unknown}; known: {sorted(known)}")
        options = dict(data)
        planner, planner_keys = _nested(options.pop("planner", {}), PlannerConfig, "planner")
        loss, loss_keys = _nested(options.pop("loss", {}), LossConfig, "loss")
        return cls(**options, planner=planner, loss=loss, _planner_keys=planner_keys, _loss_keys=loss_keys)

    @classmethod
    def from_saved(cls, data: dict[str, Any]) -> TrainConfig:
        """The config of a run's config.json (its other records skipped); removed fields load while they
        hold the behaviour mapkit now always has (:meth:`from_dict` knows only today's fields)."""
        known = {f.name for f in _option_fields()} | set(REMOVED_FIELDS)
        options = drop_removed_fields({k: v for k, v in data.items() if k in known}, TrainConfigError, REMOVED_FIELDS, "")
        for key, removed in (("planner", REMOVED_PLANNER_FIELDS), ("loss", REMOVED_LOSS_FIELDS)):
            if isinstance(options.get(key), dict):
                options[key] = drop_removed_fields(options[key], TrainConfigError, removed, f"{key} ")
        return cls.from_dict(options)

    def validate(self) -> None:
        """Raise :class:`TrainConfigError` naming the first option out of its range."""
        if self.epochs < 1:
            raise TrainConfigError(f"--epochs {self.epochs} must be at least 1")
        if self.batch_size < 1:
            raise TrainConfigError(f"batch_size {self.batch_size} must be at least 1")
        if not self.lr > 0:
            raise TrainConfigError(f"lr {self.lr} must be positive")
        if self.corridor is not None and not self.corridor > 0:
            raise TrainConfigError(f"corridor {self.corridor} must be a positive half-width in metres")
        if self.only not in TRAINED_WEIGHTS:
            raise TrainConfigError(f"only {self.only!r}: expected one of {', '.join(TRAINED_WEIGHTS)}")
        if self.only != "all" and not self.init:
            raise TrainConfigError(f"only={self.only} trains part of another model on its frozen key-points: "
                                   "pass --init MODEL")
        if self.max_steps is not None and self.max_steps < 1:
            raise TrainConfigError(f"max_steps {self.max_steps} must be at least 1")


def _option_fields() -> list[dataclasses.Field]:
    """TrainConfig's options (its fields less the private bookkeeping of named nested fields)."""
    return [f for f in dataclasses.fields(TrainConfig) if not f.name.startswith("_")]


def _named_fields(config: PlannerConfig | LossConfig, keys: tuple[str, ...]) -> dict[str, Any]:
    """The fields in ``keys`` (in that order), then every other one that differs from its default."""
    values = dataclasses.asdict(config)
    defaults = dataclasses.asdict(type(config)())
    return {k: values[k] for k in [*keys, *(k for k in values if k not in keys and values[k] != defaults[k])]}


def _nested(value: Any, cls: type, option: str) -> tuple[Any, tuple[str, ...]]:
    """A PlannerConfig / LossConfig from a dict of fields (type-checked: a wrong one is a one-line
    error naming it) or as given, with the names the dict gave."""
    if isinstance(value, cls):
        return value, ()
    if not isinstance(value, dict):
        raise TrainConfigError(f"{option}: expected {cls.__name__} fields as an object, got {value!r}")
    from mapkit._fields import check_fields

    check_fields(value, cls, option, TrainConfigError)
    built = cls.from_dict(value) if hasattr(cls, "from_dict") else cls(**value)
    return built, tuple(value)


PRESETS: dict[str, TrainConfig] = {
    # The paper's set-up: 360x640 input, batch 16, Adam 1e-4, 50 epochs, full-width ResNet-18.
    "paper": TrainConfig.from_dict({"preset": "paper", "epochs": 50, "batch_size": 16, "lr": 1e-4,
                                    "planner": {"input_size": [360, 640], "encoder_width": 1.0}}),
    # A model on a 2-core CPU within the hour: small input, a quarter-width encoder, eight scored
    # candidate paths checked against the depth image, a sharper obstacle hinge, LeakyReLU heads.
    "cpu": TrainConfig.from_dict({"preset": "cpu", "epochs": 8, "batch_size": 16, "lr": 5e-4,
                                  "planner": {"input_size": [96, 160], "encoder_width": 0.25, "num_candidates": 8,
                                              "head_activation": "leaky_relu", "depth_check": True,
                                              "velocity_input": True},
                                  "loss": {"obstacle_softness": 0.3, "time_target_iters": 5, "score_temperature": 0.5},
                                  "goals_together": True}),
}


def preset(preset_name: str, /, **overrides: Any) -> TrainConfig:
    """A copy of a named preset with fields replaced (nested dicts are merged)."""
    if preset_name not in PRESETS:
        raise TrainConfigError(f"--preset {preset_name!r}: expected one of {', '.join(PRESETS)}")
    data = PRESETS[preset_name].to_dict()
    for key, value in overrides.items():
        if key in ("planner", "loss") and isinstance(value, dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return TrainConfig.from_dict(data)
