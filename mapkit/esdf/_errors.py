"""Exception class of :mod:`mapkit.esdf`."""

from __future__ import annotations

from mapkit.errors import MapkitError


class EsdfError(MapkitError):
    """Bad input to the distance field, or an unusable map.zarr, explained in one line with the fix."""
