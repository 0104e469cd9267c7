"""What a workspace holds, for a viewer: each store opened if it is there, a note for each that is
missing or unreadable (with the command that makes it)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapkit.errors import MapkitError
from mapkit.viz._cloud import _ply_header
from mapkit.viz._errors import VizError

FRAMES, CLOUD, MAP = "frames.zarr", "cloud.ply", "map.zarr"
_MAKES = {
    FRAMES: "`mapkit ingest BAG -w {ws}`",
    CLOUD: "`mapkit fuse BAG -w {ws}`",
    MAP: "`mapkit esdf -w {ws}`",
}


@dataclass
class WorkspaceContents:
    """The stores of a workspace that opened; `notes` says what is missing or broken."""

    path: Path
    frames: Any = None
    """:class:`mapkit.ingest.FramesStore` or None."""
    cloud_path: Path | None = None
    """cloud.ply when present and its header reads (points are read by the caller)."""
    esdf_map: Any = None
    """:class:`mapkit.esdf.EsdfMap` (lazy) or None."""
    runs: list[Path] = field(default_factory=list)
    """runs/NAME directories holding a model.pt."""
    notes: list[str] = field(default_factory=list)
    """One line per missing or unreadable store, naming it and the fix."""

    @property
    def empty(self) -> bool:
        return self.frames is None and self.cloud_path is None and self.esdf_map is None


def open_workspace(path: str | Path) -> WorkspaceContents:
    """Open whatever a workspace holds. Raises :class:`VizError` only when `path` is not a directory;
    a missing or corrupt store becomes a note instead."""
    from mapkit.esdf import EsdfMap
    from mapkit.ingest import open_frames_store

    ws = Path(path)
    if not ws.is_dir():
        raise VizError(f"no workspace at {str(ws)!r} (not a directory); pass the -w folder the other commands wrote")
    out = WorkspaceContents(ws)

    def missing(name: str) -> str:
        return f"{name} is missing; make it with {_MAKES[name].format(ws=ws)}"

    if (ws / FRAMES).exists():
        try:
            out.frames = open_frames_store(ws)
            if len(out.frames) == 0:
                out.frames = None
                out.notes.append(f"{FRAMES} holds no frames; re-run `mapkit ingest --overwrite`")
        except MapkitError as exc:
            out.notes.append(f"{FRAMES} cannot be opened: {exc}")
    else:
        out.notes.append(missing(FRAMES))
    if (ws / CLOUD).exists():
        problem = _check_ply_header(ws / CLOUD)
        if problem:
            out.notes.append(f"{CLOUD} cannot be read: {problem}")
        else:
            out.cloud_path = ws / CLOUD
    else:
        out.notes.append(missing(CLOUD))
    if (ws / MAP).exists():
        try:
            out.esdf_map = EsdfMap.open(ws / MAP)
        except MapkitError as exc:
            out.notes.append(f"{MAP} cannot be opened: {exc}")
    else:
        out.notes.append(missing(MAP))
    runs = ws / "runs"
    if runs.is_dir():
        out.runs = sorted(p for p in runs.iterdir() if (p / "model.pt").is_file())
    return out


def _check_ply_header(path: Path) -> str | None:
    """None if the file has a readable PLY header, else what is wrong."""
    try:
        with open(path, "rb") as f:
            _ply_header(f, path)
    except (OSError, ValueError, VizError) as exc:
        return str(exc)
    return None
