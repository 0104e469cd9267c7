"""Axis-aligned slices of a map and the ESDF slice figure (matplotlib, Agg backend)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from mapkit.esdf._errors import EsdfError
from mapkit.esdf._map import EsdfMap, _axis_index

_PLANE_AXES = {"x": ("y", "z"), "y": ("x", "z"), "z": ("x", "y")}
_CMAP = "RdBu"  # diverging: obstacles red, free space blue
_COLUMNS = 3  # panels per row


class Slice(NamedTuple):
    """One axis-aligned plane of a map."""

    values: np.ndarray
    """float32 [nu, nv]: signed distance (metres); u, v are the two remaining axes in x, y, z order
    (z-slice: [x, y]; y-slice: [x, z]; x-slice: [y, z])."""
    extent: tuple[float, float, float, float]
    """(u_min, u_max, v_min, v_max): outer voxel edges in metres (matplotlib ``imshow`` extent of values.T)."""
    position: float
    """The plane's coordinate (metres), snapped to the nearest voxel centre."""
    observed: np.ndarray
    """bool [nu, nv]: True where a depth ray observed the voxel (all True if the map has no mask)."""


def slice_plane(map: EsdfMap, *, axis: str, position: float, raw: bool = False) -> Slice:
    """The plane of voxels nearest to ``axis = position`` (metres), reading only the zarr chunks it crosses.

    Returns a :class:`Slice` (values, extent, snapped position, observed). Raises :class:`EsdfError`
    when `position` is beyond the grid (the message gives the valid range).
    """
    a = _axis_index(axis)
    index = _plane_index(map, axis, position)
    k = index[a]
    assert isinstance(k, int)
    vs = map.voxel_size
    values = map.read("esdf_raw" if raw else "esdf", index).astype(np.float32)
    observed = np.ones(values.shape, dtype=bool) if map.observed is None else map.read("observed", index) > 0
    u_ax, v_ax = (_axis_index(s) for s in _PLANE_AXES[axis])
    ext = []
    for b in (u_ax, v_ax):
        ext += [float(map.origin[b] - 0.5 * vs), float(map.origin[b] + (map.shape[b] - 0.5) * vs)]
    return Slice(values, (ext[0], ext[1], ext[2], ext[3]), float(map.origin[a] + k * vs), observed)


def _plane_index(map: EsdfMap, axis: str, position: float) -> tuple[slice | int, ...]:
    """The index (``[:, :, k]`` for z) of the plane of voxels nearest to ``axis = position``; raises
    :class:`EsdfError` when `position` is not a number or beyond the grid."""
    a = _axis_index(axis)
    try:
        pos = float(position)
    except (TypeError, ValueError):
        raise EsdfError(f"{axis}={position!r} is not a number (metres)") from None
    vs, n = map.voxel_size, map.shape[a]
    lo_edge = map.origin[a] - 0.5 * vs
    hi_edge = map.origin[a] + (n - 0.5) * vs
    if not (math.isfinite(pos) and lo_edge <= pos <= hi_edge):
        raise EsdfError(
            f"{axis}={position!r} m is outside the map: valid {axis} is {lo_edge:.3f} .. {hi_edge:.3f} m "
            f"(voxel centres {map.origin[a]:.3f} .. {map.origin[a] + (n - 1) * vs:.3f} m)"
        )
    index: list[slice | int] = [slice(None)] * 3
    index[a] = int(min(max(round((pos - map.origin[a]) / vs), 0), n - 1))
    return tuple(index)


def render_slices(
    map: EsdfMap,
    *,
    path: str | Path,
    z: Sequence[float] = (),
    x: Sequence[float] = (),
    y: Sequence[float] = (),
    raw: bool = False,
) -> Path:
    """Write a PNG with one panel per requested slice (z first, then x, then y); returns its path.
    Panels show the signed distance on metric axes with the zero level black and unobserved voxels
    hatched, under one colour bar centred at 0 (obstacles red, free space blue)."""
    fig = _slice_figure(map, z=z, x=x, y=y, raw=raw)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    return out


def _slice_figure(map: EsdfMap, *, z: Sequence[float], x: Sequence[float], y: Sequence[float], raw: bool) -> Any:
    """The matplotlib Figure behind :func:`render_slices`."""
    # A bare Figure renders with Agg and leaves pyplot's global state (and backend) alone.
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    requests = [("z", v) for v in z] + [("x", v) for v in x] + [("y", v) for v in y]
    if not requests:
        raise EsdfError("no slice requested; pass z=(heights in m,), x=(...) or y=(...)")
    slices = [(ax, slice_plane(map, axis=ax, position=v, raw=raw)) for ax, v in requests]
    for (ax, v), (_, s) in zip(requests, slices, strict=True):
        if np.isnan(s.values).any():  # mapkit stores no NaN distance: a chunk of the store may be missing
            map.check_stored("esdf_raw" if raw else "esdf", _plane_index(map, ax, v))
    norm = _colour_norm([s for _, s in slices], voxel_size=map.voxel_size)
    cols = min(_COLUMNS, len(slices))
    rows = math.ceil(len(slices) / cols)
    fig = Figure(figsize=(4.6 * cols + 1.2, 4.2 * rows + 0.6), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    grey = ListedColormap([(0.5, 0.5, 0.5, 0.6)])
    images = [_draw_slice(panel, axis, s, norm=norm, unobserved_cmap=grey, voxel_size=map.voxel_size)
              for panel, (axis, s) in zip(axes.flat, slices, strict=False)]  # the last row may have spare panels
    for panel in list(axes.flat)[len(slices):]:
        panel.set_visible(False)
    cbar = fig.colorbar(images[-1], ax=axes.ravel().tolist(), shrink=0.9)
    cbar.set_label("signed distance [m]")
    handles = [Patch(facecolor=(0.55, 0.55, 0.55), hatch="///", label="unobserved"),
               Patch(facecolor="white", edgecolor="k", label="surface (d = 0)")]
    fig.legend(handles=handles, loc="outside lower center", ncols=2, frameon=False)
    kind = "raw ESDF" if raw else f"ESDF (Gaussian sigma = {map.sigma:g} m)"
    fig.suptitle(f"{kind}, voxel {map.voxel_size:g} m, frame {map.frame_id}")
    return fig


def _colour_norm(slices: list[Slice], *, voxel_size: float) -> Any:
    """Colour scale of all panels, centred at 0; each side of 0 spans its own range, so shallow obstacle
    interiors still show saturated."""
    from matplotlib.colors import TwoSlopeNorm

    finite = np.concatenate([s.values[np.isfinite(s.values)].ravel() for s in slices])
    if finite.size == 0:
        raise EsdfError("the requested slices hold no finite distance (unwritten map?)")
    lo, hi = min(float(finite.min()), -0.5 * voxel_size), max(float(finite.max()), 0.5 * voxel_size)
    return TwoSlopeNorm(vcenter=0.0, vmin=lo, vmax=hi)


def _draw_slice(panel: Any, axis: str, s: Slice, *, norm: Any, unobserved_cmap: Any, voxel_size: float) -> Any:
    """One panel: the distance image, unobserved voxels hatched, the zero level in black; returns the image."""
    u_name, v_name = _PLANE_AXES[axis]
    image = panel.imshow(s.values.T, origin="lower", extent=s.extent, cmap=_CMAP, norm=norm, interpolation="nearest")
    unobs = ~s.observed
    if unobs.any():
        panel.imshow(np.ma.masked_where(~unobs.T, np.ones(unobs.T.shape)), origin="lower", extent=s.extent,
                     cmap=unobserved_cmap, interpolation="nearest", vmin=0, vmax=1)
        uu = np.linspace(s.extent[0], s.extent[1], unobs.shape[0] + 1)
        vv = np.linspace(s.extent[2], s.extent[3], unobs.shape[1] + 1)
        panel.contourf(0.5 * (uu[1:] + uu[:-1]), 0.5 * (vv[1:] + vv[:-1]), unobs.T.astype(float), levels=[0.5, 1.5],
                       colors="none", hatches=["///"])
    if s.values.shape[0] > 1 and s.values.shape[1] > 1 and (s.values < 0).any() and (s.values > 0).any():
        uc = np.linspace(s.extent[0] + 0.5 * voxel_size, s.extent[1] - 0.5 * voxel_size, s.values.shape[0])
        vc = np.linspace(s.extent[2] + 0.5 * voxel_size, s.extent[3] - 0.5 * voxel_size, s.values.shape[1])
        panel.contour(uc, vc, s.values.T, levels=[0.0], colors="k", linewidths=0.8)
    panel.set_aspect("equal")
    panel.set_xlabel(f"{u_name} [m]")
    panel.set_ylabel(f"{v_name} [m]")
    label = "height z" if axis == "z" else axis
    panel.set_title(f"{label} = {s.position:.2f} m")
    return image
