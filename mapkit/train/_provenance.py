"""What a run was trained on, recorded in its config.json so the run stays usable (and its training
worlds refusable by `mapkit eval`) after the workspaces are gone — e.g. the shipped model."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence


def workspace_camera(workspace: str | Path) -> dict[str, Any]:
    """The depth camera of a workspace's frames.zarr: width, height, K (3×3), T_body_camera (4×4)
    and the store it came from. Raises MapkitError when the store cannot be read."""
    from mapkit.geometry import invert_transform
    from mapkit.ingest import open_frames_store

    store = open_frames_store(workspace)
    T_bc = invert_transform(store.T_world_body[0]) @ store.T_world_camera[0]
    return {"width": int(store.width), "height": int(store.height), "K": [list(map(float, r)) for r in store.K],
            "T_body_camera": [list(map(float, r)) for r in T_bc], "source": f"{workspace}/frames.zarr"}


def simulated_worlds(workspaces: Sequence[str | Path]) -> set[tuple[str, int]]:
    """(kind, seed) of the simulated worlds behind the workspaces' recordings (their .world.json
    beside each recording); unreadable workspaces and real recordings add nothing."""
    from mapkit.ingest import open_frames_store
    from mapkit.sim.simulate import ground_truth_paths

    out: set[tuple[str, int]] = set()
    for ws in workspaces:
        try:
            sources = open_frames_store(ws).attrs.get("sources", [])
        except Exception:  # noqa: BLE001 - a moved or deleted workspace
            continue
        for src in sources:
            p = Path(src.get("path", ""))
            for fmt in ("mcap", "ros2"):
                wj = ground_truth_paths(p, fmt)[0]
                if wj.exists():
                    try:
                        d = json.loads(wj.read_text())
                        out.add((str(d["kind"]), int(d["seed"])))
                    except (OSError, ValueError, KeyError):
                        pass
                    break
    return out
