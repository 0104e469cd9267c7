"""OME-Zarr (NGFF 0.5) multiscale metadata for map.zarr, so NGFF viewers place the ESDF in metres.

Level 0 is ``esdf``; the 2× and 4× NaN-aware block means live in the ``ngff`` subgroup, written one
x-slab at a time (ome-zarr-py's writers need the whole array in memory).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

NGFF_VERSION = "0.5"
LEVELS_GROUP = "ngff"
MAX_COARSE_LEVELS = 2
MIN_COARSE_SIDE = 8
"""Voxels: no coarse level gets an axis shorter than this."""


def _halved(fine: np.ndarray) -> np.ndarray:
    """2×2×2 block means of ``fine`` (odd sides padded with NaN), NaN-aware."""
    pad = [(0, s % 2) for s in fine.shape]
    f = np.pad(fine.astype(np.float32), pad, constant_values=np.nan)
    nx, ny, nz = (s // 2 for s in f.shape)
    blocks = f.reshape(nx, 2, ny, 2, nz, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN blocks stay NaN
        coarse: np.ndarray = np.nanmean(blocks, axis=(1, 3, 5)).astype(np.float32)
    return coarse


def _coarse_shapes(shape: tuple[int, ...]) -> list[tuple[int, ...]]:
    shapes: list[tuple[int, ...]] = []
    current = shape
    while len(shapes) < MAX_COARSE_LEVELS:
        current = tuple((s + 1) // 2 for s in current)
        if min(current) < MIN_COARSE_SIDE:
            break
        shapes.append(current)
    return shapes


def write_levels(root: Any, source: Any, compressor: Any, chunk: int, slab: int = 64) -> int:
    """Write the coarse levels of ``source`` (the root's ``esdf`` array) into ``root[LEVELS_GROUP]``,
    ``slab`` fine x-planes (even) at a time; returns how many were written."""
    group = root.require_group(LEVELS_GROUP)
    previous, written = source, 0
    for level, shape in enumerate(_coarse_shapes(tuple(source.shape)), start=1):
        out = group.create_array(str(level), shape=shape, chunks=tuple(min(chunk, s) for s in shape), dtype="float32",
                                 compressors=[compressor], fill_value=float("nan"), dimension_names=["x", "y", "z"])
        for x0 in range(0, previous.shape[0], slab):
            out[x0 // 2:(min(x0 + slab, previous.shape[0]) + 1) // 2] = _halved(np.asarray(previous[x0:x0 + slab]))
        previous, written = out, level
    return written


def multiscales(voxel_size: float, origin: list[float], levels: int) -> dict[str, Any]:
    """The ``ome`` attribute of map.zarr's root: axes x, y, z in metres, one dataset per level with
    its scale (voxel size) and translation (centre of its voxel [0, 0, 0])."""
    datasets = []
    for level in range(levels + 1):
        factor = 2**level
        path = "esdf" if level == 0 else f"{LEVELS_GROUP}/{level}"
        shift = 0.5 * (factor - 1) * voxel_size  # mean of the fine centres a coarse voxel covers
        datasets.append({"path": path, "coordinateTransformations": [
            {"type": "scale", "scale": [voxel_size * factor] * 3},
            {"type": "translation", "translation": [o + shift for o in origin]},
        ]})
    return {"version": NGFF_VERSION, "multiscales": [{
        "name": "esdf",
        "axes": [{"name": name, "type": "space", "unit": "meter"} for name in ("x", "y", "z")],
        "datasets": datasets,
    }]}
