"""Training data at scale: many simulated worlds → normal workspaces (`mapkit dataset`)."""

from mapkit._dask import available_cpus
from mapkit.dataset._build import (
    DONE,
    MANIFEST,
    CameraVariant,
    DatasetConfig,
    DatasetError,
    DatasetSummary,
    WorldSpec,
    build_dataset,
    build_world,
    dataset_workspaces,
    parse_cameras,
    split_worlds,
    world_specs,
)

__all__ = [
    "DONE",
    "MANIFEST",
    "CameraVariant",
    "DatasetConfig",
    "DatasetError",
    "DatasetSummary",
    "WorldSpec",
    "available_cpus",
    "build_dataset",
    "build_world",
    "dataset_workspaces",
    "split_worlds",
    "parse_cameras",
    "world_specs",
]
