"""Write ROS recordings (bare MCAP, rosbag2 directory, ROS1 bag) without ROS.

:class:`BagRecorder` turns numpy depth images and 4x4 poses into the messages a real drone publishes
(depth Image / compressedDepth, CameraInfo, Odometry, tf) and writes them atomically. The
simulator (``mapkit simulate``), ``mapkit plan`` (nav_msgs/Path) and the tests write their bags with it;
reading bags is :mod:`mapkit.ingest`'s job.

- :class:`BagRecorder`, :func:`output_path`: the writer and the path a format gets.
- :data:`FORMATS`, :data:`DEPTH_ENCODINGS`, ``BagFormat``: what it writes.
- :class:`BagError`: every user-facing problem, in one line.
"""

from mapkit.bags._recorder import DEPTH_ENCODINGS, FORMATS, BagError, BagFormat, BagRecorder, output_path

__all__ = ["BagError", "BagFormat", "BagRecorder", "DEPTH_ENCODINGS", "FORMATS", "output_path"]
