"""Exact signed Euclidean distance transform and the sign-preserving Gaussian smoothing."""

from __future__ import annotations

from typing import Literal

import numpy as np

from mapkit.esdf import _checks
from mapkit.esdf._errors import EsdfError
from mapkit.esdf._gauss import gaussian_3d, kernel_radius

Backend = Literal["edt", "scipy"]
BACKENDS: tuple[str, ...] = ("edt", "scipy")


def signed_distance(
    occupied: np.ndarray,
    *,
    voxel_size: float,
    max_dist: float | None = None,
    backend: Backend = "edt",
    threads: int | None = None,
) -> np.ndarray:
    """Exact signed Euclidean distance in metres of every voxel to the obstacle surface: float32
    [nx, ny, nz], positive in free space, negative inside obstacles.

    - `occupied`: bool [nx, ny, nz], True where a voxel is an obstacle (indexed [x, y, z]).
    - `voxel_size`: voxel edge in metres.
    - `max_dist`: clamp distances to [-max_dist, +max_dist] (metres). Without it every free voxel
      carries its true distance however far it is (no plateau, so gradients never vanish).
    - `backend`: ``"edt"`` (the ``edt`` package, fastest) or ``"scipy"``; both exact, equal to float32
      rounding.
    - `threads`: CPU threads of the ``edt`` backend (None: ``OMP_NUM_THREADS`` if set, else the cores).

    Half-voxel convention: a free voxel gets ``(D_occ - 0.5) * voxel_size``, with ``D_occ`` the distance
    (voxels) to the nearest occupied centre; an occupied one ``-(D_free - 0.5) * voxel_size``. So the sign
    changes between the two layers that straddle the surface and ``|d| >= voxel_size / 2``. Voxels
    beyond the grid's border are unknown, not obstacles.

    A grid with no occupied (or no free) voxel gives the constant +max_dist (-max_dist) with
    `max_dist`, an :class:`EsdfError` without it.
    """
    occ = _checks.bool_grid("occupied", occupied)
    vs = _checks.positive("voxel_size", voxel_size)
    md = None if max_dist is None else _checks.positive("max_dist", max_dist)
    if backend not in BACKENDS:
        raise EsdfError(f"backend={backend!r} is unknown; use one of {', '.join(map(repr, BACKENDS))}")
    n_threads = _checks.threads(threads)
    n_occ = int(np.count_nonzero(occ))
    if n_occ == 0 or n_occ == occ.size:
        what = "no occupied voxel (no obstacle)" if n_occ == 0 else "no free voxel (everything is occupied)"
        if md is None:
            raise EsdfError(
                f"the {occ.shape} grid has {what}, so the signed distance is infinite everywhere; "
                "pass max_dist= to get a constant clamped field, or check the occupancy input"
            )
        return np.full(occ.shape, md if n_occ == 0 else -md, dtype=np.float32)
    return _signed_distance_unchecked(occ, vs, md, backend, n_threads)


def _signed_distance_unchecked(
    occ: np.ndarray, vs: float, max_dist: float | None, backend: str, threads: int
) -> np.ndarray:
    """The transform without argument checks; single-label blocks give +-inf (clamped if max_dist)."""
    d: np.ndarray
    if backend == "edt":
        import edt

        # labels 1 = free, 2 = occupied: edt's multi-label mode measures every voxel's distance to
        # the nearest voxel of the other label, i.e. both sides of the surface in one transform.
        labels = np.add(occ.view(np.uint8), np.uint8(1), order="C")  # C order in, C order out
        d = edt.edt(labels, parallel=threads)
        del labels
        d = np.asarray(d, dtype=np.float32)
    else:
        from scipy import ndimage

        occ = np.ascontiguousarray(occ)
        d = ndimage.distance_transform_edt(~occ).astype(np.float32)  # free: to the nearest occupied
        if occ.all() or not occ.any():  # scipy's value without a background voxel is meaningless
            d.fill(np.inf)
        else:
            d_in = ndimage.distance_transform_edt(occ)
            np.copyto(d, d_in, where=occ, casting="same_kind")
            del d_in
    d -= np.float32(0.5)
    d *= np.float32(vs)
    np.negative(d, out=d, where=occ)
    if max_dist is not None:
        np.clip(d, np.float32(-max_dist), np.float32(max_dist), out=d)
    return d


def smooth(
    esdf_raw: np.ndarray,
    *,
    voxel_size: float,
    sigma: float,
    truncate: float = 3.0,
    threads: int | None = None,
) -> tuple[np.ndarray, int]:
    """Gaussian-smooth a signed distance field without flipping the sign away from the surface.

    - `esdf_raw`: float [nx, ny, nz] signed distance in metres (e.g. from :func:`signed_distance`).
    - `voxel_size`, `sigma` (the Gaussian's standard deviation; 0 returns a copy): metres.
    - `truncate`: kernel half-width in standard deviations (radius ``int(truncate * sigma/voxel_size
      + 0.5)`` voxels, as in scipy); borders repeat the edge voxel (scipy ``mode="nearest"``).
    - `threads`: CPU threads (None: ``OMP_NUM_THREADS`` if set, else the available cores).

    Returns (esdf, n_prevented): the float32 smoothed field, and the number of voxels more than one
    voxel from the surface whose sign smoothing would have flipped; they keep their raw value, so thin
    obstacles and narrow gaps are never blurred away.
    """
    vs = _checks.positive("voxel_size", voxel_size)
    sg = _checks.non_negative("sigma", sigma)
    tr = _checks.positive("truncate", truncate, unit="standard deviations")
    n_threads = _checks.threads(threads)
    raw = _checks.float_grid("esdf_raw", esdf_raw)
    if sg == 0.0:
        return raw.copy(), 0
    return _smooth_unchecked(raw, vs, sg, tr, threads=n_threads)


def _smooth_unchecked(
    raw: np.ndarray,
    vs: float,
    sigma: float,
    truncate: float,
    count_region: tuple[slice, ...] | None = None,
    threads: int = 2,
    offset: tuple[int, int, int] = (0, 0, 0),
) -> tuple[np.ndarray, int]:
    """Smoothing without checks; guarded voxels are counted only inside `count_region` if given;
    `offset` is the index of ``raw[0, 0, 0]`` in the grid `raw` is a block of (see :func:`gaussian_3d`)."""
    sigma_vox = sigma / vs
    radius = kernel_radius(sigma_vox, truncate)
    if radius == 0:
        return raw.copy(), 0
    out = np.empty_like(raw)
    counts: list[int] = []  # appended from worker threads (list.append is atomic)
    limit = np.float32(vs)

    def guard(x0: int, x1: int) -> None:
        r, e = raw[x0:x1], out[x0:x1]
        bad = (e > 0) != (r > 0)
        bad &= np.abs(r) > limit
        if not bad.any():
            return
        np.copyto(e, r, where=bad)
        if count_region is None:
            counts.append(int(np.count_nonzero(bad)))
        else:
            rx = count_region[0]
            lo, hi = max(rx.start, x0), min(rx.stop, x1)
            if lo < hi:
                counts.append(int(np.count_nonzero(bad[lo - x0 : hi - x0, count_region[1], count_region[2]])))

    gaussian_3d(raw, sigma_vox, radius, out=out, slab_hook=guard, threads=threads, offset=offset)
    return out, sum(counts)
