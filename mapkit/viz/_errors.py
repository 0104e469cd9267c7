"""Exception class of :mod:`mapkit.viz`."""

from __future__ import annotations

from mapkit.errors import MapkitError


class VizError(MapkitError):
    """Bad input to a visualisation function, or a store it cannot show, in one line with the fix."""
