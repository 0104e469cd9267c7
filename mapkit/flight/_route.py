"""The flight map: every surface the camera saw during one flight, on a 3-D grid, and the route to
the goal around them (unseen space counts as free), for a learned planner that has stopped getting
closer to its goal: one depth image draws it to the wall nearest a goal behind it. The route runs
through every column that some height keeps clear (a doorway under a lintel). Route search:
scikit-image's MCP on a cost grid from SciPy's Euclidean distance transform.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RouteConfig:
    """When the flight map steers a learned planner, and how its route is found."""

    after: float = 3.0
    """Seconds without getting ``progress`` metres closer to the goal than ever before in the flight,
    after which the route chooses the network's goal, until the flight is that much closer than ever."""
    progress: float = 0.5
    """Metres of progress that count."""
    cell: float = 0.25
    """Metres, the side of a grid cell (the same up and across, so distances are Euclidean)."""
    extent: float = 80.0
    """Metres, the side of the grid across, centred where the flight starts."""
    height: float = 6.0
    """Metres, the grid's height, centred on the height the flight starts at."""
    descend: float = 1.0
    """Metres the route may go below the lower of the vehicle's and the goal's heights (it never goes
    above the higher): a column is passable when some height in that range keeps ``inflate`` clear."""
    inflate: float = 0.45
    """Metres: places nearer a seen surface than this are not passed (the robot radius and a margin)."""
    wary: float = 1.0
    """Metres: passing nearer a seen surface than this costs up to 4× as much (routes keep to the
    middle of doorways), and the route's height through a column keeps this much clear where it can."""
    detour: float = 1.0
    """Metres the route must be longer than the straight line for the route to be used."""
    horizon: float = 5.0
    """Metres along the route within which the aim point is chosen."""
    sight: float = 0.3
    """Metres the straight line from the vehicle to the aim point must keep from seen surfaces."""
    ground: float = 0.0
    """World height of the ground (z up), which counts as seen everywhere (else a route opens under a
    wall whose foot the camera missed)."""


def depth_points(depth: np.ndarray, ray: tuple[float, float, float, float], T_world_camera: np.ndarray,
                 stride: int) -> np.ndarray:
    """(N, 3) world points of every ``stride``-th valid pixel of a depth image (``ray``: normalised fx, fy, cx, cy)."""
    full = np.asarray(depth, dtype=np.float64)
    H, W = full.shape
    sub = full[::stride, ::stride]
    fx, fy, cx, cy = ray
    v, u = np.nonzero(np.isfinite(sub) & (sub > 0))
    z = sub[v, u]
    x = ((u * stride + 0.5) / W - cx) / fx * z
    y = ((v * stride + 0.5) / H - cy) / fy * z
    return np.stack([x, y, z], axis=1) @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]


@dataclass(frozen=True)
class Aim:
    """Where the flight map sends a stalled flight."""

    xy: np.ndarray
    """(2,) world point on the route, the farthest within the horizon in straight sight."""
    height: float | None
    """World height to pass the route's first column closed at the vehicle's height; None: open."""


class FlightMap:
    """Every surface the camera saw during one flight, on a 3-D grid (:meth:`forget` starts the next)."""

    def __init__(self, config: RouteConfig = RouteConfig()) -> None:
        self.config = config
        self.size = int(round(config.extent / config.cell))
        self.levels = int(round(config.height / config.cell))
        self.occupied: np.ndarray | None = None
        self.origin: np.ndarray | None = None

    def forget(self) -> None:
        self.occupied = None
        self.origin = None

    def add(self, points_world: np.ndarray, position: np.ndarray) -> None:
        """Mark the cells of ``points_world`` (N, 3); the first call centres the grid on ``position`` (3,)."""
        c = self.config
        if self.occupied is None:
            self.occupied = np.zeros((self.size, self.size, self.levels), dtype=bool)
            half = 0.5 * c.cell * np.array([self.size, self.size, self.levels])
            self.origin = np.asarray(position, dtype=np.float64) - half
        ijk = np.floor((points_world - self.origin) / c.cell).astype(int)
        inside = (ijk >= 0).all(axis=1) & (ijk < self.occupied.shape).all(axis=1)
        self.occupied[ijk[inside, 0], ijk[inside, 1], ijk[inside, 2]] = True

    def _cells(self, xy: np.ndarray) -> np.ndarray:
        assert self.origin is not None  # after add
        return np.clip(np.floor((xy - self.origin[:2]) / self.config.cell).astype(int), 0, self.size - 1)

    def _level(self, z: float) -> int:
        assert self.origin is not None
        return int(np.clip(np.floor((z - self.origin[2]) / self.config.cell), 0, self.levels - 1))

    def aim(self, position: np.ndarray, goal: np.ndarray) -> Aim | None:
        """The farthest route point toward ``goal`` within the horizon in straight sight of ``position``, and
        the height to pass at; None when nothing is mapped near, the route is no detour, or none is in sight."""
        from skimage.graph import MCP_Geometric

        c = self.config
        if self.occupied is None or self.origin is None:
            return None
        a, b = self._cells(position[:2]), self._cells(goal[:2])
        margin = int(8.0 / c.cell)
        lo = np.maximum(np.minimum(a, b) - margin, 0)
        hi = np.minimum(np.maximum(a, b) + margin + 1, self.size)
        occupied = self.occupied[lo[0]:hi[0], lo[1]:hi[1]]
        if not occupied.any():
            return None
        clearance, column = self._clearance(occupied, position[2], goal[2])
        cost = np.where(column < c.inflate, 1e3,
                        1.0 + 3.0 * np.clip((c.wary - column) / (c.wary - c.inflate), 0.0, 1.0))
        here, there = (int(a[0] - lo[0]), int(a[1] - lo[1])), (int(b[0] - lo[0]), int(b[1] - lo[1]))
        cost[here] = min(cost[here], 1.0)  # the vehicle may start near a wall
        search = MCP_Geometric(cost)
        search.find_costs([there])
        cells = np.array(search.traceback(here))[::-1]
        route = (cells + lo + 0.5) * c.cell + self.origin[:2]
        step = np.linalg.norm(np.diff(route, axis=0), axis=1)
        if step.sum() - float(np.linalg.norm(goal[:2] - position[:2])) < c.detour:
            return None
        along = np.concatenate([[0.0], np.cumsum(step)])
        xy = self._farthest_in_sight(route, along, position[:2], column, lo)
        if xy is None:
            return None
        return Aim(xy, self._height(clearance, column, cells[along <= c.horizon], position[2]))

    def _clearance(self, occupied: np.ndarray, z_vehicle: float, z_goal: float) -> tuple[np.ndarray, np.ndarray]:
        """Metres from each cell to the nearest seen surface (0 at unusable heights), and each column's best."""
        from scipy.ndimage import distance_transform_edt

        c = self.config
        low = self._level(min(z_vehicle, z_goal) - c.descend)
        high = self._level(max(z_vehicle, z_goal))
        # surfaces farther than `wary` from the usable heights change nothing: transform that slab only
        reach = int(np.ceil(c.wary / c.cell)) + 1
        bottom, top = max(low - reach, 0), min(high + 1 + reach, self.levels)
        slab = occupied[:, :, bottom:top]
        assert self.origin is not None  # after add
        if c.ground >= self.origin[2] and self._level(c.ground) >= bottom:
            slab = slab.copy()  # the ground and below count as seen
            slab[:, :, :self._level(c.ground) - bottom + 1] = True
        clearance = np.zeros(occupied.shape)
        clearance[:, :, low:high + 1] = (distance_transform_edt(~slab) * c.cell)[:, :, low - bottom:high + 1 - bottom]
        return clearance, clearance.max(axis=2)

    def _height(self, clearance: np.ndarray, column: np.ndarray, cells: np.ndarray, z: float) -> float | None:
        """The height nearest ``z`` keeping ``wary`` clear (or the column's best) through the first of
        ``cells`` closed at ``z`` though open at another; None when there is none."""
        c = self.config
        assert self.origin is not None  # after add
        k = self._level(z)
        for i, j in cells:
            if clearance[i, j, k] >= c.inflate or column[i, j] < c.inflate:
                continue
            good = np.flatnonzero(clearance[i, j] >= min(c.wary, column[i, j]) - 1e-9)
            best = int(good[np.argmin(np.abs(good - k))])
            return float(self.origin[2] + (best + 0.5) * c.cell)
        return None

    def _farthest_in_sight(self, route: np.ndarray, along: np.ndarray, start: np.ndarray, clearance: np.ndarray,
                           lo: np.ndarray) -> np.ndarray | None:
        best = None
        for k in range(1, len(route)):
            if along[k] > self.config.horizon:
                break
            if along[k] < 1.0:
                continue
            n = max(int(np.linalg.norm(route[k] - start) / 0.1), 2)
            line = start + (route[k] - start) * np.linspace(0.0, 1.0, n)[:, None]
            ij = np.clip(self._cells(line) - lo, 0, np.array(clearance.shape) - 1)
            if (clearance[ij[:, 0], ij[:, 1]] < self.config.sight).any():
                break
            best = route[k]
        return best


@dataclass
class Progress:
    """How close a flight has come to its goal, and since when (stalled: no ``progress`` for ``after`` s)."""

    best: float = np.inf
    since: float = 0.0

    def update(self, t: float, distance: float, config: RouteConfig) -> bool:
        """Record the distance at time ``t``; True while stalled."""
        if distance < self.best - config.progress:
            self.best, self.since = distance, t
        return t - self.since > config.after
