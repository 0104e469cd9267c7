"""Training tuples: a workspace's frames.zarr + map.zarr → tuples.zarr, and what is inside it.

    python examples/05_export_training_tuples.py [WORKSPACE]

WORKSPACE holds frames.zarr and map.zarr (examples/01_ingest_and_map.py makes one). Without it the
example makes one from sample_data/forest.mcap in a temporary folder first. Each tuple is a depth
image, the body pose and velocity, and goals in the body frame: future poses of the flight, free
goals in view and goals hidden behind obstacles, each marked whether its straight line is blocked
in the map. The same as `mapkit export`. About 15 s on 2 cores.
"""

import sys
import tempfile
from pathlib import Path

import numpy as np
import zarr

from mapkit.esdf import EsdfConfig, build_esdf
from mapkit.export import GOAL_KIND_NAMES, ExportConfig, export_tuples
from mapkit.fusion import FuseConfig, fuse
from mapkit.ingest import IngestConfig

RECORDING = Path(__file__).resolve().parents[1] / "sample_data" / "forest.mcap"


def make_workspace(workspace: Path) -> None:
    """frames.zarr and map.zarr from every sixth frame of the sample forest (see example 01)."""
    fuse([RECORDING], workspace, FuseConfig(voxel=0.1), IngestConfig(stride=6), progress=False)
    build_esdf(workspace, EsdfConfig(voxel=0.2), progress=False)


def export(workspace: Path) -> None:
    """Export tuples from `workspace` and print the goal mix and the arrays of tuples.zarr."""
    summary = export_tuples(workspace, ExportConfig(goals_per_frame=5, seed=0), overwrite=True, progress=False)
    print(f"{summary.path}: {summary.frames} frames ({summary.train} train, {summary.val} val), {summary.goals} goals")
    print(f"  goal kinds {summary.kind_counts}, {summary.blocked_fraction:.0%} blocked")
    print(f"  goal distances (m) {summary.distance_histogram}")
    tuples = zarr.open_group(summary.path, mode="r")
    for name in sorted(tuples.array_keys()):
        print(f"  {name:<16} {tuples[name].dtype} {tuples[name].shape}")
    kinds = np.asarray(tuples["goal_kind"][0])
    goals = np.asarray(tuples["goals_body"][0])
    blocked = np.asarray(tuples["goal_blocked"][0])
    print("tuple 0's goals (body frame, m):")
    for kind, goal, is_blocked in zip(kinds, goals, blocked, strict=True):
        print(f"  {GOAL_KIND_NAMES[int(kind)]:<13} {goal.round(2)}{'  blocked' if is_blocked else ''}")


def main(argv: list[str]) -> None:
    if argv:
        export(Path(argv[0]))
        return
    with tempfile.TemporaryDirectory() as tmp:
        make_workspace(Path(tmp))
        export(Path(tmp))


if __name__ == "__main__":
    main(sys.argv[1:])
