"""Collision-free UAV flights through a :class:`~mapkit.sim.World`.

Coverage goals are joined by shortest legs through a :class:`~mapkit.sim.FreeSpaceGraph`, shortened by
line of sight and smoothed by a clamped cubic B-spline, densified until the exact signed distance
keeps the margin. A speed profile along the arc (slower in turns, 1–3 m/s) gives the timing; yaw
follows the horizontal velocity with a seeded look-around sway; roll and pitch stay zero.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.interpolate import BSpline

from mapkit.sim._errors import SimError
from mapkit.sim._search import FreeSpaceGraph, _NoFreeSpace, _shortcut
from mapkit.sim._world import World

MIN_SPEED = 1.0
MAX_SPEED = 3.0
_LONG_ACCEL = 1.5  # m/s², speeding up / slowing down
_LATERAL_ACCEL = 2.0  # m/s²; bounds speed in turns: v <= sqrt(a / curvature)


@dataclass
class Flight:
    """A smooth flight: B-spline arc-length, time and yaw tables; sample it with times in seconds."""

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


def _resample(poly: np.ndarray, spacing: float) -> np.ndarray:
    """Points along a polyline every <= spacing metres (vertices kept)."""
    pts = [poly[0]]
    for a, b in itertools.pairwise(poly):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / spacing)))
        for k in range(1, n + 1):
            pts.append(a + (b - a) * k / n)
    return np.array(pts)


def _bspline(ctrl: np.ndarray) -> BSpline:
    """Clamped uniform cubic B-spline with these control points (starts/ends at the ends)."""
    m = len(ctrl)
    if m < 4:
        ctrl = _resample(ctrl, float(np.linalg.norm(ctrl[-1] - ctrl[0])) / 4 + 1e-9)
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
        speed: cruise speed, m/s (1..3); turns are flown slower.
        margin: smallest allowed signed distance of the body centre along the flight, metres.
        seed: random seed for goals and the yaw sway.
        resolution: planning grid spacing (metres); default 0.25, up to 0.4 in large worlds.
    Raises:
        SimError: bad arguments, or no collision-free flight could be found.
    """
    _check_flight_args(duration=duration, speed=speed, margin=margin)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
    router = _Router(_flight_space(world, margin, resolution), rng)
    poly = router.route(speed * duration + 2.0)
    spline, u_k, p_k, d_k = _smooth(world, poly, margin)
    u_k, s_k, dp, d_k = _arc_length_table(spline, u_k, p_k, d_k)
    v = _speed_profile(dp, s_k, speed)
    # Time per segment from its mean speed (finite even where v touches 0 at a cusp).
    t_k = np.concatenate([[0.0], np.cumsum(np.diff(s_k) / np.maximum(0.5 * (v[1:] + v[:-1]), 1e-3))])
    if t_k[-1] < duration:
        raise SimError(f"planned flight lasts only {t_k[-1]:.1f} s < {duration} s; enlarge size or lower --duration")
    yaw_t, yaw, yaw_rate = _yaw_table(spline, u_k, s_k, t_k, rng)
    return Flight(spline=spline, u_k=u_k, s_k=s_k, t_k=t_k, v_k=v, yaw_t=yaw_t, yaw=yaw, yaw_rate=yaw_rate,
                  min_clearance=float(d_k.min()))


def _check_flight_args(*, duration: float, speed: float, margin: float) -> None:
    """Raise :class:`SimError` for a speed, duration or margin out of range."""
    if not (MIN_SPEED <= speed <= MAX_SPEED):
        raise SimError(f"speed {speed} m/s out of range; use {MIN_SPEED}..{MAX_SPEED} m/s")
    if not (0.0 < duration <= 3600.0):
        raise SimError(f"duration {duration} s out of range; use 0 < duration <= 3600 s")
    if not (0.05 <= margin <= 2.0):
        raise SimError(f"margin {margin} m out of range; use 0.05..2 m")


def _flight_space(world: World, margin: float, resolution: float | None) -> FreeSpaceGraph:
    """The free cells a flight's legs may use: ``margin`` plus half a cell and 10 cm from every obstacle."""
    X, Y = world.bounds[1, :2] - world.bounds[0, :2]
    res = resolution or float(np.clip(math.sqrt(X * Y / 12000.0), 0.25, 0.4))
    need = margin + 0.5 * res + 0.1
    try:
        space = FreeSpaceGraph(world, clearance=need, resolution=res, cost_margin=margin)
    except _NoFreeSpace:
        raise SimError(f"no free space with {margin} m clearance in world {world.kind!r}; lower density or the margin") from None
    if space.num_free < 20:
        raise SimError(f"world {world.kind!r} (seed {world.seed}) is too cluttered to fly through; lower density")
    return space


class _Router:
    """Coverage goals joined by shortest legs through a flight's free space, as one polyline."""

    def __init__(self, space: FreeSpaceGraph, rng: np.random.Generator) -> None:
        self.space, self.rng = space, rng
        self.grid = space.grid
        self.need = space.clearance
        self.sdf_flat = space.grid.sdf.ravel()
        self.centres = space.centres

    def route(self, want: float) -> np.ndarray:
        """Add legs between coverage goals until the polyline through them is ``want`` metres long
        (more when the shortcuts make it shorter than the legs)."""
        goals = [self.pick_goal([], first=True)]
        legs: list[list[int]] = []
        length = 0.0
        for _ in range(300):
            if length >= want:
                poly = self.build_polyline(goals, legs)
                if float(np.linalg.norm(np.diff(poly, axis=0), axis=1).sum()) >= want:
                    return poly
                want *= 1.2
            goal = self.pick_goal(goals)
            leg = None if goal == goals[-1] else self.space.cell_path(goals[-1], goal)
            if leg is None:  # the same cell, or unreachable
                continue
            legs.append(leg)
            goals.append(goal)
            length += float(np.linalg.norm(np.diff(self.centres[leg], axis=0), axis=1).sum())
        raise SimError(f"could not plan a flight of {want:.0f} m in world {self.space.world.kind!r}; enlarge size "
                       "or lower density")

    def pick_goal(self, visited: list[int], first: bool = False) -> int:
        """A free cell with room to turn, 4..15 m from the last goal and far from the goals visited."""
        free_idx, centres = self.space.free_index, self.centres
        cand = self.rng.choice(free_idx, size=min(40, len(free_idx)), replace=False)
        roomy = cand[self.sdf_flat[cand] >= self.need + 0.7]  # room to turn around
        cand = roomy if len(roomy) else cand
        if first:
            return int(cand[0])
        # Legs of 4..15 m (turns and height changes) towards the least visited region.
        hop = np.linalg.norm(centres[cand] - centres[visited[-1]], axis=1)
        near = cand[(hop >= 4.0) & (hop <= 15.0)]
        cand = near if len(near) else cand
        dist = np.linalg.norm(centres[cand][:, None, :] - centres[visited][None, :, :], axis=2).min(axis=1)
        return int(cand[np.argmax(dist * self.rng.uniform(0.7, 1.0, size=len(cand)))])

    def clear(self, a: np.ndarray, b: np.ndarray) -> bool:
        """True when the segment a→b keeps the free cells' clearance (interpolated, every half cell)."""
        n = max(2, int(math.ceil(np.linalg.norm(b - a) / (0.5 * self.space.resolution))) + 1)
        pts = a[None, :] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None, :]
        return bool(self.grid.interp_sdf(pts).min() >= self.need)

    def u_turn(self, prev: np.ndarray, g: np.ndarray, nxt: np.ndarray) -> list[np.ndarray]:
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
        z_axis = self.grid.axes[2]
        for r in (0.8, 0.6, 0.45):
            for side in (n, -n) if self.rng.random() < 0.5 else (-n, n):
                th = np.linspace(0.0, math.pi, 5)[1:]
                pts = g[None, :] + r * side[None, :] * (1 - np.cos(th))[:, None] + r * a[None, :] * np.sin(th)[:, None]
                dense = g[None, :] + r * side[None, :] * (1 - np.cos(np.linspace(0, math.pi, 40)))[:, None] \
                    + r * a[None, :] * np.sin(np.linspace(0, math.pi, 40))[:, None]
                if self.grid.interp_sdf(dense).min() >= self.need + 0.05 and np.all(dense[:, 2] >= z_axis[0] - 1e-9) \
                        and np.all(dense[:, 2] <= z_axis[-1] + 1e-9) and self.clear(pts[-1], nxt):
                    return list(pts)
        return []

    def build_polyline(self, goals: list[int], legs: list[list[int]]) -> np.ndarray:
        """The legs shortened by line of sight and joined, with a U-turn where one reverses the last."""
        pts: list[np.ndarray] = [self.centres[goals[0]]]
        shortened = [_shortcut(self.centres[leg], self.clear) for leg in legs]
        for k, leg in enumerate(shortened):
            pts += list(leg[1:])
            if k + 1 < len(shortened):  # a goal between two legs: turn around it if it reverses
                pts += self.u_turn(leg[-2], leg[-1], shortened[k + 1][1])
        return np.array(pts)


def _smooth(world: World, poly: np.ndarray, margin: float) -> tuple[BSpline, np.ndarray, np.ndarray, np.ndarray]:
    """B-spline through the resampled polyline, densified until the exact signed distance keeps ``margin``
    → (spline, u_k, p_k, d_k): the curve sampled every ~2 cm with its signed distance."""
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
            return spline, u_k, p_k, d_k
        spacing *= 0.5
    raise SimError(
        f"no collision-free flight with margin {margin} m in world {world.kind!r} "
        f"(closest {d_k.min():.3f} m); lower density, the margin, or try another --seed"
    )


def _arc_length_table(
    spline: BSpline, u_k: np.ndarray, p_k: np.ndarray, d_k: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(u_k, s_k, dp/du, d_k) with arc length s_k, repeated points dropped so s_k increases."""
    dp = spline.derivative(1)(u_k)
    seg = np.linalg.norm(np.diff(p_k, axis=0), axis=1)
    s_k = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 1e-9])  # drop repeated points so s is increasing
    return u_k[keep], s_k[keep], dp[keep], d_k[keep]


def _speed_profile(dp: np.ndarray, s_k: np.ndarray, speed: float) -> np.ndarray:
    """Speed (K,) m/s along the arc: cruise, slower in turns, zero at cusps, bounded acceleration."""
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
    return v


def _yaw_table(
    spline: BSpline, u_k: np.ndarray, s_k: np.ndarray, t_k: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(yaw_t, yaw, yaw_rate) at 200 Hz: along the horizontal velocity, smoothed over ~0.4 s, plus a slow
    seeded look-around sway."""
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
    return yaw_t, yaw, yaw_rate
