"""The chunked ESDF as a Dask graph: equal to the in-core path bit for bit, in this process and on a cluster."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scenes import box_world, orbit_poses, record_scene
from test_esdf import random_scene

import mapkit.esdf._build as build
from mapkit._dask import available_cpus, dask_client
from mapkit.cli.main import main
from mapkit.esdf import (
    EsdfConfig,
    EsdfError,
    EsdfMap,
    build_esdf,
    create_map,
    signed_distance,
    signed_distance_chunked,
    smooth,
)
from mapkit.fusion import FuseConfig, fuse


@pytest.fixture(scope="module")
def client():
    with dask_client(None, workers=2) as (c, _):
        yield c


@pytest.fixture(scope="module")
def box_ws(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("box")
    flight = record_scene(box_world(), tmp / "box.mcap", orbit_poses(36))
    fuse([flight], tmp / "ws", FuseConfig(voxel=0.05), progress=False)
    return tmp / "ws"


@pytest.mark.parametrize(("shape", "chunk", "sigma"), [((70, 53, 41), 16, 0.2), ((97, 61, 33), 24, 0.3), ((45, 130, 17), 8, 0.1)])
def test_chunks_equal_the_whole_grid_bit_for_bit(shape: tuple[int, int, int], chunk: int, sigma: float) -> None:
    """Every chunking gives the whole-grid field exactly, the smoothed one included (the Gaussian's
    products do not depend on where a voxel sits in the grid)."""
    occ = random_scene(shape, seed=sum(shape), boxes=20)
    vs, md = 0.1, 0.5
    raw = signed_distance(occ, voxel_size=vs, max_dist=md)
    esdf, n = smooth(raw, voxel_size=vs, sigma=sigma)
    for local_workers in (1, 2):  # synchronous, then threaded scheduler
        out, out_raw = np.full(shape, np.nan, np.float32), np.full(shape, np.nan, np.float32)
        s = signed_distance_chunked(occ, out, out_raw=out_raw, voxel_size=vs, max_dist=md, sigma=sigma, chunk=chunk,
                                    progress=False, local_workers=local_workers)
        np.testing.assert_array_equal(out_raw, raw)
        np.testing.assert_array_equal(out, esdf)
        assert s.n_prevented == n and s.workers == 1 and s.peak_rss_bytes > 0


@pytest.mark.slow
def test_on_a_local_cluster_into_map_zarr(tmp_path: Path, client) -> None:
    occ = random_scene((140, 100, 70), seed=3, boxes=30)
    vs, md, sigma = 0.1, 0.5, 0.2
    raw = signed_distance(occ, voxel_size=vs, max_dist=md)
    esdf, n = smooth(raw, voxel_size=vs, sigma=sigma)
    with create_map(tmp_path / "map.zarr", shape=occ.shape, origin=(0, 0, 0), voxel_size=vs, frame_id="world",
                    sigma=sigma, unknown_policy="free") as w:
        s = signed_distance_chunked(occ, w.esdf, out_raw=w.esdf_raw, voxel_size=vs, max_dist=md, sigma=sigma,
                                    chunk=64, threads=1, client=client, progress=False)
        w.observed[:] = 1
    m = EsdfMap.open(tmp_path / "map.zarr")
    np.testing.assert_array_equal(m.esdf_raw[:], raw)
    np.testing.assert_array_equal(m.esdf[:], esdf)
    assert s.chunks == 3 * 2 * 2 and s.n_prevented == n and s.workers == 2


def test_local_workers_start_without_the_profiler_and_the_malloc_setting(client, monkeypatch: pytest.MonkeyPatch) -> None:
    def worker_settings() -> tuple[bool, str | None, str | None]:
        import os

        import dask

        return (bool(dask.config.get("distributed.worker.profile.enabled")), os.environ.get("MALLOC_TRIM_THRESHOLD_"),
                os.environ.get("OMP_NUM_THREADS"))

    cores = available_cpus()  # shared among the workers by the native libraries' thread limits
    assert set(client.run(worker_settings).values()) == {(False, None, str(max(1, cores // 2)))}
    # What a LocalCluster with Dask's defaults, started earlier in this process, leaves behind; and a
    # cluster of ours (`client`) is open around the new one.
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "65536")
    omp = os.environ.get("OMP_NUM_THREADS")
    with dask_client(None, workers=1) as (c, _):
        assert set(c.run(worker_settings).values()) == {(False, None, str(cores))}
    assert os.environ["MALLOC_TRIM_THRESHOLD_"] == "65536" and os.environ.get("OMP_NUM_THREADS") == omp


def test_a_local_cluster_listens_on_loopback_only(client) -> None:
    """The scheduler, the workers and the dashboard of a cluster we start take no socket that the
    machine's network can reach (Dask's dashboard alone binds every interface unless told a host)."""
    import ipaddress
    from urllib.parse import urlparse

    import psutil

    info = client.scheduler_info()
    hosts = {urlparse(a).hostname for a in [info["address"], *info["workers"]]}
    assert hosts == {"127.0.0.1"}
    port = urlparse(client.dashboard_link).port
    listening = [c for c in psutil.Process().net_connections(kind="inet")
                 if c.status == psutil.CONN_LISTEN and c.laddr.port == port]
    assert listening, f"no socket listens on the dashboard's port {port}"
    assert all(ipaddress.ip_address(c.laddr.ip).is_loopback for c in listening), [c.laddr for c in listening]


def test_numpy_destinations_are_refused_on_a_cluster(client) -> None:
    occ = random_scene((20, 20, 20), seed=1)
    with pytest.raises(EsdfError, match="numpy array, which Dask workers cannot write"):
        signed_distance_chunked(occ, np.zeros(occ.shape, np.float32), voxel_size=0.1, max_dist=0.3, client=client, progress=False)


def _arrays(ws: Path) -> dict[str, np.ndarray]:
    m = EsdfMap.open(ws / "map.zarr")
    return {"esdf": np.asarray(m.esdf[:]), "esdf_raw": np.asarray(m.esdf_raw[:]), "observed": np.asarray(m.observed[:])}


@pytest.mark.slow
@pytest.mark.parametrize("unknown", ["free", "occupied"])
def test_build_esdf_on_dask_equals_the_in_core_path(box_ws: Path, unknown: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """`mapkit esdf --workers N` / `--scheduler` give the in-core map exactly (same max_dist, without the
    sub-voxel refinement that only the in-core path has): esdf, esdf_raw and observed, array for array."""
    config = EsdfConfig(voxel=0.1, sigma=0.1, max_dist=0.8, unknown=unknown, subvoxel=False)
    build_esdf(box_ws, config, overwrite=True, progress=False)
    dense = _arrays(box_ws)
    assert EsdfMap.open(box_ws / "map.zarr").attrs["parameters"].get("chunked") is None
    monkeypatch.setattr(build, "_CHUNK", 64)  # several chunks on this small grid
    for workers in (1, 2):
        s = build_esdf(box_ws, config, overwrite=True, progress=False, workers=workers)
        assert s.chunked is not None and s.chunked.chunks > 1 and s.chunked.workers == workers
        chunked = _arrays(box_ws)
        for name in ("esdf", "esdf_raw", "observed"):
            np.testing.assert_array_equal(chunked[name], dense[name], err_msg=f"{name} with {workers} workers")
        assert EsdfMap.open(box_ws / "map.zarr").attrs["parameters"]["chunked"] is True


@pytest.mark.slow
def test_cli_esdf_workers_and_an_unreachable_scheduler(box_ws: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    monkeypatch.setattr("mapkit._dask.CONNECT_TIMEOUT_S", 1.0)  # refused either way; not 10 s of retries
    runner = CliRunner()
    result = runner.invoke(main, ["esdf", "-w", str(box_ws), "--workers", "1", "--set", "max_dist=0.8", "--overwrite"])
    assert result.exit_code == 0, result.output
    assert "on 1 Dask worker(s)" in result.output
    result = runner.invoke(main, ["esdf", "-w", str(box_ws), "--scheduler", "tcp://127.0.0.1:9", "--overwrite"])
    assert result.exit_code == 1
    assert "cannot reach the Dask scheduler at 'tcp://127.0.0.1:9'" in result.output
    assert "Traceback" not in result.output and len(result.output.strip().splitlines()) == 1  # before any work
    result = runner.invoke(main, ["esdf", "-w", str(box_ws), "--workers", "0"])
    assert result.exit_code != 0 and "Traceback" not in result.output
