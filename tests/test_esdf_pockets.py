"""The unknown = "free" pocket rule chunk by chunk equals fill_unknown on the whole grid."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

from mapkit.esdf._pockets import free_obstacles
from mapkit.fusion._occupancy import fill_unknown


def _world(shape: tuple[int, int, int], seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tsdf, observed, behind): hollow boxes (closed, open, straddling chunk faces), a closed wall and
    one with a door, observed free space on one side only, behind-surface marks."""
    rng = np.random.default_rng(seed)
    occupied = np.zeros(shape, bool)
    for _ in range(12):
        lo = rng.integers(0, np.asarray(shape) - 6, 3)
        size = rng.integers(4, 14, 3)
        hi = np.minimum(lo + size, shape)
        occupied[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = True
        occupied[lo[0] + 1 : hi[0] - 1, lo[1] + 1 : hi[1] - 1, lo[2] + 1 : hi[2] - 1] = False  # hollow
        if rng.random() < 0.4:
            occupied[lo[0], lo[1] + 1 : hi[1] - 1, lo[2] + 1] = False  # a hole: the inside is reachable
    occupied[:, shape[1] // 2, :] = True  # a closed wall: the far half is one pocket across many chunks
    occupied[shape[0] // 2, : shape[1] // 2, :] = True  # a wall with a door: reached through the door
    occupied[shape[0] // 2, 3:6, 3:6] = False
    observed = np.zeros(shape, bool)
    observed[: shape[0] // 3, : shape[1] // 2] = rng.random((shape[0] // 3, shape[1] // 2, shape[2])) < 0.05
    observed &= ~occupied
    behind = rng.random(shape) < 0.01
    tsdf = np.where(occupied, -0.05, 0.05).astype(np.float32)
    tsdf[(rng.random(shape) < 0.3) & ~occupied] = np.nan  # free voxels without a TSDF sample
    return tsdf, observed, behind


@pytest.mark.parametrize("chunk", [16, 24])
def test_chunked_pockets_equal_fill_unknown(tmp_path: Path, chunk: int) -> None:
    shape = (61, 50, 37)
    tsdf, observed, behind = _world(shape, seed=chunk)
    occupied = tsdf < 0
    expected = fill_unknown(occupied, observed, "free", behind=behind)
    assert (expected & ~(occupied | behind)).sum() > 100, "the scene must hold unreached pockets"
    world = {name: zarr.create_array(tmp_path / name, shape=shape, chunks=(chunk,) * 3, dtype=a.dtype, zarr_format=3)
             for name, a in (("tsdf", tsdf), ("observed", observed), ("behind", behind))}
    for name, a in (("tsdf", tsdf), ("observed", observed), ("behind", behind)):
        world[name][:] = a
    labels = zarr.create_array(tmp_path / "labels", shape=shape, chunks=(chunk,) * 3, dtype="int32", zarr_format=3)
    solid = zarr.create_array(tmp_path / "solid", shape=shape, chunks=(chunk,) * 3, dtype="bool", zarr_format=3)
    n = free_obstacles(world, labels, solid, chunk=chunk, client=None, progress=False)
    np.testing.assert_array_equal(np.asarray(solid[:]), expected)
    assert n == int(expected.sum())
