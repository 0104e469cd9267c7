"""The recorder's exception class."""

from __future__ import annotations

from mapkit.errors import MapkitError


class BagError(MapkitError):
    """A bad recorder input (format, output path, depth image, transform, ...), in one line that names
    the bad value and the fix."""
