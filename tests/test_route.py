"""The flight map (`mapkit.flight.FlightMap`): what it remembers, the route it finds round a seen
wall, the point it aims at, and when a flight counts as stalled."""

from __future__ import annotations

import numpy as np
import pytest

from mapkit.flight import Aim, FlightMap, Progress, RouteConfig


def _wall(x0: float, x1: float, y: float = 0.0, z0: float = 0.0, z1: float = 3.0) -> np.ndarray:
    """Points of a wall along y = ``y`` from x0 to x1 and from height z0 to z1, every 5 cm."""
    x, z = np.meshgrid(np.arange(x0, x1 + 1e-9, 0.05), np.arange(z0, z1 + 1e-9, 0.05))
    return np.stack([x.ravel(), np.full(x.size, y), z.ravel()], axis=1)


def _room_floor_and_ceiling() -> np.ndarray:
    """Points of a floor at 0 m and a ceiling at 3 m over the test's walls, every 10 cm."""
    x, y = np.meshgrid(np.arange(-8.0, 8.0, 0.1), np.arange(-4.0, 4.0, 0.1))
    flat = np.stack([x.ravel(), y.ravel()], axis=1)
    return np.concatenate([np.column_stack([flat, np.zeros(len(flat))]), np.column_stack([flat, np.full(len(flat), 3.0)])])


def test_the_aim_leads_round_the_seen_end_of_a_wall():
    """Goal 5 m beyond a wall that ends 3 m to the side: the way round its end is 3.6 m longer than
    straight, so the aim is a point on the wall's open side, in sight, within the horizon, at the
    vehicle's own height (the wall is closed at every height)."""
    flight = FlightMap()
    start, goal = np.array([0.0, -2.0, 1.0]), np.array([0.0, 3.0, 1.0])
    flight.add(np.concatenate([_wall(-6.0, 3.0), _room_floor_and_ceiling()]), start)
    aim = flight.aim(start, goal)
    assert isinstance(aim, Aim) and aim.height is None
    assert aim.xy[0] > 3.3 and aim.xy[1] < 0.5  # beside the wall's end, not yet round it
    assert 1.0 <= np.linalg.norm(aim.xy - start[:2]) <= RouteConfig().horizon + 1e-9
    # mirrored wall: the aim mirrors too
    mirrored = FlightMap()
    mirrored.add(_wall(-3.0, 6.0), start)
    other = mirrored.aim(start, goal)
    assert other is not None and other.xy[0] < -3.3


def test_no_aim_without_a_real_detour():
    start, goal = np.array([0.0, -2.0, 1.0]), np.array([0.0, 3.0, 1.0])
    empty = FlightMap()
    assert empty.aim(start, goal) is None  # nothing seen yet
    empty.add(np.zeros((0, 3)), start)
    assert empty.aim(start, goal) is None  # nothing mapped near the way
    beside = FlightMap()
    beside.add(_wall(2.0, 6.0, y=0.0), start)  # off to the side: the straight way is open
    assert beside.aim(start, goal) is None
    strict = FlightMap(RouteConfig(detour=20.0))
    strict.add(_wall(-6.0, 3.0), start)  # the way round is not 20 m longer
    assert strict.aim(start, goal) is None


def test_a_doorway_under_a_lintel_is_passed_below_it():
    """A wall with a 1.6 m doorway (x 1–2.6 m) under a lintel from 2.2 m: a vehicle at 2.35 m cannot
    pass it level, so the aim leads through the doorway at a height that keeps clear of the lintel;
    at 1.2 m the doorway is open at the vehicle's height, and no height is named."""
    seen = np.concatenate([_wall(-6.0, 1.0), _wall(2.6, 8.0), _wall(1.0, 2.6, z0=2.2), _room_floor_and_ceiling()])
    for z, passes_level in ((2.35, False), (1.85, False), (1.2, True)):
        flight = FlightMap()
        start, goal = np.array([0.0, -2.0, z]), np.array([0.0, 3.0, z])
        flight.add(seen, start)
        aim = flight.aim(start, goal)
        assert aim is not None
        assert 1.0 <= aim.xy[0] <= 2.6 or aim.xy[1] < 0.0  # through the doorway, or toward it
        if passes_level:
            assert aim.height is None
        else:
            assert aim.height is not None and 2.2 - aim.height >= RouteConfig().inflate
    # not allowed down to 1.75 m (`descend` 0.2 m): the doorway is shut, and the route leads round an end
    shut = FlightMap(RouteConfig(descend=0.2))
    start, goal = np.array([0.0, -2.0, 2.35]), np.array([0.0, 3.0, 2.35])
    shut.add(seen, start)
    aim = shut.aim(start, goal)
    assert aim is not None and aim.height is None and abs(aim.xy[0]) > 3.0


def test_a_low_wall_is_flown_over_and_a_seen_ceiling_is_not():
    """A wall seen only up to 0.8 m does not stand in the way of a flight at 2.5 m; the same wall up to
    3 m does; nothing above the higher of the vehicle's and the goal's heights is used (the unseen space
    over a ceiling is not a way round)."""
    start, goal = np.array([0.0, -2.0, 2.5]), np.array([0.0, 3.0, 2.5])
    low = FlightMap()
    low.add(_wall(-6.0, 3.0, z0=0.0, z1=0.8), start)
    assert low.aim(start, goal) is None
    full = FlightMap()
    full.add(np.concatenate([_wall(-6.0, 3.0, z0=0.0, z1=2.9), _room_floor_and_ceiling()]), start)
    aim = full.aim(start, goal)
    assert aim is not None and aim.xy[0] > 3.3  # round the end, not over the top
    full.forget()
    assert full.aim(start, goal) is None


def test_no_route_under_a_wall_whose_foot_was_not_seen():
    """A wall seen from 0.8 m up (its foot below the camera's view) between a vehicle at 1.0 m and a
    goal at 0.6 m: the route may descend to -0.4 m, where nothing was seen. The ground (z = 0) counts
    as seen, so the aim leads round the wall's end; without it, the way under the wall counts as open
    and straight, and the map offers no route at all."""
    start, goal = np.array([0.0, -2.0, 1.0]), np.array([0.0, 3.0, 0.6])
    seen = _wall(-6.0, 3.0, z0=0.8, z1=3.0)
    grounded = FlightMap()
    grounded.add(seen, start)
    aim = grounded.aim(start, goal)
    assert aim is not None and aim.xy[0] > 3.3 and aim.height is None
    underground = FlightMap(RouteConfig(ground=-10.0))  # below the map: no ground in it
    underground.add(seen, start)
    assert underground.aim(start, goal) is None


def test_progress_stalls_after_the_configured_time_until_the_flight_is_closer_than_ever():
    config = RouteConfig(after=3.0, progress=0.5)
    p = Progress()
    assert not p.update(0.0, 10.0, config)
    assert not p.update(2.0, 9.0, config)  # 1 m closer: the clock restarts at 2 s
    assert not p.update(4.5, 8.8, config)  # 0.2 m is no progress, but only 2.5 s have passed
    assert p.update(5.5, 8.7, config)
    assert p.update(7.0, 12.0, config)  # going round, farther than before: still stalled
    assert not p.update(9.0, 8.4, config)  # 0.6 m closer than ever: the straight way again
    assert p.update(12.5, 8.4, config)
    with pytest.raises(AttributeError):
        config.after = 1.0  # frozen
