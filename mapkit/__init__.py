"""mapkit: UAV depth + pose recordings to cost maps and a self-supervised trajectory planner.

Subpackages, one per pipeline stage (imports point one way along the pipeline):
``mapkit.ingest`` (bags → frames.zarr), ``mapkit.sim`` (simulated worlds and flights),
``mapkit.trajopt`` (differentiable minimum-snap).
"""

from mapkit._version import __version__
from mapkit.errors import MapkitError

__all__ = ["__version__", "MapkitError"]
