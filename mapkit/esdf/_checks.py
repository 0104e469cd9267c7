"""Argument checks shared by the ESDF modules: one specific message per bad value, naming the fix."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mapkit.esdf._errors import EsdfError


def positive(name: str, value: Any, *, unit: str = "m", zero: bool = False) -> float:
    """``value`` as a finite float > 0 (>= 0 with ``zero``: 0 turns it off)."""
    what = f"length >= 0 in {unit}" if zero else f"positive length in {unit}"
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise EsdfError(f"{name}={value!r} is not a number; pass a {what}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not zero):
        raise EsdfError(f"{name}={value!r} must be a finite {what}" + (" (0 turns it off)" if zero else ""))
    return v


def non_negative(name: str, value: Any, *, unit: str = "m") -> float:
    return positive(name, value, unit=unit, zero=True)


def grid_shape(name: str, shape: Any) -> tuple[int, int, int]:
    if len(shape) != 3:
        raise EsdfError(f"{name} must be 3-D [nx, ny, nz]; got shape {tuple(shape)}")
    if min(shape) < 1:
        raise EsdfError(f"{name} has an empty axis (shape {tuple(shape)}); the grid needs at least one voxel per axis")
    return int(shape[0]), int(shape[1]), int(shape[2])


def bool_grid(name: str, arr: Any) -> np.ndarray:
    """A 3-D bool numpy array (no copy when it already is one)."""
    a = np.asarray(arr)
    if a.dtype != np.bool_:
        raise EsdfError(
            f"{name} must be a boolean occupancy grid; got dtype {a.dtype}. "
            f"Pass `{name} != 0` (or `{name} > threshold` for probabilities)"
        )
    grid_shape(name, a.shape)
    return a


def float_grid(name: str, arr: Any) -> np.ndarray:
    """A 3-D float32 C-contiguous array (converted, with a copy, only when needed)."""
    a = np.asarray(arr)
    if not np.issubdtype(a.dtype, np.floating):
        raise EsdfError(f"{name} must be a float array of signed distances in metres; got dtype {a.dtype}")
    grid_shape(name, a.shape)
    return np.ascontiguousarray(a, dtype=np.float32)


def threads(value: Any) -> int:
    """A thread count; None: ``OMP_NUM_THREADS`` when it is set (as Dask's workers and batch schedulers
    set it, one per worker), else the cores this process may use, so workers sharing a machine do not
    each start a thread per core."""
    if value is None:
        from mapkit._dask import default_threads

        return default_threads()
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
        raise EsdfError(f"threads={value!r} must be a positive integer (the number of CPU threads to use)")
    return int(value)

