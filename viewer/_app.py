"""The viser app behind ``mapkit view``: layers, panel and callbacks. Every computation is a call
into :mod:`mapkit.viz` (or another library stage); this module only wires them to viser."""

from __future__ import annotations

import contextlib
import errno
import io
import socket
import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

import numpy as np

from mapkit.errors import MapkitError
from mapkit.viewer._panels import CloudPanel, EvalPanel, FlightPanel, Panels, PlanPanel, SlicePanel, built

if TYPE_CHECKING:
    from viser import GuiInputHandle

    from mapkit.viz import MapSlicer

_T = TypeVar("_T")

LAYERS = ("cloud", "slice", "flight", "plan", "corridor", "eval")
_LAYER_LABELS = {
    "cloud": "point cloud", "slice": "ESDF slice", "flight": "flight", "plan": "planned trajectory",
    "corridor": "corridor", "eval": "evaluation",
}
# Panel order: the interactive planner first, the cloud's few options last.
_ORDER = {"status": 0, "message": 1, "layers": 2, "plan": 3, "slice": 4, "flight": 5, "eval": 6, "cloud": 7}
SLICE_CMAPS = ("RdBu", "coolwarm", "viridis", "magma", "turbo", "gray")
_VALUE_MODES = {"signed distance [m]": "distance", "obstacle cost": "cost"}
_COLORS = {
    "flight_path": (40, 40, 40), "frustum": (90, 90, 90), "current": (230, 120, 0), "keypoint": (200, 0, 200),
    "goal": (255, 190, 0), "corridor": (60, 150, 255), "collision": (220, 0, 0), "start": (0, 170, 0),
    "eval_goal": (255, 190, 0), "world": (185, 185, 185),
}


def _set_value(handle: GuiInputHandle[_T], value: _T) -> None:
    """Set a viser input's value: the clients show it and its update callbacks run (viser's ``value``
    setter, which mypy reads as a read-only property)."""
    handle.value = value  # type: ignore[misc]  # viser's setter, unseen by mypy


class ViewerError(MapkitError):
    """The viewer cannot start (port in use, bad host, nothing to show), in one line with the fix."""


@dataclass
class ViewerConfig:
    """What ``mapkit view`` shows and where it listens."""

    workspace: Path | None = None
    """Workspace directory (frames.zarr, cloud.ply, map.zarr; any subset)."""
    model: Path | None = None
    """Run directory with model.pt: enables live planning from the selected frame."""
    eval_dir: Path | None = None
    """A ``mapkit eval`` output directory (results.json, trajectories.npz, worlds/)."""
    host: str = "127.0.0.1"
    """Interface to bind; "0.0.0.0" exposes the viewer to the network."""
    port: int = 8080
    """TCP port; 0 picks a free one."""
    max_points: int = 2_000_000
    """Point-cloud points sent to the browser at most (voxel-grid downsampled above)."""
    frustum_every: int = 10
    """Draw a camera frustum every N frames."""
    frustum_depth: float = 0.4
    """Metres from the optical centre to the drawn image rectangle."""
    frame: int | None = None
    """Initially selected frame (default: the middle of the flight)."""
    goal: tuple[float, float, float] | None = None
    """World goal to plan to at start-up (with `model`)."""
    corridor: float | None = None
    """Corridor half-width (m) for live plans; default: the run's training corridor, else 0.3 m."""
    slice_axis: str = "z"
    slice_position: float | None = None
    """Initial slice coordinate (m); default: half a metre under the flight's median height (z), else the map centre."""
    cache_bytes: int = 384 * 2**20
    """Slab-cache budget for ESDF slices."""
    device: str = "cpu"
    """Torch device of the planner."""


class ViewerApp:
    """``mapkit view`` as an object: construct (reads the stores), :meth:`start` (binds the port,
    builds the scene and panel), interact (the ``gui`` handles' ``.value`` setters, :meth:`pick`),
    :meth:`stop`. Usable as a context manager.

    Attributes for inspection (tests, other front ends): ``server`` (the ViserServer), ``gui`` (the
    panel's handles by folder, a :class:`Panels`), ``nodes`` (name → scene handle), ``slice`` (the current
    :class:`mapkit.viz.SliceTexture`), ``plan`` (the current plan, a dict), ``summary`` (start-up
    lines), ``notes`` (what is missing or broken, as shown in the panel).
    """

    def __init__(self, config: ViewerConfig) -> None:
        from mapkit import viz

        self.config = c = config
        self.server: Any = None
        self.gui = Panels()
        self.nodes: dict[str, Any] = {}
        self.notes: list[str] = []
        self.summary: list[str] = []
        self.slice: Any = None
        self.plan: dict[str, Any] | None = None
        self.timings: dict[str, float] = {}
        self._lock = threading.RLock()
        self._stop_event = threading.Event()
        self._player: threading.Thread | None = None
        self._world_meshes: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}
        t0 = time.perf_counter()

        if c.workspace is None and c.eval_dir is None:
            raise ViewerError("nothing to view: pass -w WORKSPACE and/or --eval DIR")
        if not 0 <= int(c.port) <= 65535:
            raise ViewerError(f"--port {c.port} is not a TCP port (0..65535; 0 picks a free one)")
        self.ws = viz.open_workspace(c.workspace) if c.workspace is not None else None
        if self.ws is not None:
            self.notes += self.ws.notes
            if self.ws.empty and c.eval_dir is None:
                raise ViewerError(
                    f"workspace {str(c.workspace)!r} holds none of frames.zarr, cloud.ply, map.zarr; make them with "
                    f"`mapkit ingest`/`mapkit fuse`/`mapkit esdf -w {c.workspace}`"
                )
        self.cloud: Any = None
        self._cloud_points: np.ndarray | None = None
        self._load_cloud()
        self.map = self.ws.esdf_map if self.ws is not None else None
        self.slicer = viz.MapSlicer(self.map, cache_bytes=c.cache_bytes) if self.map is not None else None
        if self.map is not None:
            nx, ny, nz = self.map.shape
            self.summary.append(f"map.zarr: {nx}×{ny}×{nz} voxels of {self.map.voxel_size:g} m ({nx * ny * nz / 1e6:.1f} M)")
        self.frames = self.ws.frames if self.ws is not None else None
        self._velocity_body = np.zeros((0, 3))
        """(N, 3) body-frame velocity at each frame (filled with the flight panel)."""
        self._check_frames()
        self.planner: Any = None
        self.robot_radius, self.softness = 0.3, 1.0
        self._default_corridor = 0.3 if c.corridor is None else float(c.corridor)
        if c.model is not None:
            self._load_planner(Path(c.model))
        self.eval: Any = None
        if c.eval_dir is not None:
            self._load_eval(Path(c.eval_dir))
        self.summary += [f"note: {n}" for n in self.notes]
        self.timings["load_s"] = time.perf_counter() - t0

    # ------------------------------------------------------------------------------- lifecycle
    def __enter__(self) -> ViewerApp:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    @property
    def port(self) -> int:
        return int(self.server.get_port()) if self.server is not None else int(self.config.port)

    @property
    def url(self) -> str:
        host = self.config.host
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else (f"[{host}]" if ":" in host else host)
        return f"http://{shown}:{self.port}"

    def start(self) -> str:
        """Bind the port, build the scene and the panel; returns the URL."""
        import viser

        if self.server is not None:
            return self.url
        t0 = time.perf_counter()
        c = self.config
        _check_port(c.host, int(c.port))
        # viser prints a banner of its own; the command prints one URL line instead
        with contextlib.redirect_stdout(io.StringIO()):
            server = viser.ViserServer(host=c.host, port=int(c.port), label="mapkit view", verbose=False)
        if int(c.port) != 0 and server.get_port() != int(c.port):  # taken between our check and viser's bind
            self._quiet_stop(server)
            raise ViewerError(f"port {c.port} on {c.host} is in use; pass --port 0 to pick a free one")
        self.server = server
        self._stop_event.clear()
        try:
            with server.atomic():
                self._build()
        except BaseException:
            self.stop()
            raise
        self._player = threading.Thread(target=self._play_loop, name="mapkit-view-player", daemon=True)
        self._player.start()
        # No background warm-up of torch for the "obstacle cost" mode: a daemon thread still inside
        # `import torch` when Ctrl-C came could hang the interpreter's exit (seen on a loaded CI
        # machine). The first switch to cost mode pays the import (about 2 s) instead.
        self.timings["start_s"] = time.perf_counter() - t0
        return self.url

    def stop(self) -> None:
        """Stop the player thread and the server (idempotent)."""
        self._stop_event.set()
        if self._player is not None:
            self._player.join(timeout=30.0)
            self._player = None
        if self.server is not None:
            self._quiet_stop(self.server)
            self.server = None
        if self.eval is not None:
            self.eval.close()

    @staticmethod
    def _quiet_stop(server: Any) -> None:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()

    # The flight panel and planning exist only with frames.zarr, the slice panel only with map.zarr.
    def _need_frames(self) -> Any:
        """frames.zarr, for the parts of the viewer that exist only when the workspace has it."""
        if self.frames is None:
            raise ViewerError("this workspace has no frames.zarr")
        return self.frames

    def _need_map(self) -> Any:
        """map.zarr, for the parts of the viewer that exist only when the workspace has it."""
        if self.map is None:
            raise ViewerError("this workspace has no map.zarr")
        return self.map

    def _need_slicer(self) -> MapSlicer:
        """The slicer of map.zarr (see :meth:`_need_map`)."""
        if self.slicer is None:
            raise ViewerError("this workspace has no map.zarr")
        return self.slicer

    def _T_body_camera(self, i: int) -> np.ndarray:
        """(4, 4) optical camera → body at frame i (what the planner needs to check its paths)."""
        from mapkit.geometry import invert_transform

        fr = self._need_frames()
        return invert_transform(fr.T_world_body[i]) @ fr.T_world_camera[i]

    # ---------------------------------------------------------------------------------- loading
    def _load_cloud(self) -> None:
        """Read cloud.ply (downsampled to ``max_points``); an unreadable one becomes a note."""
        from mapkit import viz

        if self.ws is None or self.ws.cloud_path is None:
            return
        try:
            ply = viz.read_ply_points(self.ws.cloud_path)
            self.cloud = viz.cloud_view(ply.points, max_points=self.config.max_points, color_by="height")
            self._cloud_points = self.cloud.points_local.astype(np.float64) + self.cloud.origin
            extra = f" (voxel {self.cloud.voxel_size:.3f} m)" if self.cloud.voxel_size else ""
            self.summary.append(
                f"cloud.ply: {self.cloud.total_points:,} points, showing {self.cloud.shown_points:,}{extra}, "
                f"sent as {self.cloud.precision}"
            )
        except MapkitError as exc:
            self.notes.append(f"cloud.ply cannot be read: {exc}")

    def _check_frames(self) -> None:
        """Summarise frames.zarr; raise :class:`ViewerError` when ``--frame`` is not one of its frames."""
        if self.frames is None:
            return
        c = self.config
        n = len(self.frames)
        span = (self.frames.stamp_ns[-1] - self.frames.stamp_ns[0]) * 1e-9
        self.summary.append(f"frames.zarr: {n} frames of {self.frames.width}×{self.frames.height}, {span:.1f} s")
        if c.frame is not None and not 0 <= c.frame < n:
            raise ViewerError(f"--frame {c.frame}: frames.zarr has frames 0..{n - 1}")

    def _load_eval(self, eval_dir: Path) -> None:
        """Open a ``mapkit eval`` folder; a missing one raises, an unreadable one becomes a note."""
        from mapkit import viz

        if not eval_dir.exists():
            raise ViewerError(f"--eval {str(self.config.eval_dir)!r} does not exist; pass the folder `mapkit eval` wrote")
        try:
            self.eval = viz.load_eval(eval_dir)
            self.notes += [f"evaluation: {n}" for n in self.eval.notes]
            self.summary.append(
                f"evaluation: {len(self.eval.episodes)} episodes, worlds {', '.join(self.eval.worlds)}, "
                f"methods {', '.join(self.eval.methods)}"
            )
        except MapkitError as exc:
            self.notes.append(f"evaluation cannot be shown: {exc}")

    def _load_planner(self, run: Path) -> None:
        import json

        from mapkit.flight import resolve_model

        run = resolve_model(run)
        if not run.exists():
            raise ViewerError(f"--model {str(run)!r} does not exist; pass a run directory (WS/runs/NAME) with model.pt")
        from mapkit.flight import Planner

        try:
            self.planner = Planner.load(run, device=self.config.device)
        except MapkitError as exc:
            self.notes.append(f"model cannot be used: {exc}")
            return
        try:  # the loss parameters and corridor the run trained with (cost mode and default corridor)
            cfg = json.loads((run / "config.json").read_text())
            loss = cfg.get("loss") or {}
            self.robot_radius = float(loss.get("robot_radius", self.robot_radius))
            self.softness = float(loss.get("obstacle_softness", self.softness))
            if self.config.corridor is None and cfg.get("corridor"):
                self._default_corridor = float(cfg["corridor"])
        except (OSError, ValueError, TypeError):
            pass
        self.summary.append(f"model: {run} (robot radius {self.robot_radius:g} m)")
        if self.frames is None:
            self.notes.append("live planning needs frames.zarr (the depth image and pose of a frame)")
            return
        # one throw-away plan (with and without the corridor QP): the first call pays for lazy set-up,
        # which would otherwise show as the latency of the user's first plan
        blank = np.full((self.frames.height, self.frames.width), 5.0, np.float32)
        for corridor in (None, self._default_corridor or None):
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    self.planner.plan(blank, np.array([5.0, 0.0, 0.0]), corridor=corridor, K=self.frames.K,
                                      T_body_camera=self._T_body_camera(0))
            except MapkitError as exc:
                self.notes.append(f"model cannot plan: {exc}")
                self.planner = None
                return

    # ------------------------------------------------------------------------------------ build
    def _build(self) -> None:
        s, g = self.server.scene, self.server.gui
        for layer in LAYERS:
            self.nodes[f"/{layer}"] = s.add_frame(f"/{layer}", show_axes=False)
        self.gui.status = g.add_markdown(self._status_markdown(), order=_ORDER["status"])
        self.gui.message = g.add_markdown("", order=_ORDER["message"])
        with g.add_folder("Layers", order=_ORDER["layers"]):
            for layer in LAYERS:
                if self._layer_available(layer):
                    cb = g.add_checkbox(_LAYER_LABELS[layer], initial_value=True)

                    def toggle(_event: Any, layer: str = layer) -> None:
                        self._toggle(layer)

                    cb.on_update(self._guard(toggle))
                    setattr(self.gui.layers, layer, cb)
        if self.cloud is not None:
            self._build_cloud()
        if self.slicer is not None:
            self._build_slice()
        if self.frames is not None:
            self._build_flight()
        if self.planner is not None and self.frames is not None:
            self._build_plan()
        if self.eval is not None:
            self._build_eval()
        self._set_initial_camera()

    def _layer_available(self, layer: str) -> bool:
        return {
            "cloud": self.cloud is not None, "slice": self.slicer is not None, "flight": self.frames is not None,
            "plan": self.planner is not None and self.frames is not None,
            "corridor": self.planner is not None and self.frames is not None, "eval": self.eval is not None,
        }[layer]

    def _toggle(self, layer: str) -> None:
        self.nodes[f"/{layer}"].visible = bool(built(self.gui.layers.of(layer)).value)

    def _guard(self, fn: Callable[[Any], object]) -> Callable[[Any], None]:
        """Callbacks run one at a time; a library error goes to the status line, not a traceback."""

        def run(event: Any) -> None:
            with self._lock:
                try:
                    fn(event)
                except MapkitError as exc:
                    self._message(str(exc))

        return run

    def _message(self, text: str) -> None:
        if self.gui.message is not None:
            self.gui.message.content = f"**{text}**" if text else ""

    def _status_markdown(self) -> str:
        lines = [f"- {s}" for s in self.summary if not s.startswith("note: ")]
        if self.notes:
            lines += ["", "**Missing or unreadable:**"] + [f"- {n}" for n in self.notes]
        return "\n".join(lines) if lines else "nothing loaded"

    def _set_initial_camera(self) -> None:
        lo, hi = None, None
        if self.map is not None:
            lo, hi = self.map.bounds
        elif self._cloud_points is not None and len(self._cloud_points):
            lo, hi = self._cloud_points.min(axis=0), self._cloud_points.max(axis=0)
        elif self.frames is not None:
            p = self.frames.T_world_body[:, :3, 3]
            lo, hi = p.min(axis=0) - 2.0, p.max(axis=0) + 2.0
        elif self.eval is not None and self.eval.episodes:
            # the flights, not the world's floor quad (which spans its whole bounds)
            ends = np.array([[e.start, e.goal] for e in self.eval.episodes_of(built(self.gui.eval).world.value)],
                            dtype=np.float64).reshape(-1, 3)
            if len(ends):
                lo, hi = ends.min(axis=0) - 3.0, ends.max(axis=0) + 3.0
        if lo is None or hi is None:
            return
        centre = 0.5 * (lo + hi)
        if self.slice is not None and self.slice.axis == "z":
            centre = self.slice.centre_world.copy()
        D = max(float(np.max(hi[:2] - lo[:2])), 2.0)
        cam = self.server.initial_camera
        cam.look_at = tuple(centre)
        cam.position = tuple(centre + np.array([0.0, -0.55 * D, 0.95 * D]))
        cam.up = (0.0, 0.0, 1.0)

    # -------------------------------------------------------------------------------- point cloud
    def _build_cloud(self) -> None:
        g = self.server.gui
        with g.add_folder("Point cloud", expand_by_default=False, order=_ORDER["cloud"]):
            options = ["height"] + (["ESDF"] if self.map is not None else [])
            panel = self.gui.cloud = CloudPanel(
                color=g.add_dropdown("colour by", options, initial_value="height"),
                size=g.add_slider("point size (m)", 0.005, 0.2, 0.005, 0.03),
            )
        panel.color.on_update(self._guard(lambda _e: self._recolor_cloud()))
        panel.size.on_update(self._guard(lambda _e: self._resize_cloud()))
        self._draw_cloud(self.cloud)

    def _draw_cloud(self, cv: Any) -> None:
        self.nodes["/cloud/points"] = self.server.scene.add_point_cloud(
            "/cloud/points", cv.points_local, cv.colors, point_size=float(built(self.gui.cloud).size.value),
            precision=cv.precision, position=tuple(cv.origin), point_shape="rounded",
        )

    def _recolor_cloud(self) -> None:
        from mapkit import viz

        by: Literal["height", "esdf"] = "esdf" if built(self.gui.cloud).color.value == "ESDF" else "height"
        assert self._cloud_points is not None  # the cloud panel exists only with a cloud
        cv = viz.cloud_view(self._cloud_points, max_points=self.config.max_points, color_by=by, esdf_map=self.map)
        self.nodes["/cloud/points"].colors = cv.colors

    def _resize_cloud(self) -> None:
        self.nodes["/cloud/points"].point_size = float(built(self.gui.cloud).size.value)

    # ------------------------------------------------------------------------------------ slice
    def _build_slice(self) -> None:
        g = self.server.gui
        c = self.config
        axis = c.slice_axis if c.slice_axis in ("x", "y", "z") else "z"
        lo, hi, step = self._need_slicer().positions(axis)
        if c.slice_position is not None:
            pos = c.slice_position
        elif axis == "z" and self.frames is not None:
            pos = self._flight_slice_height()
        else:
            pos = 0.5 * (lo + hi)
        pos = self._need_slicer().snap(axis, min(max(pos, lo), hi))
        with g.add_folder("ESDF slice", order=_ORDER["slice"]):
            axis_handle = g.add_dropdown("axis", ("x", "y", "z"), initial_value=axis)
            position = g.add_slider("position (m)", lo, hi, step, pos)
            position.precision = _decimals(step)
            panel = self.gui.slice = SlicePanel(
                axis=axis_handle, position=position,
                value=g.add_dropdown("value", tuple(_VALUE_MODES), initial_value="signed distance [m]"),
                cmap=g.add_dropdown("colour map", SLICE_CMAPS, initial_value="RdBu"),
                raw=g.add_checkbox("unsmoothed (esdf_raw)", initial_value=False),
                vmin=g.add_number("min", -1.0, step=0.05),
                vmax=g.add_number("max", 1.0, step=0.05),
                auto=g.add_button("auto range"),
                colorbar=g.add_image(np.full((90, 320, 3), 255, np.uint8), label=None, format="png"),
                info=g.add_markdown(""),
            )
        self._slice_range_auto = True
        panel.axis.on_update(self._guard(lambda _e: self._on_slice_axis()))
        panel.position.on_update(self._guard(lambda _e: self.update_slice()))
        panel.value.on_update(self._guard(lambda _e: self._auto_range()))
        panel.cmap.on_update(self._guard(lambda _e: self.update_slice(colorbar=True)))
        panel.raw.on_update(self._guard(lambda _e: self.update_slice()))
        panel.vmin.on_update(self._guard(lambda _e: self._on_range()))
        panel.vmax.on_update(self._guard(lambda _e: self._on_range()))
        panel.auto.on_click(self._guard(lambda _e: self._auto_range()))
        try:
            self._auto_range()
        except MapkitError as exc:  # a corrupt map shows its error; the rest of the viewer works
            self.notes.append(f"map.zarr cannot be sliced: {exc}")
            built(self.gui.status).content = self._status_markdown()

    def _flight_slice_height(self) -> float:
        """Half a metre below the flight's median height: the distances the drone flies through,
        with the flight and plans drawn just above the plane instead of inside it."""
        return float(np.median(self._need_frames().T_world_body[:, 2, 3])) - 0.5

    def _on_slice_axis(self) -> None:
        panel = built(self.gui.slice)
        axis = panel.axis.value
        lo, hi, step = self._need_slicer().positions(axis)
        sl = panel.position
        centre = self._need_slicer().snap(axis, 0.5 * (lo + hi))
        if self.slice is not None and axis == "z" and self.frames is not None:
            centre = self._need_slicer().snap(axis, self._flight_slice_height())
        sl.min, sl.max, sl.step, sl.precision = lo, hi, step, _decimals(step)
        before = sl.value
        _set_value(sl, centre)
        if sl.value == before:  # no change event fired
            self.update_slice()

    def _on_range(self) -> None:
        if getattr(self, "_setting_range", False):
            return
        self._slice_range_auto = False
        self.update_slice(colorbar=True)

    def _auto_range(self) -> None:
        """Colour range from the current slice (percentiles), then redraw."""
        self._slice_range_auto = True
        self.update_slice(colorbar=True)

    def _slice_style(self) -> dict[str, Any]:
        panel = built(self.gui.slice)
        mode = _VALUE_MODES[panel.value.value]
        style: dict[str, Any] = dict(mode=mode, cmap=panel.cmap.value,
                                     robot_radius=self.robot_radius, softness=self.softness)
        if not self._slice_range_auto:
            style.update(vmin=float(panel.vmin.value), vmax=float(panel.vmax.value))
        return style

    def update_slice(self, *, colorbar: bool = False) -> None:
        """Re-read (cached) and re-colour the slice from the panel's values; move the textured plane."""
        from viser import transforms as vtf

        from mapkit import viz

        t0 = time.perf_counter()
        panel = built(self.gui.slice)
        axis = panel.axis.value
        position = float(panel.position.value)
        sl = self._need_slicer().slice(axis, position, raw=bool(panel.raw.value))
        tex = viz.slice_texture(sl, axis=axis, pixels_per_voxel=viz.texture_scale(sl.values.shape),
                                **self._slice_style())
        t_slice = time.perf_counter() - t0
        if self._slice_range_auto:
            self._setting_range = True
            try:
                _set_value(panel.vmin, round(float(tex.norm.vmin), 3))
                _set_value(panel.vmax, round(float(tex.norm.vmax), 3))
            finally:
                self._setting_range = False
            self._slice_range_auto = False  # the range stays put while sliding; "auto range" recomputes
            colorbar = True
        colorbar = colorbar or self.slice is None or self.slice.mode != tex.mode
        wxyz = vtf.SO3.from_matrix(tex.R_world_image).wxyz
        node = self.nodes.get("/slice/plane")
        if node is None:
            self.nodes["/slice/plane"] = self.server.scene.add_image(
                "/slice/plane", tex.texture, tex.width_m, tex.height_m, format="png", wxyz=wxyz,
                position=tuple(tex.centre_world), cast_shadow=False, receive_shadow=False,
            )
        else:
            with self.server.atomic():
                node.image = tex.texture
                node.render_width, node.render_height = tex.width_m, tex.height_m
                node.wxyz, node.position = wxyz, tuple(tex.centre_world)
        self.slice = tex
        if colorbar:
            panel.colorbar.image = viz.colorbar_image(tex.cmap, tex.norm, label=tex.label)
        a = "xyz".index(axis)
        k = int(round((tex.position - self._need_map().origin[a]) / self._need_map().voxel_size))
        unobserved = 100.0 * float(np.mean(~tex.observed))
        self.timings["slice_ms"] = 1e3 * (time.perf_counter() - t0)
        self.timings["slice_compute_ms"] = 1e3 * t_slice
        panel.info.content = (
            f"{axis} = {tex.position:.2f} m (voxel {k} of {self._need_map().shape[a]}), {tex.values.shape[0]}×{tex.values.shape[1]} "
            f"voxels, {unobserved:.0f} % unobserved (hatched); {self.timings['slice_ms']:.0f} ms"
        )

    # ----------------------------------------------------------------------------------- flight
    def _build_flight(self) -> None:
        from mapkit import viz
        from mapkit.export import body_velocities

        g, s = self.server.gui, self.server.scene
        fr = self._need_frames()
        n = len(fr)
        self._velocity_body = body_velocities(fr.stamp_ns, fr.T_world_body, fr.source_index)
        p = fr.T_world_body[:, :3, 3]
        if n >= 2:
            seg, _ = viz.polyline_segments(p)
            self.nodes["/flight/path"] = s.add_line_segments("/flight/path", seg, _COLORS["flight_path"], thickness=0.03)
        start = self.config.frame if self.config.frame is not None else n // 2
        with g.add_folder("Flight", order=_ORDER["flight"]):
            panel = self.gui.flight = FlightPanel(
                frame=g.add_slider("frame", 0, max(n - 1, 1), 1, start, disabled=n < 2),
                play=g.add_checkbox("play", initial_value=False),
                fps=g.add_slider("frames per second", 1, 30, 1, 10),
                frustum_every=g.add_slider("frustum every N frames", 1, max(1, min(200, n)), 1,
                                           min(self.config.frustum_every, max(1, n))),
                depth=g.add_image(np.zeros((fr.height, fr.width, 3), np.uint8), label="depth (m)", format="png"),
                info=g.add_markdown(""),
            )
        panel.frame.on_update(self._guard(lambda _e: self.update_frame()))
        panel.frustum_every.on_update(self._guard(lambda _e: self._draw_frustums()))
        self._draw_frustums()
        try:
            self.update_frame(replan=False)
        except MapkitError as exc:
            self._message(str(exc))

    def _draw_frustums(self) -> None:
        from mapkit import viz

        fr = self._need_frames()
        every = max(1, int(built(self.gui.flight).frustum_every.value))
        seg = viz.frustum_segments(fr.K, fr.width, fr.height, fr.T_world_camera[::every], depth=self.config.frustum_depth)
        self.nodes["/flight/frustums"] = self.server.scene.add_line_segments(
            "/flight/frustums", seg, _COLORS["frustum"], thickness=0.012)

    def update_frame(self, *, replan: bool = True) -> None:
        """Show the selected frame: its frustum, body axes, depth image; re-plan to the goal."""
        from viser import transforms as vtf

        from mapkit import viz

        fr = self._need_frames()
        panel = built(self.gui.flight)
        i = int(panel.frame.value)
        T_wb, T_wc = fr.T_world_body[i], fr.T_world_camera[i]
        s = self.server.scene
        seg = viz.frustum_segments(fr.K, fr.width, fr.height, T_wc, depth=2.5 * self.config.frustum_depth)
        self.nodes["/flight/current"] = s.add_line_segments("/flight/current", seg, _COLORS["current"], thickness=0.03)
        self.nodes["/flight/body"] = s.add_frame(
            "/flight/body", axes_length=0.4, axes_radius=0.02,
            wxyz=vtf.SO3.from_matrix(T_wb[:3, :3]).wxyz, position=tuple(T_wb[:3, 3]))
        depth = self._depth(i)
        panel.depth.image = viz.depth_image(depth)
        valid = np.isfinite(depth) & (depth > 0)
        t = (fr.stamp_ns[i] - fr.stamp_ns[0]) * 1e-9
        v = float(np.linalg.norm(self._velocity_body[i]))
        rng = f"{np.nanmin(depth[valid]):.2f}..{np.nanmax(depth[valid]):.2f} m" if valid.any() else "no valid pixel"
        x, y, z = T_wb[:3, 3]
        panel.info.content = (
            f"frame {i} of {len(fr)}, t = {t:.2f} s; body at ({x:.2f}, {y:.2f}, {z:.2f}) m, {v:.2f} m/s; "
            f"depth {rng}, {100 * valid.mean():.0f} % valid"
        )
        if replan and self.planner is not None and self.plan is not None:
            self.plan_to(self.plan["goal_world"])

    def _depth(self, i: int) -> np.ndarray:
        from mapkit.viz import VizError

        try:
            return np.asarray(self._need_frames().depth[i], dtype=np.float32)
        except Exception as exc:  # noqa: BLE001 - a damaged chunk surfaces as many exception types
            raise VizError(f"frames.zarr: cannot read the depth of frame {i} ({type(exc).__name__}: {exc}); "
                           "re-run `mapkit ingest --overwrite`") from None

    def _play_loop(self) -> None:
        while not self._stop_event.is_set():
            fps = 10.0
            flight = self.gui.flight
            try:
                playing = flight is not None and bool(flight.play.value)
                if flight is not None and playing:
                    fps = float(flight.fps.value)
                    sl = flight.frame
                    nxt = (int(sl.value) + 1) % len(self._need_frames())
                    _set_value(sl, nxt)  # fires update_frame through the slider's callback
            except Exception as exc:  # noqa: BLE001 - keep the player alive; report in the panel
                self._message(f"playback stopped: {type(exc).__name__}: {exc}")
                if flight is not None:
                    _set_value(flight.play, False)
            self._stop_event.wait(1.0 / max(fps, 1.0))

    # ------------------------------------------------------------------------------------- plan
    def _build_plan(self) -> None:
        g = self.server.gui
        fr = self._need_frames()
        i = int(built(self.gui.flight).frame.value)
        T_wb = fr.T_world_body[i]
        ahead = T_wb[:3, 3] + T_wb[:3, :3] @ np.array([6.0, 0.0, 0.0])
        initial = self.config.goal if self.config.goal is not None else tuple(float(v) for v in ahead)
        with g.add_folder("Plan (live)", order=_ORDER["plan"]):
            g.add_markdown("Click the slice (or the map) to set a goal for the selected frame, or type X Y Z (world, m).")
            panel = self.gui.plan = PlanPanel(
                click_goal=g.add_checkbox("click sets goal", initial_value=True),
                goal=g.add_vector3("goal (world, m)", tuple(round(float(v), 2) for v in initial), step=0.1),
                corridor_width=g.add_number("corridor half-width (m), 0 = off", round(self._default_corridor, 3),
                                            min=0.0, step=0.05),
                button=g.add_button("plan"),
                info=g.add_markdown("no plan yet"),
                speed_colorbar=g.add_image(np.full((90, 320, 3), 255, np.uint8), format="png", visible=False),
            )
        panel.goal.on_update(self._guard(lambda _e: self.plan_to(panel.goal.value)))
        panel.corridor_width.on_update(self._guard(lambda _e: self._replan()))
        panel.button.on_click(self._guard(lambda _e: self.plan_to(panel.goal.value)))
        self.server.scene.on_click()(self._on_scene_click)
        if self.config.goal is not None:
            try:
                self.plan_to(self.config.goal)
            except MapkitError as exc:
                self._message(str(exc))

    def _replan(self) -> None:
        if self.plan is not None:
            self.plan_to(self.plan["goal_world"])

    def _on_scene_click(self, event: Any) -> None:
        if not bool(built(self.gui.plan).click_goal.value):
            return
        with self._lock:
            try:
                self.pick(event.ray_origin, event.ray_direction)
            except MapkitError as exc:
                self._message(str(exc))

    def pick(self, ray_origin: Any, ray_direction: Any) -> np.ndarray | None:
        """A click ray (world) → a goal on the visible slice or the map surface → plan to it."""
        from mapkit import viz

        plane = None
        if self.slice is not None and self.nodes["/slice"].visible:
            plane = (self.slice.axis, self.slice.position, self.slice.corners_world)
        p, how = viz.pick_point(np.asarray(ray_origin), np.asarray(ray_direction), plane=plane, esdf_map=self.map)
        if p is None:
            self._message("the click hit neither the slice nor the map; type the goal X Y Z instead")
            return None
        self._message(f"goal from the {how}: ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}) m")
        gx, gy, gz = (round(float(v), 3) for v in p)
        goal = (gx, gy, gz)
        goal_handle = built(self.gui.plan).goal
        if tuple(goal_handle.value) == goal:
            self.plan_to(goal)
        else:
            _set_value(goal_handle, goal)  # fires plan_to
        return p

    def plan_to(self, goal_world: Any) -> dict[str, Any]:
        """Plan from the selected frame to a world goal (3,) and draw key-points, the trajectory
        coloured by speed and the corridor prisms."""
        from mapkit import viz

        panel = built(self.gui.plan)
        i = int(built(self.gui.flight).frame.value)
        T_wb = self._need_frames().T_world_body[i]
        goal_w = np.asarray(goal_world, dtype=np.float64).reshape(3)
        W = float(panel.corridor_width.value)
        corridor = W if W > 0 else None
        planned, infeasible = self._solve_plan(i, goal_w, corridor)
        result = planned.result
        traj_w, kp_w, speed, norm = self._draw_plan(T_wb, result, goal_w)
        geo = self._draw_corridor(T_wb, result, corridor)
        self.plan = {"frame": i, "goal_world": goal_w, "goal_body": planned.goal_body, "result": result,
                     "trajectory_world": traj_w, "keypoints_world": kp_w, "speed": speed, "corridor": geo,
                     "corridor_width": corridor, "infeasible": infeasible}
        panel.info.content = _plan_info(i, planned.goal_body, result, speed, geo, W, infeasible)
        panel.speed_colorbar.image = viz.colorbar_image("turbo", norm, label="speed [m/s]", unobserved=False)
        panel.speed_colorbar.visible = True
        return self.plan

    def _solve_plan(self, i: int, goal_w: np.ndarray, corridor: float | None) -> tuple[Any, bool]:
        """Plan from frame ``i`` to the world goal; (planned, whether the corridor QP was infeasible)."""
        from mapkit.flight import plan_from_frame
        from mapkit.trajopt import TrajoptWarning

        fr = self._need_frames()
        depth = self._depth(i)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TrajoptWarning)
            planned = plan_from_frame(self.planner, depth, fr.T_world_body[i], fr.T_world_camera[i], fr.K, goal_w,
                                      goal_frame="world", velocity_body=self._velocity_body[i], corridor=corridor)
        return planned, any(issubclass(w.category, TrajoptWarning) for w in caught)

    def _draw_plan(self, T_wb: np.ndarray, result: Any, goal_w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, Any]:
        """Draw the trajectory coloured by speed, the key-points and the goal; (trajectory, key-points, speed, norm)."""
        from mapkit import viz

        s = self.server.scene
        traj_w = viz.transform_points(T_wb, result.samples_body)
        kp_w = viz.transform_points(T_wb, result.keypoints)
        speed, colors, norm = viz.speed_colors(result.samples_t, result.samples_body)
        seg, seg_colors = viz.polyline_segments(traj_w, colors)
        self.nodes["/plan/trajectory"] = s.add_line_segments("/plan/trajectory", seg, seg_colors, thickness=0.08)
        self.nodes["/plan/keypoints"] = s.add_point_cloud(
            "/plan/keypoints", kp_w.astype(np.float32), np.array(_COLORS["keypoint"], np.uint8), point_size=0.16,
            point_shape="circle", precision="float32")
        self.nodes["/plan/goal"] = s.add_icosphere("/plan/goal", radius=0.18, color=_COLORS["goal"], position=tuple(goal_w))
        return traj_w, kp_w, speed, norm

    def _draw_corridor(self, T_wb: np.ndarray, result: Any, corridor: float | None) -> Any:
        """Replace the corridor prisms (none without a corridor); returns their geometry or None."""
        from mapkit import viz

        for name in ("/corridor/prisms", "/corridor/edges"):
            node = self.nodes.pop(name, None)
            if node is not None:
                node.remove()
        if corridor is None:
            return None
        s = self.server.scene
        waypoints = np.vstack([np.zeros((1, 3)), result.keypoints.astype(np.float64)])
        geo = viz.corridor_prisms(waypoints, corridor, T_world_frame=T_wb)
        self.nodes["/corridor/prisms"] = s.add_mesh_simple(
            "/corridor/prisms", geo.vertices, geo.faces, color=_COLORS["corridor"], opacity=0.18, side="double",
            cast_shadow=False, receive_shadow=False)
        self.nodes["/corridor/edges"] = s.add_line_segments(
            "/corridor/edges", geo.edges, _COLORS["corridor"], thickness=0.01)
        return geo

    # ------------------------------------------------------------------------------------- eval
    def _build_eval(self) -> None:
        from mapkit import viz

        g = self.server.gui
        ev = self.eval
        worlds = list(ev.worlds)
        self._method_colors = viz.method_colors(ev.methods)
        with g.add_folder("Evaluation", order=_ORDER["eval"]):
            g.add_markdown("Simulated evaluation worlds (not this workspace's map).")
            world = g.add_dropdown("world", worlds, initial_value=worlds[0])
            pair = g.add_dropdown("pair", self._pair_options(worlds[0]), initial_value="all")
            legend = "".join(
                f'<div style="font-size:0.8em"><span style="display:inline-block;width:0.9em;height:0.9em;'
                f'background:rgb{c};margin-right:0.4em"></span>{m}</div>' for m, c in self._method_colors.items())
            legend += ('<div style="font-size:0.8em">● red: collision point, ● green: start, ● gold: goal</div>')
            panel = self.gui.eval = EvalPanel(world=world, pair=pair, legend=g.add_html(legend), table=g.add_markdown(""))
        panel.world.on_update(self._guard(lambda _e: self._on_eval_world()))
        panel.pair.on_update(self._guard(lambda _e: self.update_eval()))
        try:
            self.update_eval()
        except MapkitError as exc:
            self._message(str(exc))

    def _pair_options(self, world: str) -> tuple[str, ...]:
        return ("all",) + tuple(str(p) for p in self.eval.pairs(world))

    def _on_eval_world(self) -> None:
        panel = built(self.gui.eval)
        opts = self._pair_options(panel.world.value)
        panel.pair.options = opts
        if panel.pair.value != "all":
            _set_value(panel.pair, "all")  # fires update_eval
        else:
            self.update_eval()

    def update_eval(self) -> None:
        """Draw the selected world's mesh and the executed paths of the selected pair(s)."""
        from mapkit import viz

        ev, s = self.eval, self.server.scene
        panel = built(self.gui.eval)
        world = panel.world.value
        pv = panel.pair.value
        pair = None if pv == "all" else int(pv)
        for name in [n for n in self.nodes if n.startswith("/eval/")]:
            self.nodes.pop(name).remove()
        if world not in self._world_meshes:
            try:
                self._world_meshes[world] = viz.world_mesh_arrays(ev.world_file(world))
            except MapkitError as exc:
                self._world_meshes[world] = None
                self._message(str(exc))
        mesh = self._world_meshes[world]
        if mesh is not None:
            self.nodes["/eval/world"] = s.add_mesh_simple(
                "/eval/world", mesh[0], mesh[1], color=_COLORS["world"], opacity=0.55, side="double", cast_shadow=False)
        episodes = ev.episodes_of(world, pair)
        missing = 0
        for method in ev.methods:
            segs = []
            for e in (e for e in episodes if e.method == method):
                path = ev.path_of(world, int(e.pair), method)
                if path is None:
                    missing += 1
                    continue
                if len(path) >= 2:
                    segs.append(viz.polyline_segments(path[:, 1:])[0])
            if segs:
                name = f"/eval/paths/{method}"
                self.nodes[name] = s.add_line_segments(name, np.concatenate(segs), self._method_colors[method],
                                                       thickness=0.04)
        hits = np.array([e.collision_point for e in episodes
                         if e.outcome == "collision" and e.collision_point is not None], dtype=np.float32)
        if len(hits):
            self.nodes["/eval/collisions"] = s.add_point_cloud(
                "/eval/collisions", hits.reshape(-1, 3), np.array(_COLORS["collision"], np.uint8), point_size=0.3,
                point_shape="circle", precision="float32")
        by_pair = {int(e.pair): e for e in episodes}
        if by_pair:
            starts = np.array([e.start for e in by_pair.values()], np.float32)
            goals = np.array([e.goal for e in by_pair.values()], np.float32)
            self.nodes["/eval/starts"] = s.add_point_cloud("/eval/starts", starts, np.array(_COLORS["start"], np.uint8),
                                                           point_size=0.3, point_shape="circle", precision="float32")
            self.nodes["/eval/goals"] = s.add_point_cloud("/eval/goals", goals, np.array(_COLORS["eval_goal"], np.uint8),
                                                          point_size=0.3, point_shape="circle", precision="float32")
        rows = ["| method | success | collision | timeout |", "|---|---|---|---|"]
        for method in ev.methods:
            outs = [e.outcome for e in episodes if e.method == method]
            rows.append(f"| {method} | {outs.count('success')} | {outs.count('collision')} | {outs.count('timeout')} |")
        if missing:
            rows.append(f"\n{missing} executed path(s) missing from trajectories.npz")
        panel.table.content = "\n".join(rows)


def _decimals(step: float) -> int:
    """Decimals that show multiples of `step` exactly (0.1 → 1, 0.05 → 2)."""
    for d in range(7):
        if abs(round(step, d) - step) < 1e-9 * max(1.0, abs(step)):
            return d
    return 6


def _check_port(host: str, port: int) -> None:
    """Raise :class:`ViewerError` when `port` on `host` cannot be bound (in use, bad host)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise ViewerError(f"--host {host!r} is not an address of this machine ({exc.strerror}); try 127.0.0.1") from None
    family, _, _, _, addr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server's own bind does
        try:
            sock.bind(addr)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise ViewerError(f"port {port} on {host} is in use; pass --port 0 to pick a free one") from None
            if exc.errno == errno.EACCES:
                raise ViewerError(f"port {port} on {host} needs privileges; pass a port above 1023 or --port 0") from None
            raise ViewerError(f"cannot listen on {host}:{port} ({exc.strerror}); check --host") from None


def _plan_info(i: int, gb: np.ndarray, result: Any, speed: np.ndarray, geo: Any, W: float, infeasible: bool) -> str:
    """The plan panel's text: goal, η and verdict, timing and how the trajectory was solved."""
    verdict = "execute" if result.execute else "do NOT execute (η ≥ 0.5)"
    if result.variant:
        verdict += f" (a {result.variant} candidate)"
    solve = (f"min-snap in a ±{W:g} m corridor ({geo.num_segments} prisms)" if geo is not None
             else "min-snap through the key-points (as `mapkit plan`)")
    if infeasible:
        solve = f"corridor ±{W:g} m infeasible: shown through the key-points; widen it"
    return (
        f"frame {i}; goal in body frame ({gb[0]:.2f}, {gb[1]:.2f}, {gb[2]:.2f}) m\n\n"
        f"**η = {result.eta:.3f}** → {verdict}; latency **{result.latency_ms:.1f} ms**\n\n"
        f"{len(result.keypoints)} key-points; segment times {np.round(result.durations.astype(float), 2).tolist()} s "
        f"(total {float(result.durations.sum()):.2f} s); peak speed {speed.max():.2f} m/s; "
        f"control effort {result.control_effort:.1f} m²/s⁷\n\n{solve}"
    )
