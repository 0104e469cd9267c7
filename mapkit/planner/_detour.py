"""Detour excess: how much longer than the straight line the way from a point to the goal is,
through the free space of the training map (the reconstructed ESDF; never the simulator's).

The paper's goal cost ‖end − goal‖ rewards a plan that stops as close to a goal behind a wall as the
wall lets it, which in an office is often a dead end; this term rewards ending where the way round
begins (a doorway) instead. scikit-image's MCP does the route search; the level grid, the height band
and the excess are what no library gives, so they are written here.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:  # pragma: no cover
    from mapkit.esdf import EsdfMap


@dataclass(frozen=True)
class DetourGrid:
    """How a map becomes a level grid of passable cells for one goal."""

    cell_voxels: int = 2
    """Map voxels per cell side (0.2 m cells on the 0.1 m training maps)."""
    band: float = 0.6
    """Metres above and below the goal's height: a cell is passable when some voxel within it and
    this band keeps the clearance (a vehicle may climb over a desk or duck under a lintel)."""
    clearance: float = 0.3
    """Metres of unsmoothed ESDF a passable voxel needs (the robot radius)."""
    wall_cost: float = 50.0
    """Cost of crossing a blocked cell, relative to a free one: a route through 0.2 m of wall counts
    as 10 m, so ways round of up to that length are preferred to it (and every field stays finite)."""


@dataclass
class _Field:
    excess: torch.Tensor  # (nx, ny) metres
    origin: np.ndarray  # (2,) world xy of cell [0, 0]'s centre
    cell: float


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # EsdfMap → {goal key: _Field}


def _passable(esdf_map: EsdfMap, goal: np.ndarray, grid: DetourGrid) -> np.ndarray:
    """(nx, ny) bool cells passable at some height within the band of ``goal``'s."""
    esdf_map.load()
    raw = np.asarray(esdf_map.esdf_raw if esdf_map.esdf_raw is not None else esdf_map.esdf)
    z = esdf_map.origin[2] + esdf_map.voxel_size * np.arange(raw.shape[2])
    band = np.abs(z - goal[2]) <= grid.band
    if not band.any():
        band[int(np.clip(round((goal[2] - esdf_map.origin[2]) / esdf_map.voxel_size), 0, raw.shape[2] - 1))] = True
    free = (raw[:, :, band] > grid.clearance).any(axis=2)
    c = grid.cell_voxels
    nx, ny = -(-free.shape[0] // c), -(-free.shape[1] // c)
    padded = np.zeros((nx * c, ny * c), dtype=bool)
    padded[:free.shape[0], :free.shape[1]] = free
    return np.asarray(padded.reshape(nx, c, ny, c).any(axis=(1, 3)))


def _field(esdf_map: EsdfMap, goal: np.ndarray, grid: DetourGrid) -> _Field:
    from skimage.graph import MCP_Geometric

    cell = esdf_map.voxel_size * grid.cell_voxels
    origin = esdf_map.origin[:2] + 0.5 * (grid.cell_voxels - 1) * esdf_map.voxel_size
    passable = _passable(esdf_map, goal, grid)
    shape = np.array(passable.shape)
    g = np.clip(np.rint((goal[:2] - origin) / cell).astype(int), 0, shape - 1)
    route, _ = MCP_Geometric(np.where(passable, 1.0, grid.wall_cost)).find_costs([tuple(g)])
    # The same grid's distance with nothing in the way (8-connected: octile), so that open space
    # has exactly zero excess whatever the grid's own metric error.
    dx, dy = np.abs(np.arange(shape[0]) - g[0])[:, None], np.abs(np.arange(shape[1]) - g[1])[None, :]
    octile = np.maximum(dx, dy) + (math.sqrt(2.0) - 1.0) * np.minimum(dx, dy)
    excess = np.where(route - octile > 1e-6, route - octile, 0.0) * cell  # float noise of the sums is no detour
    return _Field(torch.from_numpy(excess.astype(np.float32)), origin, cell)


def detour_field(esdf_map: EsdfMap, goal_world: np.ndarray, grid: DetourGrid = DetourGrid()) -> _Field:
    """The excess field of one goal (cached per map and goal: training meets every goal once an epoch)."""
    per_map = _CACHE.setdefault(esdf_map, {})
    key = (np.round(np.asarray(goal_world, dtype=np.float64), 3).tobytes(), grid)
    hit = per_map.get(key)
    if hit is None:
        hit = per_map[key] = _field(esdf_map, np.asarray(goal_world, dtype=np.float64), grid)
    return hit


def detour_excess(ends_world: torch.Tensor, goals_world: torch.Tensor, esdf_map: EsdfMap, *,
                  grid: DetourGrid = DetourGrid(), cap: float = 8.0) -> torch.Tensor:
    """(B, M) metres: the route from each of a sample's M ends (B, M, 3) to its goal (B, 3), both world
    frame, minus the straight distance on the same level grid, bilinear between cell centres (clamped
    to the grid), at most ``cap``. Differentiable with respect to ``ends_world``; zero where nothing is
    in the way."""
    goals = goals_world.detach().double().cpu().numpy()
    fields = [detour_field(esdf_map, goals[b], grid) for b in range(len(goals))]
    excess = torch.stack([f.excess for f in fields]).to(device=ends_world.device, dtype=ends_world.dtype)
    f0 = fields[0]
    B, nx, ny = excess.shape
    origin = torch.as_tensor(f0.origin, dtype=ends_world.dtype, device=ends_world.device)
    u = (ends_world[..., :2] - origin) / f0.cell  # (B, M, 2) cells
    u = torch.stack([u[..., 0].clamp(0, nx - 1), u[..., 1].clamp(0, ny - 1)], dim=-1)
    top = torch.tensor([max(nx - 2, 0), max(ny - 2, 0)], device=u.device)
    i0 = torch.minimum(u.detach().floor().long(), top)
    w = u - i0.to(u.dtype)
    i1 = torch.minimum(i0 + 1, torch.tensor([nx - 1, ny - 1], device=u.device))
    rows = torch.arange(B, device=u.device)[:, None]

    def at(i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
        return excess[rows, i, j]

    wx, wy = w[..., 0], w[..., 1]
    value = ((1 - wx) * (1 - wy) * at(i0[..., 0], i0[..., 1]) + wx * (1 - wy) * at(i1[..., 0], i0[..., 1])
             + (1 - wx) * wy * at(i0[..., 0], i1[..., 1]) + wx * wy * at(i1[..., 0], i1[..., 1]))
    return value.clamp(max=cap)
