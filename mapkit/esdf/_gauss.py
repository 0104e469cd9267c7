"""Separable Gaussian filter of a 3-D float32 grid, written as banded matrix products.

Filtering a C-ordered [nx, ny, nz] array along one axis is the product of a banded (2r+1 wide)
n-by-n matrix with the array seen as a stack of matrices. Splitting the band into row blocks keeps the
flops within a small factor of the direct convolution while BLAS (cache-blocked, vectorised) does the
arithmetic; on the 2-core reference machine this is 5-10x faster than
``scipy.ndimage.gaussian_filter`` in float32 and agrees with it to float32 rounding. The boundary
rule is scipy's ``mode="nearest"`` (the border voxel is repeated), folded into the matrix rows.

Work is split over our own threads (numpy releases the GIL in matmul) with single-threaded BLAS in
each: thousands of small products with OpenBLAS's own threads stall badly whenever another process
holds a core (each call waits for all its threads), independent slabs do not.
"""

from __future__ import annotations

import ctypes
import glob
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from functools import lru_cache

import numpy as np

_BLOCK = 32  # output rows per banded block: small enough to skip most zeros, large enough for BLAS
_SLAB_BYTES = 2 << 20  # x-slab size filtered along y and z while in cache
_COLUMNS = 4096  # columns per axis-0 product (keeps the band's input rows in cache)


def kernel_radius(sigma_vox: float, truncate: float) -> int:
    """Half-width in voxels of the truncated kernel (scipy's rule: ``int(truncate * sigma + 0.5)``)."""
    # tolerance: sigma=0.15 m at 0.1 m voxels is 1.4999999999999998 voxels in floating point
    return int(truncate * sigma_vox + 0.5 + 1e-9)


@lru_cache(maxsize=1)
def _blas_local_threads() -> Callable[[int], int] | None:
    """OpenBLAS's per-calling-thread thread count setter of numpy's BLAS, if it has one."""
    libdir = os.path.join(os.path.dirname(os.path.dirname(np.__file__)), "numpy.libs")
    for path in sorted(glob.glob(os.path.join(libdir, "*openblas*"))):
        try:
            fn = ctypes.CDLL(path).openblas_set_num_threads_local
        except (OSError, AttributeError):
            continue
        fn.argtypes, fn.restype = [ctypes.c_int], ctypes.c_int
        return fn
    return None


@contextmanager
def _single_threaded_blas() -> Iterator[None]:
    setter = _blas_local_threads()
    if setter is None:
        yield
        return
    previous = setter(1)
    try:
        yield
    finally:
        setter(previous)


@lru_cache(maxsize=32)
def _band(n: int, sigma_vox: float, radius: int) -> tuple[tuple[int, int, int, int, np.ndarray], ...]:
    """Row blocks (a, b, lo, hi, G[a:b, lo:hi]) of the n x n Gaussian matrix with nearest-border rows."""
    k = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (k / sigma_vox) ** 2)
    w /= w.sum()
    blocks = []
    for a in range(0, n, _BLOCK):
        b = min(a + _BLOCK, n)
        lo, hi = max(a - radius, 0), min(b + radius, n)
        g = np.zeros((b - a, hi - lo), dtype=np.float64)
        rows = np.arange(b - a)
        for t, wt in zip(range(-radius, radius + 1), w, strict=True):
            cols = np.clip(np.arange(a, b) + t, 0, n - 1) - lo
            np.add.at(g, (rows, cols), wt)
        g32 = g.astype(np.float32)
        g32.setflags(write=False)
        blocks.append((a, b, lo, hi, g32))
    return tuple(blocks)


def _filter_rows(src: np.ndarray, dst: np.ndarray, sigma_vox: float, radius: int) -> None:
    """Filter along axis 0 of 2-D `src` (rows) into `dst`."""
    for a, b, lo, hi, g in _band(src.shape[0], sigma_vox, radius):
        np.matmul(g, src[lo:hi], out=dst[a:b])


def _filter_axis1(src: np.ndarray, dst: np.ndarray, sigma_vox: float, radius: int) -> None:
    """Filter along axis 1 of a 3-D stack (one matrix product per plane and block)."""
    for a, b, lo, hi, g in _band(src.shape[1], sigma_vox, radius):
        np.matmul(g, src[:, lo:hi, :], out=dst[:, a:b, :])


def gaussian_3d(
    src: np.ndarray,
    sigma_vox: float,
    radius: int,
    *,
    out: np.ndarray | None = None,
    slab_hook: Callable[[int, int], None] | None = None,
    threads: int = 2,
) -> np.ndarray:
    """Gaussian-filter a C-contiguous float32 [nx, ny, nz] grid; returns `out` (allocated if None).

    `slab_hook(x0, x1)` is called (from a worker thread) once each x-slab ``out[x0:x1]`` is final, e.g.
    to post-process it while it is in cache. `src` is not modified.
    """
    if out is None:
        out = np.empty_like(src)
    nx, ny, nz = src.shape
    s2, o2 = src.reshape(nx, -1), out.reshape(nx, -1)
    ncol = ny * nz
    slab = max(1, min(nx, _SLAB_BYTES // max(ny * nz * 4, 1)))

    def columns(c0: int) -> None:
        with _single_threaded_blas():
            _filter_rows(s2[:, c0 : c0 + _COLUMNS], o2[:, c0 : c0 + _COLUMNS], sigma_vox, radius)

    def planes(x0: int) -> None:
        x1 = min(x0 + slab, nx)
        tmp = np.empty((x1 - x0, ny, nz), dtype=np.float32)
        with _single_threaded_blas():
            # along z: z becomes the stacked matrices' row axis through transposed views
            _filter_axis1(out[x0:x1].transpose(0, 2, 1), tmp.transpose(0, 2, 1), sigma_vox, radius)
            _filter_axis1(tmp, out[x0:x1], sigma_vox, radius)  # along y, back into out
        if slab_hook is not None:
            slab_hook(x0, x1)

    if threads <= 1:
        for c0 in range(0, ncol, _COLUMNS):
            columns(c0)
        for x0 in range(0, nx, slab):
            planes(x0)
        return out
    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="esdf-gauss") as pool:
        list(pool.map(columns, range(0, ncol, _COLUMNS)))
        list(pool.map(planes, range(0, nx, slab)))
    return out
