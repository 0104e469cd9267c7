"""Training the self-supervised planner (`mapkit train`): presets, data, loop, checkpoints, DDP."""

from mapkit.train._config import PRESETS, TrainConfig, TrainConfigError, preset
from mapkit.train._data import TrainDataError, TupleSamples, TupleStore
from mapkit.train._judge_tune import (
    JudgeRecords,
    JudgeScore,
    JudgeTuneConfig,
    JudgeTuneError,
    JudgeTuneSummary,
    clearance_rule,
    fit_flown_head,
    load_judge_records,
    tune_judge,
)
from mapkit.train._loop import TrainSummary, set_threads, train, validate
from mapkit.train._provenance import simulated_worlds, workspace_camera
from mapkit.train._timing_tune import (
    PlanInputs,
    TimingTuneConfig,
    TimingTuneError,
    TimingTuneSummary,
    TuneOutcome,
    load_plan_inputs,
    tune_tan,
    tune_timing,
)

__all__ = [
    "PRESETS",
    "JudgeRecords",
    "JudgeScore",
    "JudgeTuneConfig",
    "JudgeTuneError",
    "JudgeTuneSummary",
    "PlanInputs",
    "TimingTuneConfig",
    "TimingTuneError",
    "TimingTuneSummary",
    "TrainConfig",
    "TrainConfigError",
    "TrainDataError",
    "TrainSummary",
    "TupleSamples",
    "TupleStore",
    "TuneOutcome",
    "preset",
    "set_threads",
    "simulated_worlds",
    "train",
    "validate",
    "clearance_rule",
    "fit_flown_head",
    "load_judge_records",
    "tune_judge",
    "load_plan_inputs",
    "tune_tan",
    "tune_timing",
    "workspace_camera",
]
