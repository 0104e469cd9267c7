"""`mapkit view` in a real browser: headless Chromium (Debian's `chromium`, software WebGL) opens the
page, waits for the scene, and the screenshot must show the ESDF slice where the camera looks.

Skipped when no Chromium is installed (`apt-get install chromium`; .ci/run installs it). The
screenshot is kept as a test artifact in $MAPKIT_TEST_ARTIFACTS (default: <tmp>/mapkit-test-artifacts).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from test_viewer import start_app  # noqa: F401 - the fixture checks threads and the port

from mapkit.esdf import write_map
from mapkit.viewer import find_chromium, screenshot

pytestmark = pytest.mark.skipif(
    find_chromium() is None, reason="no Chromium on this machine; `apt-get install chromium` (CI installs it)"
)
ARTIFACTS = Path(os.environ.get("MAPKIT_TEST_ARTIFACTS", Path(tempfile.gettempdir()) / "mapkit-test-artifacts"))
WIDTH, HEIGHT = 1280, 800


def sphere_workspace(root: Path) -> Path:
    """map.zarr of two spheres over a floor (signed distance, exact), an unobserved corner, and a
    cloud.ply of points on those surfaces."""
    import open3d as o3d

    ws = root / "ws"
    ws.mkdir(parents=True)
    vs, shape, origin = 0.1, (80, 60, 30), np.array([0.0, 0.0, 0.0])
    g = np.stack(np.meshgrid(*(origin[a] + vs * np.arange(shape[a]) for a in range(3)), indexing="ij"), axis=-1)
    centres, radius = np.array([[2.5, 3.0, 1.0], [5.5, 2.5, 1.0]]), 0.9
    d = np.min([np.linalg.norm(g - c, axis=-1) - radius for c in centres], axis=0)
    d = np.minimum(d, g[..., 2] + 0.05)  # floor just below z = 0
    observed = np.ones(shape, bool)
    observed[60:, 45:, :] = False
    write_map(ws / "map.zarr", esdf=d, esdf_raw=d, observed=observed, origin=origin, voxel_size=vs,
              frame_id="world", sigma=0.0, unknown_policy="free")
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(20000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = np.concatenate([c + radius * dirs for c in centres])
    o3d.io.write_point_cloud(str(ws / "cloud.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    return ws


def centre_box(image: np.ndarray, frac: float = 0.08) -> np.ndarray:
    h, w = image.shape[:2]
    return image[int(h * (0.5 - frac)):int(h * (0.5 + frac)), int(w * (0.5 - frac)):int(w * (0.5 + frac))]


def page_background(image: np.ndarray) -> np.ndarray:
    """The page's background colour: the commonest colour of the screenshot's top band, left half."""
    band = image[: image.shape[0] // 20, : image.shape[1] // 2].reshape(-1, 3)
    colours, counts = np.unique(band, axis=0, return_counts=True)
    return colours[np.argmax(counts)].astype(int)


def non_background(region: np.ndarray, background: np.ndarray) -> np.ndarray:
    """bool mask of the region's pixels that differ from the background colour."""
    return np.abs(region.astype(int) - background).max(axis=-1) > 40


def palette_match(region: np.ndarray, texture: np.ndarray, *, tol: int = 30, samples: int = 3000) -> float:
    """Fraction of region pixels within `tol` (per channel) of some colour of the slice texture."""
    rng = np.random.default_rng(0)
    pix = region.reshape(-1, 3)[rng.integers(0, region.shape[0] * region.shape[1], samples)].astype(int)
    palette = np.unique(texture.reshape(-1, 3), axis=0).astype(int)
    if len(palette) > 4000:
        palette = palette[rng.choice(len(palette), 4000, replace=False)]
    dist = np.abs(pix[:, None, :] - palette[None, :, :]).max(axis=-1).min(axis=1)
    return float((dist <= tol).mean())


@pytest.mark.slow
def test_browser_shows_the_slice(tmp_path: Path, start_app) -> None:  # noqa: F811 - the fixture imported above
    from PIL import Image

    ws = sphere_workspace(tmp_path)
    app = start_app(workspace=ws, slice_axis="z", slice_position=1.0)
    app.gui.layers.cloud.value = False  # the slice alone in the view
    app.gui.slice.cmap.value = "viridis"  # no white in it: nothing can pass for the page background
    assert app.slice is not None and app.slice.axis == "z" and app.slice.cmap == "viridis"

    def slice_drawn(image: np.ndarray) -> bool:
        return bool(non_background(centre_box(image), page_background(image)).mean() > 0.95)

    artifact = ARTIFACTS / "viewer_browser.png"
    try:
        out = screenshot(app.url, tmp_path / "viewer.png", width=WIDTH, height=HEIGHT, ready=slice_drawn, timeout=120)
    finally:
        if (tmp_path / "viewer.png").exists():
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            shutil.copy(tmp_path / "viewer.png", artifact)
    image = np.asarray(Image.open(out).convert("RGB"))
    assert image.shape == (HEIGHT, WIDTH, 3)
    region = centre_box(image)  # the camera looks at the slice's centre
    assert non_background(region, page_background(image)).mean() > 0.95, f"slice region mostly background; see {artifact}"
    assert palette_match(region, app.slice.texture) > 0.9, f"the slice region does not show the slice; see {artifact}"
    # the panel is drawn too (right side: dark text on light)
    panel = image[:, int(0.8 * WIDTH):]
    assert (panel.mean(axis=-1) < 100).mean() > 0.002
