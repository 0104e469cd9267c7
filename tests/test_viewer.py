"""`mapkit view` in-process: the viser app on 127.0.0.1 with port 0 over a simulated workspace; GUI
values set from Python, scene nodes and their data checked; bad input; clean stops."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from test_viz import write_fake_eval

from mapkit.cli.main import main
from mapkit.esdf import EsdfConfig, EsdfMap, build_esdf
from mapkit.fusion import FuseConfig, fuse
from mapkit.ingest import open_frames_store
from mapkit.planner import PlannerNet, planner_preset
from mapkit.sim import SimConfig, simulate
from mapkit.viewer import ViewerApp, ViewerConfig, ViewerError
from mapkit.viz import HATCH_RGB, apply_colormap, depth_image, frustum_segments

TINY = {"input_size": [32, 48], "encoder_width": 0.125}


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("viewer")
    result = simulate(SimConfig(world="forest", seed=4, duration=3.0, width=64, height=48), tmp / "flight", progress=False)
    ws = tmp / "ws"
    fuse([result.bag_path], ws, FuseConfig(voxel=0.1), progress=False)
    build_esdf(ws, EsdfConfig(voxel=0.2, sigma=0.2), progress=False)
    # an untrained planner saved as `mapkit train` saves one (state dict + config)
    torch.manual_seed(0)
    cfg = planner_preset("cpu", **TINY)
    run = ws / "runs" / "tiny"
    run.mkdir(parents=True)
    torch.save({"state_dict": PlannerNet(cfg).state_dict(), "planner_config": cfg.to_dict()}, run / "model.pt")
    return {"ws": ws, "run": run, "eval": write_fake_eval(tmp / "eval")}


def port_is_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


@pytest.fixture
def start_app():
    """Start apps on 127.0.0.1:0; at the end stop them and check that the server thread, the
    player and every non-daemon thread started since are gone and the port is free again."""
    before = set(threading.enumerate())
    apps: list[ViewerApp] = []

    def start(**kw) -> ViewerApp:
        app = ViewerApp(ViewerConfig(port=0, **kw))
        app.start()
        apps.append(app)
        return app

    yield start
    for app in apps:
        port = app.port
        server_thread = app.server._websock_server._server_thread
        app.stop()
        app.stop()  # idempotent
        assert app.server is None and not server_thread.is_alive()
        assert port_is_free(port), f"port {port} still bound after stop()"
    deadline = time.monotonic() + 10
    while True:
        stray = [t for t in threading.enumerate() if t not in before and t.is_alive()
                 and (not t.daemon or t.name.startswith("mapkit-view"))]
        if not stray or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    assert not stray, f"threads left running: {[t.name for t in stray]}"


def expected_colour(app: ViewerApp, idx: tuple[int, int, int]) -> np.ndarray | None:
    """The colour the slice texture must show for voxel idx, or None for the unobserved hatch."""
    m = app.map
    if not m.observed[idx]:
        return None
    value = np.array([float(m.read("esdf", idx))])
    return apply_colormap(value, app.slice.cmap, app.slice.norm)[0]


def test_layers_and_slice_controls(data, start_app) -> None:
    app = start_app(workspace=data["ws"])
    assert app.url.startswith("http://127.0.0.1:") and app.port > 0
    for name in ("/cloud/points", "/slice/plane", "/flight/path", "/flight/frustums", "/flight/current", "/flight/body"):
        assert name in app.nodes, name
    assert app.server.scene.get_handle_by_name("/slice/plane") is not None
    cloud = app.nodes["/cloud/points"]
    assert len(cloud.points) == app.cloud.shown_points and np.allclose(cloud.position, app.cloud.origin)
    m = EsdfMap.open(data["ws"] / "map.zarr")

    for axis in ("x", "y", "z"):
        app.gui.slice.axis.value = axis
        a = "xyz".index(axis)
        k = m.shape[a] // 3
        app.gui.slice.position.value = float(m.origin[a] + k * m.voxel_size) + 0.04  # snaps to centre k
        tex = app.slice
        assert tex.axis == axis and tex.position == pytest.approx(m.origin[a] + k * m.voxel_size)
        node = app.nodes["/slice/plane"]
        np.testing.assert_array_equal(node.image, tex.texture)
        np.testing.assert_allclose(node.position, tex.centre_world)
        assert node.render_width == pytest.approx(tex.width_m) and node.render_height == pytest.approx(tex.height_m)
        # texture values at known voxels: the colormap colour of the stored distance, or the hatch
        ua, va = [b for b in range(3) if b != a]
        rng = np.random.default_rng(a)
        checked_hatch = checked_colour = 0
        for iu, iv in rng.integers(0, [m.shape[ua], m.shape[va]], (60, 2)):
            idx = [0, 0, 0]
            idx[a], idx[ua], idx[va] = k, iu, iv
            r, c = tex.pixel_of_voxel(iu, iv)
            want = expected_colour(app, tuple(idx))
            if want is None:
                assert any(np.array_equal(tex.texture[r, c], h) for h in HATCH_RGB)
                checked_hatch += 1
            else:
                np.testing.assert_array_equal(tex.texture[r, c], want)
                checked_colour += 1
        assert checked_colour > 0
    assert "voxel" in app.gui.slice.info.content

    # colour range, colour map, cost mode: the texture follows, the colour bar carries the units
    app.gui.slice.vmin.value = -0.5
    app.gui.slice.vmax.value = 4.0
    assert (app.slice.norm.vmin, app.slice.norm.vmax) == (-0.5, 4.0)
    app.gui.slice.cmap.value = "viridis"
    assert app.slice.cmap == "viridis"
    app.gui.slice.value.value = "obstacle cost"
    assert app.slice.mode == "cost" and "cost" in app.slice.label and app.slice.norm.vmin == 0.0
    assert app.gui.slice.colorbar.image.shape == (90, 320, 3)
    app.gui.slice.vmin.value = 9.0  # above max: a message, no exception
    assert "larger than the minimum" in app.gui.message.content

    # layer toggles
    app.gui.layers.cloud.value = False
    assert app.nodes["/cloud"].visible is False
    app.gui.layers.cloud.value = True
    assert app.nodes["/cloud"].visible is True
    app.gui.cloud.color.value = "ESDF"
    assert app.nodes["/cloud/points"].colors.shape == (app.cloud.shown_points, 3)


def test_frame_slider_depth_and_play(data, start_app) -> None:
    app = start_app(workspace=data["ws"])
    store = open_frames_store(data["ws"])
    app.gui.flight.frame.value = 7
    want = frustum_segments(store.K, store.width, store.height, store.T_world_camera[7], depth=2.5 * app.config.frustum_depth)
    np.testing.assert_allclose(app.nodes["/flight/current"].points, want.astype(np.float32), atol=1e-5)
    np.testing.assert_allclose(app.nodes["/flight/body"].position, store.T_world_body[7, :3, 3])
    np.testing.assert_array_equal(app.gui.flight.depth.image, depth_image(np.asarray(store.depth[7])))
    assert app.gui.flight.info.content.startswith("frame 7 of")
    app.gui.flight.frustum_every.value = 5
    assert len(app.nodes["/flight/frustums"].points) == 8 * len(range(0, len(store), 5))
    app.gui.flight.fps.value = 30
    app.gui.flight.play.value = True
    deadline = time.monotonic() + 10
    while int(app.gui.flight.frame.value) == 7 and time.monotonic() < deadline:
        time.sleep(0.05)
    app.gui.flight.play.value = False
    assert int(app.gui.flight.frame.value) != 7


def test_live_plan_click_and_corridor(data, start_app) -> None:
    app = start_app(workspace=data["ws"], model=data["run"], corridor=0.4)
    store = open_frames_store(data["ws"])
    i = 10
    app.gui.flight.frame.value = i
    T_wb = store.T_world_body[i]
    goal = T_wb[:3, 3] + T_wb[:3, :3] @ np.array([5.0, 1.0, 0.0])
    app.gui.plan.goal.value = tuple(float(v) for v in goal)
    plan = app.plan
    assert plan is not None and plan["frame"] == i
    res = plan["result"]
    K = len(res.keypoints)
    traj = app.nodes["/plan/trajectory"].points
    assert traj.shape == (len(res.samples_body) - 1, 2, 3)
    np.testing.assert_allclose(traj[0, 0], T_wb[:3, 3], atol=1e-4)  # starts at the body
    np.testing.assert_allclose(traj[:, 0], (res.samples_body[:-1] @ T_wb[:3, :3].T + T_wb[:3, 3]).astype(np.float32),
                               atol=1e-4)
    np.testing.assert_allclose(app.nodes["/plan/keypoints"].points, plan["keypoints_world"], atol=1e-5)
    # the corridor: one prism per key-point segment (origin → k1 → ... → kK), drawn from the body frame
    geo = plan["corridor"]
    assert geo.num_segments == K == 5 and len(geo.sections) == K
    np.testing.assert_allclose(app.nodes["/corridor/prisms"].vertices, geo.vertices.astype(np.float32), atol=1e-5)
    assert "corridor" in app.gui.plan.info.content and "η" in app.gui.plan.info.content
    assert "latency" in app.gui.plan.info.content
    assert plan["corridor_width"] == 0.4 and not plan["infeasible"]
    # corridor off: through the key-points, no prisms
    app.gui.plan.corridor_width.value = 0.0
    assert "/corridor/prisms" not in app.nodes and app.plan["corridor"] is None
    assert app.server.scene.get_handle_by_name("/corridor/prisms") is None
    # a click from above onto the visible slice sets the goal there and re-plans
    app.gui.slice.axis.value = "z"
    z = app.slice.position
    centre = app.slice.centre_world
    p = app.pick((centre[0] + 1.0, centre[1], z + 20.0), (0.0, 0.0, -1.0))
    np.testing.assert_allclose(p, [centre[0] + 1.0, centre[1], z], atol=1e-9)
    np.testing.assert_allclose(app.plan["goal_world"], [centre[0] + 1.0, centre[1], z], atol=1e-3)
    assert "goal from the slice" in app.gui.message.content
    assert app.pick((0.0, 0.0, 500.0), (0.0, 0.0, 1.0)) is None  # pointing at the sky
    assert "type the goal" in app.gui.message.content
    # a new frame re-plans from there
    app.gui.flight.frame.value = i + 5
    assert app.plan["frame"] == i + 5


def test_eval_layer(data, start_app) -> None:
    app = start_app(eval_dir=data["eval"])
    assert app.map is None and app.ws is None
    for name in ("/eval/world", "/eval/paths/learned", "/eval/paths/straight", "/eval/collisions", "/eval/starts",
                 "/eval/goals"):
        assert name in app.nodes, name
    all_pairs = len(app.nodes["/eval/paths/learned"].points)
    assert all_pairs == 2 * 30
    np.testing.assert_allclose(app.nodes["/eval/collisions"].points, [[2.5, -1.0, 1.0]])
    assert "| straight | 1 | 1 | 0 |" in app.gui.eval.table.content
    app.gui.eval.pair.value = "1"
    assert len(app.nodes["/eval/paths/learned"].points) == 30 and "/eval/collisions" not in app.nodes
    assert "| straight | 1 | 0 | 0 |" in app.gui.eval.table.content
    app.gui.layers.eval.value = False
    assert app.nodes["/eval"].visible is False


def test_partial_and_corrupt_workspaces(data, start_app, tmp_path: Path) -> None:
    only_map = tmp_path / "only_map"
    only_map.mkdir()
    shutil.copytree(data["ws"] / "map.zarr", only_map / "map.zarr")
    app = start_app(workspace=only_map)
    status = app.gui.status.content
    assert "frames.zarr is missing" in status and "mapkit ingest" in status
    assert "cloud.ply is missing" in status and "mapkit fuse" in status
    assert "/slice/plane" in app.nodes and "/cloud/points" not in app.nodes and app.gui.flight is None

    broken = tmp_path / "broken"
    shutil.copytree(data["ws"], broken)
    ply = (broken / "cloud.ply").read_bytes()
    (broken / "cloud.ply").write_bytes(ply[: len(ply) // 3])  # truncated
    for chunk in (broken / "map.zarr" / "esdf" / "c").rglob("*"):
        if chunk.is_file():
            chunk.write_bytes(b"\x00garbage")  # every chunk of the distance grid damaged
    app = start_app(workspace=broken)
    status = app.gui.status.content
    assert "cloud.ply cannot be read" in status and "truncated" in status
    assert "map.zarr cannot be sliced" in status and "esdf" in status
    assert "/flight/path" in app.nodes  # what is intact still shows

    with pytest.raises(ViewerError, match="holds none of"):
        ViewerApp(ViewerConfig(workspace=tmp_path / "only_map" / "map.zarr" / "esdf", port=0))
    with pytest.raises(ViewerError, match="nothing to view"):
        ViewerApp(ViewerConfig(port=0))


def test_port_in_use(data) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        app = ViewerApp(ViewerConfig(workspace=data["ws"], port=port))
        with pytest.raises(ViewerError) as err:
            app.start()
        assert str(err.value) == f"port {port} on 127.0.0.1 is in use; pass --port 0 to pick a free one"
        assert app.server is None
        result = CliRunner().invoke(main, ["view", "-w", str(data["ws"]), "--port", str(port)])
        assert result.exit_code == 1
        assert f"error: port {port} on 127.0.0.1 is in use; pass --port 0 to pick a free one" in result.output
        assert "Traceback" not in result.output


def test_cli_bad_inputs(data, tmp_path: Path) -> None:
    runner = CliRunner()
    for args, message in [
        ([], "nothing to view"),
        (["-w", str(tmp_path / "nope")], "no workspace at"),
        (["-w", str(data["ws"]), "--model", str(tmp_path / "nope")], "--model"),
        (["-w", str(data["ws"]), "--eval", str(tmp_path / "nope")], "--eval"),
        (["-w", str(data["ws"]), "--frame", "100000"], "--frame 100000"),
        (["-w", str(data["ws"]), "--host", "no.such.host.invalid", "--port", "0"], "--host"),
    ]:
        result = runner.invoke(main, ["view", *args])
        assert result.exit_code == 1, (args, result.output)
        assert message in result.output and "Traceback" not in result.output, (args, result.output)


def test_cli_serves_until_ctrl_c(data) -> None:
    """The real command: prints what it loaded and the URL, serves the page, stops on SIGINT."""
    proc = subprocess.Popen([sys.executable, "-m", "mapkit.cli", "view", "-w", str(data["ws"]), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"},
                            # A shell without job control starts background jobs (CI) with SIGINT
                            # ignored, and children inherit that: give the command Ctrl-C back.
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = []
    try:
        url = None
        deadline = time.monotonic() + 120
        while url is None and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            found = re.search(r"mapkit view: (http://127\.0\.0\.1:\d+)", line)
            url = found.group(1) if found else None
        assert url is not None, "".join(lines)
        with urllib.request.urlopen(url, timeout=30) as resp:
            assert resp.status == 200 and b"<html" in resp.read(2000).lower()
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    text = "".join(lines) + out
    assert proc.returncode == 0, text
    assert "cloud.ply:" in text and "map.zarr:" in text and "frames.zarr:" in text
    assert "mapkit view: stopped" in text and "Traceback" not in text
    assert port_is_free(int(url.rsplit(":", 1)[1]))
