"""mapkit: UAV depth + pose recordings to cost maps and a self-supervised trajectory planner.

Subpackages, one per pipeline stage, in pipeline order (imports point one way along it); each
re-exports its public names from private ``_modules``:

- ``mapkit.ingest``: recordings (ROS1 bag, ROS2 bag, MCAP) → synchronised depth + poses → frames.zarr.
- ``mapkit.bags``: writing recordings without ROS (depth, CameraInfo, Odometry, tf; MCAP, ROS2, ROS1).
- ``mapkit.sim``: procedural worlds with exact distances, a depth camera and flights → recordings.
- ``mapkit.fusion``: TSDF fusion of frames.zarr (Open3D) → cloud.ply, mesh.ply, tsdf.npz.
- ``mapkit.esdf``: signed distance maps → map.zarr; queries, gradients and slices of them.
- ``mapkit.export``: training tuples → tuples.zarr (depth, poses, velocities, goals, split).
- ``mapkit.batch``: the per-flight stages above (ingest → fuse → esdf → export) over many recordings, on Dask.
- ``mapkit.dataset``: training data at scale: many simulated worlds run through every stage above.
- ``mapkit.trajopt``: differentiable minimum-snap trajectories, flight corridors, time allocation.
- ``mapkit.planner``: the planner network and its self-supervised loss (batched tensors).
- ``mapkit.train``: training the planner → runs/NAME/ (presets, loop, checkpoints, validation, DDP).
- ``mapkit.flight``: flying a trained planner: the pilot (the planner and its flight stack, frame by
  frame, for any vehicle loop) and its single-shot use, ``Planner.load("pretrained").plan(...)``.
- ``mapkit.evaluation``: closed-loop flights of the pilot in unseen simulated worlds (linear tracker
  or rotorpy quadrotor) → results.json.
- ``mapkit.fly``: the pilot on a live ROS 2 / PX4 graph over DDS without ROS (``mapkit fly``), a
  simulated vehicle for software in the loop, recordings replayed as live topics.
- ``mapkit.recipe``: a model made from nothing by a declared, resumable chain of steps (``mapkit train --recipe``).
- ``mapkit.viz``: the computations behind the viewer (slices, colours, clouds, corridors); no viser.
- ``mapkit.exchange``: exports for Foxglove (MCAP) and Rerun (.rrd).
- ``mapkit.cli`` (``cli/``) and ``mapkit.viewer`` (``viewer/``): the click commands and the viser app,
  thin layers over the library.

Shared by every stage: ``mapkit.geometry`` (4x4 ``T_a_b`` transforms, quaternions ``xyzw``),
``mapkit.errors`` (:class:`MapkitError`, the base of every stage's error) and ``mapkit.workspace`` (workspace folders, atomic store writes).
The design decisions of each stage are in the repository's docs/ folder.
"""

from mapkit._version import __version__
from mapkit.errors import MapkitError

__all__ = ["__version__", "MapkitError"]
