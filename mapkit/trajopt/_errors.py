"""Exception class of :mod:`mapkit.trajopt`."""

from __future__ import annotations

from mapkit.errors import MapkitError


class TrajoptError(MapkitError):
    """Bad input to the trajectory optimiser, or a problem it cannot solve, explained in one line."""
