"""Signed distance fields (ESDF) of occupancy grids, map.zarr, and queries and slices of it.

A boolean occupancy grid [nx, ny, nz] (voxel [i, j, k] centred at ``origin + voxel_size * (i, j, k)``)
becomes an exact signed distance in metres (positive in free space), smoothed without flipping the
sign away from the surface.

>>> import numpy as np
>>> from mapkit.esdf import signed_distance, smooth
>>> occ = np.zeros((40, 40, 20), bool); occ[:, :, :2] = True          # a floor
>>> raw = signed_distance(occ, voxel_size=0.1)
>>> round(float(raw[0, 0, 5]), 4)        # centre 4 voxels above the top floor voxel: 3.5 voxels to the surface
0.35
>>> esdf, n_prevented = smooth(raw, voxel_size=0.1, sigma=0.2)

:func:`build_esdf` (``mapkit esdf``) turns a fused workspace into map.zarr; large grids run chunk by
chunk on Dask (:func:`signed_distance_chunked`).
"""

from mapkit.esdf._build import build_esdf
from mapkit.esdf._chunked import ChunkedSummary, chunk_halo, signed_distance_chunked
from mapkit.esdf._distance import signed_distance, smooth
from mapkit.esdf._errors import EsdfError
from mapkit.esdf._map import EsdfMap
from mapkit.esdf._shared import MAP, EsdfBuildError, EsdfConfig, EsdfSummary
from mapkit.esdf._slice import Slice, render_slices, slice_plane
from mapkit.esdf._store import MapWriter, create_map, write_map

__all__ = [
    "MAP",
    "EsdfBuildError",
    "EsdfConfig",
    "EsdfSummary",
    "build_esdf",
    "ChunkedSummary",
    "EsdfError",
    "EsdfMap",
    "MapWriter",
    "Slice",
    "chunk_halo",
    "create_map",
    "render_slices",
    "signed_distance",
    "signed_distance_chunked",
    "slice_plane",
    "smooth",
    "write_map",
]
