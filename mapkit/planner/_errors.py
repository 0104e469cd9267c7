"""Exception class of :mod:`mapkit.planner`."""

from __future__ import annotations

from mapkit.errors import MapkitError


class PlannerError(MapkitError):
    """Bad input to the learned planner (shapes, configs, weights), explained in one line."""
