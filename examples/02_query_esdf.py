"""Open a signed distance map and query distances and gradients at points.

    python examples/02_query_esdf.py [MAP_ZARR]

MAP_ZARR is a map.zarr made by `mapkit esdf` or examples/01_ingest_and_map.py. Without it the
example writes a map of one ball (radius 1 m, centred in the map) to a temporary folder, so the
answers can be checked by hand: the distance at a point is its distance from the centre minus 1 m,
within half a voxel (the surface is placed half-way between voxel centres). Takes a few seconds.
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

from mapkit.esdf import EsdfMap, signed_distance, write_map

VOXEL = 0.05  # metres


def write_ball_map(path: Path) -> None:
    """Write a map.zarr of a 4 m cube of space holding a ball of radius 1 m at the origin."""
    origin = np.full(3, -2.0)  # centre of voxel [0, 0, 0]
    axis = origin[0] + VOXEL * np.arange(81)
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    occupied = x**2 + y**2 + z**2 <= 1.0
    esdf = signed_distance(occupied, voxel_size=VOXEL)
    write_map(path, esdf=esdf, esdf_raw=esdf, observed=np.ones_like(occupied, dtype=np.uint8), origin=origin,
              voxel_size=VOXEL, frame_id="world", sigma=0.0, unknown_policy="free")


def query(path: Path, *, ball: bool = False) -> None:
    """Open the map at `path` and print distances and gradients at a few points around its centre."""
    esdf = EsdfMap.open(path)
    lo, hi = esdf.bounds  # the box of voxel centres, where queries are defined
    print(f"{path}: voxel {esdf.voxel_size} m, frame {esdf.frame_id!r}, centres from {lo.round(2)} to {hi.round(2)} m")
    centre = (lo + hi) / 2
    offsets = np.array([[0.0, 0.0, 0.5], [1.5, 0.0, 0.0], [0.0, -1.2, 0.3], [100.0, 0.0, 0.0]])
    points = centre + offsets
    distance, gradient = esdf.query(points)  # (N,) metres, (N, 3); NaN outside the bounds
    for p, d, g, exact in zip(points, distance, gradient, np.linalg.norm(offsets, axis=1) - 1.0, strict=True):
        check = f" (the ball's exact {exact:+.3f})" if ball else ""
        print(f"  at {p.round(2)} m: distance {d:+.3f} m{check}, gradient {g.round(2)}")
    clamped, _ = esdf.query(points[-1:], outside="clamp")  # the nearest point of the box instead of NaN
    print(f"  the last point clamped into the box: {clamped[0]:+.3f} m")


def main(argv: list[str]) -> None:
    if argv:
        query(Path(argv[0]))
        return
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "map.zarr"
        write_ball_map(path)
        query(path, ball=True)


if __name__ == "__main__":
    main(sys.argv[1:])
