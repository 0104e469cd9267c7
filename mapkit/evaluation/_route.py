"""The flight map: every surface the camera saw during one flight, on a level grid, and the route to
the goal around them, for a learned planner that has stopped getting closer to its goal.

A planner that reads one depth image is drawn to the wall nearest a goal behind it (the office's
long walls with doors): it flies there, finds no way on, leaves, and comes back. The map remembers
the whole flight, and an optimistic route (unseen space counts as free) leads along the walls seen so
far to the doorways that are left. Route search: scikit-image's MCP on a cost grid from SciPy's
Euclidean distance transform; the grid itself, the point to aim at and when to use them are written
here, because no library keeps such a map for a flight.
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
    """Metres, the side of a grid cell."""
    extent: float = 80.0
    """Metres, the side of the square grid, centred where the flight starts."""
    band: float = 0.5
    """Metres above and below the vehicle's height within which seen points count as surfaces."""
    inflate: float = 0.45
    """Metres: cells nearer a seen surface than this are not passed (the robot radius and a margin)."""
    wary: float = 1.0
    """Metres: passing nearer a seen surface than this costs up to 4× as much (routes keep to the
    middle of doorways)."""
    detour: float = 1.0
    """Metres the route must be longer than the straight line for the route to be used."""
    horizon: float = 5.0
    """Metres along the route within which the aim point is chosen."""
    sight: float = 0.3
    """Metres the straight line from the vehicle to the aim point must keep from seen surfaces."""


def depth_points(depth: np.ndarray, ray: tuple[float, float, float, float], T_world_camera: np.ndarray,
                 stride: int) -> np.ndarray:
    """(N, 3) world points of every ``stride``-th valid pixel of a depth image (metres along the
    optical axis; ``ray`` the normalised intrinsics fx, fy, cx, cy of the image)."""
    full = np.asarray(depth, dtype=np.float64)
    H, W = full.shape
    sub = full[::stride, ::stride]
    fx, fy, cx, cy = ray
    v, u = np.nonzero(np.isfinite(sub) & (sub > 0))
    z = sub[v, u]
    x = ((u * stride + 0.5) / W - cx) / fx * z
    y = ((v * stride + 0.5) / H - cy) / fy * z
    return np.stack([x, y, z], axis=1) @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]


class FlightMap:
    """Seen surfaces near the vehicle's height, on a level grid, for one flight (:meth:`forget` starts
    the next)."""

    def __init__(self, config: RouteConfig = RouteConfig()) -> None:
        self.config = config
        self.size = int(round(config.extent / config.cell))
        self.occupied: np.ndarray | None = None
        self.origin: np.ndarray | None = None

    def forget(self) -> None:
        self.occupied = None
        self.origin = None

    def add(self, points_world: np.ndarray, position: np.ndarray) -> None:
        """Mark the cells of ``points_world`` (N, 3) within the height band of ``position`` (3,)."""
        c = self.config
        if self.occupied is None:
            self.occupied = np.zeros((self.size, self.size), dtype=bool)
            self.origin = np.asarray(position[:2], dtype=np.float64) - 0.5 * self.size * c.cell
        near = points_world[np.abs(points_world[:, 2] - position[2]) < c.band]
        ij = np.floor((near[:, :2] - self.origin) / c.cell).astype(int)
        inside = (ij >= 0).all(axis=1) & (ij < self.size).all(axis=1)
        self.occupied[ij[inside, 0], ij[inside, 1]] = True

    def _cells(self, xy: np.ndarray) -> np.ndarray:
        assert self.origin is not None  # after add
        return np.clip(np.floor((xy - self.origin) / self.config.cell).astype(int), 0, self.size - 1)

    def aim(self, position: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """(2,) world point to fly to: the farthest point of the route to ``goal`` within
        :attr:`RouteConfig.horizon` (and at least a metre away) in straight sight of ``position``;
        None when nothing is mapped near the way, the route is no real detour, or no route point is
        in sight."""
        from scipy.ndimage import distance_transform_edt
        from skimage.graph import MCP_Geometric

        c = self.config
        if self.occupied is None:
            return None
        a, b = self._cells(position[:2]), self._cells(goal[:2])
        margin = int(8.0 / c.cell)
        lo = np.maximum(np.minimum(a, b) - margin, 0)
        hi = np.minimum(np.maximum(a, b) + margin + 1, self.size)
        occupied = self.occupied[lo[0]:hi[0], lo[1]:hi[1]]
        if not occupied.any():
            return None
        clearance = distance_transform_edt(~occupied) * c.cell
        cost = np.where(clearance < c.inflate, 1e3,
                        1.0 + 3.0 * np.clip((c.wary - clearance) / (c.wary - c.inflate), 0.0, 1.0))
        here, there = (int(a[0] - lo[0]), int(a[1] - lo[1])), (int(b[0] - lo[0]), int(b[1] - lo[1]))
        cost[here] = min(cost[here], 1.0)  # the vehicle may start near a wall
        search = MCP_Geometric(cost)
        search.find_costs([there])
        route = (np.array(search.traceback(here))[::-1] + lo + 0.5) * c.cell + self.origin
        step = np.linalg.norm(np.diff(route, axis=0), axis=1)
        if step.sum() - float(np.linalg.norm(goal[:2] - position[:2])) < c.detour:
            return None
        return self._farthest_in_sight(route, np.concatenate([[0.0], np.cumsum(step)]), position[:2], clearance, lo)

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
    """How close a flight has come to its goal, and since when. A flight is stalled while it has not
    come :attr:`RouteConfig.progress` closer than ever before for :attr:`RouteConfig.after` seconds,
    and no longer once it does (as a Bug algorithm leaves a wall where it is closer than ever)."""

    best: float = np.inf
    since: float = 0.0

    def update(self, t: float, distance: float, config: RouteConfig) -> bool:
        """Record the distance at time ``t``; True while stalled."""
        if distance < self.best - config.progress:
            self.best, self.since = distance, t
        return t - self.since > config.after
