"""``mapkit batch``: the per-flight pipeline (ingest → fuse → esdf → export) over many recordings, as a
Dask task graph (a local cluster or an existing scheduler); resumable, one workspace per recording.

Typical use::

    from mapkit.batch import BatchConfig, resolve_recordings, run_batch
    config = BatchConfig(recordings=resolve_recordings(["flights/*.mcap"]), root=Path("maps"))
    summary = run_batch(config)          # maps/<stem>/frames.zarr, cloud.ply, map.zarr, tuples.zarr
    summary.failed                       # each with its one-line reason
    BatchConfig(..., root="s3://bucket/maps")  # workspaces on shared storage (fsspec URL)
"""

from mapkit.batch._config import (
           STEPS,
           BatchConfig,
           BatchError,
           Recording,
           Step,
           parse_root,
           parse_steps,
           read_manifest,
           resolve_recordings,
)
from mapkit.batch._lock import LOCK
from mapkit.batch._run import BatchSummary, RecordingResult, run_batch
from mapkit.batch._steps import MARKERS, StepOutcome

__all__ = ["LOCK", "MARKERS", "STEPS", "BatchConfig", "BatchError", "BatchSummary", "Recording", "RecordingResult", "Step",
           "StepOutcome", "parse_root", "parse_steps", "read_manifest", "resolve_recordings", "run_batch"]
