"""`mapkit eval --scheduler`: pairs as Dask tasks give the same results.json; bad schedulers are one line."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from test_eval import small_config, tiny_run  # noqa: F401 - tiny_run is a fixture used by name

from mapkit.cli.main import main
from mapkit.evaluation import evaluate, load_paths


@pytest.fixture
def scheduler() -> Iterator[str]:
    """The address of a 2-worker cluster started here, as `dask scheduler` + `dask worker` would be."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        yield cluster.scheduler_address


def kill_a_busy_worker(address: str, killed: list[str]) -> None:
    """SIGKILL the first worker process seen running an evaluation task (its nanny starts another)."""
    from distributed import Client

    with Client(address) as client:
        pids = client.run(os.getpid)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not killed:
            for worker, keys in client.processing().items():
                if any(str(k).startswith("mapkit-eval-") for k in keys):
                    os.kill(pids[worker], signal.SIGKILL)
                    killed.append(worker)
                    break
            time.sleep(0.05)


@pytest.mark.slow
def test_pairs_on_a_dask_cluster_give_the_same_results_json_as_workers_even_when_one_dies(
        tiny_run: Path, scheduler: str, tmp_path: Path) -> None:  # noqa: F811 - tiny_run is a fixture
    """results.json byte for byte and every executed path array for array, with one worker killed
    while it flies a pair (the scheduler runs that pair again elsewhere). results.json holds no wall
    clock (latencies live in latency.json), so nothing is left out of the comparison."""
    evaluate(tiny_run, tmp_path / "pool", small_config(workers=2), progress=False)
    killed: list[str] = []
    killer = threading.Thread(target=kill_a_busy_worker, args=(scheduler, killed))
    killer.start()
    try:
        evaluate(tiny_run, tmp_path / "dask", small_config(scheduler=scheduler), progress=False)
    finally:
        killer.join()
    assert killed, "no worker was seen flying a pair"
    assert (tmp_path / "pool" / "results.json").read_bytes() == (tmp_path / "dask" / "results.json").read_bytes()
    a, b = load_paths(tmp_path / "pool"), load_paths(tmp_path / "dask")
    assert set(a) == set(b) and len(a) == 2 * 4
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


@pytest.mark.slow
def test_cli_scheduler_local_starts_a_cluster_and_writes_the_same_results(tiny_run: Path,  # noqa: F811 - fixture
                                                                          tmp_path: Path) -> None:
    args = ["eval", "--model", str(tiny_run), "--world", "office", "--pairs", "1", "--seed", "3",
            "--methods", "straight,oracle"]
    here = CliRunner().invoke(main, [*args, "-o", str(tmp_path / "here")])
    assert here.exit_code == 0, here.output
    dask = CliRunner().invoke(main, [*args, "--scheduler", "local", "--workers", "2", "-o", str(tmp_path / "dask")])
    assert dask.exit_code == 0, dask.output
    assert "dask: 2 worker(s) at tcp://" in dask.output and "dashboard http" in dask.output
    assert (tmp_path / "here" / "results.json").read_bytes() == (tmp_path / "dask" / "results.json").read_bytes()


def test_cli_unreachable_scheduler_is_one_line(tiny_run: Path, tmp_path: Path,  # noqa: F811 - fixture
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("mapkit._dask.CONNECT_TIMEOUT_S", 1.0)  # refused either way; not 10 s of retries
    r = CliRunner().invoke(main, ["eval", "--model", str(tiny_run), "--world", "office", "--pairs", "1",
                                  "--scheduler", "tcp://127.0.0.1:9", "-o", str(tmp_path / "ev")])
    assert r.exit_code == 1, r.output
    assert "cannot reach the Dask scheduler at 'tcp://127.0.0.1:9'" in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "ev").exists()


@pytest.mark.parametrize("args, message", [
    (["--scheduler", "not an address"], "--scheduler 'not an address' is not a Dask scheduler address"),
    (["--scheduler", "tcp://127.0.0.1:9", "--workers", "2"], "--workers 2 does nothing with --scheduler"),
])
def test_cli_bad_scheduler_settings(tiny_run: Path, tmp_path: Path,  # noqa: F811 - fixture
                                    args: list[str], message: str) -> None:
    r = CliRunner().invoke(main, ["eval", "--model", str(tiny_run), "-o", str(tmp_path / "ev"), *args])
    assert r.exit_code == 2, r.output  # a usage error
    assert message in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_a_worker_refuses_a_model_file_other_than_the_one_evaluated(tiny_run: Path) -> None:  # noqa: F811 - fixture
    """A remote worker that reads another model.pt at the run's path names itself and the fix."""
    from mapkit.evaluation import plan_runs
    from mapkit.evaluation._run import CameraSpec, EvalError, _check_worker_model, _WorkerSetup

    config = small_config()
    camera = CameraSpec(width=64, height=48, K=[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]], T_body_camera=np.eye(4).tolist(),
                        source="test")
    setup = _WorkerSetup(model=str(tiny_run.resolve()), model_sha256="0" * 64, camera=camera,
                         runs=tuple(plan_runs(config.methods, config.stacks)), config=config)
    with pytest.raises(EvalError, match=r"reads another .*model\.pt than the one evaluated.*storage every worker shares"):
        _check_worker_model(setup)
    _check_worker_model(dataclasses.replace(setup, model_sha256=hashlib.sha256((tiny_run / "model.pt").read_bytes())
                                            .hexdigest()))
