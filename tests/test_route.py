"""The flight map (`mapkit.evaluation.FlightMap`): what it remembers, the route it finds round a seen
wall, the point it aims at, and when a flight counts as stalled."""

from __future__ import annotations

import numpy as np
import pytest

from mapkit.evaluation import FlightMap, Progress, RouteConfig


def _wall(x0: float, x1: float, y: float = 0.0, z: float = 1.0) -> np.ndarray:
    """Points of a wall along y = ``y`` from x0 to x1, every 5 cm, at heights z ± 0.3 m."""
    x = np.arange(x0, x1 + 1e-9, 0.05)
    return np.stack([np.repeat(x, 3), np.full(3 * len(x), y), np.tile([z - 0.3, z, z + 0.3], len(x))], axis=1)


def test_the_aim_leads_round_the_seen_end_of_a_wall():
    """Goal 5 m beyond a wall that ends 3 m to the side: the way round its end is 3.6 m longer than
    straight, so the aim is a point on the wall's open side, in sight, within the horizon."""
    flight = FlightMap()
    start, goal = np.array([0.0, -2.0, 1.0]), np.array([0.0, 3.0, 1.0])
    flight.add(_wall(-6.0, 3.0), start)
    aim = flight.aim(start, goal)
    assert aim is not None
    assert aim[0] > 3.3 and aim[1] < 0.5  # beside the wall's end, not yet round it
    assert 1.0 <= np.linalg.norm(aim - start[:2]) <= RouteConfig().horizon + 1e-9
    # mirrored wall: the aim mirrors too
    mirrored = FlightMap()
    mirrored.add(_wall(-3.0, 6.0), start)
    other = mirrored.aim(start, goal)
    assert other is not None and other[0] < -3.3


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


def test_only_surfaces_near_the_vehicles_height_count():
    """A wall seen 1.5 m below the vehicle is flown over; the same wall at its height is not."""
    start, goal = np.array([0.0, -2.0, 2.5]), np.array([0.0, 3.0, 2.5])
    low = FlightMap()
    low.add(_wall(-6.0, 3.0, z=1.0), start)
    assert low.aim(start, goal) is None
    level = FlightMap()
    level.add(_wall(-6.0, 3.0, z=2.5), start)
    assert level.aim(start, goal) is not None
    level.forget()
    assert level.aim(start, goal) is None


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
