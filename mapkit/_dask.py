"""Where Dask work runs (``mapkit batch``, the chunked ESDF, ``mapkit eval --scheduler``): the given
scheduler, else ``DASK_SCHEDULER_ADDRESS``, else a loopback-only :class:`distributed.LocalCluster` of one
single-threaded worker process per available core, without Dask's statistical profiler. A scheduler that
cannot be reached is a :class:`SchedulerError` naming the address and the fix.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from mapkit.errors import MapkitError

if TYPE_CHECKING:
    from distributed import Client

log = logging.getLogger(__name__)

CONNECT_TIMEOUT_S = 10.0
LOOPBACK = "127.0.0.1"
"""The host a local cluster's sockets (scheduler, workers, dashboard) listen on."""


class SchedulerError(MapkitError):
    """A Dask scheduler that cannot be reached or used."""


def available_cpus() -> int:
    """CPU cores this process may run on (its affinity, not the machine's total)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def default_threads() -> int:
    """Threads for native work in this process: ``OMP_NUM_THREADS`` when set to a positive integer (a
    Dask worker's share of its machine, or a batch scheduler's), else the available cores."""
    text = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(text) if text.isdigit() and int(text) > 0 else available_cpus()


@dataclass(frozen=True)
class ClusterInfo:
    """What a connected client runs on, for progress lines and summaries."""

    address: str
    """The scheduler's address."""
    dashboard: str | None
    """The dashboard's URL, when the scheduler serves one."""
    workers: int
    """Workers connected when the client started."""
    local: bool
    """True for a cluster this process started (and stops)."""


def scheduler_address(scheduler: str | None) -> str | None:
    """The address to connect to: ``scheduler``, else ``DASK_SCHEDULER_ADDRESS``; None for a local cluster."""
    if scheduler:
        return scheduler
    import dask

    configured = dask.config.get("scheduler-address", default=None)
    return str(configured) if configured else None


@contextmanager
def dask_client(scheduler: str | None = None, *, workers: int | None = None) -> Iterator[tuple[Client, ClusterInfo]]:
    """A Dask client for the block, and what it runs on; a local cluster started here is stopped after.
    ``workers`` sizes a local cluster (default: one per available core); ignored with a scheduler."""
    with _quiet_distributed():
        yield from _client(scheduler_address(scheduler), workers)


@contextmanager
def _quiet_distributed() -> Iterator[None]:
    """distributed's INFO churn (start, stop, connections) only when the root logger wants INFO (-v)."""
    import distributed  # noqa: F401 - its import sets the levels this overrides

    logger = logging.getLogger("distributed")
    old = logger.level
    if logging.getLogger().getEffectiveLevel() > logging.INFO:
        logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(old)


def _client(address: str | None, workers: int | None) -> Iterator[tuple[Client, ClusterInfo]]:
    """The body of :func:`dask_client`."""
    import dask
    from distributed import Client, LocalCluster

    if address is None:
        n = workers if workers is not None else available_cpus()
        if n < 1:
            raise SchedulerError(f"workers={n} must be at least 1")
        # Processes (the stages hold the GIL in places; a dying worker stays isolated), one task each;
        # native threads from _worker_environ. Loopback only: the dashboard shows tasks and their code.
        environ = _worker_environ(n)
        with _worker_environment(environ), dask.config.set({"distributed.nanny.pre-spawn-environ": environ,
                                                           "distributed.worker.profile.enabled": False}), \
                LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host=LOOPBACK,
                             dashboard_address=f"{LOOPBACK}:0",
                             silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
            yield client, _info(client, local=True)
        return
    try:
        client = Client(address, timeout=f"{CONNECT_TIMEOUT_S}s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise SchedulerError(
            f"cannot reach the Dask scheduler at {address!r} ({type(exc).__name__}); start one with "
            "`dask scheduler` (and `dask worker ADDRESS`), or drop --scheduler / unset DASK_SCHEDULER_ADDRESS "
            "to run on this machine") from None
    with client:
        yield client, _info(client, local=False)


def _worker_environ(workers: int) -> dict[str, Any]:
    """The environment Dask's nanny gives local workers, less its ``MALLOC_TRIM_THRESHOLD_`` (which makes
    every large numpy temporary an mmap, faulted in and unmapped again), with the thread limits (OMP, MKL,
    OpenBLAS) set to the cores shared among the ``workers`` instead of Dask's 1."""
    import dask

    environ = dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {}
    threads = max(1, available_cpus() // workers)
    out = {k: v for k, v in dict(environ).items() if k != "MALLOC_TRIM_THRESHOLD_"}
    out.update({k: threads for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")})
    return out


@contextmanager
def _worker_environment(environ: dict[str, Any]) -> Iterator[None]:
    """This process's environment set to ``environ`` while a local cluster runs, and restored after: a
    nanny reads its variables from this environment before its config and writes them back for good.
    A ``MALLOC_TRIM_THRESHOLD_`` of the user's own (not Dask's default) reaches the workers."""
    import dask

    key = "MALLOC_TRIM_THRESHOLD_"
    # Dask's shipped default, not the current config (which a cluster of ours, open around this one, has changed)
    shipped = dask.config.merge(*dask.config.defaults)
    dasks = (dask.config.get("distributed.nanny.pre-spawn-environ", default={}, config=shipped) or {}).get(key)
    names = set(environ) | {key}
    before = {name: os.environ.get(name) for name in names}
    if dasks is not None and before[key] == str(dasks):
        del os.environ[key]
    os.environ.update({name: str(value) for name, value in environ.items()})
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _info(client: Client, *, local: bool) -> ClusterInfo:
    """Address, dashboard and worker count of a connected client."""
    try:
        dashboard: str | None = client.dashboard_link
    except (KeyError, AttributeError):  # a scheduler without the dashboard (no bokeh)
        dashboard = None
    scheduler = client.scheduler_info()
    return ClusterInfo(address=str(scheduler.get("address", "")), dashboard=dashboard,
                       workers=len(scheduler.get("workers", {})), local=local)


def compute_tasks(tasks: list[Any], client: Client | None, *, desc: str, unit: str, progress: bool,
                  local_threads: int = 1) -> list[Any]:
    """Results of Dask ``tasks`` (delayed objects) in order, with a tqdm bar (done, rate, ETA).

    ``client`` None runs them in this process, no cluster to start: on Dask's synchronous scheduler
    (``local_threads`` 1) or its threaded one with that many threads; else on the client's cluster.
    The first task that fails raises its own exception here (the others are cancelled).
    """
    from tqdm import tqdm

    bar = tqdm(total=len(tasks), unit=unit, desc=desc, disable=not progress, dynamic_ncols=True)
    try:
        if client is None:
            import dask
            from dask.callbacks import Callback

            keys = {task.key for task in tasks}

            def done(key: Any, *_: Any) -> None:
                if key in keys:
                    bar.update(1)

            with Callback(posttask=done):
                if local_threads > 1:
                    return list(dask.compute(*tasks, scheduler="threads", num_workers=local_threads))
                return list(dask.compute(*tasks, scheduler="sync"))
        from distributed import as_completed

        futures = client.compute(tasks)
        try:
            for future in as_completed(futures):
                future.result()  # the task's own exception, raised here
                bar.update(1)
        except BaseException:
            client.cancel(futures)
            raise
        return [f.result() for f in futures]
    finally:
        bar.close()
