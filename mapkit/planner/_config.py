"""The planner network's configuration (:class:`PlannerConfig`) and its named presets."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any, Literal

from mapkit.planner._errors import PlannerError
from mapkit.trajopt import BoundaryScale


@dataclass
class PlannerConfig:
    """Configuration of :class:`PlannerNet` and of how its trajectory is timed (presets: :func:`planner_preset`)."""

    input_size: tuple[int, int] = (96, 160)
    """(h, w) pixels the depth image is resized to before the encoder. Paper: (360, 640)."""
    max_depth: float = 10.0
    """Metres. Depth is clipped to [0, max_depth] and divided by it (channel 0 in [0, 1]); the goal
    is divided by it too before its embedding."""
    num_keypoints: int = 5
    """K, predicted key-points; the trajectory has K segments (origin → k1 → ... → kK)."""
    encoder_width: float = 0.25
    """ResNet-18 channel scale (1.0 = 64/128/256/512, the only width that loads torchvision weights)."""
    goal_embed_dim: int = 16
    """Width of the goal's linear embedding, broadcast over the feature map and concatenated to it."""
    conv_channels: tuple[int, int] = (64, 32)
    """Output channels of the head's two 3×3 conv layers (ReLU after each)."""
    pooled_size: tuple[int, int] = (3, 5)
    """(h, w) the head's conv output is average-pooled to before flattening (a coarse spatial layout)."""
    mlp_hidden: tuple[int, int] = (256, 128)
    """Hidden widths of the three-layer key-point MLP (flattened features → h1 → h2 → 3K)."""
    eta_hidden: tuple[int, int] = (64, 32)
    """Hidden widths of the parallel three-layer η MLP (flattened features → h1 → h2 → 1)."""
    num_candidates: int = 1
    """M, candidate key-point paths, each from its own detour anchor (:meth:`anchors`), with a learned
    score that picks one (trained winner-takes-all). 1 = a single regressed path (the paper)."""
    depth_check: bool = False
    """With several candidates: the judge also reads each candidate checked against the depth image
    (:func:`mapkit.planner.depth_margins`); every call then needs the camera's calibration (``camera=``)."""
    flown_samples: int = 0
    """N > 0: a second collision head (``flown_mlp``) judges each candidate by N points along the first
    ``flown_horizon`` metres of its trajectory as flown (:func:`mapkit.planner.flown_features`), and its
    η replaces the judge's (``PlannerNet.judge_flown``; fitted by ``mapkit lab tune-judge``). 0: the judge's η."""
    flown_horizon: float = 1.5
    """Metres of each candidate's flown trajectory the flown-path head reads (``flown_samples``)."""
    flown_history: float = 0.0
    """Seconds of the flight's earlier depth frames whose points the flown-path head's clearance also
    reads (a pillar beside the vehicle has left the image by the time the path passes it); 0: the
    current image only. A single plan has no earlier frames."""
    velocity_input: bool = False
    """The key-point MLP and the judge also read the body's velocity / ``cruise_speed`` (pass
    ``velocity=``): the trajectory starts from it. The paper's net does not."""
    head_activation: Literal["relu", "leaky_relu"] = "relu"
    """Activation between the layers of the key-point, η and judge MLPs; "leaky_relu" (slope 0.1)
    cannot die (with ReLU, the paper's, most key-point units died within an epoch on 47 worlds)."""
    tan_hidden: tuple[int, ...] = (64, 64)
    """Hidden widths of the Time Allocation Net MLP."""
    tan_boundary: bool = False
    """The TAN also reads the start velocity and acceleration and the end speed, and its U_T target is
    computed under the same conditions; without them it learns one split from rest-to-rest targets
    (the paper's TAN). Off in the presets (trained jointly it flew with more effort)."""
    tan_boundary_scale: BoundaryScale = "limits"
    """With ``tan_boundary``: how the boundary inputs are made unitless (``limits``: by the cruise
    speed and ``accel``; ``duration``: by each plan's total time and path length)."""
    cruise_speed: float = 2.0
    """m/s the total time's speed profile over the key-point path tends to (:func:`mapkit.planner.total_time`)."""
    accel: float = 1.0
    """m/s², the speed profile's rate of speeding up and slowing down (trained at 1.0; the shipped
    model flies with 1.5, set in its stored config after training)."""
    min_segment_time: float = 0.3
    """Seconds every segment gets at least (the TAN splits the rest): snap grows like 1 / T⁷."""
    min_total_time: float = 1.0
    """Seconds, lower bound of the total time."""
    max_total_time: float = 15.0
    """Seconds, upper bound of the total time."""

    def __post_init__(self) -> None:
        h, w = (int(v) for v in self.input_size)
        if h < 32 or w < 32:
            raise PlannerError(f"input_size must be at least (32, 32) pixels, got {self.input_size}")
        self.input_size = (h, w)
        if not self.max_depth > 0:
            raise PlannerError(f"max_depth must be > 0 metres, got {self.max_depth}")
        if self.num_keypoints < 1:
            raise PlannerError(f"num_keypoints must be >= 1, got {self.num_keypoints}")
        if not self.cruise_speed > 0:
            raise PlannerError(f"cruise_speed must be > 0 m/s, got {self.cruise_speed}")
        if not (self.accel > 0 and math.isfinite(self.accel)):
            raise PlannerError(f"accel must be > 0 m/s², got {self.accel}")
        if not 0 <= self.min_segment_time * self.num_keypoints <= self.max_total_time:
            raise PlannerError(f"min_segment_time must be >= 0 s and num_keypoints × it <= max_total_time, "
                               f"got {self.min_segment_time}")
        if not 0 < self.min_total_time <= self.max_total_time:
            raise PlannerError(
                f"need 0 < min_total_time <= max_total_time, got {self.min_total_time} and {self.max_total_time}"
            )
        if self.num_candidates < 1:
            raise PlannerError(f"num_candidates must be >= 1, got {self.num_candidates}")
        if self.flown_samples < 0 or not self.flown_horizon > 0 or not self.flown_history >= 0:
            raise PlannerError(f"need flown_samples >= 0, flown_horizon > 0 metres and flown_history >= 0 seconds, got "
                               f"{self.flown_samples}, {self.flown_horizon} and {self.flown_history}")
        if self.head_activation not in ("relu", "leaky_relu"):
            raise PlannerError(f"head_activation must be 'relu' or 'leaky_relu', got {self.head_activation!r}")
        if len(self.conv_channels) != 2 or len(self.mlp_hidden) != 2 or len(self.eta_hidden) != 2:
            raise PlannerError("conv_channels, mlp_hidden and eta_hidden must each have two entries")

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (tuples as lists) for JSON; :meth:`from_dict` inverts it."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PlannerConfig:
        """Build a config from :meth:`to_dict` output (a saved model's: removed fields load while they hold
        what the net now always does); unknown keys raise :class:`PlannerError`."""
        data = drop_removed_fields(data, PlannerError, REMOVED_FIELDS, "planner ")
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise PlannerError(f"unknown PlannerConfig fields {unknown}; known: {sorted(names)}")
        kw: dict[str, Any] = {k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()}
        return cls(**kw)

    def anchors(self) -> tuple[tuple[float, float], ...]:
        """One (lateral, vertical) peak offset in metres per candidate's anchor detour, at a 6 m goal (scaled
        with the goal distance, zero at the start and at the goal): straight first, then left/right detours
        of growing width, one climb for M >= 6."""
        m = self.num_candidates
        out: list[tuple[float, float]] = [(0.0, 0.0)]
        if m >= 6:
            out.append((0.0, 0.8))
        width = 1.2
        while len(out) < m:
            out.append((width, 0.0))
            if len(out) < m:
                out.append((-width, 0.0))
            width += 1.2
        return tuple(out[:m])


REMOVED_FIELDS: dict[str, Any] = {"candidate_anchors": (), "keypoint_init_scale": 0.01, "extra": {}}
"""Removed PlannerConfig fields a saved model may still name, with the value that builds the net as now."""


def drop_removed_fields(values: dict[str, Any], error: type[Exception], removed: dict[str, Any],
                        prefix: str) -> dict[str, Any]:
    """Saved fields ``values`` less those in ``removed`` (:data:`REMOVED_FIELDS`, the LossConfig and
    TrainConfig ones) that hold the value mapkit now always behaves as with; one that holds another
    raises ``error`` naming it (``prefix``: its table, "loss ")."""
    for name, value in values.items():
        if name in removed and not _same_as_removed(name, value, values, removed[name]):
            raise error(f"{prefix}{name}={json.dumps(value)}: the field was removed in mapkit 0.1.0 (issue 57), which "
                        f"always behaves as with {name}={json.dumps(removed[name])}; train a new run without it, "
                        "or use a mapkit checkout from before issue 57 for this one")
    return {k: v for k, v in values.items() if k not in removed}


def _same_as_removed(name: str, value: Any, values: dict[str, Any], now: Any) -> bool:
    """Whether removed field ``name`` = ``value`` (among ``values``) behaves as mapkit's fixed ``now``."""
    if name == "detour_cap":  # only counted with a detour weight
        return bool(values.get("detour_weight", 0.0) == 0.0)
    if name == "collision_distance" and value is not None:  # None meant the robot radius (default 0.3 m)
        return bool(value == values.get("robot_radius", 0.3))
    if name == "extra":  # free-form notes the net never read
        return True
    return bool(value == now or (isinstance(value, list) and tuple(value) == now))


PLANNER_PRESETS: dict[str, dict[str, Any]] = {
    "paper": dict(
        input_size=(360, 640), encoder_width=1.0, goal_embed_dim=16, conv_channels=(512, 256),
        pooled_size=(3, 5), mlp_hidden=(1024, 512), eta_hidden=(256, 64), tan_hidden=(128, 128),
    ),
    "cpu": dict(
        input_size=(96, 160), encoder_width=0.25, goal_embed_dim=16, conv_channels=(64, 32),
        pooled_size=(3, 5), mlp_hidden=(256, 128), eta_hidden=(64, 32), tan_hidden=(64, 64),
    ),
}
"""Named presets: "paper" (full-width ResNet-18 on 360×640 depth) and "cpu" (quarter width on 96×160)."""


def planner_preset(name: str, **overrides: Any) -> PlannerConfig:
    """A fresh :class:`PlannerConfig` for the preset ``name`` ("paper" or "cpu") with ``overrides``."""
    if name not in PLANNER_PRESETS:
        raise PlannerError(f"unknown planner preset {name!r}; choose one of {sorted(PLANNER_PRESETS)}")
    return PlannerConfig(**{**PLANNER_PRESETS[name], **overrides})
