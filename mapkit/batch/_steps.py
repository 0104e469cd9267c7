"""One step of one recording, as a Dask task: skipped when its marker ``WS/.batch/<step>.json`` says it
is up to date, else run as the single command runs it, the marker written last. The marker holds the
step's *key* (a digest of its options and its input: the recording, or the product of the step before)
and its *product* (a digest of the small file that identifies its complete output, :data:`PRODUCTS`).
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal

from mapkit import _staging
from mapkit.batch import _remote
from mapkit.batch._config import BatchError, Step
from mapkit.errors import MapkitError
from mapkit.esdf import MAP, EsdfConfig
from mapkit.export import TUPLES, ExportConfig
from mapkit.fusion import FUSE_META, FuseConfig, check_fused
from mapkit.ingest import IngestConfig
from mapkit.ingest._store import source_fingerprint
from mapkit.workspace import FRAMES, atomic_output

MARKERS = ".batch"
"""Folder in each workspace holding one marker per step (written last, atomically)."""

PRODUCTS: dict[Step, str] = {
    "ingest": f"{FRAMES}/zarr.json",
    "fuse": FUSE_META,
    "esdf": f"{MAP}/zarr.json",
    "export": f"{TUPLES}/zarr.json",
}
"""The file (relative to the workspace) whose bytes identify each step's complete output."""

PREVIOUS: dict[Step, Step] = {"fuse": "ingest", "esdf": "fuse", "export": "esdf"}
"""The step whose product each later step reads."""

Status = Literal["done", "skipped", "failed"]


@dataclass(frozen=True)
class StepJob:
    """What one task needs: the recording, its workspace, the step and that step's options."""

    name: str
    """The recording's workspace name."""
    recording: Path
    """The recording (absolute)."""
    workspace: Path | str
    """``ROOT/<name>``: an absolute path, or a URL (the step then runs in a local scratch workspace,
    see :mod:`mapkit.batch._remote`)."""
    step: Step
    """The step to run."""
    options: IngestConfig | FuseConfig | EsdfConfig | ExportConfig
    """That step's options."""
    last: bool = False
    """The recording's last step: with a URL workspace, the worker's scratch copy goes after it."""


@dataclass(frozen=True)
class StepOutcome:
    """What a task did."""

    name: str
    """The recording's workspace name."""
    step: Step
    """The step (for a failure passed down the chain: the step that failed)."""
    status: Status
    """done (ran), skipped (up to date), failed (a MapkitError; ``reason`` says which)."""
    reason: str = ""
    """Why it ran (new, options or input changed, output changed) or the one-line error."""
    seconds: float = 0.0
    """Wall time of the task."""


def run_step(job: StepJob, previous: StepOutcome | None = None) -> StepOutcome:
    """The task: skip, or run the step and write its marker; a failed ``previous`` step is passed on. A
    MapkitError comes back as a failed outcome; anything else raises, so Dask retries it."""
    t0 = time.perf_counter()
    try:
        if previous is not None and previous.status == "failed":
            return previous
        key = step_key(job)
        why = stale_reason(job, key)
        if why is None:
            return StepOutcome(job.name, job.step, "skipped", "up to date", time.perf_counter() - t0)
        _worker_threads()
        _remove_marker(job)
        if isinstance(job.workspace, str):
            _run_at_url(job, job.workspace)
        else:
            _run_library(job)
        _write_marker(job, key)
    except MapkitError as exc:
        return StepOutcome(job.name, job.step, "failed", " ".join(str(exc).split()), time.perf_counter() - t0)
    finally:
        if job.last and isinstance(job.workspace, str):
            _remote.drop_scratch(job.workspace)
    return StepOutcome(job.name, job.step, "done", why, time.perf_counter() - t0)


def _run_at_url(job: StepJob, url: str) -> None:
    """The step in this worker's scratch workspace, between bringing in what it reads and publishing
    what it made (:mod:`mapkit.batch._remote`)."""
    scratch = _remote.stage_in(url, job.step, PRODUCTS)
    _run_library(replace(job, workspace=scratch))
    _remote.stage_out(url, job.step, scratch)


def _worker_threads() -> None:
    """A torch already loaded gets the worker's share of the cores (``OMP_NUM_THREADS``, which the local
    cluster sets and numpy's BLAS, Open3D and the EDT follow). The steps never import torch: importing
    it only for this costs seconds per worker, at start and exit."""
    torch = sys.modules.get("torch")
    if torch is not None:
        from mapkit._dask import default_threads

        torch.set_num_threads(default_threads())


def _digest(payload: Any) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


def _options(options: Any) -> Any:
    """A step's options as plain JSON (arrays as lists), so the key changes exactly when they do."""
    raw = options.to_attrs() if isinstance(options, IngestConfig) else asdict(options)
    return json.loads(json.dumps(raw, default=lambda v: v.tolist()))


def _read(workspace: Path | str, rel: str) -> bytes | None:
    """A file of the workspace (local or at a URL), None when it is not there."""
    if isinstance(workspace, str):
        return _staging.read_bytes(workspace, rel)
    try:
        return (workspace / rel).read_bytes()
    except FileNotFoundError:
        return None


def product_digest(workspace: Path | str, step: Step) -> str | None:
    """sha256 of the step's product file, None when there is none (the step never completed)."""
    data = _read(workspace, PRODUCTS[step])
    return None if data is None else hashlib.sha256(data).hexdigest()


def step_key(job: StepJob) -> str:
    """Digest of what the step's output depends on: its options and its input (see the module doc)."""
    if job.step == "ingest":
        if not job.recording.exists():
            raise BatchError(f"recording {job.recording} does not exist (any more); check the path")
        source: Any = source_fingerprint(job.recording)
    else:
        source = product_digest(job.workspace, PREVIOUS[job.step])
    return _digest({"step": job.step, "options": _options(job.options), "input": source})


def stale_reason(job: StepJob, key: str) -> str | None:
    """Why the step must run (new, options or input changed, output changed), None when it is up to date."""
    raw = _read(job.workspace, f"{MARKERS}/{job.step}.json")
    if raw is None:
        return "new"
    try:
        seen = json.loads(raw)
    except ValueError:
        return "marker unreadable"
    if seen.get("key") != key:
        return "options or input changed"
    if seen.get("product") != product_digest(job.workspace, job.step):
        return "output changed or missing"
    if job.step == "fuse":  # fuse.json is a file beside others: their sizes must still match
        if isinstance(job.workspace, str):
            return None if _staging.file_set_complete(job.workspace, FUSE_META) else "output incomplete"
        try:
            check_fused(job.workspace)
        except MapkitError:
            return "output incomplete"
    return None


def _remove_marker(job: StepJob) -> None:
    rel = f"{MARKERS}/{job.step}.json"
    if isinstance(job.workspace, str):
        _staging.remove(job.workspace, rel)
    else:
        (job.workspace / rel).unlink(missing_ok=True)


def _write_marker(job: StepJob, key: str) -> None:
    product = product_digest(job.workspace, job.step)
    if product is None:
        raise BatchError(f"{job.step} of {job.workspace} left no {PRODUCTS[job.step]}; report this")
    record = {"step": job.step, "key": key, "product": product, "recording": str(job.recording),
              "options": _options(job.options)}
    text = json.dumps(record, indent=2)
    if isinstance(job.workspace, str):
        _staging.write_bytes(job.workspace, f"{MARKERS}/{job.step}.json", text.encode())
        return
    with atomic_output(job.workspace / MARKERS / f"{job.step}.json", overwrite=True) as tmp:
        tmp.write_text(text)


def _run_library(job: StepJob) -> None:
    """The same library call as `mapkit ingest`, `mapkit fuse -w WS` (the workspace's frames), `mapkit esdf`
    or `mapkit export`, with --overwrite: the key said the output is stale."""
    from mapkit.esdf import build_esdf
    from mapkit.export import export_tuples
    from mapkit.fusion import fuse
    from mapkit.ingest import ingest

    options: Any = job.options
    if job.step == "ingest":
        ingest([job.recording], job.workspace, options, overwrite=True, progress=False)
    elif job.step == "fuse":
        fuse([], job.workspace, options, overwrite=True, progress=False)
    elif job.step == "esdf":
        build_esdf(job.workspace, options, overwrite=True, progress=False)
    else:
        export_tuples(job.workspace, options, overwrite=True, progress=False)
