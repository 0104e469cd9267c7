"""Signed distance of grids too large for memory: a Dask graph of chunks with a halo, exact up to max_dist."""

from __future__ import annotations

import math
import os
import resource
import time
from dataclasses import dataclass
from itertools import product
from typing import TYPE_CHECKING, Any

import numpy as np

from mapkit._dask import compute_tasks
from mapkit.esdf import _checks
from mapkit.esdf._distance import _signed_distance_unchecked, _smooth_unchecked
from mapkit.esdf._errors import EsdfError
from mapkit.esdf._gauss import kernel_radius

if TYPE_CHECKING:
    from distributed import Client


@dataclass(frozen=True)
class ChunkedSummary:
    """What :func:`signed_distance_chunked` did."""

    shape: tuple[int, int, int]
    """Grid shape [nx, ny, nz]."""
    chunks: int
    """Number of chunks computed."""
    halo: int
    """Halo in voxels read around each chunk (distance reach + Gaussian radius)."""
    n_prevented: int
    """Voxels whose sign the smoothing guard kept (see :func:`smooth`); 0 without smoothing."""
    seconds: float
    """Wall time."""
    workers: int = 1
    """Processes that ran chunks (1: this process, on Dask's synchronous scheduler)."""
    peak_rss_bytes: int = 0
    """Largest peak resident memory of a process that ran chunks (``getrusage`` after each chunk)."""


def chunk_halo(*, voxel_size: float, max_dist: float, sigma: float = 0.0, truncate: float = 3.0) -> int:
    """Halo (voxels) that makes a chunk's result exact: ceil(max_dist/voxel_size) + 1 + Gaussian radius."""
    radius = kernel_radius(sigma / voxel_size, truncate) if sigma > 0 else 0
    return math.ceil(max_dist / voxel_size - 1e-9) + 1 + radius


def signed_distance_chunked(
    occupied: Any,
    out: Any,
    *,
    voxel_size: float,
    max_dist: float,
    chunk: int = 128,
    sigma: float = 0.0,
    truncate: float = 3.0,
    out_raw: Any = None,
    threads: int | None = None,
    progress: bool = True,
    client: Client | None = None,
    local_workers: int = 1,
) -> ChunkedSummary:
    """Signed distance (and optionally its smoothing) of a large grid, as a Dask graph of chunks.

    One task per `chunk`³ cube reads it plus a halo (:func:`chunk_halo`) from `occupied` and writes the
    core into `out` (and `out_raw`): bit for bit :func:`signed_distance` with the same `max_dist` (and
    :func:`smooth` of it), distances beyond `max_dist` clamped.

    - `occupied`: bool [nx, ny, nz], anything sliceable (zarr, numpy, memmap); on a cluster a zarr
      array on shared storage.
    - `out`, `out_raw`: float32 [nx, ny, nz] destinations of the field (smoothed when ``sigma > 0``)
      and of the unsmoothed one (optional): zarr arrays whose chunk shape divides `chunk`, or numpy
      arrays without `client`.
    - `voxel_size`, `max_dist`, `sigma` (0 = no smoothing): metres; `truncate` as in :func:`smooth`.
    - `threads`: CPU threads per task (None: ``OMP_NUM_THREADS`` if set, else the available cores).
    - `client`: a Dask client; None runs in this process, `local_workers` chunks at once.
    """
    vs = _checks.positive("voxel_size", voxel_size)
    md = _checks.positive("max_dist", max_dist)
    sg = _checks.non_negative("sigma", sigma)
    tr = _checks.positive("truncate", truncate, unit="standard deviations")
    n_threads = _checks.threads(threads)
    chunk, shape = _check_grids(occupied, out, out_raw, chunk)
    _check_writable_by_client(client, out, out_raw)
    halo = chunk_halo(voxel_size=vs, max_dist=md, sigma=sg, truncate=tr)
    t0 = time.perf_counter()
    tasks = _chunk_tasks(occupied, out, out_raw, shape, chunk, halo, (vs, md, sg, tr), n_threads)
    if isinstance(local_workers, bool) or not isinstance(local_workers, int) or local_workers < 1:
        raise EsdfError(f"local_workers={local_workers!r} must be a positive number of chunks at once (e.g. 1)")
    results = compute_tasks(tasks, client, desc="esdf", unit="chunk", progress=progress, local_threads=local_workers)
    return _summary(results, shape=shape, chunks=len(tasks), halo=halo, seconds=time.perf_counter() - t0)


def _check_writable_by_client(client: Client | None, out: Any, out_raw: Any) -> None:
    """Raise :class:`EsdfError` when a cluster's workers would have to write into this process's numpy arrays."""
    if client is not None:
        for name, arr in (("out", out), ("out_raw", out_raw)):
            if isinstance(arr, np.ndarray):
                raise EsdfError(f"{name} is a numpy array, which Dask workers cannot write into; pass zarr arrays "
                                "(create_map's esdf / esdf_raw) on storage the workers share, or run without a client")


def _summary(results: list[Any], *, shape: tuple[int, int, int], chunks: int, halo: int,
             seconds: float) -> ChunkedSummary:
    """The :class:`ChunkedSummary` of the chunk tasks' results ``(n_prevented, process id, peak RSS)``."""
    peaks: dict[int, int] = {}
    for _, pid, peak in results:
        peaks[pid] = max(peaks.get(pid, 0), peak)
    return ChunkedSummary(shape=shape, chunks=chunks, halo=halo, n_prevented=sum(r[0] for r in results),
                          seconds=seconds, workers=len(peaks), peak_rss_bytes=max(peaks.values(), default=0))


def _chunk_tasks(occupied: Any, out: Any, out_raw: Any, shape: tuple[int, int, int], chunk: int, halo: int,
                 params: tuple[float, float, float, float], n_threads: int) -> list[Any]:
    """One Dask task per chunk; the occupancy is one node of the graph, so a cluster ships it once per worker."""
    import dask
    from dask.base import tokenize

    source = dask.delayed(occupied, name=f"esdf-occupancy-{tokenize(id(occupied), shape, time.time_ns())}")
    run_chunk = dask.delayed(_chunk_task, pure=False)
    starts = [range(0, n, chunk) for n in shape]
    tasks = []
    for corner in product(*starts):
        core = tuple(slice(c, min(c + chunk, n)) for c, n in zip(corner, shape, strict=True))
        tasks.append(run_chunk(source, out, out_raw, core, shape, halo, params, n_threads,
                               dask_key_name=f"esdf-chunk-{'-'.join(map(str, corner))}-{source.key[-12:]}"))
    return tasks


def _chunk_task(occupied: Any, out: Any, out_raw: Any, core: tuple[slice, ...], shape: tuple[int, int, int],
                halo: int, params: tuple[float, float, float, float], n_threads: int) -> tuple[int, int, int]:
    """Compute one chunk and write its core; (sign flips prevented, process id, its peak RSS in bytes)."""
    vs, md, sg, tr = params
    field, raw_core, k = _chunk_field(occupied, core, shape, halo, vs, md, sg, tr, n_threads, want_raw=out_raw is not None)
    out[core] = field
    if out_raw is not None:
        out_raw[core] = raw_core
    return k, os.getpid(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _check_grids(occupied: Any, out: Any, out_raw: Any, chunk: Any) -> tuple[int, tuple[int, int, int]]:
    """(chunk as int, grid shape); raises :class:`EsdfError` for a bad chunk, destination or occupancy dtype."""
    if isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise EsdfError(f"chunk={chunk!r} must be a positive number of voxels (e.g. 128)")
    chunk = int(chunk)
    shape = _checks.grid_shape("occupied", getattr(occupied, "shape", ()))
    for name, arr in (("out", out), ("out_raw", out_raw)):
        if arr is not None:
            _check_destination(name, arr, shape, chunk)
    occ_dtype = getattr(occupied, "dtype", None)
    if occ_dtype is not None and np.dtype(occ_dtype) != np.bool_:
        raise EsdfError(f"occupied must be a boolean occupancy grid; got dtype {occ_dtype}. Store or pass it as bool")
    return chunk, shape


def _check_destination(name: str, arr: Any, shape: tuple[int, int, int], chunk: int) -> None:
    """Raise :class:`EsdfError` unless ``arr`` is a float32 grid of ``shape`` whose zarr chunks divide ``chunk``."""
    if tuple(arr.shape) != shape:
        raise EsdfError(f"{name} has shape {tuple(arr.shape)} but occupied has {shape}; create it with the same shape")
    if np.dtype(arr.dtype) != np.float32:
        raise EsdfError(f"{name} has dtype {arr.dtype}; the signed distance is float32, create it as float32")
    arr_chunks = getattr(arr, "chunks", None)
    if isinstance(arr_chunks, tuple) and len(arr_chunks) == 3 and all(isinstance(c, int) for c in arr_chunks):
        bad = [c for c, s in zip(arr_chunks, shape, strict=True) if chunk % c and c < s]
        if bad:
            raise EsdfError(
                f"chunk={chunk} is not a multiple of {name}'s zarr chunk shape {arr_chunks}; "
                f"pass chunk={max(arr_chunks) * max(1, round(chunk / max(arr_chunks)))}"
            )


def _chunk_field(occupied: Any, core: tuple[slice, ...], shape: tuple[int, int, int], halo: int, vs: float,
                 md: float, sg: float, tr: float, n_threads: int, *,
                 want_raw: bool) -> tuple[np.ndarray, np.ndarray | None, int]:
    """One chunk's (field, raw field or None, sign flips prevented), computed on the chunk plus its halo."""
    blk_lo = tuple(max(c.start - halo, 0) for c in core)
    blk_hi = tuple(min(c.stop + halo, n) for c, n in zip(core, shape, strict=True))
    block = np.asarray(occupied[tuple(slice(a, b) for a, b in zip(blk_lo, blk_hi, strict=True))])
    if block.dtype != np.bool_:
        raise EsdfError(f"occupied returned dtype {block.dtype} for a chunk; it must be bool")
    inner = tuple(slice(c.start - la, c.stop - la) for c, la in zip(core, blk_lo, strict=True))
    raw = _signed_distance_unchecked(np.ascontiguousarray(block), vs, md, "edt", n_threads)
    del block
    if sg > 0:
        # the guard's interventions are counted inside the core only (the halo belongs to others)
        sm, k = _smooth_unchecked(raw, vs, sg, tr, count_region=inner, threads=n_threads, offset=blk_lo)
        field = np.ascontiguousarray(sm[inner])
        raw_core = np.ascontiguousarray(raw[inner]) if want_raw else None
        return field, raw_core, k
    field = np.ascontiguousarray(raw[inner])
    return field, field if want_raw else None, 0
