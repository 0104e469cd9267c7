"""mapkit.esdf: signed distance against analytic shapes, smoothing guard, chunking, map.zarr, queries, slices."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from mapkit.errors import MapkitError
from mapkit.esdf import (
    EsdfError,
    EsdfMap,
    chunk_halo,
    create_map,
    render_slices,
    signed_distance,
    signed_distance_chunked,
    slice_plane,
    smooth,
    write_map,
)

VS = 0.05  # voxel size of the analytic tests (m)


# ----------------------------------------------------------------------------- helpers
def centres(shape, origin=(0.0, 0.0, 0.0), vs=VS):
    """World coordinates [nx, ny, nz, 3] of voxel centres."""
    return np.asarray(origin) + vs * np.indices(shape).transpose(1, 2, 3, 0).astype(np.float64)


def sphere_sdf(p, c, r):
    return np.linalg.norm(p - np.asarray(c), axis=-1) - r


def box_sdf(p, lo, hi):
    q = np.maximum(np.asarray(lo) - p, p - np.asarray(hi))
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def random_scene(shape, seed=0, boxes=12):
    rng = np.random.default_rng(seed)
    occ = np.zeros(shape, bool)
    occ[:, :, :2] = True  # floor
    for _ in range(boxes):
        lo = rng.integers(0, shape, 3)
        size = rng.integers(1, max(3, min(shape) // 4), 3)
        occ[lo[0] : lo[0] + size[0], lo[1] : lo[1] + size[1], lo[2] : lo[2] + size[2]] = True
    return occ


def small_map(tmp_path: Path, *, shape=(40, 30, 20), origin=(-1.0, 2.0, 0.25), vs=0.1, sigma=0.15, name="map.zarr"):
    occ = random_scene(shape, seed=3)
    raw = signed_distance(occ, voxel_size=vs)
    esdf, _ = smooth(raw, voxel_size=vs, sigma=sigma)
    observed = np.ones(shape, np.uint8)
    observed[: shape[0] // 3, :, shape[2] // 2 :] = 0
    path = write_map(
        tmp_path / name, esdf=esdf, esdf_raw=raw, observed=observed, origin=origin, voxel_size=vs,
        frame_id="world", sigma=sigma, unknown_policy="free", parameters={"max_dist": None, "note": "test"},
    )
    return path, occ, raw, esdf, observed


# ----------------------------------------------------------------------------- signed distance
@pytest.mark.parametrize(
    "name,sdf",
    [
        ("plane", lambda p: p[..., 2] - 1.013),
        ("sphere", lambda p: sphere_sdf(p, (1.6, 1.55, 1.62), 0.9)),
        ("box", lambda p: box_sdf(p, (0.83, 0.71, 0.52), (2.11, 2.3, 1.97))),
    ],
)
def test_signed_distance_matches_analytic_shapes(name, sdf):
    truth = sdf(centres((64, 64, 64)))
    d = signed_distance(truth < 0, voxel_size=VS)
    assert d.dtype == np.float32 and d.shape == truth.shape
    err = (d - truth) / VS
    # the half-voxel convention bounds the error by half a voxel for flat faces, a bit more at box edges
    assert np.abs(err).max() <= 0.9, name
    band = np.abs(truth) <= 3 * VS  # where the cost map matters most
    assert np.abs(err[band]).mean() <= 0.3, name
    if name == "plane":
        assert np.abs(err).mean() <= 0.3
    # the sign is right wherever the truth is more than half a voxel from the surface
    clear = np.abs(truth) > 0.5 * VS
    assert np.array_equal(d[clear] > 0, truth[clear] > 0)
    assert np.abs(d).min() >= 0.5 * VS - 1e-6  # never zero: the surface lies between voxel centres


def test_half_voxel_convention_on_a_wall():
    occ = np.zeros((21, 5, 5), bool)
    occ[8:13] = True  # a wall 5 voxels thick, x = 8..12
    d = signed_distance(occ, voxel_size=0.2)
    column = d[:, 2, 2]
    # free: (distance to nearest occupied centre - 0.5) voxels; occupied: -(distance to nearest free - 0.5)
    expected = np.array([7.5, 6.5, 5.5, 4.5, 3.5, 2.5, 1.5, 0.5, -0.5, -1.5, -2.5, -1.5, -0.5, 0.5, 1.5, 2.5, 3.5, 4.5, 5.5, 6.5, 7.5])
    np.testing.assert_allclose(column, 0.2 * expected, rtol=0, atol=1e-6)
    assert (d[9:12] < 0).all() and (d[:8] > 0).all() and (d[13:] > 0).all()


def test_no_plateau_gradient_is_unit_in_free_space():
    occ = np.zeros((80, 60, 40), bool)
    occ[:, :, 0] = True
    occ[10:14, 10:14, :] = True  # a pillar
    d = signed_distance(occ, voxel_size=0.1)
    assert d.max() > 3.0  # far voxels keep growing: no plateau without max_dist
    g = np.linalg.norm(np.stack(np.gradient(d.astype(np.float64), 0.1)), axis=0)
    interior = (d > 0.3)
    interior[0] = interior[-1] = False
    interior[:, 0] = interior[:, -1] = False
    interior[:, :, -1] = False
    assert np.median(g[interior]) == pytest.approx(1.0, abs=0.02)
    assert np.quantile(g[interior], 0.02) > 0.7  # nowhere flat


def test_backends_agree_and_scipy_is_exact():
    occ = random_scene((48, 40, 36), seed=1)
    a = signed_distance(occ, voxel_size=0.1, backend="edt")
    b = signed_distance(occ, voxel_size=0.1, backend="scipy")
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    ref = np.where(occ, -(ndimage.distance_transform_edt(occ) - 0.5), ndimage.distance_transform_edt(~occ) - 0.5) * 0.1
    np.testing.assert_allclose(a, ref, rtol=0, atol=1e-5)
    # any memory layout in, C-ordered float32 out
    f = signed_distance(np.asfortranarray(occ), voxel_size=0.1)
    s = signed_distance(occ[::-1].copy()[::-1], voxel_size=0.1)
    assert f.flags.c_contiguous and s.flags.c_contiguous
    np.testing.assert_array_equal(f, a)
    np.testing.assert_array_equal(s, a)


def test_max_dist_clamps_and_keeps_the_rest():
    occ = random_scene((48, 40, 36), seed=2)
    full = signed_distance(occ, voxel_size=0.1)
    clamped = signed_distance(occ, voxel_size=0.1, max_dist=0.45)
    assert np.abs(clamped).max() <= 0.45 + 1e-7
    inside = np.abs(full) <= 0.45
    np.testing.assert_array_equal(clamped[inside], full[inside])
    np.testing.assert_array_equal(clamped[~inside], np.sign(full[~inside]) * np.float32(0.45))


def test_degenerate_grids():
    free = np.zeros((8, 8, 8), bool)
    with pytest.raises(EsdfError, match="no occupied voxel"):
        signed_distance(free, voxel_size=0.1)
    np.testing.assert_array_equal(signed_distance(free, voxel_size=0.1, max_dist=2.0), np.full(free.shape, 2.0, np.float32))
    with pytest.raises(EsdfError, match="no free voxel"):
        signed_distance(~free, voxel_size=0.1, backend="scipy")
    np.testing.assert_array_equal(signed_distance(~free, voxel_size=0.1, max_dist=1.0), np.full(free.shape, -1.0, np.float32))


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"occupied": np.zeros((4, 4, 4), np.uint8)}, "dtype uint8"),
        ({"occupied": np.zeros((4, 4), bool)}, "3-D"),
        ({"voxel_size": 0.0}, "voxel_size=0.0"),
        ({"voxel_size": float("nan")}, "voxel_size=nan"),
        ({"max_dist": -1.0}, "max_dist=-1.0"),
        ({"backend": "fmm"}, "backend='fmm'"),
        ({"threads": 0}, "threads=0"),
    ],
)
def test_bad_inputs_name_the_value(kwargs, match):
    args = {"occupied": random_scene((8, 8, 8)), "voxel_size": 0.1, **kwargs}
    occ = args.pop("occupied")
    with pytest.raises(EsdfError, match=match) as info:
        signed_distance(occ, **args)
    assert isinstance(info.value, MapkitError)


# ----------------------------------------------------------------------------- smoothing
def test_smooth_matches_gaussian_filter_and_copies_at_zero_sigma():
    occ = random_scene((40, 36, 30), seed=4)
    raw = signed_distance(occ, voxel_size=0.1)
    ref = ndimage.gaussian_filter(raw, 1.5, truncate=3.0, mode="nearest")
    out, n = smooth(raw, voxel_size=0.1, sigma=0.15)
    guarded = out != ref
    moved = np.abs(out - ref) > 1e-5
    assert moved.sum() == n  # only the guarded voxels differ from the plain Gaussian
    np.testing.assert_array_equal(out[moved], raw[moved])
    np.testing.assert_allclose(out[~moved], ref[~moved], rtol=0, atol=1e-5)
    assert guarded.any()
    same, zero = smooth(raw, voxel_size=0.1, sigma=0.0)
    assert zero == 0 and np.array_equal(same, raw) and same is not raw
    with pytest.raises(EsdfError, match=r"sigma=-0.1"):
        smooth(raw, voxel_size=0.1, sigma=-0.1)


def test_smoothing_never_flips_voxels_far_from_the_surface():
    # a thin plate (3 voxels) and a thin pole in open space: a wide Gaussian averages their inside
    # with the large positive distances around them, which would flip the plate's core to positive
    occ = np.zeros((48, 48, 48), bool)
    occ[22:25, 8:40, 8:40] = True
    occ[8:11, 8:11, :] = True
    vs, sigma = 0.1, 0.3
    raw = signed_distance(occ, voxel_size=vs)
    plain = ndimage.gaussian_filter(raw, sigma / vs, truncate=3.0, mode="nearest")
    far = np.abs(raw) > vs
    would_flip = far & ((plain > 0) != (raw > 0))
    assert would_flip.sum() > 50, "the scene must be one where a plain Gaussian flips signs"
    assert raw[23, 24, 24] < 0 and plain[23, 24, 24] > 0
    out, n = smooth(raw, voxel_size=vs, sigma=sigma)
    assert n == would_flip.sum()
    assert not (far & ((out > 0) != (raw > 0))).any()
    assert out[23, 24, 24] < 0


# ----------------------------------------------------------------------------- chunked
def test_chunked_equals_dense_clamped():
    occ = random_scene((70, 53, 41), seed=5, boxes=20)
    vs, md = 0.1, 0.55
    dense = signed_distance(occ, voxel_size=vs, max_dist=md)
    out = np.full(occ.shape, np.nan, np.float32)
    summary = signed_distance_chunked(occ, out, voxel_size=vs, max_dist=md, chunk=24, progress=False)
    assert summary.chunks == 3 * 3 * 2 and summary.halo == chunk_halo(voxel_size=vs, max_dist=md) == 7
    np.testing.assert_array_equal(out, dense)

    sigma = 0.2
    sm, n = smooth(dense, voxel_size=vs, sigma=sigma)
    out_raw = np.full(occ.shape, np.nan, np.float32)
    summary = signed_distance_chunked(occ, out, voxel_size=vs, max_dist=md, chunk=24, sigma=sigma, out_raw=out_raw, progress=False)
    np.testing.assert_array_equal(out_raw, dense)
    np.testing.assert_allclose(out, sm, rtol=0, atol=2e-6)  # BLAS block shapes differ: float32 rounding only
    assert summary.n_prevented == n


def test_chunked_streams_into_a_map_store(tmp_path):
    occ = random_scene((70, 40, 30), seed=6)
    vs, md, sigma = 0.1, 0.4, 0.1
    with create_map(tmp_path / "map.zarr", shape=occ.shape, origin=(0, 0, 0), voxel_size=vs, frame_id="world",
                    sigma=sigma, unknown_policy="free", parameters={"max_dist": md}) as w:
        assert not (tmp_path / "map.zarr").exists()  # only the temporary exists while writing
        signed_distance_chunked(occ, w.esdf, voxel_size=vs, max_dist=md, chunk=64, sigma=sigma, out_raw=w.esdf_raw, progress=False)
        w.observed[:] = 1
        w.finalize()
    m = EsdfMap.open(tmp_path / "map.zarr")
    np.testing.assert_array_equal(m.esdf_raw[:], signed_distance(occ, voxel_size=vs, max_dist=md))
    assert [p.name for p in tmp_path.iterdir()] == ["map.zarr"]
    with pytest.raises(EsdfError, match="multiple of"):
        signed_distance_chunked(occ, m.esdf, voxel_size=vs, max_dist=md, chunk=50, progress=False)


def test_create_map_aborts_cleanly_and_refuses_to_overwrite(tmp_path):
    target = tmp_path / "map.zarr"
    with pytest.raises(RuntimeError), create_map(target, shape=(4, 4, 4), origin=(0, 0, 0), voxel_size=0.1,
                                                 frame_id="world", sigma=0, unknown_policy="free"):
        raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []
    small_map(tmp_path)
    with pytest.raises(EsdfError, match="overwrite"):
        small_map(tmp_path)
    with pytest.raises(EsdfError, match="unknown_policy"):
        create_map(tmp_path / "b.zarr", shape=(4, 4, 4), origin=(0, 0, 0), voxel_size=0.1, frame_id="world", sigma=0, unknown_policy="maybe")


# ----------------------------------------------------------------------------- store and xarray
def test_map_round_trip_and_xarray_coordinates(tmp_path):
    import xarray as xr

    origin, vs = (-1.0, 2.0, 0.25), 0.1
    path, occ, raw, esdf, observed = small_map(tmp_path, origin=origin, vs=vs)
    m = EsdfMap.open(path)
    assert m.shape == occ.shape and m.voxel_size == vs and m.frame_id == "world" and m.sigma == 0.15
    np.testing.assert_array_equal(m.origin, origin)
    np.testing.assert_array_equal(m.esdf[:], esdf)
    np.testing.assert_array_equal(m.esdf_raw[:], raw)
    np.testing.assert_array_equal(m.observed[:], observed)
    assert m.attrs["kind"] == "mapkit.map" and m.attrs["units"] == "m" and m.attrs["unknown_policy"] == "free"
    assert m.attrs["mapkit_version"] and m.attrs["parameters"] == {"max_dist": None, "note": "test"}
    np.testing.assert_allclose(m.bounds, [origin, np.add(origin, vs * (np.array(occ.shape) - 1))])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # consolidated metadata: xarray opens it without complaint
        ds = xr.open_zarr(path)
    assert ds.esdf.dims == ("x", "y", "z") and ds.observed.dims == ("x", "y", "z")
    np.testing.assert_allclose(ds.x.values, m.coords("x"))
    np.testing.assert_allclose(ds.z.values, origin[2] + vs * np.arange(occ.shape[2]))
    v = ds.esdf.sel(x=-1.0 + 7 * vs, y=2.0 + 4 * vs, z=0.25 + 9 * vs, method="nearest").values
    assert v == esdf[7, 4, 9]
    assert ds.attrs["voxel_size"] == vs
    loaded = m.load()
    assert isinstance(loaded.esdf, np.ndarray)


def _expect_open_error(path, *words):
    with pytest.raises(EsdfError) as info:
        EsdfMap.open(path)
    for w in words:
        assert w in str(info.value), str(info.value)


def test_missing_corrupt_and_foreign_stores(tmp_path):
    import zarr

    _expect_open_error(tmp_path / "nope.zarr", "no map at", "mapkit esdf")
    (tmp_path / "empty.zarr").mkdir()
    _expect_open_error(tmp_path / "empty.zarr", "not a zarr", "--overwrite")
    path, *_ = small_map(tmp_path)
    (path / "zarr.json").write_text("{ this is not json")
    _expect_open_error(path, "corrupt", "--overwrite")
    foreign = zarr.open_group(tmp_path / "frames.zarr", mode="w-", zarr_format=3)
    foreign.attrs["kind"] = "mapkit.frames"
    _expect_open_error(tmp_path / "frames.zarr", "not a mapkit map", "'mapkit.frames'", "--overwrite")
    path2, *_ = small_map(tmp_path, name="m2.zarr")
    import shutil

    shutil.rmtree(path2 / "esdf_raw")
    meta = json.loads((path2 / "zarr.json").read_text())
    meta.pop("consolidated_metadata", None)
    (path2 / "zarr.json").write_text(json.dumps(meta))
    _expect_open_error(path2, "'esdf_raw'", "--overwrite")


def test_damaged_chunks_are_one_line_for_every_reader(tmp_path):
    """slice, point lookups and queries all name the grid and the fix (a blosc error before)."""
    from click.testing import CliRunner

    from mapkit.cli.main import main

    path, *_ = small_map(tmp_path, name="map.zarr")
    for chunk in (path / "esdf" / "c").rglob("*"):
        if chunk.is_file():
            chunk.write_bytes(b"\x00garbage")
    m = EsdfMap.open(path)
    for read in (lambda: m.read("esdf", (0, 0, 0)), lambda: m.query(np.zeros((1, 3)))):
        with pytest.raises(EsdfError, match=r"cannot read 'esdf' of map .* re-run `mapkit esdf --overwrite`"):
            read()
    z = float(m.origin[2])
    r = CliRunner().invoke(main, ["slice", "-w", str(tmp_path), "-o", str(tmp_path / "s.png"), "--z", str(z)])
    assert r.exit_code == 1 and "cannot read 'esdf'" in r.output and "Traceback" not in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1 and not (tmp_path / "s.png").exists()


@pytest.mark.parametrize("damage", ["truncated", "deleted"])
def test_slice_of_a_map_with_one_damaged_chunk_is_one_line_naming_it(tmp_path, damage):
    """A chunk cut short or deleted (which zarr reads as NaN, without an error) under `mapkit slice`:
    exit 1, one line naming the store, the grid, the chunk, the damage and the fix, no traceback."""
    from click.testing import CliRunner

    from mapkit.cli.main import main

    path, *_ = small_map(tmp_path, shape=(70, 30, 20))  # two 64-voxel chunks along x
    chunk = path / "esdf" / "c" / "1" / "0" / "0"
    if damage == "truncated":
        chunk.write_bytes(chunk.read_bytes()[:20])
    else:
        chunk.unlink()
    out = tmp_path / "s.png"
    r = CliRunner().invoke(main, ["slice", "-w", str(tmp_path), "-o", str(out), "--z", "1.0"])
    assert r.exit_code == 1 and "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1, r.output
    words = ["error: cannot read 'esdf' of map", str(path), "chunk c/1/0/0 is", "the store is damaged",
             "re-run `mapkit esdf --overwrite`"]
    words.append("undecodable" if damage == "truncated" else "missing")
    assert all(w in r.output for w in words), r.output
    assert not out.exists()
    # a slice that stays in the sound chunk is drawn as before
    r = CliRunner().invoke(main, ["slice", "-w", str(tmp_path), "-o", str(out), "--x", "0.0"])
    assert r.exit_code == 0 and out.exists(), r.output


def test_observed_chunks_left_out_by_zarr_are_not_damage(tmp_path):
    """zarr stores no chunk that holds only the fill value (0 for observed): not a missing chunk."""
    path, *_ = small_map(tmp_path, shape=(70, 30, 20))
    (path / "observed" / "c" / "1" / "0" / "0").unlink()  # as if never observed
    m = EsdfMap.open(path)
    assert not m.read("observed", (slice(None), slice(None), 0))[64:].any()
    m.check_stored("esdf")
    (path / "esdf" / "c" / "1" / "0" / "0").unlink()
    with pytest.raises(EsdfError, match=r"chunk c/1/0/0 is missing .* re-run `mapkit esdf --overwrite`"):
        m.check_stored("esdf")
    m.load()
    m.check_stored("esdf")  # in memory: nothing to check


# ----------------------------------------------------------------------------- queries
def linear_map(shape=(12, 10, 9), origin=(0.3, -0.2, 1.0), vs=0.25, coef=(0.7, -1.3, 0.4), c0=0.5):
    p = centres(shape, origin, vs)
    field = (c0 + p @ np.asarray(coef)).astype(np.float32)
    return EsdfMap(esdf=field, esdf_raw=field * 2, voxel_size=vs, origin=origin)


def test_query_at_voxel_centre_returns_the_voxel_exactly():
    rng = np.random.default_rng(0)
    field = rng.normal(size=(9, 8, 7)).astype(np.float32)
    m = EsdfMap(esdf=field, voxel_size=0.2, origin=(1.0, -2.0, 0.5))
    idx = np.stack([rng.integers(0, n, 50) for n in field.shape], axis=-1)
    d, _ = m.query(m.origin + m.voxel_size * idx)
    np.testing.assert_array_equal(d, field[idx[:, 0], idx[:, 1], idx[:, 2]])
    import torch

    t = m.query_torch(torch.as_tensor(m.origin + m.voxel_size * idx))
    np.testing.assert_array_equal(t.numpy(), field[idx[:, 0], idx[:, 1], idx[:, 2]])


def test_trilinear_reproduces_a_linear_field_and_its_gradient():
    m = linear_map()
    rng = np.random.default_rng(1)
    lo, hi = m.bounds
    p = rng.uniform(lo, hi, size=(200, 3))
    d, g = m.query(p)
    np.testing.assert_allclose(d, 0.5 + p @ [0.7, -1.3, 0.4], atol=1e-5)
    np.testing.assert_allclose(g, np.tile([0.7, -1.3, 0.4], (200, 1)), atol=1e-4)
    d2, _ = m.query(p, raw=True)
    np.testing.assert_allclose(d2, 2 * d, atol=1e-5)


def test_query_gradient_matches_finite_differences_numpy_and_torch():
    import torch

    rng = np.random.default_rng(2)
    field = rng.normal(size=(7, 6, 5)).astype(np.float32)
    m = EsdfMap(esdf=field, voxel_size=0.3, origin=(0.1, 0.2, -0.4))
    # points well inside cells (trilinear is smooth there; cell faces are kinks)
    cell = np.stack([rng.integers(0, n - 1, 40) for n in field.shape], axis=-1)
    p = m.origin + m.voxel_size * (cell + rng.uniform(0.1, 0.9, size=(40, 3)))
    _, g = m.query(p)
    h = 1e-6
    fd = np.stack([(m.query(p + h * e)[0] - m.query(p - h * e)[0]) / (2 * h) for e in np.eye(3)], axis=-1)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6)

    pt = torch.tensor(p, dtype=torch.float64, requires_grad=True)
    d_t = m.query_torch(pt)
    np.testing.assert_allclose(d_t.detach().numpy(), m.query(p)[0], atol=1e-12)
    (grad_t,) = torch.autograd.grad(d_t.sum(), pt)
    np.testing.assert_allclose(grad_t.numpy(), g, atol=1e-10)
    assert torch.autograd.gradcheck(lambda q: m.query_torch(q), (pt,), eps=1e-6, atol=1e-6)
    d32 = m.query_torch(pt.detach().float().reshape(4, 10, 3))
    assert d32.dtype == torch.float32 and d32.shape == (4, 10)


def test_outside_policy_nan_and_clamp():
    import torch

    m = linear_map()
    lo, hi = m.bounds
    inside = (lo + hi) / 2
    out_x = np.array([hi[0] + 0.4, inside[1], inside[2]])
    below = np.array([inside[0], inside[1], lo[2] - 1.0])
    pts = np.stack([inside, out_x, below])
    d, g = m.query(pts)
    assert np.isfinite(d[0]) and np.isnan(d[1:]).all() and np.isnan(g[1:]).all()
    dc, gc = m.query(pts, outside="clamp")
    proj = np.clip(pts, lo, hi)
    np.testing.assert_allclose(dc, m.query(proj)[0], atol=1e-6)
    np.testing.assert_allclose(gc[1], [0.0, -1.3, 0.4], atol=1e-4)  # zero along the clamped axis
    np.testing.assert_allclose(gc[2], [0.7, -1.3, 0.0], atol=1e-4)
    t = m.query_torch(torch.as_tensor(pts))
    assert torch.isnan(t[1:]).all() and torch.isfinite(t[0])
    pt = torch.as_tensor(pts).requires_grad_(True)
    tc = m.query_torch(pt, outside="clamp")
    np.testing.assert_allclose(tc.detach().numpy(), dc, atol=1e-6)
    (gt,) = torch.autograd.grad(tc.sum(), pt)
    np.testing.assert_allclose(gt.numpy(), gc, atol=1e-5)
    # points on the border (within float noise) are inside
    d_edge, _ = m.query(hi[None] + 1e-12)
    assert np.isfinite(d_edge).all()
    with pytest.raises(EsdfError, match="outside='wrap'"):
        m.query(pts, outside="wrap")
    with pytest.raises(EsdfError, match=r"shape \(N, 3\)"):
        m.query(np.zeros((4, 2)))


# ----------------------------------------------------------------------------- slices
def test_slice_plane_snaps_and_reads_the_plane(tmp_path):
    path, _, raw, esdf, observed = small_map(tmp_path)
    m = EsdfMap.open(path)
    s = slice_plane(m, axis="z", position=0.25 + 5 * 0.1 + 0.03)
    assert s.position == pytest.approx(0.25 + 0.5)
    np.testing.assert_array_equal(s.values, esdf[:, :, 5])
    np.testing.assert_array_equal(s.observed, observed[:, :, 5] > 0)
    assert s.extent == pytest.approx((-1.05, -1.0 + 39 * 0.1 + 0.05, 1.95, 2.0 + 29 * 0.1 + 0.05))
    sx = slice_plane(m, axis="x", position=-1.0, raw=True)
    np.testing.assert_array_equal(sx.values, raw[0])
    assert sx.values.shape == (30, 20)
    with pytest.raises(EsdfError, match=r"valid z is 0\.200 \.\. 2\.200 m"):
        slice_plane(m, axis="z", position=5.0)
    with pytest.raises(EsdfError, match="axis='w'"):
        slice_plane(m, axis="w", position=0.0)


def test_render_slices_png(tmp_path):
    from matplotlib import image as mpimg

    from mapkit.esdf._slice import _slice_figure

    occ = np.zeros((60, 50, 40), bool)
    occ[:, :, :2] = True
    rng = np.random.default_rng(7)
    for _ in range(12):  # trees
        cx, cy, r = rng.uniform(5, 55), rng.uniform(5, 45), rng.uniform(1.0, 3.0)
        xx, yy = np.meshgrid(np.arange(60), np.arange(50), indexing="ij")
        occ[(xx - cx) ** 2 + (yy - cy) ** 2 <= r * r, : int(rng.uniform(15, 40))] = True
    raw = signed_distance(occ, voxel_size=0.1)
    esdf, _ = smooth(raw, voxel_size=0.1, sigma=0.1)
    observed = np.ones(occ.shape, np.uint8)
    observed[40:, 30:, :] = 0
    m = EsdfMap(esdf=esdf, esdf_raw=raw, observed=observed, voxel_size=0.1, origin=(0, 0, 0.0), sigma=0.1)
    heights = (1.0, 2.5, 3.5)
    fig = _slice_figure(m, z=heights, x=(), y=(), raw=False)
    panels = [a for a in fig.axes if a.get_label() != "<colorbar>" and a.get_visible()]
    assert len(panels) == 3
    assert [a.get_title() for a in panels] == [f"height z = {h:.2f} m" for h in heights]
    out = render_slices(m, z=heights, path=tmp_path / "slices.png")
    assert out.exists() and out.stat().st_size > 10_000
    img = mpimg.imread(out)
    non_white = np.any(img[..., :3] < 0.95, axis=-1).mean()
    assert non_white > 0.3  # the panels are filled, not blank
    out2 = render_slices(m, z=(1.0,), y=(2.0,), path=tmp_path / "v.png")
    assert out2.exists()
    with pytest.raises(EsdfError, match="valid z"):
        render_slices(m, z=(9.0,), path=tmp_path / "bad.png")
    with pytest.raises(EsdfError, match="no slice requested"):
        render_slices(m, path=tmp_path / "none.png")


def test_query_torch_on_cuda_matches_cpu():
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    m = linear_map()
    rng = np.random.default_rng(3)
    lo, hi = m.bounds
    p = torch.tensor(rng.uniform(lo - 0.2, hi + 0.2, size=(64, 3)))
    for dtype in (torch.float32, torch.float64):
        q = p.to("cuda", dtype).requires_grad_(True)
        d = m.query_torch(q, outside="clamp")
        (g,) = torch.autograd.grad(d.sum(), q)
        assert d.device.type == "cuda" and d.dtype == dtype
        ref = m.query(p.numpy(), outside="clamp")
        np.testing.assert_allclose(d.detach().cpu().numpy(), ref[0], atol=1e-4)
        np.testing.assert_allclose(g.cpu().numpy(), ref[1], atol=1e-3)


def test_map_zarr_is_an_ome_zarr_image_in_metres(tmp_path):
    """The ome-zarr package's reader finds the ESDF with axes x/y/z in metres, 3 levels, and scale and
    translation that put every level's voxels where the map's are; xarray still opens the root."""
    import xarray as xr
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    path, _, _, esdf, _ = small_map(tmp_path, shape=(40, 30, 20), origin=(-1.0, 2.0, 0.25), vs=0.1)
    image = next(iter(Reader(parse_url(str(path)))()))
    levels = [np.asarray(level) for level in image.data]
    assert [a.shape for a in levels] == [(40, 30, 20), (20, 15, 10), (10, 8, 5)][: len(levels)] and len(levels) >= 2
    np.testing.assert_array_equal(levels[0], np.asarray(esdf, dtype=np.float32))
    assert [a["name"] for a in image.metadata["axes"]] == ["x", "y", "z"]
    assert {a["unit"] for a in image.metadata["axes"]} == {"meter"}
    transforms = image.metadata["coordinateTransformations"]
    (scale0, shift0), (scale1, shift1) = ([t["scale" if t["type"] == "scale" else "translation"] for t in level]
                                          for level in transforms[:2])
    np.testing.assert_allclose(scale0, [0.1] * 3) and np.testing.assert_allclose(shift0, [-1.0, 2.0, 0.25])
    np.testing.assert_allclose(scale1, [0.2] * 3)
    fine = esdf[2:4, 6:8, 4:6]  # the 8 voxels under coarse voxel (1, 3, 2)
    np.testing.assert_allclose(levels[1][1, 3, 2], fine.mean(), rtol=1e-5)
    centres = np.array([-1.0, 2.0, 0.25]) + 0.1 * np.array([[i, j, k] for i in (2, 3) for j in (6, 7) for k in (4, 5)])
    np.testing.assert_allclose(np.asarray(shift1) + 0.2 * np.array([1, 3, 2]), centres.mean(axis=0))
    with xr.open_zarr(path) as ds:  # the ngff subgroup stays out of the xarray view
        assert set(ds.data_vars) == {"esdf", "esdf_raw", "observed"}
    assert EsdfMap.open(path).load().shape == (40, 30, 20)
