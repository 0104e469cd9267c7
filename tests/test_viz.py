"""mapkit.viz: cached slices and their textures, clouds, frustums, corridor prisms (against the
min_snap constraint rows), picking, workspace and evaluation loading. No viser here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from mapkit.errors import MapkitError
from mapkit.esdf import EsdfMap, slice_plane, write_map
from mapkit.sim import Box, HalfSpace, World
from mapkit.viz import (
    HATCH_RGB,
    MapSlicer,
    SlabCache,
    VizError,
    apply_colormap,
    cloud_view,
    colorbar_image,
    corridor_cross_section,
    corridor_prisms,
    depth_image,
    downsample_to,
    frustum_segments,
    load_eval,
    make_norm,
    method_colors,
    obstacle_cost_of_distance,
    open_workspace,
    pick_point,
    polyline_segments,
    read_ply_points,
    slice_texture,
    speed_colors,
    transfer_precision,
    voxel_downsample,
    world_mesh_arrays,
)

SHAPE = (130, 70, 66)  # more than one 64-chunk along x and z
VOXEL = 0.1
ORIGIN = (-3.0, 2.0, -0.5)


def analytic_fields() -> tuple[np.ndarray, np.ndarray]:
    """esdf = distance to the plane z = 1 m minus a ramp in x (every voxel distinct), observed False
    in a block."""
    i, j, k = np.meshgrid(*(np.arange(n) for n in SHAPE), indexing="ij")
    z = ORIGIN[2] + VOXEL * k
    esdf = (z - 1.0) + 0.001 * i + 0.0001 * j
    observed = np.ones(SHAPE, bool)
    observed[10:30, 5:25, 20:40] = False
    return esdf.astype(np.float32), observed


@pytest.fixture(scope="module")
def map_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    esdf, observed = analytic_fields()
    path = tmp_path_factory.mktemp("viz") / "map.zarr"
    write_map(path, esdf=esdf, esdf_raw=esdf - 0.01, observed=observed, origin=ORIGIN, voxel_size=VOXEL,
              frame_id="world", sigma=0.1, unknown_policy="free")
    return path


# ----------------------------------------------------------------------------------------- slices
class CountingArray:
    """A numpy array with zarr-like chunks that records each region read."""

    def __init__(self, data: np.ndarray, chunks: tuple[int, int, int]) -> None:
        self.data, self.chunks, self.shape, self.dtype = data, chunks, data.shape, data.dtype
        self.reads: list[tuple] = []

    def __getitem__(self, index):
        self.reads.append(index)
        return self.data[index]


def test_slab_cache_reads_chunk_aligned_slabs_once_and_evicts() -> None:
    data = np.arange(130 * 20 * 10, dtype=np.float32).reshape(130, 20, 10)
    arr = CountingArray(data, (64, 20, 10))
    cache = SlabCache(max_bytes=2 * 64 * 20 * 10 * 4)  # room for two x-slabs
    slab, k0 = cache.slab("esdf", arr, 0, 70)
    assert k0 == 64 and slab.shape == (64, 20, 10)
    assert arr.reads == [(slice(64, 128), slice(None), slice(None))]  # only the chunks that hold plane 70
    np.testing.assert_array_equal(slab[70 - k0], data[70])
    cache.slab("esdf", arr, 0, 100)  # same slab: a hit, no read
    assert len(arr.reads) == 1 and (cache.hits, cache.misses) == (1, 1)
    last, k0 = cache.slab("esdf", arr, 0, 129)  # the short last slab
    assert k0 == 128 and last.shape == (2, 20, 10)
    cache.slab("esdf", arr, 0, 3)
    assert cache.nbytes <= cache.max_bytes
    cache.slab("esdf", arr, 0, 70)  # evicted as least recently used: read again
    assert len(arr.reads) == 4
    with pytest.raises(VizError, match="must be > 0"):
        SlabCache(0)


def test_map_slicer_equals_slice_plane(map_path: Path) -> None:
    m = EsdfMap.open(map_path)
    slicer = MapSlicer(m)
    for axis, position in [("z", 1.0), ("z", 1.04), ("x", -1.23), ("y", 5.0), ("x", ORIGIN[0] - 0.05)]:
        for raw in (False, True):
            got, want = slicer.slice(axis, position, raw=raw), slice_plane(m, axis=axis, position=position, raw=raw)
            np.testing.assert_array_equal(got.values, want.values)
            np.testing.assert_array_equal(got.observed, want.observed)
            assert got.extent == want.extent and got.position == want.position
    misses = slicer.cache.misses
    slicer.slice("z", 1.1)  # same 64-slab along z as 1.0: served from memory
    assert slicer.cache.misses == misses
    with pytest.raises(MapkitError, match="valid z is"):
        slicer.texture("z", 99.0)
    lo, hi, step = slicer.positions("y")
    assert (lo, step) == (2.0, VOXEL) and hi == pytest.approx(2.0 + 69 * VOXEL)
    assert slicer.snap("z", 1.04) == pytest.approx(1.0) and slicer.snap("z", -50) == ORIGIN[2]


@pytest.mark.parametrize("axis,ppv", [("z", 1), ("x", 3), ("y", 2)])
def test_slice_texture_colours_layout_and_pose(map_path: Path, axis: str, ppv: int) -> None:
    m = EsdfMap.open(map_path)
    esdf, observed = analytic_fields()
    sl = MapSlicer(m).slice(axis, {"z": 1.5, "x": -1.0, "y": 3.5}[axis])
    tex = slice_texture(sl, axis=axis, cmap="RdBu", vmin=-1.0, vmax=2.0, pixels_per_voxel=ppv)
    nu, nv = sl.values.shape
    assert tex.texture.shape == (nv * ppv, nu * ppv, 3) and tex.texture.dtype == np.uint8
    assert tex.label == "signed distance [m]" and tex.norm.vcenter == 0.0  # diverging: centred on 0
    a = "xyz".index(axis)
    k = int(round((tex.position - ORIGIN[a]) / VOXEL))
    ua, va = {"x": (1, 2), "y": (0, 2), "z": (0, 1)}[axis]
    R, c = tex.R_world_image, tex.centre_world
    H, W = tex.texture.shape[:2]
    rng = np.random.default_rng(0)
    for iu, iv in [(0, 0), (nu - 1, nv - 1), (nu - 1, 0)] + [tuple(x) for x in rng.integers(0, [nu, nv], (20, 2))]:
        idx = [0, 0, 0]
        idx[a], idx[ua], idx[va] = k, iu, iv
        r, col = tex.pixel_of_voxel(iu, iv)
        pixel = tex.texture[r, col]
        if observed[tuple(idx)]:
            want = apply_colormap(np.array([esdf[tuple(idx)]]), "RdBu", tex.norm)[0]
            np.testing.assert_array_equal(pixel, want)
        else:
            assert any(np.array_equal(pixel, h) for h in HATCH_RGB)
        # the textured plane's pose puts this pixel's centre inside the voxel it shows
        x_img = (col + 0.5) / W * tex.width_m - 0.5 * tex.width_m
        y_img = (r + 0.5) / H * tex.height_m - 0.5 * tex.height_m
        world = c + R @ np.array([x_img, y_img, 0.0])
        centre = m.origin + m.voxel_size * np.asarray(idx)
        assert np.all(np.abs(world - centre) <= 0.5 * VOXEL + 1e-9), (world, centre)
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(tex.corners_world[0] - tex.corners_world[3], -tex.height_m * R[:, 1])
    # a whole unobserved block of the slice (if it crosses one) is hatched with both greys
    if not sl.observed.all():
        miss = ~sl.observed
        iu, iv = np.argwhere(miss)[0]
        r, col = tex.pixel_of_voxel(iu, iv)
        assert any(np.array_equal(tex.texture[r, col], h) for h in HATCH_RGB)


def test_slice_cost_mode_is_the_planner_penalty(map_path: Path) -> None:
    from mapkit.planner import obstacle_penalty

    sl = MapSlicer(EsdfMap.open(map_path)).slice("x", 0.0)
    tex = slice_texture(sl, axis="x", mode="cost", cmap="viridis", robot_radius=0.4, softness=0.5)
    want = obstacle_penalty(torch.from_numpy(sl.values.astype(np.float64)), robot_radius=0.4, softness=0.5).numpy()
    np.testing.assert_allclose(tex.values, want)
    assert "cost" in tex.label and "0.4 m" in tex.label and tex.norm.vmin == 0.0
    assert obstacle_cost_of_distance(np.array([10.0]))[0] < 0.03 < obstacle_cost_of_distance(np.array([-0.5]))[0]
    with pytest.raises(VizError, match="mode="):
        slice_texture(sl, axis="x", mode="height")
    with pytest.raises(VizError, match="colormap"):
        slice_texture(sl, axis="x", cmap="nope")
    with pytest.raises(VizError, match="larger than the minimum"):
        slice_texture(sl, axis="x", vmin=1.0, vmax=0.0)


def test_colorbar_and_colours() -> None:
    img = colorbar_image("RdBu", make_norm(-1.0, 3.0, centre_zero=True), label="signed distance [m]")
    assert img.shape == (90, 320, 3) and img.dtype == np.uint8 and (img < 200).any() and (img == 255).any()
    colours = method_colors(["learned", "straight", "learned-corridor"])
    assert len(set(colours.values())) == 3
    depth = np.full((4, 5), 2.0, np.float32)
    depth[0, 0] = np.nan
    rgb = depth_image(depth)
    assert rgb.shape == (4, 5, 3) and (rgb[0, 0] == 0).all() and rgb[1, 1].any()


# ------------------------------------------------------------------------------------------ clouds
def test_read_ply_points_binary_ascii_and_broken(tmp_path: Path) -> None:
    import open3d as o3d

    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3)) * 10 + 1000.0
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.normals = o3d.utility.Vector3dVector(rng.normal(size=(500, 3)))
    pc.colors = o3d.utility.Vector3dVector(rng.uniform(size=(500, 3)))
    for ascii_ in (False, True):
        path = tmp_path / f"c{int(ascii_)}.ply"
        assert o3d.io.write_point_cloud(str(path), pc, write_ascii=ascii_)
        got = read_ply_points(path)
        np.testing.assert_allclose(got.points, np.asarray(o3d.io.read_point_cloud(str(path)).points), atol=1e-6)
        assert got.colors is not None and got.colors.shape == (500, 3)
    data = (tmp_path / "c0.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) // 2])
    with pytest.raises(VizError, match="truncated"):
        read_ply_points(tmp_path / "cut.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all")
    with pytest.raises(VizError, match="not a PLY"):
        read_ply_points(tmp_path / "junk.ply")
    with pytest.raises(VizError, match="mapkit fuse"):
        read_ply_points(tmp_path / "missing.ply")


def test_voxel_downsample_and_budget() -> None:
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.05, 0.07], [0.15, 0.0, 0.0], [0.19, 0.02, 0.0]])
    got = voxel_downsample(pts, voxel_size=0.1)
    np.testing.assert_allclose(got, [[0.02, 0.03, 0.04], [0.17, 0.01, 0.0]])
    rng = np.random.default_rng(2)
    sheet = np.column_stack([rng.uniform(0, 50, 200_000), rng.uniform(0, 50, 200_000), np.zeros(200_000)])
    out, voxel = downsample_to(sheet, 20_000)
    assert len(out) <= 20_000 and len(out) > 10_000 and voxel > 0  # not over-thinned either
    same, v0 = downsample_to(sheet[:100], 20_000)
    assert v0 == 0.0 and np.array_equal(same, sheet[:100])


def test_cloud_view_origin_precision_and_colours(map_path: Path) -> None:
    rng = np.random.default_rng(3)
    far = rng.uniform(-4, 4, (1000, 3)) + [5000.0, -7000.0, 100.0]  # UTM-like offsets
    cv = cloud_view(far)
    assert cv.points_local.dtype == np.float32 and np.abs(cv.points_local).max() < 5.0
    np.testing.assert_allclose(cv.points_local + cv.origin, far, atol=1e-4)
    assert cv.precision == "float16" and cv.total_points == cv.shown_points == 1000
    wide = rng.uniform(-100, 100, (1000, 3))
    assert cloud_view(wide).precision == "float32"  # ±100 m in float16 would move points by ~3 cm
    assert transfer_precision(np.array([[1.0, 2.0, 3.0]])) == "float16"
    # by height: higher points get later colormap colours (viridis goes dark → yellow)
    col = cloud_view(np.array([[0, 0, 0.0], [0, 0, 1.0], [0, 0, 2.0]]), color_by="height").colors
    assert col[0].sum() < col[1].sum() < col[2].sum()
    # by ESDF: points on the zero level of the map are the diverging map's centre (near white)
    m = EsdfMap.open(map_path)
    on = np.array([[-2.0, 3.0, 1.0], [-1.0, 4.0, 1.0]])  # z = 1 m: distance ≈ 0 there
    cv = cloud_view(on, color_by="esdf", esdf_map=m)
    assert (cv.colors > 200).all()
    with pytest.raises(VizError, match="mapkit esdf"):
        cloud_view(on, color_by="esdf")


# ---------------------------------------------------------------------------------------- geometry
def test_frustum_segments_reach_the_pixel_edges() -> None:
    K = np.array([[100.0, 0, 31.5], [0, 90.0, 20.0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1.0], [-1, 0, 0], [0, -1, 0]])  # optical camera looking along +x
    T[:3, 3] = [1.0, 2.0, 3.0]
    seg = frustum_segments(K, 64, 48, np.stack([np.eye(4), T]), depth=2.0)
    assert seg.shape == (16, 2, 3)
    corners = seg[:4, 1]  # camera 0 is at the world origin with identity rotation
    uv = (K @ (corners / corners[:, 2:]).T).T[:, :2]
    np.testing.assert_allclose(uv, [[-0.5, -0.5], [63.5, -0.5], [63.5, 47.5], [-0.5, 47.5]], atol=1e-9)
    np.testing.assert_allclose(corners[:, 2], 2.0)
    np.testing.assert_allclose(seg[4:8, 0], corners)  # the rectangle joins the corners
    np.testing.assert_allclose(seg[8:12, 0], np.broadcast_to([1.0, 2.0, 3.0], (4, 3)))
    np.testing.assert_allclose(seg[8:12, 1], corners @ T[:3, :3].T + T[:3, 3])
    with pytest.raises(VizError, match="depth"):
        frustum_segments(K, 64, 48, T, depth=0.0)


def test_speed_colors_and_polylines() -> None:
    t = np.linspace(0, 2, 21)
    p = np.column_stack([3.0 * t, np.zeros_like(t), np.ones_like(t)])
    speed, colors, norm = speed_colors(t, p)
    np.testing.assert_allclose(speed, 3.0)
    assert colors.shape == (21, 3) and norm.vmax == pytest.approx(3.0)
    seg, seg_colors = polyline_segments(p, colors)
    assert seg.shape == (20, 2, 3) and seg_colors.shape == (20, 2, 3)
    np.testing.assert_array_equal(seg[1:, 0], seg[:-1, 1])
    with pytest.raises(VizError, match="increasing"):
        speed_colors(t[::-1], p)


def test_corridor_cross_sections() -> None:
    sq = corridor_cross_section(np.array([0.0, 0.0, 2.0]), 0.5)
    np.testing.assert_allclose(sorted(map(tuple, np.round(sq, 12))),
                               [(-0.5, -0.5, 0), (-0.5, 0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0)])
    rect = corridor_cross_section(np.array([1.0, 1.0, 0.0]), 0.5)  # a diagonal plane cuts a rectangle
    assert len(rect) == 4 and np.isclose(np.abs(rect).max(), 0.5)
    hexagon = corridor_cross_section(np.array([1.0, 1.0, 1.0]), 0.5)
    assert len(hexagon) == 6
    for poly, d in ((sq, [0, 0, 1.0]), (rect, [1.0, 1, 0]), (hexagon, [1.0, 1, 1])):
        u = np.asarray(d) / np.linalg.norm(d)
        np.testing.assert_allclose(poly @ u, 0.0, atol=1e-12)  # in the plane ⊥ u
        np.testing.assert_allclose(np.abs(poly).max(axis=1), 0.5)  # every vertex on the cube's surface
        n = np.cross(poly, np.roll(poly, -1, axis=0))
        assert (n @ u > 0).all()  # counter-clockwise seen from the tip of u
    with pytest.raises(VizError, match="zero-length"):
        corridor_cross_section(np.zeros(3), 0.5)


def _constraint_rows(waypoints: np.ndarray, W: float):
    """min_snap's own corridor rows (deviation per axis, and position along the line) for a
    trajectory sitting still at a point: each row r of segment s bounds sum_b coef[r, b] * p_b
    within [lo_r, hi_r]."""
    from mapkit.trajopt._minsnap import _corridor_rows

    w = torch.as_tensor(waypoints, dtype=torch.float64)[None]
    M = w.shape[1] - 1
    rows, seg, lo, hi = _corridor_rows(w, torch.ones(1, M, dtype=torch.float64), torch.full((1, M), W, dtype=torch.float64), 3)
    # knot-vector entries 0 and 4 are the positions at both ends of the segment (then vel, acc, jerk):
    # a constant trajectory p has those = p and the rest 0, so a row's value is coef @ p.
    coef = (rows[0, :, :, 0] + rows[0, :, :, 4]).numpy()
    return coef, np.asarray(seg), lo[0].numpy(), hi[0].numpy()


def _violation(p: np.ndarray, coef, seg, lo, hi, s: int) -> float:
    v = coef[seg == s] @ p
    return float(np.max(np.maximum(v - hi[seg == s], lo[seg == s] - v)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_corridor_prisms_are_exactly_the_min_snap_corridor(seed: int) -> None:
    rng = np.random.default_rng(seed)
    waypoints = np.vstack([np.zeros(3), np.cumsum(rng.normal(size=(4, 3)) * 2.0, axis=0)])
    waypoints[2] = waypoints[1] + [3.0, 0.0, 0.0]  # one axis-aligned segment (square section)
    W = 0.3 + 0.2 * seed
    geo = corridor_prisms(waypoints, W)
    coef, seg, lo, hi = _constraint_rows(waypoints, W)
    assert geo.num_segments == 4 and len(geo.sections) == 4
    on_surface = 0
    for s in range(4):
        a, b = waypoints[s], waypoints[s + 1]
        L = np.linalg.norm(b - a)
        u = (b - a) / L
        poly = geo.sections[s]
        P = len(poly)
        for e in range(P):
            for t in (-W / L, 0.0, 0.37, 1.0, 1.0 + W / L):  # the prism reaches W beyond both ends
                for f in (0.0, 0.5, 0.9):
                    x = (1 - f) * poly[e] + f * poly[(e + 1) % P]  # on a side face of the prism
                    p = a + t * (b - a) + x
                    assert abs(_violation(p, coef, seg, lo, hi, s)) < 1e-9  # active: equality
                    assert _violation(a + t * (b - a) + 1.01 * x, coef, seg, lo, hi, s) > 1e-5  # just outside
                    on_surface += 1
                    if 0.0 < t < 1.0:
                        assert _violation(a + t * (b - a) + 0.99 * x, coef, seg, lo, hi, s) < -1e-5  # just inside
        for end, sign in ((a, -1.0), (b, 1.0)):  # the caps: active along the line, outside beyond them
            cap = end + sign * W * u + 0.5 * poly[0]
            assert abs(_violation(cap, coef, seg, lo, hi, s)) < 1e-9
            assert _violation(cap + sign * 0.01 * W * u, coef, seg, lo, hi, s) > 1e-5
    assert on_surface > 100
    # the mesh: outward faces, vertices = waypoints + sections
    V, F = geo.vertices, geo.faces
    for s in range(4):
        fs = F[geo.face_segment == s]
        centre = V[np.unique(fs)].mean(axis=0)
        n = np.cross(V[fs[:, 1]] - V[fs[:, 0]], V[fs[:, 2]] - V[fs[:, 0]])
        assert (np.einsum("ij,ij->i", n, V[fs].mean(axis=1) - centre) > 0).all()
    # drawn in the world through T_world_body: the same prisms, rotated and moved
    T = np.eye(4)
    yaw = 0.7
    T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = [10.0, -3.0, 1.5]
    world = corridor_prisms(waypoints, W, T_world_frame=T)
    np.testing.assert_allclose(world.vertices, V @ T[:3, :3].T + T[:3, 3])
    assert world.edges.shape[1:] == (2, 3)
    with pytest.raises(VizError, match="half_width"):
        corridor_prisms(waypoints, -1.0)


def test_degenerate_segment_is_a_cube() -> None:
    waypoints = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0]])
    geo = corridor_prisms(waypoints, 0.25)
    cube = geo.vertices[np.unique(geo.faces[geo.face_segment == 1])]
    np.testing.assert_allclose(cube.min(axis=0), [0.75, -0.25, -0.25])
    np.testing.assert_allclose(cube.max(axis=0), [1.25, 0.25, 0.25])
    coef, seg, lo, hi = _constraint_rows(waypoints, 0.25)
    assert abs(_violation(np.array([1.25, 0.1, -0.25]), coef, seg, lo, hi, 1)) < 1e-9  # a cube corner region
    assert _violation(np.array([1.26, 0.0, 0.0]), coef, seg, lo, hi, 1) > 1e-5


def test_pick_point(map_path: Path) -> None:
    m = EsdfMap.open(map_path)
    corners = np.array([[-3.05, 8.95, 1.0], [9.85, 8.95, 1.0], [9.85, 1.95, 1.0], [-3.05, 1.95, 1.0]])
    p, how = pick_point([0.0, 3.0, 10.0], [0.0, 0.0, -1.0], plane=("z", 1.0, corners), esdf_map=m)
    assert how == "slice" and np.allclose(p, [0.0, 3.0, 1.0])
    # outside the slice: the map's zero level (z = 1 m, shifted by the ramp), pulled back 0.5 m
    p, how = pick_point([-2.5, 3.0, 4.0], [0.0, 0.0, -1.0], plane=("z", 1.0, corners * [0, 1, 1]), esdf_map=m)
    assert how == "surface" and abs(p[2] - 1.5) < 0.05
    p, how = pick_point([0.0, 3.0, 10.0], [0.0, 0.0, 1.0], esdf_map=m)  # looking away
    assert p is None and how == "none"


# ---------------------------------------------------------------------------------------- stores
def test_open_workspace_notes(tmp_path: Path, map_path: Path) -> None:
    import shutil

    with pytest.raises(VizError, match="not a directory"):
        open_workspace(tmp_path / "nope")
    ws = tmp_path / "ws"
    ws.mkdir()
    c = open_workspace(ws)
    assert c.empty and len(c.notes) == 3
    assert any("frames.zarr is missing" in n and "mapkit ingest" in n for n in c.notes)
    assert any("cloud.ply is missing" in n and "mapkit fuse" in n for n in c.notes)
    assert any("map.zarr is missing" in n and "mapkit esdf" in n for n in c.notes)
    shutil.copytree(map_path, ws / "map.zarr")
    (ws / "cloud.ply").write_bytes(b"garbage")
    (ws / "frames.zarr").mkdir()
    c = open_workspace(ws)
    assert c.esdf_map is not None and c.cloud_path is None and c.frames is None
    assert any(n.startswith("cloud.ply cannot be read") for n in c.notes)
    assert any(n.startswith("frames.zarr cannot be opened") for n in c.notes)
    (ws / "map.zarr" / "zarr.json").write_text("{broken")
    assert any(n.startswith("map.zarr cannot be opened") for n in open_workspace(ws).notes)


def write_fake_eval(root: Path, *, with_npz: bool = True) -> Path:
    """A small `mapkit eval` output: one box world, two pairs, two methods, one collision."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "worlds").mkdir(exist_ok=True)
    world = World([Box((3.0, 0.0, 1.0), (0.5, 0.5, 1.0)), HalfSpace((0.0, 0.0, 1.0), 0.0)], bounds=[[-2, -3, 0], [8, 3, 3]])
    world.to_json(root / "worlds" / "boxes.world.json")
    episodes, paths = [], {}
    for pair in range(2):
        start, goal = [0.0, -1.0 + 2 * pair, 1.0], [6.0, -1.0 + 2 * pair, 1.0]
        for method in ("learned", "straight"):
            collided = method == "straight" and pair == 0
            t = np.linspace(0, 3, 31)
            xyz = np.column_stack([np.linspace(start[0], goal[0] if not collided else 2.5, 31),
                                   np.full(31, start[1]) + (0.8 * np.sin(np.pi * t / 3) if method == "learned" else 0),
                                   np.full(31, 1.0)])
            paths[f"boxes/{pair:03d}/{method}"] = np.column_stack([t, xyz]).astype(np.float32)
            episodes.append({"world": "boxes", "pair": pair, "method": method,
                             "outcome": "collision" if collided else "success", "start": start, "goal": goal,
                             "collision_point": [2.5, -1.0, 1.0] if collided else None, "time_s": 3.0})
    (root / "results.json").write_text(json.dumps({
        "format": "mapkit-eval/1", "worlds": {"boxes": {"seed": 0, "world_json": "worlds/boxes.world.json"}},
        "methods": ["learned", "straight"], "episodes": episodes}))
    if with_npz:
        np.savez(root / "trajectories.npz", **paths)
    return root


def test_load_eval(tmp_path: Path) -> None:
    ev = load_eval(write_fake_eval(tmp_path / "ev"))
    assert ev.methods == ["learned", "straight"] and ev.pairs("boxes") == [0, 1]
    assert len(ev.episodes_of("boxes")) == 4 and len(ev.episodes_of("boxes", 1)) == 2
    path = ev.path_of("boxes", 0, "learned")
    assert path.shape == (31, 4) and path[0, 0] == 0.0
    assert ev.path_of("boxes", 5, "learned") is None
    V, F = world_mesh_arrays(ev.world_file("boxes"))
    assert V.shape[1] == 3 and F.shape[1] == 3 and F.max() < len(V)
    ev.close()
    ev = load_eval(write_fake_eval(tmp_path / "nonpz", with_npz=False))
    assert any("trajectories.npz is missing" in n for n in ev.notes)
    (tmp_path / "nonpz" / "results.json").write_text(json.dumps({"format": "other/2"}))
    with pytest.raises(VizError, match="mapkit-eval/1"):
        load_eval(tmp_path / "nonpz")
    (tmp_path / "nonpz" / "results.json").write_text("{not json")
    with pytest.raises(VizError, match="not readable JSON"):
        load_eval(tmp_path / "nonpz")
    with pytest.raises(VizError, match=r"no results.json"):
        load_eval(tmp_path)
