"""`mapkit view`: the web viewer (viser) for a workspace, a trained model and evaluation results."""

from __future__ import annotations

import time
from pathlib import Path

import click

from mapkit.cli._group import FINITE, INDEX, STORE_PATH, library_call, main, refuse_url


def _local_workspace(ctx: click.Context, param: click.Parameter, value: Path | str | None) -> Path | str | None:
    refuse_url(ctx, "-w/--workspace", value, "the viewer reads cloud.ply and mesh.ply as local files")
    return value


@main.command("view")
@click.option("-w", "--workspace", type=STORE_PATH, default=None, callback=_local_workspace,
              help="Workspace (frames.zarr, cloud.ply, map.zarr; whatever it holds is shown).")
@click.option("--model", "run_dir", type=click.Path(path_type=Path), default=None,
              help="Run directory with model.pt (or \"pretrained\"): click a goal to plan from the selected frame.")
@click.option("--eval", "eval_dir", type=click.Path(path_type=Path), default=None,
              help="Output folder of `mapkit eval`: executed paths per method in the simulated worlds.")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Interface to listen on; 0.0.0.0 exposes the viewer to your network.")
@click.option("--port", type=click.IntRange(0, 65535), default=8080, show_default=True, help="TCP port; 0 picks a free one.")
@click.option("--max-points", type=click.IntRange(min=1), default=2_000_000, show_default=True,
              help="Point-cloud points sent to the browser at most (voxel-grid downsampled).")
@click.option("--frame", "frame_index", type=INDEX, default=None, help="Frame selected at start (default: the middle).")
@click.option("--goal", type=FINITE, nargs=3, default=None, metavar="X Y Z", help="World goal planned to at start (with --model).")
@click.option("--corridor", type=click.FloatRange(min=0.0), default=None,
              help="Corridor half-width (m) for live plans; 0 = through the key-points. Default: the run's, else 0.3.")
@click.option("--slice", "slice_spec", type=(click.Choice(["x", "y", "z"]), float), default=None, metavar="AXIS M",
              help="Initial ESDF slice, e.g. --slice z 1.5 (default: z half a metre under the flight's median height).")
@click.option("--screenshot", type=click.Path(path_type=Path), default=None,
              help="Save a PNG of the page from headless Chromium, then stop (for docs and CI).")
@library_call
def view_cmd(workspace: Path | None, run_dir: Path | None, eval_dir: Path | None, host: str, port: int, max_points: int,
             frame_index: int | None, goal: tuple[float, float, float] | None, corridor: float | None,
             slice_spec: tuple[str, float] | None, screenshot: Path | None) -> None:
    """Browse a workspace in the browser: point cloud, ESDF slices, the flight, live plans, corridors.

    Runs until Ctrl-C. Binds 127.0.0.1 unless --host says otherwise.
    """
    from mapkit.viewer import ViewerApp, ViewerConfig

    config = ViewerConfig(
        workspace=workspace, model=run_dir, eval_dir=eval_dir, host=host, port=port, max_points=max_points,
        frame=frame_index, goal=goal or None, corridor=corridor,
        slice_axis=slice_spec[0] if slice_spec else "z", slice_position=slice_spec[1] if slice_spec else None,
    )
    t0 = time.perf_counter()
    app = ViewerApp(config)
    for line in app.summary:
        click.echo(line)
    url = app.start()
    try:
        click.echo(f"mapkit view: {url} (ready in {time.perf_counter() - t0:.1f} s; Ctrl-C to stop)")
        if host in ("0.0.0.0", "::"):
            click.echo("mapkit view: listening on every interface (--host 0.0.0.0): anyone on your network can open it")
        if screenshot is not None:
            from mapkit.viewer import screenshot as take

            click.echo(f"mapkit view: wrote {take(url, screenshot)}")
            return
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        app.stop()
        click.echo("mapkit view: stopped")
