"""Training tuples: frames.zarr + map.zarr → tuples.zarr (depth, poses, velocities, goals, split)."""

from mapkit.export._tuples import (
    FUTURE,
    GOAL_KIND_NAMES,
    HIDDEN,
    RANDOM,
    TUPLES,
    ExportConfig,
    ExportError,
    ExportSummary,
    blocked_lines,
    body_velocities,
    export_tuples,
    map_digest,
    split_segments,
)

__all__ = [
    "HIDDEN",
    "blocked_lines",
    "FUTURE",
    "GOAL_KIND_NAMES",
    "RANDOM",
    "TUPLES",
    "ExportConfig",
    "ExportError",
    "ExportSummary",
    "body_velocities",
    "export_tuples",
    "map_digest",
    "split_segments",
]
