"""What `mapkit esdf` on a fused workspace and on a world directory share: options, summary, error and
where the chunked computation runs."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from mapkit._resources import available_memory
from mapkit.esdf._chunked import ChunkedSummary, chunk_halo
from mapkit.esdf._errors import EsdfError

if TYPE_CHECKING:
    from distributed import Client

MAP = "map.zarr"
_CHUNKED_DEFAULT_MAX_DIST = 2.0
_CHUNK = 128  # voxels per chunk edge of the chunked ESDF (a multiple of map.zarr's 64)


class EsdfBuildError(EsdfError):
    """The ESDF cannot be built from this workspace with these options."""


@dataclass
class EsdfConfig:
    """Options of `mapkit esdf`: each field is a setting (`mapkit config esdf`)."""

    voxel: float = 0.1
    """ESDF voxel size in metres (a multiple of the TSDF voxel keeps samples on voxel centres)."""
    padding: float = 1.0
    """Metres added around the fused map's bounds."""
    sigma: float = 0.1
    """Gaussian smoothing in metres; 0 = none."""
    unknown: str = "free"
    """Unobserved space: 'free' (default, as the paper's cost map: distances to reconstructed
    obstacles; unseen pockets that no observed free space reaches, such as the inside of a box or
    the ground under the floor, stay solid) or 'occupied' (conservative: everything no ray saw is an
    obstacle, which puts walls at the edge of every field of view)."""
    solid_depth: float = 0.5
    """With unknown = "free": unobserved space up to this far (metres) behind each measured surface,
    along the sensor's rays, counts as solid (object interiors, the ground under the floor)."""
    max_dist: float | None = None
    """Clamp |distance| to this (metres); required for chunked computation of large maps."""
    subvoxel: bool = True
    """Measure distances to the fused surface points tied to each boundary voxel (sub-voxel zero
    crossing) instead of the fixed half-voxel convention of the plain EDT."""

    def validate(self) -> None:
        if not self.voxel > 0:
            raise EsdfBuildError(f"--voxel {self.voxel} must be positive (metres, e.g. 0.1)")
        if self.padding < 0:
            raise EsdfBuildError(f"padding {self.padding} must be >= 0 metres")
        if self.sigma < 0:
            raise EsdfBuildError(f"sigma {self.sigma} must be >= 0 metres (0 = no smoothing)")
        if self.unknown not in ("occupied", "free"):
            raise EsdfBuildError(f"unknown {self.unknown!r}: expected occupied or free")
        if self.solid_depth < 0:
            raise EsdfBuildError(f"solid_depth {self.solid_depth} must be >= 0 metres")
        if self.max_dist is not None and not self.max_dist > 0:
            raise EsdfBuildError(f"max_dist {self.max_dist} must be positive (metres)")


@dataclass
class EsdfSummary:
    path: Path | str
    """Where map.zarr was written: a local path, or the URL given as ``output``."""
    shape: tuple[int, int, int]
    origin: NDArray[np.float64]
    voxel_size: float
    observed_fraction: float
    occupied_fraction: float
    sign_flips_prevented: int
    seconds: float
    chunked: ChunkedSummary | None = None
    """What the chunked (Dask) computation did; None when the whole grid was computed at once."""


@dataclass(frozen=True)
class _Runner:
    """Where the chunked ESDF's tasks run."""

    client: Client | None
    """The Dask client; None = this process."""
    threads: int
    """CPU threads per chunk task."""
    local_workers: int = 1
    """Without a client: chunks computed at once in this process (Dask's threaded scheduler)."""


@contextmanager
def _dask_runner(scheduler: str | None, workers: int | None) -> Iterator[_Runner]:
    """This process for one local worker (no cluster to start), else a local cluster or the scheduler's."""
    from mapkit._dask import available_cpus, dask_client

    if scheduler is None and (workers or 1) == 1:
        # one chunk per core at once, one thread each: a chunk's EDT and Gaussian threads would wait
        # on each other
        yield _Runner(None, 1, available_cpus())
        return
    with dask_client(scheduler, workers=workers) as (client, info):
        # a local cluster splits this machine's cores between its workers; on a remote one each
        # worker thread runs one single-threaded task
        yield _Runner(client, max(1, available_cpus() // info.workers) if info.local else 1)


def _chunks_at_once(runner: _Runner, *, chunk: int, voxel: float, max_dist: float, sigma: float) -> int:
    """Chunks to compute at once in this process: one per core, fewer when their work arrays would
    take over a quarter of the available memory; 1 on a cluster."""
    if runner.client is not None:
        return 1
    halo = chunk_halo(voxel_size=voxel, max_dist=max_dist, sigma=sigma)
    per_chunk = (chunk + 2 * halo) ** 3 * 18 + chunk**3 * 8
    return max(1, min(runner.local_workers, int(0.25 * available_memory() // per_chunk)))
