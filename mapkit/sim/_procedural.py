"""Procedural worlds: ``forest``, ``office`` and ``garage``, seeded and reproducible.

``density`` means something physical per world:

- forest: tree trunks per square metre of ground (default 0.06 → ~100 trees on 40 m x 40 m);
  fallen logs are a fifth of that.
- office: furniture items (desks, shelves) per square metre of floor (default 0.05).
- garage: fraction of parking bays holding a car (default 0.6).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np

from mapkit.sim._errors import SimError
from mapkit.sim._world import Box, Capsule, Cylinder, HalfSpace, Primitive, World

WORLD_KINDS: tuple[str, ...] = ("forest", "office", "garage")
DEFAULT_SIZES: dict[str, tuple[float, float, float]] = {
    "forest": (40.0, 40.0, 10.0),
    "office": (20.0, 14.0, 3.0),
    "garage": (30.0, 20.0, 2.6),
}
DEFAULT_DENSITIES: dict[str, float] = {"forest": 0.06, "office": 0.05, "garage": 0.6}
MIN_SIZES: dict[str, tuple[float, float, float]] = {
    "forest": (6.0, 6.0, 3.0),
    "office": (8.0, 6.0, 2.4),
    "garage": (12.0, 12.0, 2.2),
}

FLOOR = HalfSpace((0.0, 0.0, 1.0), 0.0)


def _ceiling(h: float) -> HalfSpace:
    return HalfSpace((0.0, 0.0, -1.0), -h)


def _outer_walls(X: float, Y: float, Z: float, t: float = 0.2) -> list[Primitive]:
    """Four walls whose inner faces lie on the bounds; they overlap floor and ceiling."""
    zc, hz = 0.5 * Z, 0.5 * Z + 0.1
    return [
        Box((-0.5 * t, 0.5 * Y, zc), (0.5 * t, 0.5 * Y + t, hz)),
        Box((X + 0.5 * t, 0.5 * Y, zc), (0.5 * t, 0.5 * Y + t, hz)),
        Box((0.5 * X, -0.5 * t, zc), (0.5 * X + t, 0.5 * t, hz)),
        Box((0.5 * X, Y + 0.5 * t, zc), (0.5 * X + t, 0.5 * t, hz)),
    ]


def _clearance(prims: list[Primitive], bounds: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Signed distance to what is placed so far (used to keep new items apart)."""
    if not prims:
        return lambda p: np.full(len(np.atleast_2d(p)), np.inf)
    w = World(list(prims), bounds)
    return lambda p: w.signed_distance(np.atleast_2d(p))


# ------------------------------------------------------------------------------------ forest
def _forest(rng: np.random.Generator, X: float, Y: float, Z: float, density: float) -> tuple[list[Primitive], tuple[float, float]]:
    prims: list[Primitive] = [FLOOR]
    n_trees = int(round(density * X * Y))
    trunks: list[tuple[float, float, float]] = []
    # Rejection sampling keeps corridors (>= 1.4 m between bark) so a drone can pass.
    attempts = 0
    while len(trunks) < n_trees and attempts < 50 * max(n_trees, 1):
        attempts += 1
        r = float(rng.uniform(0.08, 0.4) if rng.random() < 0.8 else rng.uniform(0.4, 0.6))
        x, y = float(rng.uniform(0.0, X)), float(rng.uniform(0.0, Y))
        if all(math.hypot(x - tx, y - ty) >= tr + r + 1.4 for tx, ty, tr in trunks):
            trunks.append((x, y, r))
    for x, y, r in trunks:
        top = float(rng.uniform(0.6, 1.0) * Z + 2.0)  # most trunks reach above the view
        # Start slightly below ground so the trunk meets the floor without a seam.
        prims.append(Cylinder((x, y, -0.2), (x, y, top), r))
    n_logs = int(round(0.2 * n_trees))
    placed = 0
    attempts = 0
    while placed < n_logs and attempts < 50 * max(n_logs, 1):
        attempts += 1
        r = float(rng.uniform(0.12, 0.35))
        length = float(rng.uniform(2.0, 6.0))
        yaw = float(rng.uniform(0.0, math.pi))
        cx, cy = float(rng.uniform(0.0, X)), float(rng.uniform(0.0, Y))
        u = np.array([math.cos(yaw), math.sin(yaw), 0.0]) * 0.5 * length
        a = (cx - u[0], cy - u[1], r * 0.9)  # rests on (sinks a little into) the ground
        b = (cx + u[0], cy + u[1], r * 0.9)
        axis = np.linspace(a, b, 12)
        if any(np.hypot(axis[:, 0] - tx, axis[:, 1] - ty).min() < tr + r + 0.3 for tx, ty, tr in trunks):
            continue
        prims.append(Capsule(a, b, r) if rng.random() < 0.6 else Cylinder(a, b, r))
        placed += 1
    return prims, (1.0, min(4.5, Z - 1.0))


# ------------------------------------------------------------------------------------ office
def _office(rng: np.random.Generator, X: float, Y: float, Z: float, density: float) -> tuple[list[Primitive], tuple[float, float]]:
    prims: list[Primitive] = [FLOOR, _ceiling(Z)] + _outer_walls(X, Y, Z)
    t = 0.15  # inner wall thickness
    door_h = min(2.2, Z - 0.3)

    def wall(axis: int, at: float, s0: float, s1: float, doors: list[float], width: float) -> None:
        """Wall along x (axis 0) or y (axis 1) at ``at``, from s0 to s1, with doorways centred at ``doors``."""

        def box(c: float, half: float, zc: float, hz: float) -> Box:
            return Box((c, at, zc), (half, 0.5 * t, hz)) if axis == 0 else Box((at, c, zc), (0.5 * t, half, hz))

        edges = [s0]
        for d in sorted(doors):
            edges += [d - 0.5 * width, d + 0.5 * width]
            prims.append(box(d, 0.5 * width + 0.01, 0.5 * (door_h + Z), 0.5 * (Z - door_h) + 0.05))
        edges.append(s1)
        for e0, e1 in zip(edges[0::2], edges[1::2], strict=False):
            if e1 - e0 > 1e-3:
                prims.append(box(0.5 * (e0 + e1), 0.5 * (e1 - e0), 0.5 * Z, 0.5 * Z + 0.05))

    def door_positions(length: float, n: int, width: float) -> list[float]:
        slots = np.linspace(0.0, length, n + 2)[1:-1]
        jitter = rng.uniform(-0.25, 0.25, size=n) * length / (n + 1)
        return [float(np.clip(s + j, width, length - width)) for s, j in zip(slots, jitter, strict=True)]

    # A corridor wall along x splits the floor; cross walls make rooms on both sides.
    y_split = float(rng.uniform(0.4, 0.6) * Y)
    width = float(rng.uniform(1.5, 1.9))
    wall(0, y_split, 0.0, X, door_positions(X, max(2, int(X // 7)), width), width)
    n_cross = max(1, int(X // 8))
    xs = np.linspace(0.0, X, n_cross + 2)[1:-1] + rng.uniform(-1.0, 1.0, size=n_cross)
    for x in xs:
        if rng.random() < 0.8:
            w = float(rng.uniform(1.5, 1.9))
            wall(1, float(x), 0.0, y_split - 0.5 * t, [float(rng.uniform(w, y_split - w))], w)
        if rng.random() < 0.8:
            w = float(rng.uniform(1.5, 1.9))
            wall(1, float(x), y_split + 0.5 * t, Y, [y_split + float(rng.uniform(w, Y - y_split - w))], w)

    return prims + _furniture(rng, X, Y, Z, density, prims), (0.6, Z - 0.6)


def _furniture(rng: np.random.Generator, X: float, Y: float, Z: float, density: float,
               structure: list[Primitive]) -> list[Primitive]:
    """Pillars, desks and shelves placed among the office's walls (``structure``: floor, ceiling, the
    four outer walls, then the inner ones). Pillars stand in the open; desks keep ~1 m of floor around
    them for flying; shelves lean on outer walls but keep clear of inner walls so doorways stay open."""
    bounds = np.array([[0.0, 0.0, 0.0], [X, Y, Z]])
    outer_and_inner, inner = structure[2:], structure[6:]
    placed: list[Primitive] = []

    def try_place(make: Callable[[], Box | Cylinder], need: float, against: list[Primitive]) -> None:
        """Place ``make()`` where it keeps ``need`` metres of floor from ``against`` + placed."""
        for _ in range(60):
            prim = make()
            lo, hi = prim.aabb()
            if lo[0] < 0 or lo[1] < 0 or hi[0] > X or hi[1] > Y:
                continue
            z = min(0.5 * (lo[2] + hi[2]), 1.0)
            probe = np.array([[x, y, z] for x in np.linspace(lo[0], hi[0], 4) for y in np.linspace(lo[1], hi[1], 4)])
            if _clearance(against + placed, bounds)(probe).min() >= need:
                placed.append(prim)
                return

    for _ in range(max(1, int(round(X * Y / 80.0)))):
        r = float(rng.uniform(0.2, 0.3))
        try_place(functools.partial(_pillar, rng, X, Y, Z, r), 1.6, outer_and_inner)
    for i in range(int(round(density * X * Y))):
        if i % 3 == 2:
            try_place(lambda: _shelf(rng, X, Y), 1.2, inner)
        else:
            try_place(lambda: _desk(rng, X, Y), 1.1, outer_and_inner)
    return placed


def _pillar(rng: np.random.Generator, X: float, Y: float, Z: float, r: float) -> Cylinder:
    x, y = float(rng.uniform(1.5, X - 1.5)), float(rng.uniform(1.5, Y - 1.5))
    return Cylinder((x, y, -0.1), (x, y, Z + 0.1), r)


def _desk(rng: np.random.Generator, X: float, Y: float) -> Box:
    hx, hy, hz = float(rng.uniform(0.6, 0.9)), float(rng.uniform(0.35, 0.45)), 0.375
    yaw = float(rng.choice([0.0, 0.5 * math.pi]) + rng.uniform(-0.3, 0.3))
    return Box((float(rng.uniform(1, X - 1)), float(rng.uniform(1, Y - 1)), hz), (hx, hy, hz), yaw)


def _shelf(rng: np.random.Generator, X: float, Y: float) -> Box:
    hx, hy, hz = float(rng.uniform(0.45, 0.6)), float(rng.uniform(0.17, 0.22)), float(rng.uniform(0.9, 1.1))
    side = int(rng.integers(4))
    if side < 2:  # along a wall parallel to x
        x = float(rng.uniform(hx + 0.2, X - hx - 0.2))
        y = hy + 0.01 if side == 0 else Y - hy - 0.01
        return Box((x, y, hz), (hx, hy, hz), 0.0)
    y = float(rng.uniform(hx + 0.2, Y - hx - 0.2))
    x = hy + 0.01 if side == 2 else X - hy - 0.01
    return Box((x, y, hz), (hx, hy, hz), 0.5 * math.pi)


# ------------------------------------------------------------------------------------ garage
def _garage(rng: np.random.Generator, X: float, Y: float, Z: float, density: float) -> tuple[list[Primitive], tuple[float, float]]:
    prims: list[Primitive] = [FLOOR, _ceiling(Z)] + _outer_walls(X, Y, Z)
    bay_depth, bay_width = 5.0, 2.5
    # Parking rows along both long walls; pillars and beams at the row/aisle boundary.
    rows = [(0.0, bay_depth, 0.5 * math.pi), (Y - bay_depth, Y, -0.5 * math.pi)]
    if Y - 2 * bay_depth >= 16.0:  # wide enough for a central island of two rows
        yc = 0.5 * Y
        rows += [(yc - bay_depth, yc, 0.5 * math.pi), (yc, yc + bay_depth, -0.5 * math.pi)]
    beam_h = 0.35
    pillar_rows = sorted({round(r[1] if r[0] == 0.0 else r[0], 6) for r in rows if 0 < r[0] or r[1] < Y})
    pillar_rows = [y for y in pillar_rows if 0.5 < y < Y - 0.5]
    n_bays = int(X // bay_width)
    x0 = 0.5 * (X - n_bays * bay_width)
    for yp in pillar_rows:
        for k in range(0, n_bays + 1, 3):
            xp = x0 + k * bay_width
            if 0.4 < xp < X - 0.4:
                prims.append(Box((xp, yp, 0.5 * Z), (0.25, 0.25, 0.5 * Z + 0.05)))
        prims.append(Box((0.5 * X, yp, Z - 0.5 * beam_h), (0.5 * X, 0.2, 0.5 * beam_h + 0.05)))
    # Cross beams along y every few bays (the ceiling structure a drone sees overhead).
    for k in range(0, n_bays + 1, 6):
        xp = x0 + k * bay_width
        if 0.4 < xp < X - 0.4:
            prims.append(Box((xp, 0.5 * Y, Z - 0.5 * beam_h), (0.2, 0.5 * Y, 0.5 * beam_h + 0.05)))
    for y0, y1, yaw in rows:
        for k in range(n_bays):
            xc = x0 + (k + 0.5) * bay_width
            u = rng.random()
            if u < density:
                prims += _car(rng, xc, 0.5 * (y0 + y1) + float(rng.uniform(-0.3, 0.3)), yaw + float(rng.uniform(-0.06, 0.06)))
            elif u < density + 0.1:  # crates in some empty bays
                for _ in range(int(rng.integers(1, 4))):
                    h = float(rng.uniform(0.3, 0.6))
                    prims.append(Box((xc + float(rng.uniform(-0.6, 0.6)), 0.5 * (y0 + y1) + float(rng.uniform(-1.5, 1.5)), h),
                                     (float(rng.uniform(0.3, 0.6)), float(rng.uniform(0.3, 0.6)), h),
                                     float(rng.uniform(-0.4, 0.4))))
    return prims, (0.6, Z - 0.6)


def _car(rng: np.random.Generator, x: float, y: float, yaw: float) -> list[Primitive]:
    """A car: body and cabin boxes on four wheel cylinders; ``yaw`` is its length direction."""
    L, W = float(rng.uniform(4.0, 4.8)), float(rng.uniform(1.7, 1.9))
    c, s = math.cos(yaw), math.sin(yaw)
    fwd, left = np.array([c, s]), np.array([-s, c])
    body_lo, body_hi = 0.3, float(rng.uniform(0.95, 1.05))
    cabin_h = float(rng.uniform(0.4, 0.55))
    parts: list[Primitive] = [
        Box((x, y, 0.5 * (body_lo + body_hi)), (0.5 * L, 0.5 * W, 0.5 * (body_hi - body_lo)), yaw),
        Box((x - 0.1 * L * c, y - 0.1 * L * s, body_hi + 0.5 * cabin_h - 0.01),
            (0.28 * L, 0.45 * W, 0.5 * cabin_h), yaw),
    ]
    r_wheel, w_wheel = 0.32, 0.22
    for sl in (-1.0, 1.0):
        for sf in (-1.0, 1.0):
            centre = np.array([x, y]) + sf * 0.32 * L * fwd + sl * (0.5 * W - 0.5 * w_wheel) * left
            a = centre - 0.5 * w_wheel * left
            b = centre + 0.5 * w_wheel * left
            parts.append(Cylinder((float(a[0]), float(a[1]), r_wheel), (float(b[0]), float(b[1]), r_wheel), r_wheel))
    return parts


_GENERATORS = {"forest": _forest, "office": _office, "garage": _garage}


def make_world(
    kind: str,
    *,
    seed: int = 0,
    size: tuple[float, float, float] | None = None,
    density: float | None = None,
) -> World:
    """Build a procedural world.

    Args:
        kind: ``forest``, ``office`` or ``garage``.
        seed: the same (kind, seed, size, density) gives the same world.
        size: (x, y, z) extent in metres, the world spanning [0, x] x [0, y] x [0, z] (z: the ceiling
            indoors); defaults in ``DEFAULT_SIZES``.
        density: obstacle density (module doc); defaults in ``DEFAULT_DENSITIES``.
    """
    if kind not in _GENERATORS:
        raise SimError(f"unknown world {kind!r}; use one of {', '.join(WORLD_KINDS)}")
    X, Y, Z = (float(v) for v in (size if size is not None else DEFAULT_SIZES[kind]))
    lo = MIN_SIZES[kind]
    if X < lo[0] or Y < lo[1] or Z < lo[2] or not all(math.isfinite(v) for v in (X, Y, Z)):
        raise SimError(f"world size {(X, Y, Z)} too small for {kind}; use at least {lo} metres")
    if X * Y > 250_000 or Z > 100:
        raise SimError(f"world size {(X, Y, Z)} too large; keep x*y <= 250000 m² and z <= 100 m")
    dens = float(density if density is not None else DEFAULT_DENSITIES[kind])
    max_dens = 1.0 if kind == "garage" else 0.3
    if not 0.0 <= dens <= max_dens:
        raise SimError(f"density {dens} out of range for {kind}; use 0..{max_dens} (default {DEFAULT_DENSITIES[kind]})")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), WORLD_KINDS.index(kind)]))
    prims, flight_z = _GENERATORS[kind](rng, X, Y, Z, dens)
    return World(
        primitives=prims,
        bounds=np.array([[0.0, 0.0, 0.0], [X, Y, Z]]),
        kind=kind,
        seed=int(seed),
        flight_z=(float(flight_z[0]), float(flight_z[1])),
        params={"size": [X, Y, Z], "density": dens},
    )
