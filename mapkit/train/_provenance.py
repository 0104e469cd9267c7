"""What a run was trained on, recorded in its config.json so the run stays usable (and its training
worlds refusable by `mapkit eval`) after the workspaces are gone — e.g. the shipped model."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


def workspace_camera(workspace: str | Path) -> dict[str, Any]:
    """The depth camera of a workspace's frames.zarr: width, height, K (3×3), T_body_camera (4×4)
    and the store it came from. Raises MapkitError when the store cannot be read."""
    from mapkit.geometry import invert_transform
    from mapkit.ingest import open_frames_store

    store = open_frames_store(workspace)
    T_bc = invert_transform(store.T_world_body[0]) @ store.T_world_camera[0]
    return {"width": int(store.width), "height": int(store.height), "K": [list(map(float, r)) for r in store.K],
            "T_body_camera": [list(map(float, r)) for r in T_bc], "source": f"{workspace}/frames.zarr"}


def simulated_worlds(workspaces: Sequence[str | Path], *, unreadable_level: int = logging.WARNING) -> set[tuple[str, int]]:
    """(kind, seed) of the simulated worlds behind the workspaces' recordings (their .world.json
    beside each recording); real recordings add nothing. An unreadable workspace or .world.json adds
    nothing either and is logged with the reason at ``unreadable_level`` (the caller knows whether
    it matters: `mapkit eval` of a run that recorded its worlds loses nothing)."""
    from mapkit.ingest import open_frames_store

    out: set[tuple[str, int]] = set()
    for ws in workspaces:
        try:
            sources = open_frames_store(ws).attrs.get("sources", [])
        except Exception as exc:  # noqa: BLE001 - a moved, deleted or damaged workspace: logged, the caller decides
            log.log(unreadable_level, "workspace %s is not readable (%s: %s); the simulated worlds of its "
                    "recordings are not known", ws, type(exc).__name__, exc)
            continue
        for src in sources:
            world = _recording_world(Path(src.get("path", "")), unreadable_level)
            if world is not None:
                out.add(world)
    return out


def _recording_world(recording: Path, unreadable_level: int) -> tuple[str, int] | None:
    """(kind, seed) from the .world.json beside a simulated recording; None for a real recording or
    an unreadable file (logged at ``unreadable_level``)."""
    from mapkit.sim import ground_truth_paths

    for fmt in ("mcap", "ros2"):
        wj = ground_truth_paths(recording, fmt)[0]
        if wj.exists():
            try:
                d = json.loads(wj.read_text())
                return str(d["kind"]), int(d["seed"])
            except (OSError, ValueError, KeyError) as exc:
                log.log(unreadable_level, "%s is not a readable world file (%s: %s); its world is not known",
                        wj, type(exc).__name__, exc)
            return None
    return None
