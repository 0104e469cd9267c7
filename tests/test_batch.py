"""`mapkit batch`: each workspace equals the single commands' result, array for array; reruns skip;
failures, bad manifests, an unreachable scheduler, a held root and a killed worker are handled."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from mapkit.batch import LOCK, MARKERS, BatchConfig, BatchError, Recording, read_manifest, resolve_recordings, run_batch
from mapkit.batch import _steps as steps_module
from mapkit.batch._steps import StepJob, run_step
from mapkit.cli.main import main
from mapkit.esdf import EsdfConfig
from mapkit.export import ExportConfig
from mapkit.fusion import FuseConfig
from mapkit.ingest import IngestConfig
from mapkit.sim import SimConfig, simulate

FUSE = FuseConfig(voxel=0.1)
ESDF = EsdfConfig(voxel=0.2)
EXPORT = ExportConfig(goals_per_frame=2)
OPTIONS = ["--set", "fuse.voxel=0.1", "--set", "esdf.voxel=0.2", "--set", "export.goals_per_frame=2"]
STORES = ("frames.zarr", "map.zarr", "tuples.zarr")


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Three tiny simulated flights (MCAP) in one folder."""
    tmp = tmp_path_factory.mktemp("flights")
    return [simulate(SimConfig(world="forest", seed=seed, duration=2.0, width=64, height=48), tmp / f"flight{seed}",
                     progress=False).bag_path for seed in (1, 2, 3)]


@pytest.fixture(scope="module")
def reference(flights: list[Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Workspaces made by the single commands, in sequence, with the batch's options."""
    tmp = tmp_path_factory.mktemp("single")
    out = {}
    runner = CliRunner()
    for flight in flights:
        ws = tmp / flight.stem
        for args in (["ingest", str(flight)], ["fuse", "--voxel", "0.1"], ["esdf", "--voxel", "0.2"],
                     ["export", "--set", "goals_per_frame=2"]):
            result = runner.invoke(main, [*args, "-w", str(ws)])
            assert result.exit_code == 0, result.output
        out[flight.stem] = ws
    return out


@pytest.fixture(scope="module")
def scheduler() -> Any:
    """A two-worker local cluster shared by the Dask tests (its address is passed as --scheduler)."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        yield cluster.scheduler_address


def broken_recording(folder: Path) -> Path:
    path = folder / "broken.mcap"
    path.write_bytes(b"\x89MCAP0\r\nthis is not a recording")
    return path


def arrays(store: Path) -> dict[str, np.ndarray]:
    """Every array of a zarr group, by path (attrs, which hold versions and paths, left out)."""
    root = zarr.open_group(store, mode="r")
    return {name: np.asarray(array[...]) for name, array in root.arrays()}


def cloud_points(ws: Path) -> np.ndarray:
    import open3d as o3d

    points = np.asarray(o3d.io.read_point_cloud(str(ws / "cloud.ply")).points)
    return points[np.lexsort(points.T[::-1])]


def assert_same_workspace(ws: Path, ref: Path) -> None:
    for store in STORES:
        got, want = arrays(ws / store), arrays(ref / store)
        assert got.keys() == want.keys(), store
        for name in want:
            np.testing.assert_array_equal(got[name], want[name], err_msg=f"{store}/{name}")
    # Open3D's multi-threaded hash map orders the points by thread timing: the same points, sorted.
    np.testing.assert_array_equal(cloud_points(ws), cloud_points(ref))
    assert not [p for p in ws.iterdir() if ".partial-" in p.name or ".old-" in p.name]


def config(flights: list[Path], root: Path, **kw: Any) -> BatchConfig:
    return BatchConfig(recordings=resolve_recordings(flights), root=root, **{"fuse": FUSE, "esdf": ESDF, "export": EXPORT, **kw})


@pytest.mark.slow
def test_batch_equals_single_commands_then_skips_and_reruns_a_changed_step(
        flights: list[Path], reference: dict[str, Path], scheduler: str, tmp_path: Path) -> None:
    root = tmp_path / "root"
    first = run_batch(config(flights[:2] + [broken_recording(tmp_path)], root, scheduler=scheduler), progress=False)
    status = {r.name: r.status for r in first.results}
    assert status == {"flight1": "done", "flight2": "done", "broken": "failed"}
    assert first.failed[0].reason.startswith("ingest: ") and "broken.mcap" in first.failed[0].reason
    for flight in flights[:2]:
        assert_same_workspace(root / flight.stem, reference[flight.stem])
    again = run_batch(config(flights[:2], root, scheduler=scheduler), progress=False)
    assert [r.status for r in again.results] == ["skipped", "skipped"]
    changed = run_batch(config(flights[:1], root, scheduler=scheduler, esdf=EsdfConfig(voxel=0.25)), progress=False)
    ran = {o.step: o.status for o in changed.results[0].steps}
    assert ran == {"ingest": "skipped", "fuse": "skipped", "esdf": "done", "export": "done"}
    assert zarr.open_group(root / "flight1" / "map.zarr", mode="r").attrs["voxel_size"] == 0.25


@pytest.mark.slow
def test_cli_batch_local_cluster_reports_failures_and_exits_1(flights: list[Path], reference: dict[str, Path],
                                                             tmp_path: Path) -> None:
    """The default path: a local cluster of --workers 2; a glob and a broken recording."""
    broken_recording(tmp_path)
    root = tmp_path / "root"
    pattern = str(flights[2].parent / "flight3*.mcap")
    result = CliRunner().invoke(main, ["batch", pattern, str(tmp_path / "broken.mcap"), "-o", str(root),
                                       "--workers", "2", *OPTIONS])
    assert result.exit_code == 1, result.output
    assert "dashboard: http" in result.output
    assert "1 done, 0 skipped, 1 failed" in result.output
    assert "failed   broken: ingest: " in result.output and "Traceback" not in result.output
    assert_same_workspace(root / "flight3", reference["flight3"])
    assert not (root / LOCK).exists()


@pytest.mark.slow
def test_batch_survives_a_worker_killed_mid_task(flights: list[Path], reference: dict[str, Path], tmp_path: Path) -> None:
    """SIGKILL the worker holding an esdf task: Dask reschedules it, the outputs are still exact."""
    from distributed import Client, LocalCluster

    killed: list[str] = []

    def kill_esdf_worker(client: Client) -> None:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not killed:
            for address, keys in client.processing().items():
                if any(str(k).startswith("batch-esdf-") for k in keys):
                    pid = client.run(os.getpid, workers=[address])[address]
                    os.kill(pid, signal.SIGKILL)
                    killed.append(address)
                    return
            time.sleep(0.05)

    root = tmp_path / "root"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        killer = threading.Thread(target=kill_esdf_worker, args=(client,), daemon=True)
        killer.start()
        summary = run_batch(config(flights[:2], root, scheduler=cluster.scheduler_address), progress=False)
        killer.join(timeout=5)
    assert killed, "no esdf task was seen running"
    assert [r.status for r in summary.results] == ["done", "done"], summary.lines()
    for flight in flights[:2]:
        assert_same_workspace(root / flight.stem, reference[flight.stem])


# --- without Dask: the step logic in this process, and the errors raised before any work --------------


@pytest.fixture
def one_process(monkeypatch: pytest.MonkeyPatch) -> None:
    """run_step sets torch threads for worker processes; not for the test process."""
    monkeypatch.setattr(steps_module, "_worker_threads", lambda: None)


def test_step_skips_when_current_and_reruns_on_option_input_or_output_change(
        flights: list[Path], tmp_path: Path, one_process: None) -> None:
    flight = tmp_path / "f.mcap"
    flight.write_bytes(flights[0].read_bytes())
    ws = tmp_path / "ws"

    def ingest(**kw: Any) -> str:
        job = StepJob(name="f", recording=flight, workspace=ws, step="ingest", options=IngestConfig(**kw))
        outcome = run_step(job)
        return outcome.status if outcome.status != "done" else outcome.reason

    assert ingest() == "new"
    assert json.loads((ws / MARKERS / "ingest.json").read_text())["recording"] == str(flight)
    assert ingest() == "skipped"
    assert ingest(stride=2) == "options or input changed"
    assert ingest(stride=2) == "skipped"
    os.utime(flight, ns=(time.time_ns(), time.time_ns() + 10**9))  # the recording changed
    assert ingest(stride=2) == "options or input changed"
    (ws / "frames.zarr" / "zarr.json").write_text((ws / "frames.zarr" / "zarr.json").read_text() + " ")
    assert ingest(stride=2) == "output changed or missing"
    # A later step whose input is missing fails with the library's own one-line error.
    fuse = run_step(StepJob(name="f", recording=flight, workspace=tmp_path / "empty", step="fuse", options=FUSE))
    assert fuse.status == "failed" and "mapkit ingest" in fuse.reason
    assert run_step(StepJob(name="f", recording=flight, workspace=ws, step="esdf", options=ESDF), fuse) is fuse


def write_manifest(path: Path, body: str) -> Path:
    path.write_text(body)
    return path


def test_manifest_per_recording_options(flights: list[Path], tmp_path: Path) -> None:
    rel = os.path.relpath(flights[0], tmp_path)
    toml = write_manifest(tmp_path / "m.toml", f"""
[defaults]
pose_topic = "/odom"
[[recordings]]
path = "{rel}"
name = "first"
extrinsic = [0.1, 0, 0, 0, 0, 0, 1]
[[recordings]]
path = "{flights[1]}"
stride = 2
""")
    a, b = read_manifest(toml)
    assert (a.name, a.path, a.ingest.pose_topic) == ("first", flights[0].resolve(), "/odom")
    np.testing.assert_allclose(a.ingest.extrinsic[:3, 3], [0.1, 0, 0])
    assert (b.name, b.ingest.stride, b.ingest.extrinsic) == ("flight2", 2, None)
    as_json = write_manifest(tmp_path / "m.json", json.dumps({"recordings": [{"path": str(flights[2]), "max_frames": 5}]}))
    (c,) = resolve_recordings([as_json], IngestConfig(stride=3))
    assert (c.name, c.ingest.max_frames, c.ingest.stride) == ("flight3", 5, 3)


@pytest.mark.parametrize("entry,message", [
    ('path = "{p}"\nextrinsc = "identity"', "recording 1 ({p}): unknown field 'extrinsc'"),
    ('path = "{p}"\nextrinsic = "1,2"', "recording 1 ({p}): field 'extrinsic': extrinsic '1,2' is not x,y,z"),
    ('path = "{p}"\nstride = 0', "recording 1 ({p}): field 'stride' = 0: expected an integer >= 1"),
    ('path = "{p}"\npose_topic = 3', "recording 1 ({p}): field 'pose_topic' = 3: expected a string"),
    ('path = "nothere.mcap"', "recording 1 (nothere.mcap): recording"),
    ('name = "x"', "recording 1: needs a field `path`"),
])
def test_bad_manifest_entry_is_one_line_naming_entry_and_field(flights: list[Path], tmp_path: Path, entry: str,
                                                               message: str) -> None:
    manifest = write_manifest(tmp_path / "m.toml", "[[recordings]]\n" + entry.format(p=flights[0]) + "\n")
    result = CliRunner().invoke(main, ["batch", str(manifest), "-o", str(tmp_path / "root")])
    assert result.exit_code == 1
    line = result.output.strip()
    assert "\n" not in line and line.startswith(f"error: manifest {manifest}: ") and message.format(p=flights[0]) in line
    assert not (tmp_path / "root").exists()


def test_bad_recordings_and_steps_are_one_line_errors(flights: list[Path], tmp_path: Path) -> None:
    twin = tmp_path / "flight1.mcap"
    twin.write_bytes(b"")
    cases = [
        ([str(flights[0]), str(twin)], "would both be workspace 'flight1'"),
        ([str(tmp_path / "none*.mcap")], "matches no recording"),
        ([str(tmp_path / "absent.mcap")], "does not exist"),
        ([str(flights[0]), "--steps", "ingest,mesh"], "unknown step 'mesh'"),  # a usage error: exit 2
        ([str(tmp_path / "bad.toml")], "cannot be read"),
    ]
    write_manifest(tmp_path / "broken.toml", "[[recordings]\n")
    cases.append(([str(tmp_path / "broken.toml")], "is not valid TOML"))
    for args, message in cases:
        result = CliRunner().invoke(main, ["batch", *args, "-o", str(tmp_path / "root")])
        assert result.exit_code == (2 if "--steps" in args else 1), (args, result.output)
        assert result.output.count("\n") == 1 and message in result.output, result.output


@pytest.mark.slow
def test_unreachable_scheduler_is_one_line(flights: list[Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("mapkit._dask.CONNECT_TIMEOUT_S", 1.0)  # refused either way; not 10 s of retries
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    result = CliRunner().invoke(main, ["batch", str(flights[0]), "-o", str(tmp_path / "root"),
                                       "--scheduler", f"tcp://127.0.0.1:{port}"])
    assert result.exit_code == 1
    assert result.output.startswith(f"error: cannot reach the Dask scheduler at 'tcp://127.0.0.1:{port}'")
    assert result.output.count("\n") == 1 and "dask scheduler" in result.output
    assert not (tmp_path / "root" / LOCK).exists()


def test_root_in_use_is_one_line_naming_holder_and_a_dead_holder_is_taken_over(
        flights: list[Path], tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = tmp_path / "root"
    root.mkdir()
    host = socket.gethostname()
    (root / LOCK).write_text(json.dumps({"pid": os.getpid(), "host": host, "since": "now"}))
    result = CliRunner().invoke(main, ["batch", str(flights[0]), "-o", str(root)])
    assert result.exit_code == 1 and result.output.count("\n") == 1
    assert f"error: {root} is in use by another `mapkit batch` (pid {os.getpid()} on {host}" in result.output
    # A lock whose process is gone is taken over (with a warning) and released after.
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (root / LOCK).write_text(json.dumps({"pid": int(dead.stdout), "host": host, "since": "then"}))
    from mapkit.batch._lock import root_lock

    with root_lock(root):
        assert json.loads((root / LOCK).read_text())["pid"] == os.getpid()
    assert "taking over" in caplog.text and not (root / LOCK).exists()


def test_config_validation(flights: list[Path], tmp_path: Path) -> None:
    (tmp_path / "file").write_text("")
    rec = Recording(name="a", path=flights[0], ingest=IngestConfig())
    with pytest.raises(BatchError, match="is a file"):
        BatchConfig(recordings=(rec,), root=tmp_path / "file").validate()
    with pytest.raises(BatchError, match="given twice"):
        BatchConfig(recordings=(rec, rec), root=tmp_path).validate()
    with pytest.raises(BatchError, match="no recordings"):
        BatchConfig(recordings=(), root=tmp_path).validate()


def test_unexpected_task_errors_are_one_line() -> None:
    from distributed import KilledWorker

    from mapkit.batch._run import _unexpected

    assert _unexpected(ValueError("bad\n  thing")) == "unexpected ValueError: bad thing; report this"
    assert _unexpected(OSError(28, "No space left on device")) == "OSError: [Errno 28] No space left on device"
    assert _unexpected(KilledWorker("batch-esdf-0-abc", "tcp://w", 3)).startswith("its worker died each time it ran")


@pytest.fixture
def threaded_scheduler() -> Any:
    """Two worker threads in this process: they share its memory:// filesystem, as a cluster's workers
    share an object store."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster:
        yield cluster.scheduler_address


def download(url: str, local: Path) -> Path:
    from mapkit._stores import Location, download_tree

    download_tree(Location.of(url), local)
    return local


@pytest.mark.slow
# the map writer silences zarr's note on consolidated metadata with catch_warnings, which is not
# thread-safe: with two worker threads in one process the note can escape
@pytest.mark.filterwarnings("ignore:Consolidated metadata")
def test_batch_root_at_a_url_equals_single_commands_skips_and_reruns(
        flights: list[Path], reference: dict[str, Path], threaded_scheduler: str, tmp_path: Path) -> None:
    import fsspec

    fs = fsspec.filesystem("memory")
    root = f"memory://batch-{tmp_path.name}"
    first = run_batch(config(flights[:2] + [broken_recording(tmp_path)], root, scheduler=threaded_scheduler), progress=False)
    assert {r.name: r.status for r in first.results} == {"flight1": "done", "flight2": "done", "broken": "failed"}
    assert first.root == root and not fs.exists(f"/batch-{tmp_path.name}/{LOCK}")
    for flight in flights[:2]:
        ws = download(f"{root}/{flight.stem}", tmp_path / "down" / flight.stem)
        assert_same_workspace(ws, reference[flight.stem])
        assert {p.name for p in (ws / MARKERS).iterdir()} == {"ingest.json", "fuse.json", "esdf.json", "export.json"}
    from mapkit.batch._remote import scratch_for

    assert not scratch_for(f"{root}/flight1").parent.exists()  # every worker's scratch of the root is removed
    again = run_batch(config(flights[:2], root, scheduler=threaded_scheduler), progress=False)
    assert [r.status for r in again.results] == ["skipped", "skipped"]
    # A fuse whose files are not the ones fuse.json describes runs again, and a map that is gone is made
    # again; both make the same product file as before, so the tuples after them stay up to date.
    fs.pipe_file(f"/batch-{tmp_path.name}/flight1/cloud.ply", b"truncated")
    fs.rm(f"/batch-{tmp_path.name}/flight1/map.zarr", recursive=True)
    redo = run_batch(config(flights[:1], root, scheduler=threaded_scheduler), progress=False)
    assert {o.step: o.status for o in redo.results[0].steps} == {
        "ingest": "skipped", "fuse": "done", "esdf": "done", "export": "skipped"}
    assert_same_workspace(download(f"{root}/flight1", tmp_path / "redo"), reference["flight1"])
    # A step whose input was never made at the URL: one line naming it and the fix.
    alone = run_batch(config(flights[2:3], root, scheduler=threaded_scheduler, steps=("esdf",)), progress=False)
    assert alone.failed[0].reason == (f"esdf: {root}/flight3 has no frames.zarr/zarr.json: the ingest step has not "
                                      "run there; add ingest to --steps")
    # Another batch holding the root: one line naming it.
    fs.pipe_file(f"/batch-{tmp_path.name}/{LOCK}", json.dumps({"pid": 1, "host": "elsewhere", "since": "now"}).encode())
    result = CliRunner().invoke(main, ["batch", str(flights[0]), "-o", root, "--scheduler", threaded_scheduler])
    assert result.exit_code == 1 and result.output.count("\n") == 1
    assert f"error: {root} is in use by another `mapkit batch` (pid 1 on elsewhere" in result.output


def test_batch_root_url_without_a_backend_is_one_line(flights: list[Path]) -> None:
    result = CliRunner().invoke(main, ["batch", str(flights[0]), "-o", "nosuchfs://bucket/maps"])
    assert result.exit_code == 1 and result.output.count("\n") == 1
    assert "nosuchfs://bucket/maps" in result.output and "fsspec backend" in result.output
