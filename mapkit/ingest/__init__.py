"""Recordings (ROS1 bag, ROS2 bag, MCAP, db3) → synchronised depth frames → ``frames.zarr``.

Typical use::

    from mapkit.ingest import IngestConfig, open_frames, ingest
    for frame in open_frames(["flight.mcap"]):          # streams, one depth image at a time
        frame.depth, frame.T_world_camera, frame.K
    ingest(["flight.mcap"], "ws")                        # writes ws/frames.zarr
"""

from mapkit.ingest._errors import IngestError
from mapkit.ingest._reader import Frame, FrameStream, IngestConfig, RecordingInfo, inspect_recordings, open_frames
from mapkit.ingest._sources import BagSummary, Source, TopicSummary
from mapkit.ingest._store import FramesStore, IngestSummary, ingest, open_frames_store

__all__ = ["BagSummary", "Frame", "FrameStream", "FramesStore", "IngestConfig", "IngestError", "IngestSummary",
           "RecordingInfo", "Source", "TopicSummary", "ingest", "inspect_recordings", "open_frames",
           "open_frames_store"]
