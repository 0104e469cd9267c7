"""Evaluation results (``mapkit eval`` output, format "mapkit-eval/1") for viewing: episodes,
executed paths per method, and the simulated worlds they ran in."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapkit._formats import EPISODE_KEYS, EVAL_FORMAT, EpisodeRecord
from mapkit.viz._errors import VizError


@dataclass
class EvalResults:
    """An evaluation directory: results.json, trajectories.npz and worlds/*.world.json."""

    path: Path
    worlds: dict[str, dict[str, Any]]
    """name → {"seed": int, "world_json": path relative to :attr:`path`}."""
    methods: list[str]
    episodes: list[EpisodeRecord]
    """The rows of results.json as typed records, in file order."""
    notes: list[str] = field(default_factory=list)
    """Problems found that do not stop viewing (missing paths, unreadable worlds)."""
    _npz: Any = None

    def pairs(self, world: str) -> list[int]:
        """Sorted pair indices evaluated in `world`."""
        return sorted({int(e.pair) for e in self.episodes if e.world == world})

    def episodes_of(self, world: str, pair: int | None = None) -> list[EpisodeRecord]:
        """Episodes of `world` (one pair, or all when `pair` is None), in file order."""
        return [e for e in self.episodes if e.world == world and (pair is None or int(e.pair) == pair)]

    def path_of(self, world: str, pair: int, method: str) -> np.ndarray | None:
        """float64 (N, 4) rows [t, x, y, z] (world frame) of an executed path, or None if absent."""
        if self._npz is None:
            return None
        key = f"{world}/{int(pair):03d}/{method}"
        if key not in self._npz.files:
            return None
        try:
            a = np.asarray(self._npz[key], dtype=np.float64)
        except Exception as exc:  # noqa: BLE001 - a damaged member of the zip
            raise VizError(f"{self.path / 'trajectories.npz'}: cannot read {key!r} ({type(exc).__name__}: {exc})") from None
        if a.ndim != 2 or a.shape[1] != 4:
            raise VizError(f"{self.path / 'trajectories.npz'}: {key!r} has shape {a.shape}, expected (N, 4) [t, x, y, z]")
        return a

    def world_file(self, world: str) -> Path:
        """The .world.json of `world`."""
        return self.path / str(self.worlds[world]["world_json"])

    def close(self) -> None:
        """Close trajectories.npz."""
        if self._npz is not None:
            self._npz.close()
            self._npz = None


def load_eval(path: str | Path) -> EvalResults:
    """Open an evaluation directory. Raises :class:`VizError` naming the file when results.json is
    missing, not JSON, of another format, or lacks worlds/methods/episodes; a missing
    trajectories.npz is only a note (outcomes still show)."""
    d = Path(path)
    if not d.is_dir():
        raise VizError(f"no evaluation at {str(d)!r} (not a directory); pass the folder `mapkit eval` wrote")
    rj = d / "results.json"
    if not rj.is_file():
        raise VizError(f"{str(d)!r} has no results.json; it is not a `mapkit eval` output (or the run did not finish)")
    try:
        data = json.loads(rj.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise VizError(f"{str(rj)!r} is not readable JSON ({exc}); re-run `mapkit eval`") from None
    if not isinstance(data, dict) or data.get("format") != EVAL_FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise VizError(f"{str(rj)!r} has format {got!r}, expected {EVAL_FORMAT!r}; re-run `mapkit eval` with this version")
    worlds, methods, episodes = data.get("worlds"), data.get("methods"), data.get("episodes")
    if not isinstance(worlds, dict) or not isinstance(methods, list) or not isinstance(episodes, list):
        raise VizError(f"{str(rj)!r} lacks 'worlds' (object), 'methods' (list) or 'episodes' (list); re-run `mapkit eval`")
    for i, e in enumerate(episodes):
        if not isinstance(e, dict) or not set(EPISODE_KEYS) <= set(e):
            raise VizError(f"{str(rj)!r}: episode {i} lacks world/pair/method/outcome/start/goal; re-run `mapkit eval`")
        if e["world"] not in worlds:
            raise VizError(f"{str(rj)!r}: episode {i} names world {e['world']!r}, which 'worlds' does not list")
    notes: list[str] = []
    for name, w in worlds.items():
        if not isinstance(w, dict) or "world_json" not in w:
            raise VizError(f"{str(rj)!r}: world {name!r} has no 'world_json'")
    npz = None
    tp = d / "trajectories.npz"
    if tp.is_file():
        try:
            npz = np.load(tp, allow_pickle=False)
        except Exception as exc:  # noqa: BLE001 - zipfile / format errors
            notes.append(f"trajectories.npz cannot be read ({type(exc).__name__}: {exc}); paths are not shown")
    else:
        notes.append("trajectories.npz is missing; executed paths are not shown")
    records = [EpisodeRecord.from_dict(e) for e in episodes]
    return EvalResults(d, dict(worlds), [str(m) for m in methods], records, notes, npz)


def world_mesh_arrays(world_json: str | Path, *, resolution: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """vertices float64 (V, 3) and faces int64 (F, 3) of a simulated world's mesh
    (:meth:`mapkit.sim.World.mesh`). Raises :class:`VizError` naming the file if it cannot be read."""
    from mapkit.errors import MapkitError
    from mapkit.sim import World

    p = Path(world_json)
    if not p.is_file():
        raise VizError(f"world file {str(p)!r} is missing")
    try:
        mesh = World.from_json(p).mesh(resolution=resolution, color=False)
    except MapkitError as exc:
        raise VizError(f"world file {str(p)!r} cannot be used: {exc}") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise VizError(f"world file {str(p)!r} cannot be read ({type(exc).__name__}: {exc})") from None
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)
