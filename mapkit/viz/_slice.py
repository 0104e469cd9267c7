"""ESDF slices for interactive viewing: :class:`MapSlicer` serves planes from an LRU cache of
chunk-aligned slabs (the first plane of a slab reads the chunks it touches, the others are memory
copies); :func:`slice_texture` colours a slice, hatches unobserved voxels and places it in the world.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from mapkit.esdf import EsdfMap, Slice, slice_plane
from mapkit.viz._color import apply_colormap, hatch, is_diverging, make_norm
from mapkit.viz._errors import VizError

SliceMode = Literal["distance", "cost"]
SLICE_MODES: tuple[str, ...] = ("distance", "cost")
#: The plane's in-plane axes (u, v) per slice axis, as in :class:`mapkit.esdf.Slice`.
PLANE_AXES = {"x": ("y", "z"), "y": ("x", "z"), "z": ("x", "y")}
_AXES = "xyz"
DEFAULT_CACHE_BYTES = 384 * 2**20


class SlabCache:
    """LRU cache of chunk-aligned slabs (``array[..., s*c:(s+1)*c, ...]``, c the chunk length along the
    axis) of 3-D arrays, bounded in bytes, thread-safe."""

    def __init__(self, max_bytes: int = DEFAULT_CACHE_BYTES) -> None:
        if max_bytes <= 0:
            raise VizError(f"cache size {max_bytes} bytes must be > 0")
        self.max_bytes = int(max_bytes)
        self._slabs: OrderedDict[tuple[str, int, int], np.ndarray] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self.hits = 0
        self.misses = 0

    @property
    def nbytes(self) -> int:
        """Bytes held now."""
        return self._bytes

    def clear(self) -> None:
        """Forget every slab (the next reads are cold)."""
        with self._lock:
            self._slabs.clear()
            self._bytes = 0

    def slab(self, name: str, array: Any, axis: int, k: int) -> tuple[np.ndarray, int]:
        """The slab of `array` (3-D, zarr or numpy; cached under `name`) holding plane `k` along
        `axis`, and the index of the slab's first plane."""
        chunks = getattr(array, "chunks", None) or array.shape
        c = max(1, int(chunks[axis]))
        s = k // c
        key = (name, axis, s)
        with self._lock:
            hit = self._slabs.get(key)
            if hit is not None:
                self._slabs.move_to_end(key)
                self.hits += 1
                return hit, s * c
            self.misses += 1
        index: list[slice] = [slice(None)] * 3
        index[axis] = slice(s * c, min((s + 1) * c, array.shape[axis]))
        data = np.asarray(array[tuple(index)])
        with self._lock:
            if key not in self._slabs:
                self._slabs[key] = data
                self._bytes += data.nbytes
            while self._bytes > self.max_bytes and len(self._slabs) > 1:
                _, old = self._slabs.popitem(last=False)
                self._bytes -= old.nbytes
        return data, s * c


class _SlabArray:
    """Array-like view of one grid of a map: a plane request ``a[:, :, k]`` (one integer index, the
    rest full slices) is served from the slab cache; anything else reads the array directly."""

    def __init__(self, array: Any, name: str, cache: SlabCache, store: str) -> None:
        self._array, self._name, self._cache, self._store = array, name, cache, store
        self.shape = tuple(array.shape)
        self.dtype = array.dtype
        self.ndim = 3
        self.chunks = getattr(array, "chunks", None)

    def __getitem__(self, index: Any) -> np.ndarray:
        try:
            if isinstance(index, tuple) and len(index) == 3:
                ints = [i for i, v in enumerate(index) if isinstance(v, (int, np.integer))]
                if len(ints) == 1 and all(v == slice(None) for i, v in enumerate(index) if i != ints[0]):
                    a = ints[0]
                    k = int(index[a])
                    slab, k0 = self._cache.slab(self._name, self._array, a, k)
                    sub: list[Any] = [slice(None)] * 3
                    sub[a] = k - k0
                    return slab[tuple(sub)]
            return np.asarray(self._array[index])
        except VizError:
            raise
        except Exception as exc:  # noqa: BLE001 - damaged chunks surface as many exception types
            raise VizError(
                f"cannot read {self._name!r} of map {self._store} ({type(exc).__name__}: {exc}); the store is "
                "corrupt or incomplete; re-run `mapkit esdf --overwrite`"
            ) from None


class MapSlicer:
    """Cached axis-aligned slices of an opened or in-memory map: :meth:`slice` is
    :func:`mapkit.esdf.slice_plane` served from a :class:`SlabCache` of `cache_bytes`."""

    def __init__(self, esdf_map: EsdfMap, *, cache_bytes: int = DEFAULT_CACHE_BYTES) -> None:
        self.map = esdf_map
        self.cache = SlabCache(cache_bytes)
        store = repr(str(esdf_map.path)) if esdf_map.path is not None else "(in memory)"

        def wrap(name: str) -> Any:
            if name in esdf_map._dense:  # already in memory: nothing to cache
                return esdf_map._dense[name]
            arr = getattr(esdf_map, name)
            return None if arr is None else _SlabArray(arr, name, self.cache, store)

        self._view = EsdfMap(
            esdf=wrap("esdf"), esdf_raw=wrap("esdf_raw"), observed=wrap("observed"),
            voxel_size=esdf_map.voxel_size, origin=esdf_map.origin, frame_id=esdf_map.frame_id,
            sigma=esdf_map.sigma, unknown_policy=esdf_map.unknown_policy, attrs=esdf_map.attrs, path=esdf_map.path,
        )

    def positions(self, axis: str) -> tuple[float, float, float]:
        """(first, last, step): the voxel-centre coordinates (metres) a slice along `axis` can take."""
        c = self.map.coords(axis)
        return float(c[0]), float(c[-1]), float(self.map.voxel_size)

    def snap(self, axis: str, position: float) -> float:
        """The voxel-centre coordinate nearest to `position` along `axis` (clamped to the grid)."""
        a = _axis_index(axis)
        k = int(min(max(round((float(position) - self.map.origin[a]) / self.map.voxel_size), 0), self.map.shape[a] - 1))
        return float(self.map.origin[a] + k * self.map.voxel_size)

    def slice(self, axis: str, position: float, *, raw: bool = False) -> Slice:
        """The plane of voxels nearest to ``axis = position`` (see :func:`mapkit.esdf.slice_plane`)."""
        return slice_plane(self._view, axis=axis, position=position, raw=raw)

    def texture(self, axis: str, position: float, *, raw: bool = False, **style: Any) -> SliceTexture:
        """:meth:`slice` coloured by :func:`slice_texture` (keyword `style` options are its own)."""
        return slice_texture(self.slice(axis, position, raw=raw), axis=axis, **style)


def obstacle_cost_of_distance(distance: np.ndarray, *, robot_radius: float = 0.3, softness: float = 1.0) -> np.ndarray:
    """The planner's obstacle cost (metres) of signed distances (metres), elementwise:
    :func:`mapkit.planner.obstacle_penalty` (the smooth hinge ½(√(u² + ε²) − u) of the clearance
    u = d − robot_radius), the same function the training loss uses. NaN stays NaN."""
    import torch

    from mapkit.planner import obstacle_penalty

    d = torch.from_numpy(np.asarray(distance, dtype=np.float64))
    return obstacle_penalty(d, robot_radius=float(robot_radius), softness=float(softness)).numpy()


def auto_range(values: np.ndarray, mode: SliceMode, *, voxel_size: float) -> tuple[float, float]:
    """A colour range for slice `values`: the 1st..99th percentile of the finite ones; for signed
    distance widened to include ±½ voxel (so 0 sits inside), for cost starting at 0."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return (-1.0, 1.0) if mode == "distance" else (0.0, 1.0)
    lo, hi = (float(x) for x in np.percentile(v, [1.0, 99.0]))
    if mode == "distance":
        lo, hi = min(lo, -0.5 * voxel_size), max(hi, 0.5 * voxel_size)
    else:
        lo, hi = 0.0, max(hi, 1e-3)
    return lo, hi


@dataclass(frozen=True)
class SliceTexture:
    """A coloured slice and where its textured plane lies (world frame of the map). Columns run along
    the plane's first axis u, rows down its second axis v (row 0 at v max); each voxel is a block of
    ``pixels_per_voxel``² pixels."""

    texture: np.ndarray
    """uint8 (nv·p, nu·p, 3) RGB; unobserved or unwritten voxels as a two-grey diagonal hatch."""
    values: np.ndarray
    """float (nu, nv): the quantity coloured (signed distance in m, or obstacle cost in m)."""
    distance: np.ndarray
    """float32 (nu, nv): signed distance (m), NaN where unwritten."""
    observed: np.ndarray
    """bool (nu, nv)."""
    axis: str
    position: float
    """Plane coordinate (m), snapped to a voxel centre."""
    mode: str
    cmap: str
    norm: Any
    """matplotlib norm used for the colours (for :func:`mapkit.viz.colorbar_image`)."""
    label: str
    """Colour-bar label with units."""
    pixels_per_voxel: int
    corners_world: np.ndarray
    """float64 (4, 3): texture corners top-left, top-right, bottom-right, bottom-left (outer voxel edges)."""
    R_world_image: np.ndarray
    """float64 (3, 3): columns are the image's x (along columns), y (down the rows) and normal in the world."""
    centre_world: np.ndarray
    """float64 (3,): centre of the plane."""
    width_m: float
    height_m: float

    def pixel_of_voxel(self, iu: int, iv: int) -> tuple[int, int]:
        """(row, col) of the top-left pixel of in-plane voxel (iu, iv) (indices into `values`)."""
        nv = self.values.shape[1]
        p = self.pixels_per_voxel
        return (nv - 1 - int(iv)) * p, int(iu) * p


def slice_texture(
    sl: Slice,
    *,
    axis: str,
    mode: SliceMode = "distance",
    cmap: str = "RdBu",
    vmin: float | None = None,
    vmax: float | None = None,
    pixels_per_voxel: int = 1,
    robot_radius: float = 0.3,
    softness: float = 1.0,
) -> SliceTexture:
    """Colour a slice along `axis` ("x", "y" or "z") and place it in the world.

    `mode`: "distance" (signed distance, m) or "cost" (:func:`obstacle_cost_of_distance` with
    `robot_radius` and `softness` in m). A diverging `cmap` is centred on 0 for signed distance.
    `vmin`, `vmax`: colour range (default :func:`auto_range`). `pixels_per_voxel` (>= 1) keeps voxel
    edges crisp under linear texture filtering.
    """
    _axis_index(axis)
    if mode not in SLICE_MODES:
        raise VizError(f"mode={mode!r} must be one of {', '.join(map(repr, SLICE_MODES))}")
    if isinstance(pixels_per_voxel, bool) or int(pixels_per_voxel) != pixels_per_voxel or pixels_per_voxel < 1:
        raise VizError(f"pixels_per_voxel={pixels_per_voxel!r} must be a positive integer")
    p = int(pixels_per_voxel)
    dist = np.asarray(sl.values, dtype=np.float32)
    nu, _ = dist.shape
    u0, u1, v0, v1 = sl.extent
    voxel = (u1 - u0) / nu
    if mode == "cost":
        values = obstacle_cost_of_distance(dist, robot_radius=robot_radius, softness=softness)
        label = f"obstacle cost [m] (robot radius {robot_radius:g} m)"
    else:
        values = dist
        label = "signed distance [m]"
    if vmin is None or vmax is None:
        lo, hi = auto_range(values, mode, voxel_size=voxel)
    lo = lo if vmin is None else float(vmin)
    hi = hi if vmax is None else float(vmax)
    norm = make_norm(lo, hi, centre_zero=(mode == "distance" and is_diverging(cmap)))
    rgb = apply_colormap(values, cmap, norm)  # (nu, nv, 3)
    missing = ~np.asarray(sl.observed, dtype=bool) | ~np.isfinite(dist)
    tex = np.ascontiguousarray(rgb.transpose(1, 0, 2)[::-1])  # (nv, nu, 3), row 0 = v max
    miss_t = missing.T[::-1]
    if p > 1:
        tex = np.repeat(np.repeat(tex, p, axis=0), p, axis=1)
        miss_t = np.repeat(np.repeat(miss_t, p, axis=0), p, axis=1)
    if miss_t.any():
        tex[miss_t] = hatch(miss_t, period=max(8, 4 * p))[miss_t]

    corners, R = _plane_pose(sl, axis)
    return SliceTexture(
        texture=tex, values=values, distance=dist, observed=np.asarray(sl.observed, dtype=bool), axis=axis,
        position=float(sl.position), mode=mode, cmap=cmap, norm=norm, label=label, pixels_per_voxel=p,
        corners_world=corners, R_world_image=R, centre_world=corners.mean(axis=0),
        width_m=float(u1 - u0), height_m=float(v1 - v0),
    )


def _plane_pose(sl: Slice, axis: str) -> tuple[np.ndarray, np.ndarray]:
    """(texture corners (4, 3) top-left, top-right, bottom-right, bottom-left; R_world_image) of a slice."""
    a = _axis_index(axis)
    ua, va = (_axis_index(s) for s in PLANE_AXES[axis])
    e = np.eye(3)
    x_img, y_img = e[ua], -e[va]
    R = np.stack([x_img, y_img, np.cross(x_img, y_img)], axis=1)
    u0, u1, v0, v1 = sl.extent

    def point(u: float, v: float) -> np.ndarray:
        q = np.zeros(3)
        q[a], q[ua], q[va] = sl.position, u, v
        return q

    return np.stack([point(u0, v1), point(u1, v1), point(u1, v0), point(u0, v0)]), R


def texture_scale(shape_uv: tuple[int, int], *, target_px: int = 512, max_factor: int = 8) -> int:
    """Pixels per voxel (1..`max_factor`) that bring the longer side of a (nu, nv) slice to about
    `target_px` pixels: small maps stay crisp, large ones cheap to PNG-encode."""
    longest = max(1, max(shape_uv))
    return int(max(1, min(max_factor, math.floor(target_px / longest))))


def _axis_index(axis: str) -> int:
    if axis not in ("x", "y", "z"):
        raise VizError(f"axis={axis!r} must be 'x', 'y' or 'z'")
    return _AXES.index(axis)
