"""The fly package's exception."""

from mapkit.errors import MapkitError


class FlyError(MapkitError):
    """A link, message or option `mapkit fly` cannot work with; the message names the value and the fix."""
