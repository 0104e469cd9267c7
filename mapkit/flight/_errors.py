"""The flight package's exception."""

from mapkit.errors import MapkitError


class FlightError(MapkitError):
    """An input the pilot cannot fly from (a bad image, camera, pose, goal or time stamp); the message
    names the value and the fix."""
