"""Training samples from one or more tuples.zarr stores: one sample per (tuple, goal)."""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypedDict

import numpy as np
import torch

from mapkit._stores import Location, StoreError
from mapkit._zarr import read_whole
from mapkit.errors import MapkitError
from mapkit.planner._depthcheck import CameraInput


class TrainDataError(MapkitError):
    """Training data that cannot be used (missing, foreign or inconsistent stores)."""


@dataclass
class TupleStore:
    """One workspace's tuples.zarr, with its arrays loaded except depth (read per batch)."""

    workspace: Location
    """The workspace (a local path or an fsspec URL); ``workspace / "map.zarr"`` is its map."""
    depth: Any
    goals_body: np.ndarray
    velocity_body: np.ndarray
    T_world_body: np.ndarray
    split: np.ndarray
    attrs: dict[str, Any]
    T_body_camera: np.ndarray
    """(n, 4, 4) camera (optical) → body per tuple."""
    goal_blocked: np.ndarray | None = None
    """(n, G) uint8: the goal's straight line is blocked in the map (stores exported before the goal
    mix lack it: None)."""

    @classmethod
    def open(cls, workspace: str | Path | Location) -> TupleStore:
        """``workspace/tuples.zarr`` (a local path or an fsspec URL, e.g. ``s3://bucket/ws``)."""
        import zarr

        ws = Location.of(workspace)
        path = ws / "tuples.zarr"
        try:
            if not path.exists():
                raise TrainDataError(f"{path} does not exist; run `mapkit export -w {ws}` first")
            path.require_complete(f"mapkit export -w {ws} --overwrite")
        except StoreError as exc:
            raise TrainDataError(str(exc)) from None
        try:
            root = zarr.open_group(path.zarr_store(read_only=True), mode="r")
            attrs = dict(root.attrs)
            if attrs.get("kind") != "mapkit.tuples":
                raise KeyError("kind")
            blocked = read_whole(root, "goal_blocked") if "goal_blocked" in root else None
            T_wb = read_whole(root, "T_world_body")
            T_bc = np.linalg.inv(T_wb) @ read_whole(root, "T_world_camera")
            return cls(ws, root["depth"], read_whole(root, "goals_body"), read_whole(root, "velocity_body"), T_wb,
                       read_whole(root, "split"), attrs, T_bc, blocked)
        except Exception as exc:  # noqa: BLE001 - zarr raises many kinds for a damaged or foreign store
            raise TrainDataError(f"{path} is not a mapkit tuples store ({type(exc).__name__}: {exc}); re-run `mapkit export --overwrite`") from None


class Batch(TypedDict):
    """One training batch (:meth:`TupleSamples.load`)."""

    depth: torch.Tensor
    image_index: torch.Tensor
    goal: torch.Tensor
    velocity: torch.Tensor
    T_world_body: torch.Tensor
    camera: CameraInput
    blocked: torch.Tensor


class TupleSamples:
    """(store, tuple, goal) triples of one split over several stores; batches stay within one store
    so that each batch is scored against a single map."""

    def __init__(self, stores: Sequence[TupleStore], split: str, *, goals_together: bool = False) -> None:
        self.goals_together = goals_together
        if split not in ("train", "val", "all"):
            raise TrainDataError(f"split {split!r}: expected train, val or all")
        self.stores = list(stores)
        self.index: list[np.ndarray] = []  # per store: (n, 2) tuple index, goal index
        for s in self.stores:
            if split == "all":  # whole workspaces on one side (held-out worlds)
                tuples = np.arange(len(s.split))
            else:
                tuples = np.flatnonzero(s.split == (0 if split == "train" else 1))
            goals = np.arange(s.goals_body.shape[1])
            grid = np.stack(np.meshgrid(tuples, goals, indexing="ij"), axis=-1).reshape(-1, 2)
            self.index.append(grid)

    def __len__(self) -> int:
        return int(sum(len(i) for i in self.index))

    def blocked_count(self) -> int | None:
        """Samples whose goal is blocked in the map (None when no store records it)."""
        counts = [int(s.goal_blocked[i[:, 0], i[:, 1]].sum()) for s, i in zip(self.stores, self.index, strict=True)
                  if s.goal_blocked is not None]
        return sum(counts) if counts else None

    def batches(self, batch_size: int, *, shuffle: bool, generator: np.random.Generator | None = None,
                rank: int = 0, world_size: int = 1) -> Iterator[tuple[int, np.ndarray]]:
        """(store index, (b, 2) [tuple, goal]) batches; with world_size > 1 each rank takes every
        world_size-th batch (the same order on every rank), the list padded with its first batches so
        every rank takes the same number of steps (as torch's DistributedSampler)."""
        batches: list[tuple[int, np.ndarray]] = []
        for k, idx in enumerate(self.index):
            if self.goals_together:
                # Whole tuples (all their goals) in shuffled order: the encoder runs once per image.
                tuples = np.unique(idx[:, 0])
                if shuffle and generator is not None:
                    tuples = generator.permutation(tuples)
                order = np.concatenate([np.flatnonzero(idx[:, 0] == t) for t in tuples]) if len(tuples) else np.arange(0)
            else:
                order = generator.permutation(len(idx)) if shuffle and generator is not None else np.arange(len(idx))
            for start in range(0, len(order), batch_size):
                part = idx[order[start : start + batch_size]]
                if len(part):
                    batches.append((k, part))
        if shuffle and generator is not None:
            batches = [batches[i] for i in generator.permutation(len(batches))]
        if world_size > 1 and batches and len(batches) % world_size:
            rounds = -(-len(batches) // world_size)
            batches = list(itertools.islice(itertools.cycle(batches), rounds * world_size))
        yield from batches[rank::world_size]

    def load(self, store_index: int, part: np.ndarray, device: torch.device) -> Batch:
        """Tensors of one batch: depth (U,H,W) metres with NaN of the U distinct tuples, image_index (B,)
        (each sample's depth image), goal (B,3), velocity (B,3), T_world_body (B,4,4),
        camera (:class:`mapkit.planner.CameraInput` per sample), blocked (B,) bool (all False for stores
        without the record)."""
        s = self.stores[store_index]
        tuples, goals = part[:, 0], part[:, 1]
        unique, inverse = np.unique(tuples, return_inverse=True)
        depth = np.stack([np.asarray(s.depth[int(t)]) for t in unique])
        return {
            "depth": torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32)).to(device),
            "image_index": torch.from_numpy(inverse.astype(np.int64).reshape(-1)).to(device),
            "goal": torch.from_numpy(s.goals_body[tuples, goals].astype(np.float32)).to(device),
            "velocity": torch.from_numpy(s.velocity_body[tuples].astype(np.float32)).to(device),
            "T_world_body": torch.from_numpy(s.T_world_body[tuples].astype(np.float32)).to(device),
            "camera": CameraInput.from_calibration(np.asarray(s.attrs["K"]), int(s.attrs["width"]), int(s.attrs["height"]),
                                                    torch.from_numpy(s.T_body_camera[tuples])).to(device),
            "blocked": torch.from_numpy(np.zeros(len(part), dtype=bool) if s.goal_blocked is None
                                        else s.goal_blocked[tuples, goals].astype(bool)).to(device),
        }
