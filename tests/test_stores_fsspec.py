"""Stores at fsspec URLs (issue 15, part 3): frames/map/tuples through memory:// and file:// equal the local
stores array for array; a store without its published root zarr.json is refused; an interrupted write
never publishes; --overwrite; training's loader on memory:// with per-rank sharding; one-line errors."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import fsspec
import numpy as np
import pytest
import torch
import zarr
from click.testing import CliRunner

from mapkit._stores import Location, StoreError, copy_store
from mapkit.cli.main import main
from mapkit.esdf import EsdfConfig, EsdfError, EsdfMap, build_esdf, create_map
from mapkit.export import ExportConfig, export_tuples, map_digest
from mapkit.fusion import FuseConfig, fuse
from mapkit.ingest import IngestError, ingest, open_frames_store
from mapkit.sim import SimConfig, simulate
from mapkit.train import TrainDataError, TupleSamples, TupleStore, preset, train
from mapkit.workspace import WorkspaceError

EXPORT = ExportConfig(goals_per_frame=3, seed=1)


@pytest.fixture(scope="module")
def local(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(recording, workspace) with frames.zarr, map.zarr and tuples.zarr made by the local path."""
    tmp = tmp_path_factory.mktemp("stores")
    result = simulate(SimConfig(world="forest", seed=2, duration=6.0, width=64, height=48), tmp / "flight", progress=False)
    ws = tmp / "ws"
    fuse([result.bag_path], ws, FuseConfig(voxel=0.1), progress=False)
    build_esdf(ws, EsdfConfig(voxel=0.2, sigma=0.0), progress=False)
    export_tuples(ws, EXPORT, progress=False)
    return result.bag_path, ws


@pytest.fixture
def mem() -> Iterator[str]:
    """A fresh memory:// workspace URL, removed afterwards (the memory filesystem is process-wide)."""
    url = f"memory://mapkit-test-{uuid.uuid4().hex[:8]}/ws"
    yield url
    fs = fsspec.filesystem("memory")
    root = url.split("://", 1)[1].split("/", 1)[0]
    if fs.exists(f"/{root}"):
        fs.rm(f"/{root}", recursive=True)


def _assert_same_group(a: zarr.Group, b: zarr.Group, *, skip_attrs: tuple[str, ...] = ()) -> None:
    """Every array equal (values, dtype, chunks) and the attrs equal except `skip_attrs`."""
    names = sorted(k for k, v in a.members(max_depth=None) if isinstance(v, zarr.Array))
    assert names == sorted(k for k, v in b.members(max_depth=None) if isinstance(v, zarr.Array))
    for name in names:
        x, y = a[name], b[name]
        assert (x.dtype, x.shape, x.chunks) == (y.dtype, y.shape, y.chunks), name
        np.testing.assert_array_equal(x[...], y[...], err_msg=name)
    assert {k: v for k, v in a.attrs.items() if k not in skip_attrs} == {k: v for k, v in b.attrs.items() if k not in skip_attrs}


def _group(where: str | Path) -> zarr.Group:
    return zarr.open_group(Location.of(where).zarr_store(read_only=True), mode="r")


@pytest.mark.parametrize("scheme", ["memory", "file"])
def test_frames_at_a_url_equal_the_local_store(local: tuple[Path, Path], tmp_path: Path, mem: str, scheme: str) -> None:
    bag, _ = local
    ingest([bag], tmp_path / "ref", progress=False)
    url = mem if scheme == "memory" else f"file://{tmp_path / 'viaurl'}"
    summary = ingest([bag], url, progress=False)
    assert str(summary.path).endswith("frames.zarr")
    _assert_same_group(_group(tmp_path / "ref" / "frames.zarr"), _group(f"{url}/frames.zarr"))
    store = open_frames_store(url)
    np.testing.assert_array_equal(store.depth[:], open_frames_store(tmp_path / "ref").depth[:])


def test_map_and_tuples_at_a_url_equal_the_local_stores(local: tuple[Path, Path], mem: str, tmp_path: Path) -> None:
    _, ws = local
    for name in ("frames.zarr", "map.zarr"):
        copy_store(ws / name, f"{mem}/{name}")
    _assert_same_group(_group(ws / "map.zarr"), _group(f"{mem}/map.zarr"))
    assert map_digest(f"{mem}/map.zarr") == map_digest(ws / "map.zarr")
    remote, here = EsdfMap.open(f"{mem}/map.zarr"), EsdfMap.open(ws / "map.zarr")
    points = here.origin + here.voxel_size * np.array([[1, 2, 3], [5, 4, 2]]) + 0.03
    np.testing.assert_array_equal(remote.query(points)[0], here.query(points)[0])
    result = CliRunner().invoke(main, ["slice", "-w", mem, "-o", str(tmp_path / "s.png"), "--z", "1.0"])
    assert result.exit_code == 0 and (tmp_path / "s.png").stat().st_size > 0, result.output
    export_tuples(mem, EXPORT, progress=False)
    _assert_same_group(_group(ws / "tuples.zarr"), _group(f"{mem}/tuples.zarr"), skip_attrs=("map", "frames"))
    attrs = dict(_group(f"{mem}/tuples.zarr").attrs)
    assert attrs["map"]["path"] == f"{mem}/map.zarr" and attrs["frames"] == f"{mem}/frames.zarr"


def test_map_writer_streams_into_a_url(local: tuple[Path, Path], mem: str) -> None:
    """The chunk-by-chunk writer (what the chunked/Dask ESDF fills) publishes at a URL like locally."""
    here = EsdfMap.open(local[1] / "map.zarr")
    with create_map(f"{mem}/map.zarr", shape=here.shape, origin=here.origin, voxel_size=here.voxel_size,
                    frame_id=here.frame_id, sigma=here.sigma, unknown_policy=here.unknown_policy) as w:
        assert not Location.of(f"{mem}/map.zarr").exists()  # nothing at the name until finalize
        w.esdf[...] = here.read("esdf", ...)
        w.esdf_raw[...] = here.read("esdf_raw", ...)
        w.observed[...] = here.read("observed", ...)
    remote = EsdfMap.open(f"{mem}/map.zarr")
    for name in ("esdf", "esdf_raw", "observed"):
        np.testing.assert_array_equal(remote.read(name, ...), here.read(name, ...))


def test_a_store_without_its_root_metadata_is_refused(local: tuple[Path, Path], mem: str) -> None:
    _, ws = local
    for name in ("frames.zarr", "map.zarr", "tuples.zarr"):
        copy_store(ws / name, f"{mem}/{name}")
        fsspec.filesystem("memory").rm_file(f"{Location.of(mem).path}/{name}/zarr.json")
    with pytest.raises(IngestError, match=r"incomplete \(no completion marker"):
        open_frames_store(mem)
    with pytest.raises(EsdfError, match=r"incomplete \(no completion marker.*mapkit esdf --overwrite"):
        EsdfMap.open(f"{mem}/map.zarr")
    with pytest.raises(TrainDataError, match=r"incomplete \(no completion marker.*mapkit export"):
        TupleStore.open(mem)
    result = CliRunner().invoke(main, ["export", "-w", mem])
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "incomplete (no completion marker" in lines[0] and "Traceback" not in result.output


def test_an_interrupted_write_never_publishes(local: tuple[Path, Path], mem: str) -> None:
    _, ws = local
    here = EsdfMap.open(ws / "map.zarr")
    fs = fsspec.filesystem("memory")
    kw = dict(shape=here.shape, origin=here.origin, voxel_size=here.voxel_size, frame_id=here.frame_id, sigma=0.0,
              unknown_policy="free")
    with pytest.raises(RuntimeError, match="killed"), create_map(f"{mem}/map.zarr", **kw) as w:
        w.esdf[...] = here.read("esdf", ...)
        raise RuntimeError("killed mid-write")
    assert not Location.of(f"{mem}/map.zarr").exists()
    assert fs.find(Location.of(mem).path) == []  # the temporary prefix is gone too
    # over an existing map: the old one stays, whole
    copy_store(ws / "map.zarr", f"{mem}/map.zarr")
    with pytest.raises(RuntimeError, match="killed"), create_map(f"{mem}/map.zarr", overwrite=True, **kw) as w:
        w.esdf[...] = np.zeros(here.shape, np.float32)
        raise RuntimeError("killed mid-write")
    np.testing.assert_array_equal(EsdfMap.open(f"{mem}/map.zarr").read("esdf", ...), here.read("esdf", ...))
    assert sorted(p.rsplit("/", 1)[-1] for p in fs.ls(Location.of(mem).path, detail=False)) == ["map.zarr"]


def test_overwrite_on_a_url(local: tuple[Path, Path], mem: str) -> None:
    bag, _ = local
    ingest([bag], mem, progress=False)
    with pytest.raises(WorkspaceError, match=r"already exists; pass --overwrite"):
        ingest([bag], mem, progress=False)
    result = CliRunner().invoke(main, ["ingest", str(bag), "-w", mem])
    assert result.exit_code == 1 and "already exists; pass --overwrite" in result.output
    result = CliRunner().invoke(main, ["ingest", str(bag), "-w", mem, "--overwrite", "--set", "ingest.stride=2"])
    assert result.exit_code == 0, result.output
    assert len(open_frames_store(mem)) == len(open_frames_store(local[1])) // 2 + len(open_frames_store(local[1])) % 2


def test_training_loader_reads_tuples_from_a_url_sharded_by_rank(local: tuple[Path, Path], mem: str) -> None:
    _, ws = local
    copy_store(ws / "tuples.zarr", f"{mem}/tuples.zarr")
    remote, here = TupleStore.open(mem), TupleStore.open(ws)
    assert remote.workspace.url == mem
    samples, reference = TupleSamples([remote], "train"), TupleSamples([here], "train")
    everything = list(samples.batches(4, shuffle=True, generator=np.random.default_rng(7)))
    assert len(everything) % 2 == 0, "the store should give an even batch count (see the next test)"
    shards = [list(samples.batches(4, shuffle=True, generator=np.random.default_rng(7), rank=r, world_size=2))
              for r in range(2)]
    seen = [{(int(t), int(g)) for _, part in shard for t, g in part} for shard in shards]
    assert seen[0] and seen[1] and not seen[0] & seen[1]
    assert len(seen[0]) + len(seen[1]) == len(samples)
    for (k, part), (k_ref, part_ref) in zip(shards[1], reference.batches(4, shuffle=True, generator=np.random.default_rng(7),
                                                                           rank=1, world_size=2), strict=True):
        np.testing.assert_array_equal(part, part_ref)
        a, b = samples.load(k, part, torch.device("cpu")), reference.load(k_ref, part_ref, torch.device("cpu"))
        for key in ("depth", "goal", "velocity", "T_world_body", "blocked", "image_index"):
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("world_size", [2, 3, 5])
def test_every_rank_takes_the_same_number_of_batches(local: tuple[Path, Path], world_size: int) -> None:
    """Batches that do not share out evenly are completed with the first ones again, so DDP's
    collectives stay in step; every sample is still in some rank's share."""
    samples = TupleSamples([TupleStore.open(local[1])], "train")
    for batch_size in (3, 4, 7, 11):
        whole = list(samples.batches(batch_size, shuffle=True, generator=np.random.default_rng(3)))
        shards = [list(samples.batches(batch_size, shuffle=True, generator=np.random.default_rng(3), rank=r,
                                       world_size=world_size)) for r in range(world_size)]
        assert len({len(shard) for shard in shards}) == 1
        assert len(shards[0]) == -(-len(whole) // world_size)
        seen = {(int(t), int(g)) for shard in shards for _, part in shard for t, g in part}
        assert len(seen) == len(samples)
        one = list(samples.batches(batch_size, shuffle=True, generator=np.random.default_rng(3), world_size=1))
        assert [p.tolist() for _, p in one] == [p.tolist() for _, p in whole]


def _one_line(args: list[str]) -> str:
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.output, result.output
    return lines[0]


def test_commands_that_need_local_files_refuse_a_url(tmp_path: Path) -> None:
    line = _one_line(["view", "-w", "s3://b/ws"])
    assert "mapkit view" in line and "needs a local folder" in line and "copy" in line
    line = _one_line(["train", "-w", "memory://nothing/ws", "--runs-dir", str(tmp_path / "runs")])
    assert "tuples.zarr does not exist" in line


@pytest.mark.slow
def test_a_run_folder_at_a_url(local: tuple[Path, Path], mem: str) -> None:
    """Training on tuples at memory:// with the default run folder WS/runs/NAME there too: every file
    lands at the URL; --resume continues from it; an existing run is refused naming the URL."""
    copy_store(local[1] / "tuples.zarr", f"{mem}/tuples.zarr")
    copy_store(local[1] / "map.zarr", f"{mem}/map.zarr")
    config = preset("cpu", name="r", epochs=1, batch_size=8, max_steps=1, val_batches=1,
                    planner={"input_size": [32, 48], "encoder_width": 0.125})
    summary = train([mem], config, progress=False)
    run = f"{mem}/runs/r"
    assert summary.run_dir == run
    fs = fsspec.filesystem("memory")
    names = {p.rsplit("/", 1)[-1] for p in fs.find(Location.of(run).path)}
    assert {"config.json", "metrics.jsonl", "checkpoint.pt", "model.pt", "training_curves.png"} <= names
    assert json.loads(fs.cat_file(f"{Location.of(run).path}/config.json"))["workspaces"] == [mem]
    line = _one_line(["train", "-w", mem, "--name", "r", "--set", "max_steps=1"])
    assert f"run {run} exists" in line
    train([mem], dataclasses.replace(config, epochs=2, max_steps=2), resume=True, progress=False)
    rows = [json.loads(x) for x in fs.cat_file(f"{Location.of(run).path}/metrics.jsonl").decode().splitlines()]
    assert [r["epoch"] for r in rows] == [0, 1, 2]


def test_unknown_protocol_is_one_line() -> None:
    line = _one_line(["export", "-w", "nosuchfs://bucket/ws"])
    assert "nosuchfs://bucket/ws" in line and "fsspec backend" in line
    with pytest.raises(StoreError, match="nosuchfs"):
        Location.of("nosuchfs://x")


@pytest.fixture
def offline_s3(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """No AWS credentials anywhere, no instance metadata, one quick attempt per request."""
    pytest.importorskip("s3fs", reason="s3fs (the s3:// backend of fsspec) is not installed")
    for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_PROFILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")
    monkeypatch.setenv("AWS_CONFIG_FILE", "/nonexistent")
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", "/nonexistent")
    yield


def _s3_conf(monkeypatch: pytest.MonkeyPatch, endpoint: str, **extra: object) -> None:
    """What a user puts in fsspec's config (or FSSPEC_S3_* variables): endpoint, short timeouts."""
    monkeypatch.setitem(fsspec.config.conf, "s3", {
        "endpoint_url": endpoint, "skip_instance_cache": True,
        "config_kwargs": {"connect_timeout": 1, "read_timeout": 1, "retries": {"max_attempts": 1}}, **extra,
    })


@pytest.mark.timeout(60)
def test_s3_without_credentials_is_one_line(local: tuple[Path, Path], offline_s3: None, monkeypatch: pytest.MonkeyPatch) -> None:
    _s3_conf(monkeypatch, "http://127.0.0.1:9")
    line = _one_line(["ingest", str(local[0]), "-w", "s3://mapkit-bucket/ws"])
    assert "no credentials for s3://mapkit-bucket/ws/frames.zarr" in line and "AWS_ACCESS_KEY_ID" in line
    line = _one_line(["export", "-w", "s3://mapkit-bucket/ws"])
    assert "no credentials for s3://mapkit-bucket/ws" in line


class _NoSuchBucket(BaseHTTPRequestHandler):
    """An S3 endpoint that knows no bucket: 404 NoSuchBucket for everything."""

    def _answer(self) -> None:
        body = (b'<?xml version="1.0" encoding="UTF-8"?><Error><Code>NoSuchBucket</Code>'
                b"<Message>The specified bucket does not exist</Message></Error>")
        self.send_response(404)
        self.send_header("Content-Type", "application/xml")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    do_GET = do_HEAD = do_PUT = do_POST = do_DELETE = _answer

    def log_message(self, *args: object) -> None:
        pass


@pytest.mark.timeout(60)
def test_s3_missing_bucket_is_one_line(local: tuple[Path, Path], offline_s3: None, monkeypatch: pytest.MonkeyPatch) -> None:
    server = ThreadingHTTPServer(("127.0.0.1", 0), _NoSuchBucket)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        _s3_conf(monkeypatch, f"http://127.0.0.1:{server.server_address[1]}", key="test", secret="test")
        line = _one_line(["ingest", str(local[0]), "-w", "s3://no-such-bucket/ws"])
        assert "bucket 'no-such-bucket' of s3://no-such-bucket/ws/frames.zarr does not exist" in line
        line = _one_line(["export", "-w", "s3://no-such-bucket/ws"])
        assert "no-such-bucket" in line
    finally:
        server.shutdown()
        server.server_close()


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_two_gloo_ranks_train_on_tuples_over_http_with_uneven_batches(local: tuple[Path, Path], tmp_path: Path) -> None:
    """`torchrun` with 2 CPU processes reads tuples.zarr and map.zarr through fsspec (http://, served by
    `python -m http.server`) and finishes an epoch whose batch count is odd: the loader evens the ranks
    out, so DDP's collectives stay in step."""
    pytest.importorskip("aiohttp", reason="fsspec's http:// backend needs aiohttp")
    ws = tmp_path / "serve" / "ws"
    ws.mkdir(parents=True)
    for name in ("frames.zarr", "map.zarr"):
        shutil.copytree(local[1] / name, ws / name)
    export_tuples(ws, ExportConfig(goals_per_frame=1, stride=6, seed=1), progress=False)
    n = len(TupleSamples([TupleStore.open(ws)], "train"))
    batch_size = next(b for b in range(2, n) if -(-n // b) % 2 == 1)  # an odd number of batches
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"],
                              cwd=tmp_path / "serve", stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        url = f"http://127.0.0.1:{port}/ws"
        for _ in range(100):
            with contextlib.suppress(Exception):
                if Location.of(url).fs.exists(f"{url}/tuples.zarr/zarr.json"):
                    break
            time.sleep(0.1)
        env = {**os.environ, "MAPKIT_DDP_BACKEND": "gloo", "OMP_NUM_THREADS": "1"}
        cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2", "--master-port", "29547",
               "-m", "mapkit.cli", "train", "-w", url, "--name", "ddp", "--runs-dir", str(tmp_path / "runs"),
               "--epochs", "1", "--set", f"batch_size={batch_size}", "--set", "val_batches=1",
               "--set", "planner.input_size=[32,48]", "--set", "planner.encoder_width=0.125"]
        result = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=540)
    finally:
        server.terminate()
        server.wait(timeout=10)
    assert result.returncode == 0, result.stderr[-2000:]
    rows = [json.loads(x) for x in (tmp_path / "runs" / "ddp" / "metrics.jsonl").read_text().splitlines()]
    batches = -(-n // batch_size)
    assert rows[-1]["epoch"] == 1 and rows[-1]["step"] == -(-batches // 2)  # each rank: half, rounded up
    config = json.loads((tmp_path / "runs" / "ddp" / "config.json").read_text())
    assert config["workspaces"] == [url]


def test_cli_copy_store_publishes_a_complete_copy_and_refuses_an_incomplete_source(tmp_path: Path):
    import zarr
    from click.testing import CliRunner

    from mapkit.cli.main import main

    src = tmp_path / "map.zarr"
    root = zarr.open_group(src, mode="w", zarr_format=3)
    root.create_array("esdf", data=np.arange(24, dtype=np.float32).reshape(2, 3, 4))
    out = CliRunner().invoke(main, ["copy-store", str(src), "memory://copy_cli/map.zarr"])
    assert out.exit_code == 0, out.output
    copied = zarr.open_group("memory://copy_cli/map.zarr", mode="r")
    np.testing.assert_array_equal(copied["esdf"][:], root["esdf"][:])
    again = CliRunner().invoke(main, ["copy-store", str(src), "memory://copy_cli/map.zarr"])
    assert again.exit_code == 1 and "--overwrite" in again.output and "Traceback" not in again.output
    (tmp_path / "empty.zarr").mkdir()
    bad = CliRunner().invoke(main, ["copy-store", str(tmp_path / "empty.zarr"), "memory://copy_cli/x.zarr"])
    assert bad.exit_code == 1 and "not a complete zarr store" in bad.output


def test_cli_esdf_writes_map_zarr_to_a_url_equal_to_the_local_one(local: tuple[Path, Path], mem: str) -> None:
    """`mapkit esdf -w WS -o URL`: the workspace's fusion stays local, the map goes to the URL, equal
    array for array (and in its attrs) to the map the same options wrote into the workspace."""
    _, ws = local
    args = ["esdf", "-w", str(ws), "--voxel", "0.2", "--set", "sigma=0", "-o", f"{mem}/map.zarr"]
    out = CliRunner().invoke(main, args)
    assert out.exit_code == 0, out.output
    assert f"{mem}/map.zarr" in out.output
    _assert_same_group(_group(ws / "map.zarr"), _group(f"{mem}/map.zarr"))
    again = CliRunner().invoke(main, args)  # a complete map there: refused without --overwrite
    assert again.exit_code == 1 and "--overwrite" in again.output and "Traceback" not in again.output


@pytest.mark.slow
def test_fuse_and_esdf_on_a_workspace_at_a_url_equal_the_local_ones(local: tuple[Path, Path], mem: str, tmp_path: Path) -> None:
    """`mapkit fuse BAG -w URL`, `mapkit esdf -w URL`, `mapkit export -w URL`: every store equal to the
    local workspace's, array for array; the fused files published with fuse.json last; an existing
    fused map refused without --overwrite and a missing one named, each in one line."""
    bag, ws = local
    fs = fsspec.filesystem("memory")
    base = Location.of(mem).path
    assert "has no complete fused map" in _one_line(["esdf", "-w", mem])
    out = CliRunner().invoke(main, ["fuse", str(bag), "-w", mem, "--voxel", "0.1"])
    assert out.exit_code == 0, out.output
    assert f"wrote {mem}/frames.zarr, {mem}/cloud.ply, {mem}/tsdf.npz, {mem}/fuse.json" in out.output, out.output
    assert "mapkit-fuse-" not in out.output
    meta = json.loads(fs.cat_file(f"{base}/fuse.json"))
    assert {n: fs.size(f"{base}/{n}") for n in meta["outputs"]} == meta["outputs"]
    assert (ws / "tsdf.npz").read_bytes() == fs.cat_file(f"{base}/tsdf.npz")
    _assert_same_group(_group(ws / "frames.zarr"), _group(f"{mem}/frames.zarr"))
    assert f"{mem}/fuse.json exists" in _one_line(["fuse", str(bag), "-w", mem, "--voxel", "0.1"])
    out = CliRunner().invoke(main, ["esdf", "-w", mem, "--voxel", "0.2", "--set", "sigma=0"])
    assert out.exit_code == 0 and f"wrote {mem}/map.zarr" in out.output, out.output
    _assert_same_group(_group(ws / "map.zarr"), _group(f"{mem}/map.zarr"))
    out = CliRunner().invoke(main, ["export", "-w", mem, "--set", "goals_per_frame=3", "--seed", "1"])
    assert out.exit_code == 0, out.output
    _assert_same_group(_group(ws / "tuples.zarr"), _group(f"{mem}/tuples.zarr"), skip_attrs=("map", "frames"))
