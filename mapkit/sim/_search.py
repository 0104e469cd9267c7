"""Search-based paths through a :class:`~mapkit.sim.World`'s exact free space.

The ground-truth counterpart of a learned planner: the world's signed distance is sampled on a grid
over the flight volume, cells with enough clearance form a 26-neighbour graph (the same one
:func:`~mapkit.sim.plan_flight` uses, with a cost that keeps paths to the middle of
corridors), and Dijkstra + line-of-sight shortcuts give a short polyline with a guaranteed
clearance. Used by ``mapkit eval`` to sample start–goal pairs and as its ``oracle`` planner.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.sparse.csgraph import dijkstra

from mapkit.sim._errors import SimError
from mapkit.sim._flight import _graph, _Grid, _shortcut
from mapkit.sim._world import World

__all__ = ["FreeSpaceGraph"]


class FreeSpaceGraph:
    """The largest connected region of a world's flight volume with at least ``clearance`` metres
    to every obstacle, as a grid graph.

    Args:
        world: the world.
        clearance: metres every cell centre (and every shortcut) keeps from obstacles.
        resolution: grid spacing, metres (default 0.25 indoors, up to 0.4 in large worlds).
        inset: metres kept from the world's x/y bounds (default 0 for walled worlds, 1 otherwise).

    Raises:
        SimError: no free space with that clearance.
    """

    def __init__(self, world: World, *, clearance: float, resolution: float | None = None,
                 inset: float | None = None) -> None:
        if not clearance > 0:
            raise SimError(f"clearance must be > 0 metres, got {clearance}")
        X, Y = world.bounds[1, :2] - world.bounds[0, :2]
        self.world = world
        self.clearance = float(clearance)
        self.resolution = float(resolution or np.clip(math.sqrt(X * Y / 12000.0), 0.25, 0.4))
        walled = world.kind in ("office", "garage")
        self.grid = _Grid(world, self.resolution, self.clearance,
                          inset=(0.0 if walled else 1.0) if inset is None else float(inset))
        free = self.grid.sdf >= self.clearance
        labels, n = ndimage.label(free, structure=np.ones((3, 3, 3)))
        if n == 0:
            raise SimError(
                f"world {world.kind!r} (seed {world.seed}) has no free space with {self.clearance} m clearance"
            )
        sizes = ndimage.sum_labels(np.ones_like(labels), labels, index=np.arange(1, n + 1))
        self.free = labels == (1 + int(np.argmax(sizes)))
        self.free_index = np.flatnonzero(self.free.ravel())
        self.centres = self.grid.centres
        self._graph = _graph(self.grid, self.free, self.clearance)

    @property
    def num_free(self) -> int:
        return int(len(self.free_index))

    def sdf_at_cells(self, cells: np.ndarray) -> np.ndarray:
        """Exact signed distance (N,) at the centres of flat cell indices (N,)."""
        return self.grid.sdf.ravel()[cells]

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
        dist, pred = dijkstra(self._graph, indices=a, return_predecessors=True)
        if not np.isfinite(dist[b]):
            raise SimError(f"no path with {self.clearance} m clearance from {start.round(2).tolist()} to "
                           f"{goal.round(2).tolist()}")
        cells = [b]
        while cells[-1] != a:
            cells.append(int(pred[cells[-1]]))
        pts = [start, *self.centres[cells[::-1]], goal]
        poly = np.array(pts)
        # Drop the snapped cell centres when the true end points see past them.
        return _shortcut(poly, lambda p, q: self.segment_clear(p, q))
