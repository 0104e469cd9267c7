"""Computations behind the viewers (``mapkit view``), usable by any front end: no viser, no click.

- Slices: :class:`MapSlicer`, :func:`slice_texture`, :func:`colorbar_image`.
- Point clouds: :func:`read_ply_points`, :func:`voxel_downsample`, :func:`downsample_to`, :func:`cloud_view`.
- Geometry: :func:`frustum_segments`, :func:`polyline_segments`, :func:`speed_colors`,
  :func:`corridor_cross_section` and :func:`corridor_prisms` (the corridor :func:`mapkit.trajopt.min_snap`
  enforces), :func:`pick_point` (a click ray → a goal).
- Stores: :func:`open_workspace`, :func:`load_eval` (``mapkit eval`` output), :func:`world_mesh_arrays`.

>>> import numpy as np
>>> from mapkit.viz import corridor_cross_section
>>> corridor_cross_section(np.array([1.0, 0.0, 0.0]), 0.5).shape   # a square ⊥ x
(4, 3)
>>> corridor_cross_section(np.array([1.0, 1.0, 1.0]), 0.5).shape   # a hexagon
(6, 3)
"""

from mapkit.viz._cloud import (
    CloudView,
    PlyPoints,
    cloud_view,
    downsample_to,
    read_ply_points,
    transfer_precision,
    voxel_downsample,
)
from mapkit.viz._color import (
    HATCH_RGB,
    apply_colormap,
    colorbar_image,
    colormap,
    depth_image,
    hatch,
    make_norm,
    method_colors,
    speed_colors,
)
from mapkit.viz._errors import VizError
from mapkit.viz._eval import EvalResults, load_eval, world_mesh_arrays
from mapkit.viz._geometry import (
    CorridorGeometry,
    corridor_cross_section,
    corridor_prisms,
    frustum_segments,
    pick_point,
    polyline_segments,
    transform_points,
)
from mapkit.viz._slice import (
    MapSlicer,
    SlabCache,
    SliceTexture,
    obstacle_cost_of_distance,
    slice_texture,
    texture_scale,
)
from mapkit.viz._workspace import WorkspaceContents, open_workspace

__all__ = [
    "HATCH_RGB",
    "CloudView",
    "CorridorGeometry",
    "EvalResults",
    "MapSlicer",
    "PlyPoints",
    "SlabCache",
    "SliceTexture",
    "VizError",
    "WorkspaceContents",
    "apply_colormap",
    "cloud_view",
    "colorbar_image",
    "colormap",
    "corridor_cross_section",
    "corridor_prisms",
    "depth_image",
    "downsample_to",
    "frustum_segments",
    "hatch",
    "load_eval",
    "make_norm",
    "method_colors",
    "obstacle_cost_of_distance",
    "open_workspace",
    "pick_point",
    "polyline_segments",
    "read_ply_points",
    "slice_texture",
    "speed_colors",
    "texture_scale",
    "transfer_precision",
    "transform_points",
    "voxel_downsample",
    "world_mesh_arrays",
]
