"""TSDF fusion of ingested frames (Open3D VoxelBlockGrid) → fused cloud, mesh and the TSDF itself; many
flights → one world.zarr, tile by tile on Dask (:func:`fuse_world`)."""

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
from mapkit.fusion._world import WORLD, WorldConfig, WorldSummary, fuse_world, open_world

__all__ = ["CLOUD", "FUSE_META", "MESH", "TSDF", "FuseConfig", "FuseSummary", "FusionError", "check_fused", "estimate_blocks",
           "fuse", "fuse_store", "WORLD", "WorldConfig", "WorldSummary", "fuse_world", "open_world"]
