"""Point clouds for viewing: a PLY reader, voxel-grid downsampling, colours, and a local origin."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mapkit.viz._color import apply_colormap, is_diverging, make_norm
from mapkit.viz._errors import VizError

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FIX = "re-run `mapkit fuse --overwrite` to rewrite it"
CloudColoring = Literal["height", "esdf"]
CLOUD_COLORINGS: tuple[str, ...] = ("height", "esdf")


@dataclass(frozen=True)
class PlyPoints:
    """The vertices of a PLY file."""

    points: np.ndarray
    """float64 (N, 3) x, y, z."""
    colors: np.ndarray | None
    """uint8 (N, 3) red, green, blue when the file has them."""


@dataclass
class _PlyElement:
    """One ``element`` line of a PLY header and the ``property`` lines under it."""

    name: str
    count: int
    properties: list[tuple[str, str | None]] = field(default_factory=list)
    """(name, numpy type code), the code None for a list property."""


def _ply_header(f: Any, p: Path) -> tuple[str | None, list[_PlyElement]]:
    """(format, elements) of the PLY header at the start of the open file ``f``; leaves ``f`` at the body."""
    if f.readline().strip() != b"ply":
        raise VizError(f"{str(p)!r} is not a PLY file (no 'ply' magic); {_FIX}")
    fmt: str | None = None
    elements: list[_PlyElement] = []
    while True:
        line = f.readline()
        if not line:
            raise VizError(f"{str(p)!r}: PLY header has no end_header; the file is truncated; {_FIX}")
        words = line.decode("ascii", "replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            return fmt, elements
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append(_PlyElement(words[1], int(words[2])))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1].properties.append((words[-1], None))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1].properties.append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise VizError(f"{str(p)!r}: PLY property line {line.strip()!r} is not understood; {_FIX}")


def read_ply_points(path: str | Path) -> PlyPoints:
    """Read the vertex positions (and colours) of a PLY file (binary little/big endian or ASCII), as
    Open3D writes ``cloud.ply``; other elements (faces) are ignored when they follow the vertices.
    Raises :class:`VizError` naming the file for anything missing, truncated or malformed."""
    p = Path(path)
    if not p.is_file():
        raise VizError(f"no point cloud at {str(p)!r}; make it with `mapkit fuse BAG -w WS`")
    try:
        with open(p, "rb") as f:
            fmt, elements = _ply_header(f, p)
            body = f.read()
    except OSError as exc:
        raise VizError(f"cannot read {str(p)!r}: {exc}") from None
    except ValueError as exc:
        raise VizError(f"{str(p)!r}: malformed PLY header ({exc}); {_FIX}") from None
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise VizError(f"{str(p)!r}: PLY format {fmt!r} is not supported (binary or ascii)")
    if not elements or elements[0].name != "vertex":
        raise VizError(f"{str(p)!r}: the first PLY element must be 'vertex' (got {[e.name for e in elements]}); {_FIX}")
    n, props = elements[0].count, elements[0].properties
    names = [name for name, _ in props]
    if not {"x", "y", "z"} <= set(names) or any(t is None for _, t in props):
        raise VizError(f"{str(p)!r}: PLY vertices need scalar x, y, z properties (have {names}); {_FIX}")
    if fmt == "ascii":
        try:
            table = np.loadtxt(body.decode("ascii").splitlines()[:n], dtype=np.float64, ndmin=2)
        except ValueError as exc:
            raise VizError(f"{str(p)!r}: bad ASCII PLY vertex data ({exc}); {_FIX}") from None
        if table.shape != (n, len(props)):
            raise VizError(f"{str(p)!r}: expected {n} vertices of {len(props)} values, read {table.shape}; {_FIX}")
        col = {name: table[:, i] for i, name in enumerate(names)}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, order + t) for name, t in props if t is not None])  # no lists: checked above
        if len(body) < n * dtype.itemsize:
            raise VizError(
                f"{str(p)!r}: PLY declares {n} vertices ({n * dtype.itemsize} bytes) but holds {len(body)} bytes; "
                f"the file is truncated; {_FIX}"
            )
        rec = np.frombuffer(body, dtype=dtype, count=n)
        col = {name: rec[name] for name in names}
    pts = np.stack([col["x"], col["y"], col["z"]], axis=1).astype(np.float64)
    if not np.all(np.isfinite(pts)):
        raise VizError(f"{str(p)!r}: some vertex positions are NaN or infinite; {_FIX}")
    colors = None
    if {"red", "green", "blue"} <= set(names):
        colors = np.stack([col["red"], col["green"], col["blue"]], axis=1)
        if colors.dtype != np.uint8:  # float colours are 0..1
            colors = np.clip(np.asarray(colors, np.float64) * (255.0 if colors.dtype.kind == "f" else 1.0), 0, 255)
        colors = colors.astype(np.uint8)
    return PlyPoints(pts, colors)


def _cell_keys(pts: np.ndarray, voxel_size: float, lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
    """int64 (N,): one key per grid cell of `voxel_size` (cells aligned to the corner `lo`; `lo`,
    `hi` default to the points' minimum and maximum)."""
    lo = pts.min(axis=0) if lo is None else lo
    hi = pts.max(axis=0) if hi is None else hi
    scale = 1.0 / voxel_size
    cell = ((pts - lo) * scale).astype(np.int64)  # non-negative: truncation = floor
    dims = ((hi - lo) * scale).astype(np.int64) + 1  # the same arithmetic, so every cell index fits
    return (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]


def _count_distinct(keys: np.ndarray) -> int:
    # sort + compare: numpy 2.4's np.unique is ~100x slower than this on millions of int64 keys
    ks = np.sort(keys)
    return int(1 + np.count_nonzero(ks[1:] != ks[:-1])) if len(ks) else 0


def voxel_downsample(points: np.ndarray, *, voxel_size: float) -> np.ndarray:
    """float64 (M, 3): the centroid of the points (N, 3) in each occupied cell of a grid of
    `voxel_size` metres (cells aligned to the points' minimum corner), in cell order (x-major)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise VizError(f"points must have shape (N, 3); got {pts.shape}")
    if not voxel_size > 0:
        raise VizError(f"voxel_size={voxel_size!r} must be > 0 metres")
    if len(pts) == 0:
        return pts.copy()
    key = _cell_keys(pts, voxel_size)
    order = np.argsort(key)
    ks = key[order]
    start = np.flatnonzero(np.concatenate([[True], ks[1:] != ks[:-1]]))
    counts = np.diff(np.append(start, len(ks)))
    return np.add.reduceat(pts[order], start, axis=0) / counts[:, None]


def downsample_to(points: np.ndarray, max_points: int) -> tuple[np.ndarray, float]:
    """Voxel-grid downsample points (N, 3) to at most `max_points`; returns the points and the cell
    size used (0.0 when nothing was done). The cell grows until the occupied cells fit, then bisects
    back until at least 90 % of the budget is used."""
    pts = np.asarray(points, dtype=np.float64)
    if isinstance(max_points, bool) or int(max_points) != max_points or max_points < 1:
        raise VizError(f"max_points={max_points!r} must be a positive integer")
    if len(pts) <= max_points:
        return pts, 0.0
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ext = hi - lo
    area = 2.0 * (ext[0] * ext[1] + ext[1] * ext[2] + ext[0] * ext[2])
    voxel = max(float(np.sqrt(max(area, 1e-12) / max_points)) * 0.5, 1e-6)

    def count(v: float) -> int:
        return _count_distinct(_cell_keys(pts, v, lo, hi))

    n = count(voxel)
    previous: tuple[float, int] | None = None
    while n > max_points:
        # count ∝ cell^-p: p = 2 for surfaces, measured from the last two tries once there are two
        p = 2.0
        if previous is not None and previous[1] > n:
            p = float(np.clip(np.log(previous[1] / n) / np.log(voxel / previous[0]), 0.5, 3.0))
        step = float(np.clip((n / max_points) ** (1.0 / p) * 1.01, 1.01, 4.0))
        previous = (voxel, n)
        voxel *= step
        n = count(voxel)
    if previous is not None:  # bisect (in log cell size) so the budget is used, not overshot
        too_fine = previous[0]
        for _ in range(6):
            if n >= 0.9 * max_points:
                break
            mid = float(np.sqrt(too_fine * voxel))
            m = count(mid)
            if m <= max_points:
                voxel, n = mid, m
            else:
                too_fine = mid
    return voxel_downsample(pts, voxel_size=voxel), voxel


@dataclass(frozen=True)
class CloudView:
    """A point cloud ready to send to a browser."""

    points_local: np.ndarray
    """float32 (M, 3): positions relative to :attr:`origin` (metres)."""
    origin: np.ndarray
    """float64 (3,): world position of the local origin; place the cloud node there."""
    colors: np.ndarray
    """uint8 (M, 3)."""
    total_points: int
    """Points in the file."""
    voxel_size: float
    """Downsampling cell (m), 0.0 when not downsampled."""
    precision: str
    """"float16" when half precision keeps every local coordinate within `tolerance`, else "float32"."""
    color_by: str
    norm: Any
    """matplotlib norm of the colours (for a colour bar)."""

    @property
    def shown_points(self) -> int:
        return len(self.points_local)


def local_origin(points: np.ndarray) -> np.ndarray:
    """float64 (3,): the centre of the points' bounding box rounded to whole metres (a readable
    origin that halves the largest local coordinate)."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(3)
    return np.round(0.5 * (pts.min(axis=0) + pts.max(axis=0)))


def transfer_precision(points_local: np.ndarray, *, tolerance: float = 0.005) -> str:
    """"float16" if rounding local coordinates to half precision moves none by more than
    `tolerance` metres (|x| ≤ 2^11 · tolerance ≈ 10 m for 5 mm), else "float32"."""
    p = np.asarray(points_local)
    if p.size == 0:
        return "float16"
    err = np.abs(p.astype(np.float16).astype(np.float64) - p)
    return "float16" if float(err.max()) <= tolerance and np.all(np.isfinite(p.astype(np.float16))) else "float32"


def cloud_view(
    points: np.ndarray,
    *,
    max_points: int = 2_000_000,
    color_by: CloudColoring = "height",
    esdf_map: Any = None,
    cmap: str | None = None,
    tolerance: float = 0.005,
) -> CloudView:
    """Downsample (to `max_points`), colour and re-centre a world point cloud (N, 3) for display.

    `color_by`: "height" (z, `cmap` default viridis over the 2nd..98th percentile) or "esdf" (the
    `esdf_map`'s signed distance, default RdBu over ±2 voxels; points outside the map grey).
    `tolerance`: metres of float16 rounding accepted before float32 is chosen.
    """
    pts, voxel = downsample_to(points, max_points)
    if color_by not in CLOUD_COLORINGS:
        raise VizError(f"color_by={color_by!r} must be one of {', '.join(map(repr, CLOUD_COLORINGS))}")
    if color_by == "height":
        cm = cmap or "viridis"
        z = pts[:, 2]
        lo, hi = (np.percentile(z, [2.0, 98.0]) if len(z) else (0.0, 1.0))
        norm = make_norm(float(lo), float(max(hi, lo + 1e-3)), centre_zero=False)
        colors = apply_colormap(z, cm, norm)
    else:
        if esdf_map is None:
            raise VizError("color_by='esdf' needs the map (map.zarr); make it with `mapkit esdf -w WS`")
        cm = cmap or "RdBu"
        d, _ = esdf_map.query(pts)
        r = 2.0 * esdf_map.voxel_size
        norm = make_norm(-r, r, centre_zero=is_diverging(cm))
        colors = apply_colormap(np.where(np.isfinite(d), d, 0.0), cm, norm)
        colors[~np.isfinite(d)] = 128
    origin = local_origin(pts)
    local = (pts - origin).astype(np.float32)
    return CloudView(
        points_local=local, origin=origin, colors=colors, total_points=int(len(points)), voxel_size=voxel,
        precision=transfer_precision(local, tolerance=tolerance), color_by=color_by, norm=norm,
    )
