"""mapkit.sim: exact worlds, exact rendering, safe flights, complete recordings, the CLI."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mapkit.sim import (
    Box,
    CameraModel,
    Capsule,
    Cylinder,
    HalfSpace,
    SimConfig,
    SimError,
    World,
    make_world,
    plan_flight,
    render_depth,
    render_flight,
    simulate,
)

BOUNDS = np.array([[-5.0, -5.0, -5.0], [5.0, 5.0, 5.0]])


def _world(*prims) -> World:
    return World(list(prims), BOUNDS)


# ------------------------------------------------------------------------------ signed distance
def test_box_sdf_analytic() -> None:
    w = _world(Box((1.0, 2.0, 3.0), (0.5, 1.0, 1.5)))
    pts = np.array([
        [1.0, 2.0, 3.0],     # centre: inside by the smallest half extent
        [2.5, 2.0, 3.0],     # 1 m beyond the +x face
        [2.5, 4.0, 3.0],     # beyond an edge: (1, 1) → sqrt 2
        [2.5, 4.0, 5.5],     # beyond a corner: (1, 1, 1) → sqrt 3
        [1.4, 2.0, 3.0],     # inside, 0.1 from the +x face
        [1.5, 2.3, 3.2],     # on the face
    ])
    np.testing.assert_allclose(w.signed_distance(pts), [-0.5, 1.0, math.sqrt(2), math.sqrt(3), -0.1, 0.0], atol=1e-12)


def test_yawed_box_sdf() -> None:
    yaw = 0.7
    w = _world(Box((0.0, 0.0, 0.0), (2.0, 0.5, 1.0), yaw))
    u = np.array([math.cos(yaw), math.sin(yaw), 0.0])   # box x axis
    v = np.array([-math.sin(yaw), math.cos(yaw), 0.0])  # box y axis
    pts = np.stack([3.0 * u, 1.5 * v, 0.2 * v, 3.0 * u + 1.5 * v])
    np.testing.assert_allclose(w.signed_distance(pts), [1.0, 1.0, -0.3, math.sqrt(2)], atol=1e-12)


def test_cylinder_capsule_halfspace_sdf() -> None:
    cyl = _world(Cylinder((0.0, 0.0, 0.0), (0.0, 0.0, 4.0), 0.5))
    pts = np.array([[2.0, 0.0, 2.0], [0.0, 0.0, 5.0], [1.5, 0.0, 5.0], [0.0, 0.3, 2.0], [0.0, 0.0, 0.1], [0.5, 0, 2]])
    np.testing.assert_allclose(cyl.signed_distance(pts), [1.5, 1.0, math.sqrt(2), -0.2, -0.1, 0.0], atol=1e-12)
    # A horizontal cylinder: axis along y.
    hcyl = _world(Cylinder((0.0, -1.0, 1.0), (0.0, 1.0, 1.0), 0.3))
    np.testing.assert_allclose(hcyl.signed_distance(np.array([[0.0, 0.0, 2.0], [0.0, 2.0, 1.0]])), [0.7, 1.0], atol=1e-12)
    cap = _world(Capsule((0.0, 0.0, 1.0), (2.0, 0.0, 1.0), 0.25))
    pts = np.array([[1.0, 1.0, 1.0], [-1.0, 0.0, 1.0], [3.0, 0.0, 2.0], [1.0, 0.0, 1.1]])
    np.testing.assert_allclose(cap.signed_distance(pts), [0.75, 0.75, math.sqrt(2) - 0.25, -0.15], atol=1e-12)
    floor_ceiling = _world(HalfSpace((0, 0, 1.0), 0.0), HalfSpace((0, 0, -1.0), -3.0))
    np.testing.assert_allclose(floor_ceiling.signed_distance(np.array([[7.0, 1.0, 1.0], [0.0, 0.0, -0.5], [0, 0, 2.5]])),
                               [1.0, -0.5, 0.5], atol=1e-12)
    # Union outside = the nearest primitive.
    both = _world(Box((3.0, 0.0, 0.0), (0.5, 0.5, 0.5)), Cylinder((0.0, 0.0, -1.0), (0.0, 0.0, 1.0), 0.5))
    np.testing.assert_allclose(both.signed_distance(np.array([[1.5, 0.0, 0.0]])), [1.0], atol=1e-12)
    with pytest.raises(SimError, match="shape"):
        both.signed_distance(np.zeros(3))


def test_world_json_round_trip_and_determinism(tmp_path: Path) -> None:
    for kind in ("forest", "office", "garage"):
        w = make_world(kind, seed=3, size=(14.0, 12.0, 3.0) if kind != "forest" else (12.0, 12.0, 6.0))
        assert make_world(kind, seed=3, size=w.params["size"]).to_dict() == w.to_dict()
        assert make_world(kind, seed=4, size=w.params["size"]).to_dict() != w.to_dict()
        w.to_json(tmp_path / f"{kind}.json")
        w2 = World.from_json(tmp_path / f"{kind}.json")
        pts = np.random.default_rng(0).uniform(w.bounds[0] - 1, w.bounds[1] + 1, size=(500, 3))
        np.testing.assert_array_equal(w.signed_distance(pts), w2.signed_distance(pts))
        assert len(w.mesh().triangles) > 0
    with pytest.raises(SimError, match="unknown world 'moon'"):
        make_world("moon", seed=0)
    with pytest.raises(SimError, match="too small"):
        make_world("office", seed=0, size=(1.0, 1.0, 1.0))


# ------------------------------------------------------------------------------ rendering
def _look_at(eye, target) -> np.ndarray:
    """T_world_camera (optical) looking from eye to target with image 'down' towards -z."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


def _backproject(depth: np.ndarray, K: np.ndarray, T: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(np.isfinite(depth))
    z = depth[v, u].astype(np.float64)
    pc = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z, np.ones_like(z)])
    return (T @ pc)[:3].T


def test_pixel_centre_convention() -> None:
    cam = CameraModel(width=64, height=48)
    K = cam.K
    assert K[0, 2] == 31.5 and K[1, 2] == 23.5 and K[0, 0] == pytest.approx(387.0 * 64 / 640)
    # A wall 2 m ahead (optical z): every pixel reads exactly 2 (depth is z, not ray length).
    wall = _world(Box((0.0, 0.0, 3.0), (10.0, 10.0, 1.0)))
    depth = render_depth(wall, np.eye(4), cam)
    np.testing.assert_array_equal(depth, np.float32(2.0))
    # A point on a thin vertical pole projects to u = fx x / z + cx: only that column is hit.
    x = (38 - K[0, 2]) / K[0, 0] * 3.0  # seen through the centre of column 38
    pole = _world(Cylinder((x, -3.0, 3.0), (x, 3.0, 3.0), 1e-3))
    depth = render_depth(pole, np.eye(4), cam)
    cols = np.unique(np.nonzero(np.isfinite(depth))[1])
    assert list(cols) == [38]
    assert np.nanmax(np.abs(depth - 3.0)) < 1e-3


def test_range_limits_give_nan() -> None:
    cam = CameraModel(width=32, height=24, min_range=0.2, max_range=10.0)
    near = _world(Box((0.0, 0.0, 0.15), (10.0, 10.0, 0.05)))  # face at z = 0.1
    assert np.isnan(render_depth(near, np.eye(4), cam)).all()
    far = _world(Box((0.0, 0.0, 11.0), (100.0, 100.0, 0.5)))  # face at z = 10.5
    assert np.isnan(render_depth(far, np.eye(4), cam)).all()
    assert np.isnan(render_depth(_world(), np.eye(4), cam)).all()


@pytest.mark.parametrize("kind", ["forest", "office", "garage"])
def test_render_backprojects_onto_surface(kind: str) -> None:
    """No noise: every valid pixel back-projected with K, T_world_camera lies on the surface."""
    cfg = SimConfig(world=kind, seed=1, width=96, height=72, duration=1.0, rate=5.0)
    world, stamps, _, T_wc, K, depths = render_flight(cfg)
    n_valid = 0
    for depth, T in zip(depths, T_wc, strict=True):
        pts = _backproject(depth, K, T)
        n_valid += len(pts)
        assert np.abs(world.signed_distance(pts)).max() < 1e-4
    assert n_valid > 0.3 * len(stamps) * 96 * 72
    # The culled renderer equals brute-force ray casting against every primitive.
    cam = cfg.camera()
    full = world.raycast(T_wc[0][:3, 3], cam.rays() @ T_wc[0][:3, :3].T).reshape(72, 96)
    full = np.where((full >= 0.2) & (full <= 10.0), full, np.nan).astype(np.float32)
    np.testing.assert_array_equal(render_depth(world, T_wc[0], cam), full)


def test_render_matches_open3d_raycast_on_mesh() -> None:
    """The mesh (for display) and open3d agree with the analytic renderer up to tessellation."""
    import open3d as o3d

    cfg = SimConfig(world="office", seed=2, width=80, height=60, duration=0.2, rate=5.0)
    world, _, _, T_wc, _, depths = render_flight(cfg)
    depth = next(iter(depths))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(world.mesh()))
    d_cam = cfg.camera().rays()
    d_world = d_cam @ T_wc[0][:3, :3].T
    rays = np.concatenate([np.broadcast_to(T_wc[0][:3, 3], d_world.shape), d_world], axis=1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(60, 80)
    both = np.isfinite(depth) & np.isfinite(t)
    assert both.mean() > 0.8
    assert np.median(np.abs(depth[both] - t[both])) < 1e-3


def test_realsense_noise_is_seeded_and_plausible() -> None:
    base = dict(world="garage", seed=5, width=64, height=48, duration=0.4, rate=5.0)
    exact = list(render_flight(SimConfig(**base)).depths)
    noisy = list(render_flight(SimConfig(**base, noise="realsense")).depths)
    again = list(render_flight(SimConfig(**base, noise="realsense")).depths)
    for e, n, a in zip(exact, noisy, again, strict=True):
        np.testing.assert_array_equal(n, a)
        both = np.isfinite(e) & np.isfinite(n)
        assert np.isnan(n).sum() > np.isnan(e).sum()
        err = (n[both] - e[both]) / (0.0015 * e[both].astype(np.float64) ** 2)
        assert 0.7 < np.std(err) < 1.3


# ------------------------------------------------------------------------------ flight
@pytest.mark.parametrize("kind", ["forest", "office", "garage"])
def test_flight_collision_free_and_speeds(kind: str) -> None:
    world = make_world(kind, seed=4)
    traj = plan_flight(world, duration=12.0, speed=2.0, margin=0.4, seed=4)
    t = np.arange(0.0, 12.0, 1.0 / 240.0)
    p, v, yaw, _ = traj.sample(t)
    assert world.signed_distance(p).min() >= 0.4
    assert traj.min_clearance >= 0.4
    assert np.all((p >= world.bounds[0]) & (p <= world.bounds[1]))
    speed = np.linalg.norm(v, axis=1)
    assert speed.max() <= 3.0 + 1e-9
    # 1..3 m/s except at a rare on-the-spot turn-around (then it slows smoothly through ~0).
    assert np.mean(speed >= 1.0 - 1e-6) > 0.9
    # Velocity is the derivative of the position.
    fd = np.gradient(p, t, axis=0)
    assert np.median(np.linalg.norm(fd - v, axis=1)) < 0.02
    assert np.ptp(p[:, 2]) > 0.2 or kind == "garage"  # height varies
    assert np.ptp(yaw) > 0.3
    with pytest.raises(SimError, match="speed"):
        plan_flight(world, duration=5.0, speed=5.0)


# ------------------------------------------------------------------------------ recordings
def _read_topics(path: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, stamp, raw in reader.messages():
            out.setdefault(conn.topic, []).append((stamp, reader.deserialize(raw, conn.msgtype)))
    return out


def _stamp(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


@pytest.mark.parametrize("fmt,encoding", [("mcap", "16UC1"), ("ros2", "32FC1"), ("ros1", "compressedDepth")])
def test_simulate_formats(tmp_path: Path, fmt: str, encoding: str) -> None:
    from scipy.spatial.transform import Rotation

    cfg = SimConfig(world="office", seed=0, format=fmt, width=40, height=30, duration=0.5, rate=10.0,
                    depth_encoding=encoding)
    res = simulate(cfg, tmp_path / "rec", progress=False)
    n = len(res.stamps_ns)
    assert n == 5
    expected = {"mcap": "rec.mcap", "ros2": "rec", "ros1": "rec.bag"}[fmt]
    assert res.bag_path == tmp_path / expected
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [expected, "rec.world.json", "rec.world.ply", "rec.flight.npz"])
    assert np.all(np.diff(res.stamps_ns) > 0)
    assert res.stamps_ns[1] - res.stamps_ns[0] == 100_000_000

    msgs = _read_topics(res.bag_path)
    depth_topic = "/camera/depth/image_rect_raw" + ("/compressedDepth" if encoding == "compressedDepth" else "")
    assert {k: len(v) for k, v in msgs.items()} == {
        depth_topic: n, "/camera/depth/camera_info": n, "/odom": 4 * n, "/tf": 4 * n, "/tf_static": 1}
    odom = {_stamp(m.header): m for _, m in msgs["/odom"]}
    for i, stamp in enumerate(res.stamps_ns):
        _, img = msgs[depth_topic][i]
        assert _stamp(img.header) == stamp and img.header.frame_id == "camera_depth_optical_frame"
        m = odom[int(stamp)]  # an odometry sample at exactly the depth stamp
        assert m.header.frame_id == "world" and m.child_frame_id == "base_link"
        q, pos = m.pose.pose.orientation, m.pose.pose.position
        np.testing.assert_allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), res.T_world_body[i, :3, :3],
                                   atol=1e-12)
        np.testing.assert_allclose([pos.x, pos.y, pos.z], res.T_world_body[i, :3, 3], atol=1e-12)
    _, info = msgs["/camera/depth/camera_info"][0]
    K = np.asarray(info.K if fmt == "ros1" else info.k).reshape(3, 3)
    np.testing.assert_array_equal(K, res.K)
    # The static chain gives T_world_camera.
    _, tfs = msgs["/tf_static"][0]
    chain = np.eye(4)
    for tr in tfs.transforms:
        T = np.eye(4)
        r, t = tr.transform.rotation, tr.transform.translation
        T[:3, :3] = Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()
        T[:3, 3] = [t.x, t.y, t.z]
        chain = chain @ T
    assert [tr.child_frame_id for tr in tfs.transforms] == ["camera_link", "camera_depth_optical_frame"]
    np.testing.assert_allclose(res.T_world_body[0] @ chain, res.T_world_camera[0], atol=1e-12)
    # Ground truth beside the recording.
    npz = np.load(tmp_path / "rec.flight.npz")
    np.testing.assert_array_equal(npz["stamps_ns"], res.stamps_ns)
    np.testing.assert_array_equal(npz["T_world_camera"], res.T_world_camera)
    assert int(npz["width"]) == 40 and int(npz["height"]) == 30
    w = World.from_json(tmp_path / "rec.world.json")
    pts = np.random.default_rng(1).uniform(w.bounds[0], w.bounds[1], size=(200, 3))
    np.testing.assert_array_equal(w.signed_distance(pts), res.world.signed_distance(pts))


def test_simulate_deterministic_and_exact_16uc1(tmp_path: Path) -> None:
    cfg = SimConfig(world="forest", seed=2, width=48, height=36, duration=0.4, rate=10.0)
    a = simulate(cfg, tmp_path / "a", progress=False)
    b = simulate(cfg, tmp_path / "b", progress=False)
    np.testing.assert_array_equal(a.T_world_camera, b.T_world_camera)
    ma, mb = _read_topics(a.bag_path), _read_topics(b.bag_path)
    exact = list(render_flight(cfg).depths)
    for (_, ia), (_, ib), d in zip(ma["/camera/depth/image_rect_raw"], mb["/camera/depth/image_rect_raw"], exact, strict=False):
        assert bytes(ia.data) == bytes(ib.data)
        mm = np.frombuffer(bytes(ia.data), "<u2").reshape(36, 48)
        np.testing.assert_array_equal(mm == 0, np.isnan(d))
        valid = np.isfinite(d)
        assert np.abs(mm[valid] / 1000.0 - d[valid]).max() <= 0.0005 + 1e-6


def test_simulate_refuses_existing_and_bad_values(tmp_path: Path) -> None:
    cfg = SimConfig(world="office", seed=0, width=32, height=24, duration=0.2, rate=10.0)
    simulate(cfg, tmp_path / "rec.mcap", progress=False)
    before = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    with pytest.raises(SimError, match="exists"):
        simulate(cfg, tmp_path / "rec", progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == before
    with pytest.raises(SimError, match="bad resolution"):
        simulate(SimConfig(width=0), tmp_path / "x", progress=False)
    with pytest.raises(SimError, match="unknown world"):
        simulate(SimConfig(world="mars"), tmp_path / "x", progress=False)
    assert sorted(before) == sorted(p.name for p in tmp_path.iterdir())


# ------------------------------------------------------------------------------ CLI
def test_cli(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from mapkit.cli.main import main

    runner = CliRunner()
    out = tmp_path / "flight"
    args = ["simulate", "--world", "garage", "--seed", "3", "-o", str(out), "--set", "width=32", "--set", "height=24",
            "--duration", "0.3", "--set", "rate=10"]
    res = runner.invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "3 frames" in res.output and "flight.mcap" in res.output
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["flight.flight.npz", "flight.mcap", "flight.world.json", "flight.world.ply"]
    res = runner.invoke(main, args)
    assert res.exit_code == 1
    err = res.output.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--overwrite" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == files
    res = runner.invoke(main, args + ["--overwrite"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["simulate", "-o", str(tmp_path / "bad"), "--set", "width=0"])
    assert res.exit_code == 2 and "bad resolution" in res.output  # a usage error
    assert "\ndepth_encoding = \"16UC1\"\n" in runner.invoke(main, ["config", "simulate"]).output
