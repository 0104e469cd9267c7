"""TSDF fusion of ingested frames (Open3D VoxelBlockGrid) → fused cloud, mesh and the TSDF itself."""

from mapkit.fusion._tsdf import (
    CLOUD,
    FUSE_META,
    MESH,
    TSDF,
    FuseConfig,
    FuseSummary,
    FusionError,
    check_fused,
    estimate_blocks,
    fuse,
    fuse_store,
)

__all__ = ["CLOUD", "FUSE_META", "MESH", "TSDF", "FuseConfig", "FuseSummary", "FusionError", "check_fused", "estimate_blocks",
           "fuse", "fuse_store"]
