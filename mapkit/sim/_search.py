"""Search-based paths through a world's exact free space: a 26-neighbour grid graph of the cells with
enough clearance, Dijkstra and line-of-sight shortcuts (``mapkit eval``'s pairs and ``oracle`` planner,
and the legs of :func:`~mapkit.sim.plan_flight`)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.csgraph import dijkstra

from mapkit.sim._errors import SimError
from mapkit.sim._world import World


class _NoFreeSpace(SimError):
    """No cell of the flight volume has the clearance asked for (callers may say it their way)."""


class _Grid:
    """Flight-volume grid with signed distance at cell centres."""

    def __init__(self, world: World, res: float, inset: float) -> None:
        lo = world.bounds[0].copy()
        hi = world.bounds[1].copy()
        lo[:2] += inset
        hi[:2] -= inset
        lo[2], hi[2] = world.flight_z
        if np.any(hi - lo < res):
            raise SimError(f"flight volume {lo}..{hi} is empty; enlarge size")
        self.axes = [np.arange(lo[i], hi[i] + 1e-9, res) for i in range(3)]
        self.shape = tuple(len(a) for a in self.axes)
        self.res = res
        self.origin = np.array([a[0] for a in self.axes])
        self.centres = np.stack(np.meshgrid(*self.axes, indexing="ij"), axis=-1).reshape(-1, 3)
        self.sdf = world.signed_distance(self.centres).reshape(self.shape)

    def interp_sdf(self, pts: np.ndarray) -> np.ndarray:
        """Trilinear signed distance (N,) at points (N, 3) from the cell-centre samples."""
        idx = ((pts - self.origin) / self.res).T
        return ndimage.map_coordinates(self.sdf, idx, order=1, mode="nearest")


def _graph(grid: _Grid, free: np.ndarray, margin: float) -> sparse.csr_matrix:
    """Symmetric 26-neighbour graph of the free cells; an edge costs its length times the mean penalty
    of its ends, which grows as the signed distance falls towards ``margin``."""
    n = free.size
    index = np.arange(n).reshape(free.shape)
    # Cost per metre grows near obstacles so paths keep to the middle of corridors.
    penalty = 1.0 + np.exp(-(np.maximum(grid.sdf, margin) - margin) / 0.3)
    rows, cols, vals = [], [], []
    offsets = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) > (0, 0, 0)]
    nx, ny, nz = free.shape
    for dx, dy, dz in offsets:
        a = (slice(max(0, -dx), nx - max(0, dx)), slice(max(0, -dy), ny - max(0, dy)), slice(max(0, -dz), nz - max(0, dz)))
        b = (slice(max(0, -dx) + dx, nx - max(0, dx) + dx), slice(max(0, -dy) + dy, ny - max(0, dy) + dy),
             slice(max(0, -dz) + dz, nz - max(0, dz) + dz))
        ok = free[a] & free[b]
        length = grid.res * math.sqrt(dx * dx + dy * dy + dz * dz)
        rows.append(index[a][ok])
        cols.append(index[b][ok])
        vals.append(length * 0.5 * (penalty[a][ok] + penalty[b][ok]))
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    return sparse.csr_matrix((np.concatenate([v, v]), (np.concatenate([r, c]), np.concatenate([c, r]))), shape=(n, n))


def _shortcut(path: np.ndarray, clear: Callable[[np.ndarray, np.ndarray], bool]) -> np.ndarray:
    """Greedy line-of-sight shortening of a polyline (keeps the end points)."""
    out = [path[0]]
    i, n = 0, len(path)
    while i < n - 1:
        # Exponential then binary search for the farthest visible vertex.
        step, j = 1, i + 1
        while i + 2 * step < n and clear(path[i], path[i + 2 * step]):
            step *= 2
        lo, hi = i + step, min(i + 2 * step, n - 1)
        j = lo
        while lo <= hi:
            mid = (lo + hi) // 2
            if clear(path[i], path[mid]):
                j, lo = mid, mid + 1
            else:
                hi = mid - 1
        out.append(path[j])
        i = j
    return np.array(out)


class FreeSpaceGraph:
    """The largest connected region of a world's flight volume with at least ``clearance`` metres
    to every obstacle, as a grid graph.

    Args:
        clearance: metres every cell centre (and every shortcut) keeps from obstacles.
        resolution: grid spacing, metres (default 0.25, up to 0.4 in large worlds).
        cost_margin: signed distance (metres) below which an edge's cost stops growing (default
            ``clearance``).

    Raises:
        SimError: no free space with that clearance.
    """

    def __init__(self, world: World, *, clearance: float, resolution: float | None = None,
                 cost_margin: float | None = None) -> None:
        if not clearance > 0:
            raise SimError(f"clearance must be > 0 metres, got {clearance}")
        X, Y = world.bounds[1, :2] - world.bounds[0, :2]
        self.world = world
        self.clearance = float(clearance)
        self.resolution = float(resolution or np.clip(math.sqrt(X * Y / 12000.0), 0.25, 0.4))
        # metres kept from the world's x/y bounds: none in walled worlds
        self.grid = _Grid(world, self.resolution, inset=0.0 if world.kind in ("office", "garage") else 1.0)
        free = self.grid.sdf >= self.clearance
        labels, n = ndimage.label(free, structure=np.ones((3, 3, 3)))
        if n == 0:
            raise _NoFreeSpace(
                f"world {world.kind!r} (seed {world.seed}) has no free space with {self.clearance} m clearance"
            )
        sizes = ndimage.sum_labels(np.ones_like(labels), labels, index=np.arange(1, n + 1))
        self.free = labels == (1 + int(np.argmax(sizes)))
        self.free_index = np.flatnonzero(self.free.ravel())
        self.centres = self.grid.centres
        # Symmetric sparse (cells x cells) edge costs between free neighbours.
        self.graph = _graph(self.grid, self.free, self.clearance if cost_margin is None else cost_margin)

    @property
    def num_free(self) -> int:
        return int(len(self.free_index))

    def nearest_cell(self, point: np.ndarray) -> int:
        """Flat index of the free cell nearest to ``point`` (3,)."""
        d = np.linalg.norm(self.centres[self.free_index] - np.asarray(point, dtype=np.float64)[None], axis=1)
        return int(self.free_index[int(np.argmin(d))])

    def segment_clear(self, a: np.ndarray, b: np.ndarray, clearance: float | None = None) -> bool:
        """True when the straight segment a→b keeps ``clearance`` (default the graph's) everywhere,
        checked on the exact signed distance every quarter of a cell."""
        need = self.clearance if clearance is None else clearance
        n = max(2, int(math.ceil(np.linalg.norm(b - a) / (0.25 * self.resolution))) + 1)
        pts = a[None, :] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None, :]
        return bool(self.world.signed_distance(pts).min() >= need)

    def path(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Shortest polyline (N, 3) from ``start`` to ``goal`` through free cells, shortened by
        line-of-sight shortcuts that keep the clearance; starts and ends at the given points.

        Raises:
            SimError: the two points are not connected in the free space.
        """
        start = np.asarray(start, dtype=np.float64).reshape(3)
        goal = np.asarray(goal, dtype=np.float64).reshape(3)
        a, b = self.nearest_cell(start), self.nearest_cell(goal)
        cells = self.cell_path(a, b)
        if cells is None:
            raise SimError(f"no path with {self.clearance} m clearance from {start.round(2).tolist()} to "
                           f"{goal.round(2).tolist()}")
        # Drop the snapped cell centres when the true end points see past them.
        return _shortcut(np.array([start, *self.centres[cells], goal]), self.segment_clear)

    def cell_path(self, a: int, b: int) -> list[int] | None:
        """Cheapest sequence of flat cell indices from cell ``a`` to cell ``b`` (both included), or None
        when they are not connected."""
        dist, pred = dijkstra(self.graph, indices=a, return_predecessors=True)
        if not np.isfinite(dist[b]):
            return None
        cells = [b]
        while cells[-1] != a:
            cells.append(int(pred[cells[-1]]))
        return cells[::-1]
