"""Colour helpers: colormaps to uint8 RGB, the unobserved hatch, colour bars, method and speed colours."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from mapkit.viz._errors import VizError

#: Diverging colormaps: signed distances are centred on 0 with them (as ``mapkit slice`` does).
DIVERGING = frozenset({
    "rdbu", "rdylbu", "coolwarm", "bwr", "seismic", "puor", "brbg", "prgn", "piyg", "rdgy", "spectral", "rdylgn",
})
#: The two greys of the diagonal hatch that marks unobserved (or unwritten) voxels.
HATCH_RGB = (np.array([206, 206, 206], np.uint8), np.array([158, 158, 158], np.uint8))


def colormap(name: str) -> Any:
    """The matplotlib colormap `name`; :class:`VizError` if there is none."""
    from matplotlib import colormaps

    if name not in colormaps:
        raise VizError(f"colormap {name!r} is not a matplotlib colormap; try 'RdBu', 'viridis' or 'turbo'")
    return colormaps[name]


def is_diverging(name: str) -> bool:
    """True for diverging colormaps (RdBu, coolwarm, ...; reversed ones too)."""
    return name.lower().removesuffix("_r") in DIVERGING


def make_norm(vmin: float, vmax: float, *, centre_zero: bool) -> Any:
    """A matplotlib norm for [vmin, vmax]; with `centre_zero` and vmin < 0 < vmax each side of 0 gets
    half of the colormap (so shallow obstacle interiors still show saturated, as in ``mapkit slice``)."""
    from matplotlib.colors import Normalize, TwoSlopeNorm

    lo, hi = float(vmin), float(vmax)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise VizError(f"value range [{vmin}, {vmax}] must be finite numbers")
    if not hi > lo:
        raise VizError(f"value range [{vmin}, {vmax}]: the maximum must be larger than the minimum")
    if centre_zero and lo < 0.0 < hi:
        return TwoSlopeNorm(vcenter=0.0, vmin=lo, vmax=hi)
    return Normalize(vmin=lo, vmax=hi, clip=True)


def apply_colormap(values: np.ndarray, cmap: str, norm: Any) -> np.ndarray:
    """uint8 RGB (..., 3) of float `values` (...,) through `norm` and the colormap `cmap`.
    NaN values come out as the colormap's "bad" colour; callers overdraw them."""
    cm = colormap(cmap)
    with np.errstate(invalid="ignore"):
        scaled = np.clip(np.ma.filled(norm(np.asarray(values, dtype=np.float64)), np.nan), 0.0, 1.0)
    rgba = cm(scaled, bytes=True)
    return np.ascontiguousarray(rgba[..., :3])


def hatch(mask: np.ndarray, *, period: int = 8) -> np.ndarray:
    """uint8 RGB (H, W, 3) diagonal two-grey stripes where `mask` (H, W) is True (zeros elsewhere):
    unmistakable against every smooth colormap, including grey ones."""
    h, w = mask.shape
    r, c = np.ogrid[:h, :w]
    light = ((r + c) % period) < period // 2
    out = np.zeros((h, w, 3), np.uint8)
    out[mask & light] = HATCH_RGB[0]
    out[mask & ~light] = HATCH_RGB[1]
    return out


def colorbar_image(
    cmap: str,
    norm: Any,
    *,
    label: str,
    unobserved: bool = True,
    width_px: int = 320,
    height_px: int = 90,
) -> np.ndarray:
    """uint8 RGB (height_px, width_px, 3): a horizontal colour bar of `cmap` over `norm` with ticks
    and `label` (put the units in it, e.g. "signed distance [m]"), and a hatched "unobserved" swatch."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    dpi = 100
    fig = Figure(figsize=(width_px / dpi, height_px / dpi), dpi=dpi, facecolor="white")  # the viser panel is white
    canvas = FigureCanvasAgg(fig)
    left = 0.05
    right = 0.72 if unobserved else 0.95
    ax = fig.add_axes((left, 0.55, right - left, 0.3))
    cb = fig.colorbar(ScalarMappable(norm=norm, cmap=colormap(cmap)), cax=ax, orientation="horizontal")
    cb.ax.tick_params(labelsize=7, length=2, pad=1)
    cb.set_label(label, fontsize=8, labelpad=1)
    if unobserved:
        fig.legend(handles=[Patch(facecolor=tuple(HATCH_RGB[0] / 255), edgecolor=tuple(HATCH_RGB[1] / 255),
                                  hatch="////", label="unobserved")],
                   loc="center right", fontsize=7, frameon=False, handlelength=1.4, borderaxespad=0.2)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[..., :3])


def method_colors(methods: Sequence[str]) -> dict[str, tuple[int, int, int]]:
    """A distinct uint8 RGB colour per method name (matplotlib's tab10, in the order given)."""
    cm = colormap("tab10")
    out = {}
    for i, m in enumerate(methods):
        r, g, b, _ = cm(i % 10, bytes=True)
        out[str(m)] = (int(r), int(g), int(b))
    return out


def speed_colors(
    t: np.ndarray, positions: np.ndarray, *, cmap: str = "turbo", vmax: float | None = None
) -> tuple[np.ndarray, np.ndarray, Any]:
    """Speeds and colours along a trajectory sampled at increasing times `t` (N,) s, `positions` (N, 3) m;
    `vmax`: top of the colour scale in m/s (default: the largest speed).

    Returns speed float64 (N,) m/s (finite differences), colours uint8 (N, 3) and the matplotlib norm
    (for :func:`colorbar_image`).
    """
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    p = np.asarray(positions, dtype=np.float64)
    if p.shape != (t.size, 3):
        raise VizError(f"positions must have shape (N={t.size}, 3) to match t; got {p.shape}")
    if t.size < 2:
        speed = np.zeros(t.size)
    else:
        if not np.all(np.diff(t) > 0):
            raise VizError("trajectory sample times must be strictly increasing")
        speed = np.linalg.norm(np.gradient(p, t, axis=0), axis=1)
    top = float(vmax) if vmax is not None else float(speed.max(initial=0.0))
    norm = make_norm(0.0, max(top, 1e-6), centre_zero=False)
    return speed, apply_colormap(speed, cmap, norm), norm


def depth_image(depth: np.ndarray, *, max_depth: float | None = None, cmap: str = "turbo") -> np.ndarray:
    """uint8 RGB (H, W, 3) of a depth image (H, W) in metres, near = blue .. far = red with turbo;
    invalid (NaN / non-positive) pixels black. `max_depth`: top of the scale (default: 99th
    percentile of the valid depths)."""
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise VizError(f"depth must be a 2-D image (H, W); got shape {d.shape}")
    valid = np.isfinite(d) & (d > 0)
    if max_depth is None:
        max_depth = float(np.percentile(d[valid], 99)) if valid.any() else 1.0
    norm = make_norm(0.0, max(float(max_depth), 1e-3), centre_zero=False)
    rgb = apply_colormap(np.where(valid, d, 0.0), cmap, norm)
    rgb[~valid] = 0
    return rgb
