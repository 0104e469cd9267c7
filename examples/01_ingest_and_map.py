"""A recording → frames.zarr → cloud.ply → map.zarr: the first three stages on a sample flight.

    python examples/01_ingest_and_map.py [WORKSPACE]

Ingests every third frame of sample_data/forest.mcap, fuses them into a point cloud and builds
the signed distance map (ESDF) from it. The same as `mapkit ingest`, `mapkit fuse` and
`mapkit esdf`. Without WORKSPACE it works in a temporary folder that is removed at the end.
About 15 s on 2 cores.
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

from mapkit.esdf import EsdfConfig, build_esdf
from mapkit.fusion import FuseConfig, fuse
from mapkit.ingest import IngestConfig, ingest, open_frames_store

RECORDING = Path(__file__).resolve().parents[1] / "sample_data" / "forest.mcap"
# Every third of the 300 frames: consecutive frames at 30 Hz add little to the map.
EVERY_THIRD = IngestConfig(stride=3)


def make_map(workspace: Path) -> None:
    """Ingest, fuse and build the ESDF in `workspace`, printing what each stage made."""
    frames = ingest([RECORDING], workspace, EVERY_THIRD, overwrite=True, progress=False)
    print(f"ingest: {frames.frames} frames of {frames.width}x{frames.height} px → {frames.path}")

    store = open_frames_store(workspace)  # depth stays on disk until indexed
    depth = store.depth[0]
    print(f"  frame 0: {len(store)} frames; depth {depth.shape}, nearest {np.nanmin(depth):.2f} m (NaN = no return); "
          f"body at {store.T_world_body[0][:3, 3].round(2)} m")

    # fuse() reuses the up-to-date frames.zarr written above (same recording, same IngestConfig).
    fused = fuse([RECORDING], workspace, FuseConfig(voxel=0.1), EVERY_THIRD, overwrite=True, progress=False)
    print(f"fuse: {fused.points} points from {fused.frames_used} frames → {', '.join(p.name for p in fused.outputs)}")

    # 0.2 m voxels keep this example quick; `make demo` uses 0.1 m.
    esdf = build_esdf(workspace, EsdfConfig(voxel=0.2), overwrite=True, progress=False)
    print(f"esdf: {esdf.shape} voxels of {esdf.voxel_size} m, {esdf.observed_fraction:.0%} observed → {esdf.path}")


def main(argv: list[str]) -> None:
    if argv:
        make_map(Path(argv[0]))
        return
    with tempfile.TemporaryDirectory() as tmp:
        make_map(Path(tmp))


if __name__ == "__main__":
    main(sys.argv[1:])
