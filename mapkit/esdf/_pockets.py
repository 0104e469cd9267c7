"""The ``--unknown free`` obstacles of a world, chunk by chunk: unseen pockets that no observed free
voxel reaches stay solid (:func:`mapkit.fusion._occupancy.fill_unknown`), without the whole grid in
one process.

Three Dask passes, one task per chunk: label each chunk's free voxels (noting which labels hold an
observed one), pair the labels touching across chunk faces (joined into components on the client),
then mark components with no observed voxel solid. Bit for bit ``fill_unknown(..., "free")``.
"""

from __future__ import annotations

from itertools import product
from typing import TYPE_CHECKING, Any

import numpy as np

from mapkit._dask import compute_tasks

if TYPE_CHECKING:
    from distributed import Client


def _base(tsdf: Any, observed: Any, behind: Any, key: tuple[slice, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(solid before the pocket rule, observed) of one block: inside per the TSDF, or unseen behind a surface."""
    obs = np.asarray(observed[key], dtype=bool)
    solid: np.ndarray = np.asarray(tsdf[key]) < 0
    solid |= np.asarray(behind[key], dtype=bool) & ~obs
    return solid, obs


def _label_task(world: dict[str, Any], labels: Any, key: tuple[slice, ...]) -> tuple[int, np.ndarray]:
    """Pass 1: (free components in the chunk, which of them hold an observed voxel); labels stored."""
    from scipy import ndimage

    solid, obs = _base(world["tsdf"], world["observed"], world["behind"], key)
    lab, n = ndimage.label(~solid)
    labels[key] = lab.astype(np.int32)
    reached = np.zeros(n + 1, dtype=bool)
    reached[np.unique(lab[obs & ~solid])] = True
    return int(n), reached[1:]


def _pairs_task(labels: Any, key: tuple[slice, ...], shape: tuple[int, ...]) -> list[tuple[int, int, np.ndarray]]:
    """Pass 2: per upper face with a neighbour, (axis, neighbour's chunk start, unique label pairs [k, 2])."""
    out = []
    for axis in range(3):
        stop = key[axis].stop
        if stop >= shape[axis]:
            continue
        last = tuple(slice(stop - 1, stop) if a == axis else key[a] for a in range(3))
        first = tuple(slice(stop, stop + 1) if a == axis else key[a] for a in range(3))
        a, b = np.asarray(labels[last]).reshape(-1), np.asarray(labels[first]).reshape(-1)
        both = (a > 0) & (b > 0)
        pairs = np.unique(np.stack([a[both], b[both]], axis=1), axis=0) if both.any() else np.zeros((0, 2), np.int32)
        out.append((axis, stop, pairs))
    return out


def _solid_task(world: dict[str, Any], labels: Any, solid_out: Any, key: tuple[slice, ...], pocket: np.ndarray) -> int:
    """Pass 3: store the chunk's obstacles (pocket[label] marks free voxels of unreached components); returns solids."""
    solid, _ = _base(world["tsdf"], world["observed"], world["behind"], key)
    solid |= pocket[np.asarray(labels[key])]
    solid_out[key] = solid
    return int(np.count_nonzero(solid))


def free_obstacles(world: dict[str, Any], labels: Any, solid_out: Any, *, chunk: int, client: Client | None,
                   progress: bool) -> int:
    """Write the ``--unknown free`` obstacles of the world arrays (tsdf, observed, behind) into
    `solid_out` (bool zarr), using `labels` (int32 zarr, same shape) as scratch; returns the solid count."""
    import dask
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    shape = tuple(int(n) for n in world["tsdf"].shape)
    keys = [tuple(slice(c, min(c + chunk, n)) for c, n in zip(corner, shape, strict=True))
            for corner in product(*(range(0, n, chunk) for n in shape))]
    index = {tuple(k.start for k in key): i for i, key in enumerate(keys)}
    label = dask.delayed(_label_task, pure=False)
    counted = compute_tasks([label(world, labels, key) for key in keys], client, desc="pockets 1/3 label",
                            unit="chunk", progress=progress)
    counts = np.array([n for n, _ in counted], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])  # global id = offset[chunk] + local label - 1
    reached = np.concatenate([r for _, r in counted]) if len(counted) else np.zeros(0, bool)
    pair = dask.delayed(_pairs_task, pure=False)
    faces = compute_tasks([pair(labels, key, shape) for key in keys], client, desc="pockets 2/3 join",
                          unit="chunk", progress=progress)
    src, dst = [], []
    for i, (key, found) in enumerate(zip(keys, faces, strict=True)):
        for axis, start, pairs in found:
            corner = tuple(start if a == axis else key[a].start for a in range(3))
            j = index[corner]
            src.append(offsets[i] + pairs[:, 0].astype(np.int64) - 1)
            dst.append(offsets[j] + pairs[:, 1].astype(np.int64) - 1)
    total = int(offsets[-1])
    s = np.concatenate(src) if src else np.zeros(0, np.int64)
    d = np.concatenate(dst) if dst else np.zeros(0, np.int64)
    _, component = connected_components(coo_matrix((np.ones(len(s)), (s, d)), shape=(total, total)), directed=False)
    component_reached = np.zeros(int(component.max(initial=-1)) + 1, dtype=bool)
    np.logical_or.at(component_reached, component, reached)
    pocket = ~component_reached[component]
    solid = dask.delayed(_solid_task, pure=False)
    luts = [np.concatenate([[False], pocket[offsets[i] : offsets[i + 1]]]) for i in range(len(keys))]
    done = compute_tasks([solid(world, labels, solid_out, key, lut) for key, lut in zip(keys, luts, strict=True)],
                         client, desc="pockets 3/3 mark", unit="chunk", progress=progress)
    return int(sum(done))
