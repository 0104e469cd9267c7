"""Separable Gaussian filter of a 3-D float32 grid as row blocks of banded matrix products (BLAS does
the arithmetic), equal to ``scipy.ndimage.gaussian_filter(mode="nearest")`` to float32 rounding.

Work is split over our own threads with single-threaded BLAS in each: OpenBLAS's own threads stall
on thousands of small products whenever another process holds a core.
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
_COLUMNS = 4096  # columns per axis-0 product (keeps the band's input rows in cache); a multiple of _LANES
_LANES = 16  # column counts are padded to this: BLAS (OpenBLAS sgemm: 16 per kernel) rounds left-over columns differently


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


@lru_cache(maxsize=64)
def _band(n: int, sigma_vox: float, radius: int, phase: int) -> tuple[tuple[int, np.ndarray], ...]:
    """Row blocks (a, G) of the n x n Gaussian matrix with nearest-border rows: a at ``-phase + k *
    _BLOCK``, G ``_BLOCK x (_BLOCK + 2 * radius)`` over input rows ``a - radius ..``, zero outside [0, n)."""
    k = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (k / sigma_vox) ** 2)
    w /= w.sum()
    blocks = []
    for a in range(-phase, n, _BLOCK):
        g = np.zeros((_BLOCK, _BLOCK + 2 * radius), dtype=np.float64)
        rows = np.arange(max(a, 0), min(a + _BLOCK, n))
        for t, wt in zip(range(-radius, radius + 1), w, strict=True):
            cols = np.clip(rows + t, 0, n - 1) - (a - radius)
            np.add.at(g, (rows - a, cols), wt)
        g32 = g.astype(np.float32)
        g32.setflags(write=False)
        blocks.append((a, g32))
    return tuple(blocks)


def _filter_stack(src: np.ndarray, dst: np.ndarray, sigma_vox: float, radius: int, phase: int, *,
                  n: int, base: int = 0) -> None:
    """Filter along axis 1 of a stack [s, rows, columns]: local row r of the grid is row ``base + r``
    of `src` / `dst`, the grid has `n` rows. Every product is the same ``_BLOCK x (_BLOCK + 2r)``
    band times a window of input rows: a view where the window lies inside `src`, else a zero-padded
    copy. Output rows outside [0, n) are written only where `dst` has room for them (as zeros)."""
    rows_held = src.shape[1]
    for a, g in _band(n, sigma_vox, radius, phase):
        lo, hi = base + a - radius, base + a + _BLOCK + radius
        if lo >= 0 and hi <= rows_held:
            window = src[:, lo:hi, :]
        else:
            window = np.zeros((src.shape[0], hi - lo, src.shape[2]), dtype=np.float32)
            window[:, max(lo, 0) - lo : min(hi, rows_held) - lo, :] = src[:, max(lo, 0) : min(hi, rows_held), :]
        r0, r1 = base + a, base + a + _BLOCK
        if r0 >= 0 and r1 <= dst.shape[1]:
            np.matmul(g, window, out=dst[:, r0:r1, :])
        else:
            v0, v1 = base + max(a, 0), base + min(a + _BLOCK, n)
            dst[:, v0:v1, :] = np.matmul(g, window)[:, v0 - r0 : v1 - r0, :]


def _padded(n: int) -> int:
    """`n` rounded up to a multiple of :data:`_LANES`."""
    return -(-n // _LANES) * _LANES


def _filter_columns(s2: np.ndarray, o2: np.ndarray, c0: int, sigma_vox: float, radius: int, phase: int) -> None:
    """Filter columns ``c0 : c0 + _COLUMNS`` of 2-D `s2` along axis 0 into `o2`; a last block of a
    width that is not a multiple of ``_LANES`` goes through a zero-padded copy."""
    c1 = min(c0 + _COLUMNS, s2.shape[1])
    width = c1 - c0
    n = s2.shape[0]
    if width % _LANES == 0:
        _filter_stack(s2[None, :, c0:c1], o2[None, :, c0:c1], sigma_vox, radius, phase, n=n)
        return
    src = np.zeros((1, n, _padded(width)), dtype=np.float32)
    src[0, :, :width] = s2[:, c0:c1]
    dst = np.empty_like(src)
    _filter_stack(src, dst, sigma_vox, radius, phase, n=n)
    o2[:, c0:c1] = dst[0, :, :width]


def _margins(n: int, phase: int, radius: int) -> tuple[int, int]:
    """(base, length) of a buffer axis that holds every band window of an axis of `n` rows."""
    base = phase + radius
    last = -phase + ((n - 1 + phase) // _BLOCK) * _BLOCK
    return base, _padded(base + last + _BLOCK + radius)


def _filter_planes(slab: np.ndarray, sigma_vox: float, radius: int, phase_y: int, phase_z: int) -> None:
    """Filter an x-slab [s, ny, nz] along z then y, in place, through zero-padded buffers that hold
    every band window (so each product's operands have the same layout) and whose y and z extents
    are multiples of ``_LANES``."""
    s, ny, nz = slab.shape
    by, ly = _margins(ny, phase_y, radius)
    bz, lz = _margins(nz, phase_z, radius)
    a = np.zeros((s, ly, lz), dtype=np.float32)
    a[:, by : by + ny, bz : bz + nz] = slab
    b = np.zeros_like(a)
    # along z: z becomes the stacked matrices' row axis through transposed views
    _filter_stack(a.transpose(0, 2, 1), b.transpose(0, 2, 1), sigma_vox, radius, phase_z, n=nz, base=bz)
    _filter_stack(b, a, sigma_vox, radius, phase_y, n=ny, base=by)  # along y
    slab[...] = a[:, by : by + ny, bz : bz + nz]


def gaussian_3d(
    src: np.ndarray,
    sigma_vox: float,
    radius: int,
    *,
    out: np.ndarray | None = None,
    slab_hook: Callable[[int, int], None] | None = None,
    threads: int = 2,
    offset: tuple[int, int, int] = (0, 0, 0),
) -> np.ndarray:
    """Gaussian-filter a C-contiguous float32 [nx, ny, nz] grid; returns `out` (allocated if None).

    `slab_hook(x0, x1)` is called (from a worker thread) once each x-slab ``out[x0:x1]`` is final.
    `offset`: the index of ``src[0, 0, 0]`` in a larger grid: every voxel goes through the same
    products wherever it sits, so a block with a halo of `radius` gives the whole grid's values bit
    for bit in its interior (the chunked ESDF relies on it).
    """
    if out is None:
        out = np.empty_like(src)
    nx, ny, nz = src.shape
    phase_x, phase_y, phase_z = (int(o) % _BLOCK for o in offset)
    s2, o2 = src.reshape(nx, -1), out.reshape(nx, -1)
    ncol = ny * nz
    slab = max(1, min(nx, _SLAB_BYTES // max(_padded(ny) * _padded(nz) * 4, 1)))

    def columns(c0: int) -> None:
        with _single_threaded_blas():
            _filter_columns(s2, o2, c0, sigma_vox, radius, phase_x)

    def planes(x0: int) -> None:
        x1 = min(x0 + slab, nx)
        with _single_threaded_blas():
            _filter_planes(out[x0:x1], sigma_vox, radius, phase_y, phase_z)
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
