"""Collision-free UAV flights through a :class:`~mapkit.sim.World`.

How a flight is made:

1. The world's signed distance is sampled on a grid over the flight volume; cells with at least
   ``margin + extra`` clearance form a graph (26-neighbours, edge cost grows near obstacles so
   paths keep to the middle of corridors).
2. Goals are drawn far from the goals already visited (coverage) and joined by shortest paths
   (Dijkstra) until the path is long enough for the requested duration.
3. The path is shortened by line-of-sight shortcuts, resampled, and smoothed with a clamped
   cubic B-spline whose control points are the resampled path (C2, stays in the convex hull of
   neighbouring path points). The exact signed distance is checked every few centimetres along
   the curve; where the margin is violated the control points are densified and the check
   repeated; if it still fails a :class:`SimError` says so.
4. Time: a speed profile along the arc length (cruise speed, slower in tight turns, always within
   1–3 m/s) gives position and velocity at any time. Yaw follows the horizontal velocity,
   smoothed, with a gentle seeded look-around sway; roll and pitch stay zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import ndimage, sparse
from scipy.interpolate import BSpline
from scipy.sparse.csgraph import dijkstra

from mapkit.sim._errors import SimError
from mapkit.sim._world import World

__all__ = ["Flight", "plan_flight", "MIN_SPEED", "MAX_SPEED"]

MIN_SPEED = 1.0
MAX_SPEED = 3.0
_LONG_ACCEL = 1.5  # m/s², speeding up / slowing down
_LATERAL_ACCEL = 2.0  # m/s²; bounds speed in turns: v <= sqrt(a / curvature)


@dataclass
class Flight:
    """A smooth flight: arc-length tables of a B-spline plus a time mapping and yaw table.

    Use :meth:`sample` / :meth:`T_world_body` with times in seconds from the start.
    """

    spline: BSpline
    """Position curve p(u), u in [0, u_end]."""
    u_k: np.ndarray
    """Dense curve parameters (K,)."""
    s_k: np.ndarray
    """Arc length at u_k (K,), metres."""
    t_k: np.ndarray
    """Time at u_k (K,), seconds."""
    v_k: np.ndarray
    """Speed at u_k (K,), m/s."""
    yaw_t: np.ndarray
    """Time grid of the yaw table (J,), seconds."""
    yaw: np.ndarray
    """Yaw (J,), radians, unwrapped."""
    yaw_rate: np.ndarray
    """Yaw rate (J,), rad/s."""
    min_clearance: float
    """Smallest signed distance along the curve, metres."""

    @property
    def duration(self) -> float:
        return float(self.t_k[-1])

    @property
    def length(self) -> float:
        return float(self.s_k[-1])

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(position (N,3), world velocity (N,3), yaw (N,), yaw rate (N,)) at times t (N,) s."""
        t = np.asarray(t, dtype=np.float64)
        if t.min() < -1e-9 or t.max() > self.duration + 1e-9:
            raise SimError(f"time {t.max():.3f} s beyond the flight ({self.duration:.3f} s); plan a longer flight")
        s = np.interp(t, self.t_k, self.s_k)
        u = np.interp(s, self.s_k, self.u_k)
        p = self.spline(u)
        dp = self.spline.derivative(1)(u)
        speed = np.interp(s, self.s_k, self.v_k)
        vel = dp / np.linalg.norm(dp, axis=1, keepdims=True) * speed[:, None]
        return p, vel, np.interp(t, self.yaw_t, self.yaw), np.interp(t, self.yaw_t, self.yaw_rate)

    def T_world_body(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) body poses (FLU, level: yaw only) at times t (N,) seconds."""
        p, _, yaw, _ = self.sample(t)
        return _poses(p, yaw)


def _poses(p: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    T = np.zeros((len(p), 4, 4))
    c, s = np.cos(yaw), np.sin(yaw)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    T[:, 2, 2] = 1.0
    T[:, 3, 3] = 1.0
    T[:, :3, 3] = p
    return T


class _Grid:
    """Flight-volume grid with signed distance at cell centres."""

    def __init__(self, world: World, res: float, margin: float, inset: float) -> None:
        lo = world.bounds[0].copy()
        hi = world.bounds[1].copy()
        lo[:2] += inset
        hi[:2] -= inset
        lo[2], hi[2] = world.flight_z
        if np.any(hi - lo < res):
            raise SimError(f"flight volume {lo}..{hi} is empty; enlarge --size")
        self.axes = [np.arange(lo[i], hi[i] + 1e-9, res) for i in range(3)]
        self.shape = tuple(len(a) for a in self.axes)
        self.res = res
        self.origin = np.array([a[0] for a in self.axes])
        mesh = np.stack(np.meshgrid(*self.axes, indexing="ij"), axis=-1).reshape(-1, 3)
        self.centres = mesh
        self.sdf = world.signed_distance(mesh).reshape(self.shape)

    def interp_sdf(self, pts: np.ndarray) -> np.ndarray:
        idx = ((pts - self.origin) / self.res).T
        return ndimage.map_coordinates(self.sdf, idx, order=1, mode="nearest")


def _graph(grid: _Grid, free: np.ndarray, margin: float) -> sparse.csr_matrix:
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


def _resample(poly: np.ndarray, spacing: float) -> np.ndarray:
    """Points along a polyline every <= spacing metres (vertices kept)."""
    pts = [poly[0]]
    for a, b in zip(poly[:-1], poly[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / spacing)))
        for k in range(1, n + 1):
            pts.append(a + (b - a) * k / n)
    return np.array(pts)


def _bspline(ctrl: np.ndarray) -> BSpline:
    """Clamped uniform cubic B-spline with these control points (starts/ends at the ends)."""
    m = len(ctrl)
    if m < 4:
        ctrl = _resample(ctrl, np.linalg.norm(ctrl[-1] - ctrl[0]) / 4 + 1e-9)
        m = len(ctrl)
    inner = np.arange(1, m - 3, dtype=np.float64)
    knots = np.concatenate([np.zeros(4), inner, np.full(4, float(m - 3))])
    return BSpline(knots, ctrl, 3)


def plan_flight(
    world: World,
    *,
    duration: float,
    speed: float = 1.5,
    margin: float = 0.4,
    seed: int = 0,
    resolution: float | None = None,
) -> Flight:
    """Plan a smooth collision-free flight of at least ``duration`` seconds.

    Args:
        world: the world to fly through.
        duration: seconds of flight needed.
        speed: cruise speed, m/s (1..3); turns are flown slower, never below 1 m/s.
        margin: smallest allowed signed distance of the body centre along the flight, metres.
        seed: random seed for goals and the yaw sway.
        resolution: planning grid spacing (metres); default 0.25 indoors, up to 0.4 in large
            worlds.
    Raises:
        SimError: bad arguments, or no collision-free flight could be found.
    """
    if not (MIN_SPEED <= speed <= MAX_SPEED):
        raise SimError(f"speed {speed} m/s out of range; use {MIN_SPEED}..{MAX_SPEED} m/s")
    if not (0.0 < duration <= 3600.0):
        raise SimError(f"duration {duration} s out of range; use 0 < duration <= 3600 s")
    if not (0.05 <= margin <= 2.0):
        raise SimError(f"margin {margin} m out of range; use 0.05..2 m")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    X, Y = world.bounds[1, :2] - world.bounds[0, :2]
    res = resolution or float(np.clip(math.sqrt(X * Y / 12000.0), 0.25, 0.4))
    has_walls = world.kind in ("office", "garage")
    grid = _Grid(world, res, margin, inset=0.0 if has_walls else 1.0)
    need = margin + 0.5 * res + 0.1
    free = grid.sdf >= need
    labels, n_lab = ndimage.label(free, structure=np.ones((3, 3, 3)))
    if n_lab == 0:
        raise SimError(f"no free space with {margin} m clearance in world {world.kind!r}; lower --density or the margin")
    sizes = ndimage.sum_labels(np.ones_like(labels), labels, index=np.arange(1, n_lab + 1))
    free = labels == (1 + int(np.argmax(sizes)))
    free_idx = np.flatnonzero(free.ravel())
    if len(free_idx) < 20:
        raise SimError(f"world {world.kind!r} (seed {world.seed}) is too cluttered to fly through; lower --density")
    graph = _graph(grid, free, margin)
    sdf_flat = grid.sdf.ravel()
    centres = grid.centres

    def pick_goal(visited: list[int], first: bool = False) -> int:
        cand = rng.choice(free_idx, size=min(40, len(free_idx)), replace=False)
        roomy = cand[sdf_flat[cand] >= need + 0.7]  # room to turn around
        cand = roomy if len(roomy) else cand
        if first:
            return int(cand[0])
        # Legs of 4..15 m (turns and height changes) towards the least visited region.
        hop = np.linalg.norm(centres[cand] - centres[visited[-1]], axis=1)
        near = cand[(hop >= 4.0) & (hop <= 15.0)]
        cand = near if len(near) else cand
        dist = np.linalg.norm(centres[cand][:, None, :] - centres[visited][None, :, :], axis=2).min(axis=1)
        return int(cand[np.argmax(dist * rng.uniform(0.7, 1.0, size=len(cand)))])

    def clear(a: np.ndarray, b: np.ndarray) -> bool:
        n = max(2, int(math.ceil(np.linalg.norm(b - a) / (0.5 * res))) + 1)
        pts = a[None, :] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None, :]
        return bool(grid.interp_sdf(pts).min() >= need)

    def leg_to(start: int, goal: int) -> list[int] | None:
        dist, pred = dijkstra(graph, indices=start, return_predecessors=True)
        if not np.isfinite(dist[goal]) or goal == start:
            return None
        leg = [goal]
        while leg[-1] != start:
            leg.append(int(pred[leg[-1]]))
        return leg[::-1]

    def u_turn(prev: np.ndarray, g: np.ndarray, nxt: np.ndarray) -> list[np.ndarray]:
        """Half-circle control points replacing a reversal at goal g (empty if no room)."""
        a, b = g - prev, nxt - g
        if np.linalg.norm(a) < 1e-6 or np.linalg.norm(b) < 1e-6:
            return []
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        if a @ b > -0.5:  # turn below 120°: the spline rounds it well enough
            return []
        n = np.array([-a[1], a[0], 0.0])
        if np.linalg.norm(n) < 1e-6:
            return []
        n /= np.linalg.norm(n)
        for r in (0.8, 0.6, 0.45):
            for side in (n, -n) if rng.random() < 0.5 else (-n, n):
                th = np.linspace(0.0, math.pi, 5)[1:]
                pts = g[None, :] + r * side[None, :] * (1 - np.cos(th))[:, None] + r * a[None, :] * np.sin(th)[:, None]
                dense = g[None, :] + r * side[None, :] * (1 - np.cos(np.linspace(0, math.pi, 40)))[:, None] \
                    + r * a[None, :] * np.sin(np.linspace(0, math.pi, 40))[:, None]
                if grid.interp_sdf(dense).min() >= need + 0.05 and np.all(dense[:, 2] >= grid.axes[2][0] - 1e-9) \
                        and np.all(dense[:, 2] <= grid.axes[2][-1] + 1e-9) and clear(pts[-1], nxt):
                    return list(pts)
        return []

    def build_polyline(goals: list[int], legs: list[list[int]]) -> np.ndarray:
        pts: list[np.ndarray] = [centres[goals[0]]]
        shortened = [_shortcut(centres[leg], clear) for leg in legs]
        for k, leg in enumerate(shortened):
            pts += list(leg[1:])
            if k + 1 < len(shortened):  # a goal between two legs: turn around it if it reverses
                pts += u_turn(leg[-2], leg[-1], shortened[k + 1][1])
        return np.array(pts)

    # Add legs between coverage goals until the smoothed flight is long enough.
    goals = [pick_goal([], first=True)]
    legs: list[list[int]] = []
    want = speed * duration + 2.0
    length = 0.0
    for _ in range(300):
        if length >= want:
            poly = build_polyline(goals, legs)
            if float(np.linalg.norm(np.diff(poly, axis=0), axis=1).sum()) >= want:
                break
            want *= 1.2
        goal = pick_goal(goals)
        leg = leg_to(goals[-1], goal)
        if leg is None:
            continue
        legs.append(leg)
        goals.append(goal)
        length += float(np.linalg.norm(np.diff(centres[leg], axis=0), axis=1).sum())
    else:
        raise SimError(f"could not plan a flight of {want:.0f} m in world {world.kind!r}; enlarge --size or lower --density")

    spacing = 1.0
    for _ in range(6):
        ctrl = _resample(poly, spacing)
        spline = _bspline(ctrl)
        u_end = float(spline.t[-1])
        n = max(200, int(u_end * spacing / 0.02))
        u_k = np.linspace(0.0, u_end, n)
        p_k = spline(u_k)
        d_k = world.signed_distance(p_k)
        if d_k.min() >= margin:
            break
        spacing *= 0.5
    else:
        raise SimError(
            f"no collision-free flight with margin {margin} m in world {world.kind!r} "
            f"(closest {d_k.min():.3f} m); lower --density, the margin, or try another --seed"
        )
    dp = spline.derivative(1)(u_k)
    ddp = spline.derivative(2)(u_k)
    seg = np.linalg.norm(np.diff(p_k, axis=0), axis=1)
    s_k = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-9])  # drop repeated points so s is increasing
    u_k, p_k, s_k, dp, ddp, d_k = u_k[keep], p_k[keep], s_k[keep], dp[keep], ddp[keep], d_k[keep]
    # Curvature from the turn of the unit tangent per metre: also sees cusps (dp -> 0, where
    # |dp x ddp| / |dp|^3 is 0/0 and a straight reversal would read as zero curvature).
    tangent = dp / np.maximum(np.linalg.norm(dp, axis=1, keepdims=True), 1e-12)
    turn = np.arccos(np.clip(np.einsum("ij,ij->i", tangent[1:], tangent[:-1]), -1.0, 1.0))
    kappa_seg = turn / np.maximum(np.diff(s_k), 1e-9)
    curvature = np.maximum(np.concatenate([kappa_seg[:1], kappa_seg]), np.concatenate([kappa_seg, kappa_seg[-1:]]))
    v_turn = np.sqrt(_LATERAL_ACCEL / np.maximum(curvature, 1e-9))
    v = np.clip(np.minimum(speed, v_turn), MIN_SPEED, MAX_SPEED)
    # A cusp (the path turns around on the spot where no U-turn fitted) must be flown through
    # at zero speed, or the velocity would flip.
    v[np.concatenate([turn, [0.0]]) > math.radians(60.0)] = 0.0
    v[np.concatenate([[0.0], turn]) > math.radians(60.0)] = 0.0
    # Bound the along-track acceleration: forward and backward passes of v² <= v0² + 2 a ds.
    ds_k = np.diff(s_k)
    for i in range(1, len(v)):
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2.0 * _LONG_ACCEL * ds_k[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2.0 * _LONG_ACCEL * ds_k[i]))
    v[0] = v[-1] = max(v[0], MIN_SPEED)  # the recording starts and ends in motion
    # Time per segment from its mean speed (finite even where v touches 0 at a cusp).
    t_k = np.concatenate([[0.0], np.cumsum(np.diff(s_k) / np.maximum(0.5 * (v[1:] + v[:-1]), 1e-3))])
    if t_k[-1] < duration:
        raise SimError(f"planned flight lasts only {t_k[-1]:.1f} s < {duration} s; enlarge --size or lower --duration")

    # Yaw along the horizontal velocity, smoothed over ~0.4 s, plus a slow look-around sway.
    yaw_t = np.arange(0.0, t_k[-1] + 1e-3, 1.0 / 200.0)
    s_y = np.interp(yaw_t, t_k, s_k)
    u_y = np.interp(s_y, s_k, u_k)
    d_y = spline.derivative(1)(u_y)
    heading = np.unwrap(np.arctan2(d_y[:, 1], d_y[:, 0]))
    horiz = np.hypot(d_y[:, 0], d_y[:, 1]) / np.linalg.norm(d_y, axis=1)
    # Where the flight is nearly vertical the heading is noise: hold the neighbouring value.
    good = horiz > 0.2
    if good.any() and not good.all():
        heading = np.interp(yaw_t, yaw_t[good], heading[good])
    yaw = ndimage.gaussian_filter1d(heading, sigma=0.4 * 200.0, mode="nearest")
    period, phase = float(rng.uniform(6.0, 10.0)), float(rng.uniform(0, 2 * math.pi))
    yaw = yaw + 0.25 * np.sin(2 * math.pi * yaw_t / period + phase)
    yaw_rate = np.gradient(yaw, yaw_t)
    return Flight(spline=spline, u_k=u_k, s_k=s_k, t_k=t_k, v_k=v, yaw_t=yaw_t, yaw=yaw, yaw_rate=yaw_rate,
                      min_clearance=float(d_k.min()))
