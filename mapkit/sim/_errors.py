"""The simulator's exception class."""

from __future__ import annotations

from mapkit.errors import MapkitError


class SimError(MapkitError):
    """A bad simulator or recorder input (world kind, resolution, output path, ...), in one line
    that names the bad value and the fix."""
