from mapkit.errors import MapkitError


class IngestError(MapkitError):
    """A recording, topic or option that ingestion cannot use; the message says which and why."""
