"""TSDF fusion of ingested frames (Open3D VoxelBlockGrid) → fused cloud, mesh and the TSDF itself."""

from mapkit.fusion._tsdf import (
    CLOUD,
    MESH,
    TSDF,
    FuseConfig,
    FusionError,
    FuseSummary,
    estimate_blocks,
    fuse,
    fuse_store,
)

__all__ = ["CLOUD", "MESH", "TSDF", "FuseConfig", "FuseSummary", "FusionError", "estimate_blocks", "fuse", "fuse_store"]
