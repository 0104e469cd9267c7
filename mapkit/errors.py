"""Exception base class. Each subpackage derives its own; the CLI turns any of them into a
one-line message and exit code 1 (2, a usage error, when a config refuses an option's value before
any work), so messages must name the bad value and the fix."""


class MapkitError(Exception):
    """A problem with the user's input or environment, explained in one line."""
