"""`run_batch`: one Dask task per recording per step, each depending on the step before it."""

from __future__ import annotations

import logging
import sys
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapkit._dask import ClusterInfo, dask_client
from mapkit.batch import _remote
from mapkit.batch._config import BatchConfig, Recording, parse_root
from mapkit.batch._lock import root_lock
from mapkit.batch._steps import Status, StepJob, StepOutcome, run_step

if TYPE_CHECKING:
    from distributed import Client, Future

    from mapkit.esdf import EsdfConfig
    from mapkit.export import ExportConfig
    from mapkit.fusion import FuseConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RecordingResult:
    """What the batch did with one recording."""

    name: str
    """Workspace name (``ROOT/<name>``)."""
    recording: Path
    """The recording."""
    status: Status
    """failed if a step failed; done if any step ran; skipped if every step was up to date."""
    reason: str
    """For a failure the step and its one-line error; else which steps ran and why."""
    steps: tuple[StepOutcome, ...]
    """The outcome of each step that got to run or be skipped."""


@dataclass(frozen=True)
class BatchSummary:
    """A finished batch."""

    root: Path | str
    """The batch root (a path, or a URL)."""
    results: tuple[RecordingResult, ...]
    """One per recording, in the order given."""
    seconds: float
    """Wall time from connecting to the last result."""
    cluster: ClusterInfo
    """Where it ran."""

    def having(self, status: Status) -> tuple[RecordingResult, ...]:
        """The results with this status."""
        return tuple(r for r in self.results if r.status == status)

    @property
    def failed(self) -> tuple[RecordingResult, ...]:
        return self.having("failed")

    def lines(self) -> list[str]:
        """The summary as printed by `mapkit batch`: a count line, then one line per recording."""
        counts = ", ".join(f"{len(self.having(s))} {s}" for s in ("done", "skipped", "failed"))
        head = (f"batch {self.root}: {len(self.results)} recording(s) in {self.seconds:.1f} s on "
                f"{self.cluster.workers} worker(s): {counts}")
        return [head] + [f"  {r.status:<8} {r.name}: {r.reason}" for r in self.results]


def run_batch(config: BatchConfig, *, progress: bool = True) -> BatchSummary:
    """Run ``config.steps`` for every recording on Dask; each gets ``ROOT/<name>/``, a normal workspace.

    Up-to-date steps are skipped (see :mod:`mapkit.batch._steps`); a recording that fails is reported
    and the others go on. Raises a BatchError before any work for bad config or a root in use, and a
    SchedulerError for a scheduler that cannot be reached.
    """
    config.validate()
    root = parse_root(config.root)
    with root_lock(root), dask_client(config.scheduler, workers=config.workers) as (client, info):
        t0 = time.perf_counter()
        _announce(config, info, progress=progress)
        chains = _submit(client, config, root)
        results = _collect(config.recordings, chains, progress=progress)
        if isinstance(root, str):
            client.run(_remote.drop_root_scratch, root)
        return BatchSummary(root=root, results=results, seconds=time.perf_counter() - t0, cluster=info)


def _announce(config: BatchConfig, info: ClusterInfo, *, progress: bool) -> None:
    where = "a local cluster" if info.local else info.address
    line = (f"batch: {len(config.recordings)} recording(s), steps {','.join(config.steps)}, on {where} with "
            f"{info.workers} worker(s); dashboard: {info.dashboard or 'none (install bokeh)'}")
    if progress:
        print(line, file=sys.stderr, flush=True)
    log.info(line)


def _submit(client: Client, config: BatchConfig, root: Path | str) -> list[list[Future]]:
    """Per recording, its chain of step futures (each task takes the previous step's outcome)."""
    token = uuid.uuid4().hex[:8]  # keys unique to this run on a shared scheduler
    options: dict[str, FuseConfig | EsdfConfig | ExportConfig] = {"fuse": config.fuse, "esdf": config.esdf, "export": config.export}
    chains = []
    n = len(config.recordings)
    for i, rec in enumerate(config.recordings):
        previous: Future | None = None
        chain = []
        workspace = f"{root}/{rec.name}" if isinstance(root, str) else root / rec.name
        for step in config.steps:
            job = StepJob(name=rec.name, recording=rec.path.resolve(), workspace=workspace, step=step,
                          options=rec.ingest if step == "ingest" else options[step], last=step == config.steps[-1])
            # Earlier recordings first, so whole workspaces finish steadily (progress, partial results).
            previous = client.submit(run_step, job, previous, key=f"batch-{step}-{i}-{token}",
                                     retries=config.retries, priority=n - i, pure=False)
            chain.append(previous)
        chains.append(chain)
    return chains


def _collect(recordings: Sequence[Recording], chains: list[list[Future]], *, progress: bool) -> tuple[RecordingResult, ...]:
    """Wait for every chain (progress per finished recording) and summarise each."""
    from distributed import as_completed
    from tqdm import tqdm

    index = {chain[-1].key: i for i, chain in enumerate(chains)}
    results: list[RecordingResult | None] = [None] * len(chains)
    counts = {"done": 0, "skipped": 0, "failed": 0}
    with tqdm(total=len(chains), unit="flight", desc="batch", disable=not progress, dynamic_ncols=True) as bar:
        for future in as_completed([chain[-1] for chain in chains]):
            i = index[future.key]
            result = _result(recordings[i], chains[i])
            results[i] = result
            counts[result.status] += 1
            bar.set_postfix(counts, refresh=False)
            bar.update(1)
    return tuple(r for r in results if r is not None)


def _result(recording: Recording, chain: list[Future]) -> RecordingResult:
    """One recording's result from its finished chain."""
    outcomes: list[StepOutcome] = []
    for future in chain:
        if future.status != "finished":
            why = (_unexpected(future.exception()) if future.status == "error" else
                   f"{future.status} (the scheduler lost the task); rerun the batch to resume")
            return RecordingResult(recording.name, recording.path, "failed", f"{_step_of(future)}: {why}",
                                   tuple(outcomes))
        outcome: StepOutcome = future.result()
        if outcome.status == "failed":
            return RecordingResult(recording.name, recording.path, "failed", f"{outcome.step}: {outcome.reason}",
                                   tuple(outcomes) + (outcome,))
        outcomes.append(outcome)
    ran = [o for o in outcomes if o.status == "done"]
    if not ran:
        return RecordingResult(recording.name, recording.path, "skipped", "up to date", tuple(outcomes))
    reason = ", ".join(f"{o.step} ({o.reason}, {o.seconds:.1f} s)" for o in ran)
    return RecordingResult(recording.name, recording.path, "done", reason, tuple(outcomes))


def _step_of(future: Future) -> str:
    return str(future.key).split("-")[1]


def _unexpected(exc: Any) -> str:
    """One line for an exception a task raised (after its retries) or a worker death."""
    from distributed import KilledWorker

    if isinstance(exc, KilledWorker):
        return ("its worker died each time it ran (out of memory, or killed); give workers more memory "
                "or raise distributed.scheduler.allowed-failures")
    text = " ".join(str(exc).split())
    if isinstance(exc, OSError):
        return f"{type(exc).__name__}: {text}"
    return f"unexpected {type(exc).__name__}: {text}; report this"
