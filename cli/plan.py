"""`mapkit plan`."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from mapkit._choices import GOAL_FRAMES, GoalFrame
from mapkit.cli._group import FINITE, INDEX, library_call, main, workspace_option


@main.command("plan")
@click.option("--model", "run_dir", required=True, type=click.Path(path_type=Path), help="Run directory with model.pt, or \"pretrained\" for the shipped model.")
@workspace_option("Workspace with frames.zarr.")
@click.option("--frame", "frame_index", type=INDEX, required=True, help="Index of the frame in frames.zarr.")
@click.option("--goal", type=FINITE, nargs=3, required=True, metavar="X Y Z", help="Goal, metres.")
@click.option("--goal-frame", type=click.Choice(GOAL_FRAMES), default="body", show_default=True, help="Frame of --goal.")
@click.option("-o", "--output", type=click.Path(path_type=Path), default=None, help="Output folder (default: WS/plans).")
@click.option("--device", default="cpu", show_default=True, help="cpu or cuda.")
@click.option("--widen/--no-widen", default=True, show_default=True,
              help="Also judge each candidate with its detour widened ×1.5 and ×2.5 (mapkit.flight.WIDEN).")
@click.option("--shift/--no-shift", default=True, show_default=True,
              help="Also judge every candidate shifted sideways by ±0.3 and ±0.6 m (mapkit.flight.SHIFT).")
@library_call
def plan_cmd(run_dir: Path, workspace: Path, frame_index: int, goal: tuple[float, float, float], goal_frame: GoalFrame,
             output: Path | None, device: str, widen: bool, shift: bool) -> None:
    """Plan from a recorded frame; writes the trajectory as JSON, TUM and MCAP (nav_msgs/Path)."""
    from mapkit.export import body_velocities
    from mapkit.flight import FlightError, Planner, plan_from_frame, write_plan_outputs
    from mapkit.flight._single import LOCAL_GOAL_RANGE, check_output_folder
    from mapkit.ingest import open_frames_store

    out = output or workspace / "plans"
    check_output_folder(out)
    store = open_frames_store(workspace)
    if not 0 <= frame_index < len(store):
        raise FlightError(f"--frame {frame_index}: frames.zarr has frames 0..{len(store) - 1}")
    T_wb = store.T_world_body[frame_index]
    velocity = body_velocities(store.stamp_ns, store.T_world_body, store.source_index)[frame_index]
    planner = Planner.load(run_dir, device=device)
    planned = plan_from_frame(planner, np.asarray(store.depth[frame_index]), T_wb, store.T_world_camera[frame_index],
                              store.K, goal, goal_frame=goal_frame, velocity_body=velocity,
                              widen=None if widen else (), shift=None if shift else ())
    g, result = planned.goal_body, planned.result
    paths = write_plan_outputs(result, T_wb, int(store.stamp_ns[frame_index]), out,
                               world_frame=str(store.attrs.get("world_frame", "world")), stem=f"plan_{frame_index:06d}")
    if result.goal_clipped:
        click.echo(f"goal {np.linalg.norm(g):.4g} m away is beyond the planner's {LOCAL_GOAL_RANGE:g} m range: planned to "
                   f"the point {LOCAL_GOAL_RANGE:g} m along the way (body {np.round(result.goal_body, 3).tolist()}); "
                   "replan from a later frame to go on")
    verdict = "execute" if result.execute else "do NOT execute (eta >= 0.5)"
    if result.variant:
        verdict += f" (a {result.variant} candidate)"
    click.echo(
        f"eta {result.eta:.3f} → {verdict}; segment times {np.round(result.durations.astype(float), 2).tolist()} s "
        f"(total {result.durations.sum():.2f} s); control effort {result.control_effort:.2f} m²/s⁷; "
        f"latency {result.latency_ms:.1f} ms"
    )
    click.echo("wrote " + ", ".join(str(p) for p in paths))
