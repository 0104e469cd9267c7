"""Signed distance of grids too large for memory: chunk by chunk with a halo, exact up to max_dist."""

from __future__ import annotations

import math
import queue
import threading
import time
from dataclasses import dataclass
from itertools import product
from typing import Any

import numpy as np

from mapkit.esdf import _checks
from mapkit.esdf._distance import _signed_distance_unchecked, _smooth_unchecked
from mapkit.esdf._errors import EsdfError
from mapkit.esdf._gauss import kernel_radius


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

    @property
    def voxels_per_second(self) -> float:
        n = self.shape[0] * self.shape[1] * self.shape[2]
        return n / self.seconds if self.seconds > 0 else float("inf")


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
    threads: int = 2,
    progress: bool = True,
) -> ChunkedSummary:
    """Signed distance (and optionally its smoothing) of a large grid, one chunk at a time.

    Parameters
    ----------
    occupied
        bool [nx, ny, nz] occupancy; anything sliceable with ``occupied[x0:x1, y0:y1, z0:z1]`` that
        returns a bool array (a zarr array, a numpy array or memmap). Only one chunk plus halo is read
        at a time.
    out
        float32 [nx, ny, nz] destination (a zarr array or numpy array) for the field: smoothed when
        ``sigma > 0``, else the raw signed distance. For a zarr array, `chunk` must be a multiple of
        its chunk shape, so that every chunk is written once, whole.
    voxel_size, max_dist
        Metres. Each chunk is computed with a halo of ``ceil(max_dist/voxel_size) + 1`` voxels (plus
        the Gaussian's radius), so the result equals :func:`signed_distance` with the same
        `max_dist` (and :func:`smooth` of it) exactly: every distance up to `max_dist` is exact,
        larger ones are clamped to +-max_dist.
    chunk
        Edge, in voxels, of the cube computed at once. Peak memory is about
        ``(chunk + 2*halo)**3 * 18`` bytes of work arrays plus up to three finished chunks
        (``chunk**3 * 8`` bytes each) waiting for the writer thread; nothing grid-sized. Measured:
        chunk 128 ~0.2 GB, chunk 256 ~0.6 GB above the baseline (halo 22); 256 is ~20 % faster.
    sigma, truncate
        Gaussian smoothing as in :func:`smooth` (metres; 0 = none).
    out_raw
        Optional float32 [nx, ny, nz] destination for the unsmoothed (clamped) field.
    threads
        CPU threads for the EDT.
    progress
        Show a tqdm bar on stderr.

    Returns
    -------
    ChunkedSummary (shape, chunk count, halo, n_prevented, seconds).
    """
    vs = _checks.positive("voxel_size", voxel_size)
    md = _checks.positive("max_dist", max_dist)
    sg = _checks.non_negative("sigma", sigma)
    tr = _checks.positive("truncate", truncate, unit="standard deviations")
    n_threads = _checks.threads(threads)
    chunk, shape = _check_grids(occupied, out, out_raw, chunk)
    halo = chunk_halo(voxel_size=vs, max_dist=md, sigma=sg, truncate=tr)

    from tqdm import tqdm

    starts = [range(0, n, chunk) for n in shape]
    t0 = time.perf_counter()
    total = math.prod(len(s) for s in starts)
    bar = tqdm(total=total, unit="chunk", desc="esdf", disable=not progress, dynamic_ncols=True)
    writer = _ChunkWriter(out, out_raw)
    prevented = 0
    try:
        for corner in product(*starts):
            core = tuple(slice(c, min(c + chunk, n)) for c, n in zip(corner, shape, strict=True))
            field, raw_core, k = _chunk_field(occupied, core, shape, halo, vs, md, sg, tr, n_threads,
                                              want_raw=out_raw is not None)
            prevented += k
            writer.put(core, field, raw_core)
            bar.update(1)
    finally:
        writer.close()
        bar.close()
    writer.raise_error()
    return ChunkedSummary(shape=shape, chunks=total, halo=halo, n_prevented=prevented, seconds=time.perf_counter() - t0)


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


class _ChunkWriter:
    """Writes finished chunks into ``out`` (and ``out_raw``) from a background thread, at most two queued;
    the first failure is kept and raised in the caller's thread."""

    def __init__(self, out: Any, out_raw: Any) -> None:
        self.out, self.out_raw = out, out_raw
        self.jobs: queue.Queue[tuple[tuple[slice, ...], np.ndarray, np.ndarray | None] | None] = queue.Queue(maxsize=2)
        self.errors: list[BaseException] = []
        self.thread = threading.Thread(target=self._run, name="esdf-chunk-writer", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        """The thread: write jobs until None; after a failure, drain the queue without writing."""
        while (job := self.jobs.get()) is not None:
            if self.errors:
                continue
            core, field, raw_core = job
            try:
                self.out[core] = field
                if raw_core is not None:
                    self.out_raw[core] = raw_core
            except BaseException as exc:  # noqa: BLE001 - surfaced in the caller's thread
                self.errors.append(exc)

    def put(self, core: tuple[slice, ...], field: np.ndarray, raw_core: np.ndarray | None) -> None:
        """Queue one chunk (raises first what an earlier write failed with)."""
        self.raise_error()
        self.jobs.put((core, field, raw_core))

    def close(self) -> None:
        """Let the thread finish the queued chunks and stop."""
        self.jobs.put(None)
        self.thread.join()

    def raise_error(self) -> None:
        """Raise the first write failure, if any."""
        if self.errors:
            raise self.errors[0]
