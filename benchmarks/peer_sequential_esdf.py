"""The benchmark's peer: the in-process chunked ESDF driver as it was before the Dask graph (issue 15).

Kept verbatim in its logic from mapkit/esdf/_chunked.py at commit 2c08846: a plain loop over the
chunks in this process, each chunk's field computed by the same chunk function the Dask graph runs
(:func:`mapkit.esdf._chunked._chunk_field`: EDT + Gaussian on the chunk plus halo, `threads` CPU
threads), finished chunks written into the zarr arrays by one background thread (at most two
queued). Only the driver differs from the Dask path, so the benchmark compares schedulers, not math.
"""

from __future__ import annotations

import math
import queue
import threading
from itertools import product
from typing import Any

import numpy as np

from mapkit.esdf._chunked import _chunk_field, chunk_halo


def sequential_chunked(occupied: Any, out: Any, *, voxel_size: float, max_dist: float, chunk: int = 128,
                       sigma: float = 0.0, truncate: float = 3.0, out_raw: Any = None,
                       threads: int = 2) -> tuple[int, int]:
    """(chunks, sign flips prevented) after writing the field of `occupied` into `out` / `out_raw`."""
    shape = tuple(int(n) for n in occupied.shape)
    halo = chunk_halo(voxel_size=voxel_size, max_dist=max_dist, sigma=sigma, truncate=truncate)
    starts = [range(0, n, chunk) for n in shape]
    writer = _ChunkWriter(out, out_raw)
    prevented = 0
    try:
        for corner in product(*starts):
            core = tuple(slice(c, min(c + chunk, n)) for c, n in zip(corner, shape, strict=True))
            field, raw_core, k = _chunk_field(occupied, core, shape, halo, voxel_size, max_dist, sigma, truncate,
                                              threads, want_raw=out_raw is not None)
            prevented += k
            writer.put(core, field, raw_core)
    finally:
        writer.close()
    writer.raise_error()
    return math.prod(len(s) for s in starts), prevented


class _ChunkWriter:
    """Writes finished chunks from a background thread, at most two queued; the first failure is re-raised."""

    def __init__(self, out: Any, out_raw: Any) -> None:
        self.out, self.out_raw = out, out_raw
        self.jobs: queue.Queue[tuple[tuple[slice, ...], np.ndarray, np.ndarray | None] | None] = queue.Queue(maxsize=2)
        self.errors: list[BaseException] = []
        self.thread = threading.Thread(target=self._run, name="esdf-chunk-writer", daemon=True)
        self.thread.start()

    def _run(self) -> None:
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
        self.raise_error()
        self.jobs.put((core, field, raw_core))

    def close(self) -> None:
        self.jobs.put(None)
        self.thread.join()

    def raise_error(self) -> None:
        if self.errors:
            raise self.errors[0]


__all__ = ["sequential_chunked"]
