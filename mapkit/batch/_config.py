"""What a batch runs: the recordings (paths, globs or a manifest), the steps and each step's options."""

from __future__ import annotations

import glob
import json
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal, get_args

from mapkit._stores import Location, is_url
from mapkit.errors import MapkitError
from mapkit.esdf import EsdfConfig
from mapkit.export import ExportConfig
from mapkit.fusion import FuseConfig
from mapkit.ingest import IngestConfig
from mapkit.ingest._decode import parse_extrinsic, parse_intrinsics

Step = Literal["ingest", "fuse", "esdf", "export"]
STEPS: tuple[Step, ...] = get_args(Step)
"""The per-flight pipeline in order; a batch runs a subset of it, always in this order."""

MANIFEST_SUFFIXES = (".toml", ".json")
"""A RECORDINGS argument with one of these suffixes is a manifest, not a recording."""


class BatchError(MapkitError):
    """A batch that cannot start: bad recordings, manifest, steps or root."""


@dataclass(frozen=True)
class Recording:
    """One recording of a batch and how to read it."""

    name: str
    """Workspace name under the batch root (``ROOT/<name>/``): the file stem unless a manifest names it."""
    path: Path
    """The recording (a file, or a rosbag2 folder), absolute so that workers elsewhere find it."""
    ingest: IngestConfig
    """How `mapkit ingest` reads it (topics, frames, extrinsic, ...)."""


@dataclass(frozen=True)
class BatchConfig:
    """A batch: every recording through ``steps``, one workspace each under ``root``."""

    recordings: tuple[Recording, ...]
    """The recordings, with unique names (see :func:`resolve_recordings`)."""
    root: Path | str
    """Folder holding one workspace per recording (``ROOT/<name>/``): a path, or an fsspec URL
    (``s3://bucket/flights``; see :mod:`mapkit.batch._remote`)."""
    steps: tuple[Step, ...] = STEPS
    """The steps to run, in pipeline order; a step whose outputs are up to date is skipped."""
    scheduler: str | None = None
    """Dask scheduler address (``tcp://HOST:8786``); None: ``DASK_SCHEDULER_ADDRESS``, else a local cluster."""
    workers: int | None = None
    """Worker processes of a local cluster (default: one per available core); ignored with a scheduler."""
    retries: int = 1
    """Extra attempts of a task that raised an unexpected error (a worker that dies is Dask's business:
    its tasks are rescheduled up to ``distributed.scheduler.allowed-failures`` times)."""
    fuse: FuseConfig = field(default_factory=FuseConfig)
    """Options of the fuse step (`mapkit fuse`)."""
    esdf: EsdfConfig = field(default_factory=EsdfConfig)
    """Options of the esdf step (`mapkit esdf`)."""
    export: ExportConfig = field(default_factory=ExportConfig)
    """Options of the export step (`mapkit export`)."""

    def validate(self) -> None:
        """Raise a :class:`BatchError` (or the step's own error) naming the first bad field."""
        if not self.recordings:
            raise BatchError("no recordings given; pass paths, globs or a manifest (.toml/.json)")
        _check_steps(self.steps, "steps")
        if self.retries < 0:
            raise BatchError(f"retries={self.retries} must be >= 0")
        if isinstance(self.root, str):
            Location.of(self.root)  # an unknown protocol or missing backend is one line here
        elif self.root.exists() and not self.root.is_dir():
            raise BatchError(f"-o {self.root} is a file; pass a folder for the workspaces")
        _check_unique(self.recordings)
        for recording in self.recordings:
            recording.ingest.validate()
        self.fuse.validate()
        self.esdf.validate()
        self.export.validate()


def parse_root(text: str | Path) -> Path | str:
    """A batch root as given on the command line: an fsspec URL stays text, a local path (or a
    ``file://`` URL, whose folders rename atomically) becomes an absolute Path."""
    if not is_url(text):
        return Path(text).resolve()
    loc = Location.of(str(text))
    return loc.local.resolve() if loc.local is not None else str(text).rstrip("/")


def parse_steps(text: str) -> tuple[Step, ...]:
    """``"ingest,fuse"`` → the steps in pipeline order; an unknown or repeated name is a BatchError."""
    names = [s.strip() for s in text.split(",") if s.strip()]
    _check_steps(names, "--steps")
    return tuple(s for s in STEPS if s in names)


def _check_steps(steps: Sequence[str], option: str) -> None:
    """A BatchError naming ``option`` when ``steps`` is empty, or names an unknown step or one twice."""
    unknown = [s for s in steps if s not in STEPS]
    if unknown or not steps:
        what = f"unknown step {unknown[0]!r}" if unknown else "no step given"
        raise BatchError(f"{option}: {what}; choose from {','.join(STEPS)}")
    if len(set(steps)) != len(steps):
        raise BatchError(f"{option} {','.join(steps)} name a step twice")


def resolve_recordings(items: Sequence[str | Path], defaults: IngestConfig | None = None) -> tuple[Recording, ...]:
    """Recordings from paths, globs (``flights/*.mcap``) and manifests, each with ``defaults`` (the command
    line's ingest options) where its manifest entry gives no value; two with one name are a BatchError."""
    defaults = defaults or IngestConfig()
    out: list[Recording] = []
    for item in items:
        text = str(item)
        if text.lower().endswith(MANIFEST_SUFFIXES):
            out.extend(read_manifest(Path(text), defaults))
        elif glob.has_magic(text):
            matches = sorted(glob.glob(text))
            if not matches:
                raise BatchError(f"{text!r} matches no recording; check the pattern (quote it so the shell does not expand it)")
            out.extend(_recording(Path(m), None, defaults) for m in matches)
        else:
            out.append(_recording(Path(text), None, defaults))
    _check_unique(out)
    return tuple(out)


def _recording(path: Path, name: str | None, ingest: IngestConfig, *, where: str = "") -> Recording:
    """A Recording for an existing ``path``; ``where`` names the manifest entry in errors."""
    if not path.exists():
        raise BatchError(f"{where}recording {str(path)!r} does not exist; check the path")
    stem = path.name[: -len(path.suffix)] if path.suffix and path.is_file() else path.name
    return Recording(name=name or stem, path=path.resolve(), ingest=ingest)


def _check_unique(recordings: Sequence[Recording]) -> None:
    seen: dict[str, Path] = {}
    for r in recordings:
        if r.name in seen and seen[r.name] != r.path:
            raise BatchError(f"recordings {seen[r.name]} and {r.path} would both be workspace {r.name!r}; rename one "
                             "or give them names in a manifest (name = \"...\")")
        if r.name in seen:
            raise BatchError(f"recording {r.path} is given twice; give it once")
        if not r.name or r.name.startswith(".") or "/" in r.name or "\\" in r.name:
            raise BatchError(f"workspace name {r.name!r} of {r.path} is not a plain folder name; name it in a manifest")
        seen[r.name] = r.path


# Manifest fields of a recording entry, beside `path` and `name`: IngestConfig's fields, spelt as
# in the manifest (same names as the `mapkit ingest` options, with underscores).
_TEXT_FIELDS = ("depth_topic", "camera_info_topic", "pose_topic", "world_frame", "camera_frame", "body_frame")
_INGEST_FIELDS = {f.name for f in fields(IngestConfig)}


def read_manifest(path: Path, defaults: IngestConfig | None = None) -> list[Recording]:
    """The recordings a manifest lists (format in docs/batch.md); a bad entry is a BatchError naming
    the manifest, the entry and the field. Relative paths are relative to the manifest's folder."""
    defaults = defaults or IngestConfig()
    data = _load(path)
    if not isinstance(data, dict) or not isinstance(data.get("recordings"), list) or not data["recordings"]:
        raise BatchError(f"manifest {path}: expected a non-empty list `recordings` (see docs/batch.md)")
    extra = sorted(set(data) - {"recordings", "defaults"})
    if extra:
        raise BatchError(f"manifest {path}: unknown top-level key {extra[0]!r}; expected `recordings` and `defaults`")
    base = defaults
    if "defaults" in data:
        base = _ingest_config(data["defaults"], defaults, where=f"manifest {path}: defaults: ")
    out = []
    for i, entry in enumerate(data["recordings"], start=1):
        where = f"manifest {path}: recording {i}: "
        if not isinstance(entry, dict) or not isinstance(entry.get("path"), str):
            raise BatchError(f"{where}needs a field `path` (a string)")
        where = f"manifest {path}: recording {i} ({entry['path']}): "
        name = entry.get("name")
        if name is not None and not isinstance(name, str):
            raise BatchError(f"{where}field `name` must be a string, not {name!r}")
        options = {k: v for k, v in entry.items() if k not in ("path", "name")}
        config = _ingest_config(options, base, where=where)
        out.append(_recording(path.parent / entry["path"], name, config, where=where))
    return out


def _load(path: Path) -> Any:
    try:
        text = path.read_text()
    except OSError as exc:
        raise BatchError(f"manifest {path} cannot be read ({exc.strerror or exc}); check the path") from None
    try:
        if path.suffix.lower() == ".json":
            return json.loads(text)
        return tomllib.loads(text)
    except ValueError as exc:  # json.JSONDecodeError and tomllib.TOMLDecodeError
        raise BatchError(f"manifest {path} is not valid {path.suffix[1:].upper()}: {exc}") from None


def _ingest_config(options: Any, base: IngestConfig, *, where: str) -> IngestConfig:
    """``base`` with the manifest's ``options`` applied, each checked by type and parsed as the CLI does."""
    if not isinstance(options, dict):
        raise BatchError(f"{where}expected a table of options, not {options!r}")
    changes: dict[str, Any] = {}
    for key, value in options.items():
        if key not in _INGEST_FIELDS:
            raise BatchError(f"{where}unknown field {key!r}; expected path, name or one of {', '.join(sorted(_INGEST_FIELDS))}")
        changes[key] = _field_value(key, value, where=where)
    return replace(base, **changes)


def _field_value(key: str, value: Any, *, where: str) -> Any:
    """One manifest field as IngestConfig holds it; a wrong type or value is a BatchError naming it."""

    def bad(expected: str) -> BatchError:
        return BatchError(f"{where}field {key!r} = {value!r}: expected {expected}")

    if key in _TEXT_FIELDS:
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if key in ("intrinsics", "extrinsic"):
        if isinstance(value, list) and all(isinstance(v, (int, float)) for v in value):
            value = ",".join(str(v) for v in value)
        if not isinstance(value, str):
            raise bad("a string or a list of numbers")
        try:
            return parse_intrinsics(value) if key == "intrinsics" else parse_extrinsic(value)
        except MapkitError as exc:
            raise BatchError(f"{where}field {key!r}: {exc}") from None
    if key == "drop_nonmonotonic":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if key == "max_pose_gap":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise bad("a positive number of seconds")
        return float(value)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:  # stride, max_frames
        raise bad("an integer >= 1")
    return value
