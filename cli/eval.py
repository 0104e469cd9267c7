"""`mapkit eval`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from mapkit._choices import ON_REJECT, VEHICLES, OnReject, VehicleKind
from mapkit.cli._group import COUNT, FINITE, FRACTION, INDEX, library_call, main, option_values

if TYPE_CHECKING:
    from mapkit.flight import Execution


_SECTIONS: dict[str, tuple[str, ...]] = {
    "What to fly": ("run_dir", "world", "pairs", "seed", "min_distance", "methods", "stacks", "untrained_seeds",
                    "vehicle", "gimbal", "drop_frames", "depth_delay", "pose_noise"),
    "Output and parallelism": ("output", "workers", "scheduler", "record_plans", "record_judge", "judge_history",
                              "overwrite"),
    "The closed loop (every method)": ("replan_interval", "horizon", "ignore_eta", "on_reject", "plan_latency",
                                       "final_approach", "look_ahead"),
    "Flight stack: corridor": ("corridor", "corridor_check", "check_memory", "unchecked_corridor"),
    "Flight stack: depth memory": ("memory", "subgoal_speed", "turn_toward_open"),
    "Flight stack: routing": ("route_after",),
    "Flight stack: follow the reference": ("follow", "keep_choice", "flown_judge", "shift"),
    "Flight stack: speed profile": ("speed", "search_speed", "turn_accel", "turn_min_speed", "stop_decel", "v_max",
                                    "a_max"),
}
"""`mapkit eval --help` in sections: the flight stack's layers (``--stack none`` turns off all but the
corridor, at its unchecked width, and the speed profile) apart from what is flown and the loop every method shares."""


class _SectionedCommand(click.Command):
    """A command whose --help lists its options under the headings of :data:`_SECTIONS`."""

    def format_options(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = {p.name: p.get_help_record(ctx) for p in self.get_params(ctx)}
        placed = {name for names in _SECTIONS.values() for name in names}
        sections = [*_SECTIONS.items(), ("Other", tuple(n for n in rows if n and n not in placed))]
        for title, names in sections:
            records = [r for n in names if (r := rows.get(n)) is not None]
            if records:
                with formatter.section(title):
                    formatter.write_dl(records)


@main.command("eval", cls=_SectionedCommand)
@click.option("--model", "run_dir", type=click.Path(path_type=Path), default=None,
              help="Run directory with model.pt, or \"pretrained\" for the model shipped with mapkit (needed by every method but straight and oracle).")
@click.option("--world", "world", default="all", show_default=True, help="forest, office, garage, all, or a comma list.")
@click.option("--pairs", type=COUNT, default=60, show_default=True, help="Start-goal pairs per world.")
@click.option("--seed", type=INDEX, default=0, show_default=True,
              help="Seed of the evaluation worlds and pairs (must not be a training world's seed).")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="Output folder.")
@click.option("--methods", default="all", show_default=True,
              help="Comma list of: learned, learned+uniform, learned+poly5, learned+gradient, untrained (the model's "
                   "architecture at its initial weights), straight-keypoints (key-points on the straight line to the "
                   "goal), iplanner-style, straight, oracle.")
@click.option("--stack", "stacks", default="full", show_default=True,
              help="Comma list of flight stacks the learned methods fly under: full (every layer below: memory, checked "
                   "corridor, turn toward open space, routing, follow) and/or none (the paper's protocol: the "
                   "network's key-points through the unchecked corridor, replanned every interval). Each method flies under "
                   "each; runs under none are labelled NAME@none.")
@click.option("--untrained-seeds", "--untrained-seed", "untrained_seeds", default="0,1,2,3", show_default=True,
              help="Comma list of seeds of the untrained method's initial weights: each flies every pair "
                   "(untrained#SEED) and the ablation pools them; one set of weights flies well or badly by chance.")
@click.option("--vehicle", type=click.Choice(VEHICLES), default="tracker", show_default=True,
              help="What flies the pilot's references: tracker (a linear 4th-order tracker, level body; fast) or "
                   "rotorpy (rotorpy's quadrotor with rotor dynamics and drag under its SE(3) controller at 100 Hz, "
                   "the camera tilting with the airframe).")
@click.option("--drop-frames", type=FRACTION, default=0.0, show_default=True,
              help="Fault injection: the fraction of depth frames lost (the pilot gets no depth for them).")
@click.option("--depth-delay", type=FINITE, default=0.0, show_default=True,
              help="Fault injection: seconds by which depth (and its pose) lags the vehicle.")
@click.option("--pose-noise", type=FINITE, default=0.0, show_default=True,
              help="Fault injection: metres of noise (std per axis) on the state's position and the frame's pose.")
@click.option("--gimbal", is_flag=True, help="With --vehicle rotorpy: render the camera level instead of at the airframe's attitude.")
@click.option("--workers", type=COUNT, default=1, show_default=True,
              help="Processes running pairs in parallel (with --scheduler local: the local Dask cluster's size).")
@click.option("--scheduler", metavar="ADDRESS", default=None,
              help="Run every pair as a Dask task on the scheduler at ADDRESS (tcp://HOST:8786; its workers must read "
                   "--model at the same path), or 'local' for a Dask cluster of --workers processes here. The same results.json.")
@click.option("--replan-interval", type=FINITE, default=0.5, show_default=True, help="Seconds between plans.")
@click.option("--horizon", type=FINITE, default=6.0, show_default=True, help="Local goal distance, metres.")
@click.option("--min-distance", type=FINITE, default=8.0, show_default=True, help="Start-goal distance, metres.")
@click.option("--ignore-eta", is_flag=True, help="Execute plans even when eta >= 0.5.")
@click.option("--on-reject", type=click.Choice(ON_REJECT), default="continue", show_default=True,
              help="A rejected plan (eta >= 0.5) in flight: keep flying the previous plan, or brake to rest and look around.")
@click.option("--corridor", type=FINITE, default=1.0, show_default=True,
              help="Widest half-width (m) of the flight corridor learned plans may use around their key-points; 0 = through them.")
@click.option("--corridor-check/--no-corridor-check", default=True, show_default=True,
              help="Narrow the corridor (½, ¼, ⅒, then through the key-points) while the trajectory comes closer to "
                   "seen surfaces in the depth image than the one through the key-points.")
@click.option("--check-memory/--no-check-memory", default=True, show_default=True,
              help="The corridor's check also counts remembered surfaces near the trajectory's first seconds "
                   "(the jamb of a doorway the camera no longer sees).")
@click.option("--unchecked-corridor", type=FINITE, default=0.3, show_default=True,
              help="Widest half-width (m) of the corridor when it flies without its check (--no-corridor-check, "
                   "--stack none), at most --corridor; 0 = through the key-points.")
@click.option("--turn-toward-open/--no-turn-toward-open", default=True, show_default=True,
              help="A blocked learned planner that hovers turns toward the side with fewer remembered surfaces "
                   "(off: always counter-clockwise).")
@click.option("--v-max", type=FINITE, default=3.0, show_default=True, help="Per-axis speed limit of learned plans, m/s; 0 = none.")
@click.option("--a-max", type=FINITE, default=4.0, show_default=True, help="Per-axis acceleration limit of learned plans, m/s²; 0 = none.")
@click.option("--memory", type=FINITE, default=8.0, show_default=True,
              help="Seconds of depth images the learned planner remembers: paths that come near a remembered surface "
                   "are replaced by a clear candidate, or a detour toward open space, or braking; 0 = off.")
@click.option("--route-after", type=FINITE, default=3.0, show_default=True,
              help="Seconds without getting 0.5 m closer to the goal after which the learned planner aims along a "
                   "route around every surface seen in the flight (unseen space free); 0 = never.")
@click.option("--subgoal-speed", type=FINITE, default=None,
              help="m/s at which learned plans pass a way out toward open space (when nothing leads on toward "
                   "the goal); default: the cruise speed; 0 = stop there.")
@click.option("--speed", type=FINITE, default=1.2, show_default=True,
              help="Cruise speed (m/s) of the speed profile that times learned plans (the oracle's pace); 0 = the "
                   "model's cruise speed (2 m/s for the shipped model: flights about a third shorter, at about 20x "
                   "the effort; the effort grows with the 7th power of the pace). The time limit follows it "
                   "(4x the straight distance at this speed).")
@click.option("--search-speed", type=FINITE, default=None,
              help="Cruise speed (m/s) for the rest of a flight once it searches for its way (stalled, or flown "
                   "1.4x its progress toward the goal + 1 m); default: the model's cruise speed.")
@click.option("--turn-accel", type=FINITE, default=1.5, show_default=True,
              help="m/s²: a learned plan whose key-points turn is timed at most at sqrt(turn-accel x the turn's "
                   "radius) (and at least --turn-min-speed): turns are flown slower, straight paths at cruise "
                   "speed; 0 = every plan at the cruise speed.")
@click.option("--turn-min-speed", type=FINITE, default=1.0, show_default=True,
              help="m/s: the slowest cruise speed --turn-accel sets.")
@click.option("--stop-decel", type=FINITE, default=0.75, show_default=True,
              help="m/s²: until a flight searches for its way, learned plans that end at rest at the goal slow "
                   "down to it at this rate; 0 = the model's acceleration.")
@click.option("--follow", type=FRACTION, default=0.75, show_default=True,
              help="Fraction of the way each key-point of a new plan moves toward the reference being flown "
                   "(at most the corridor's width): smoother replanning; 0 = the network's key-points.")
@click.option("--keep-choice", type=FINITE, default=3.0, show_default=True,
              help="Score margin within which a replan keeps the candidate the last plan chose while the network "
                   "still accepts it (η < 0.5), instead of switching to the best-scored one; 0 = switch every plan.")
@click.option("--flown-judge/--no-flown-judge", default=False, show_default=True,
              help="With the full stack, also gate and choose with the model's flown-path head where it has one "
                   "(each candidate's trajectory as flown, judged against the depth image); without the stack "
                   "(--stack none) it always does.")
@click.option("--shift/--no-shift", default=True, show_default=True,
              help="Also judge every candidate of the network shifted sideways by ±0.3 and ±0.6 m (mapkit.flight.SHIFT).")
@click.option("--plan-latency", type=FINITE, default=0.02, show_default=True,
              help="Seconds from the depth frame to the plan taking over (the vehicle flies on meanwhile).")
@click.option("--final-approach", type=FINITE, default=0.0, show_default=True,
              help="Metres from the goal where one segment to rest at the goal replaces the planner's plans (0: never).")
@click.option("--look-ahead", type=FINITE, default=1.5, show_default=True,
              help="Seconds: the moving vehicle heads toward where its reference will be this much later (0: along the velocity).")
@click.option("--record-plans", is_flag=True,
              help="Also write plans.npz: what the learned method's time allocation was given at every plan "
                   "(for `mapkit tune-timing`).")
@click.option("--record-judge", is_flag=True,
              help="Also write judge.npz: every candidate of the learned method's plans as a flown-path judge "
                   "reads it, labelled against the world (for `mapkit tune-judge`).")
@click.option("--judge-history", type=FINITE, default=None,
              help="With --record-judge: seconds of each flight's earlier frames the recorded clearances also read "
                   "(the head fitted to them reads as many) [default: the model's flown_history].")
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@library_call
def eval_cmd(run_dir: Path | None, world: str, pairs: int, seed: int, output: Path, methods: str, stacks: str,
             untrained_seeds: str, vehicle: VehicleKind, drop_frames: float, depth_delay: float, pose_noise: float,
             gimbal: bool, workers: int, scheduler: str | None,
             replan_interval: float, horizon: float, min_distance: float, ignore_eta: bool, on_reject: OnReject, corridor: float,
             corridor_check: bool, check_memory: bool, unchecked_corridor: float, turn_toward_open: bool, v_max: float, a_max: float, memory: float, route_after: float, subgoal_speed: float | None, speed: float, search_speed: float | None, turn_accel: float, turn_min_speed: float, stop_decel: float, follow: float, keep_choice: float, flown_judge: bool, shift: bool, plan_latency: float, final_approach: float, look_ahead: float,
             record_plans: bool, record_judge: bool, judge_history: float | None, overwrite: bool) -> None:
    """Closed-loop evaluation in unseen simulated worlds: success, effort, latency; report + PNGs."""
    from mapkit.evaluation import (
        METHODS,
        WORLD_ORDER,
        EvalConfig,
        Faults,
        LoopConfig,
        comparison_lines,
        evaluate,
        parse_stacks,
        parse_untrained_seeds,
    )
    from mapkit.flight import PilotConfig

    with option_values():
        worlds = WORLD_ORDER if world.strip() == "all" else tuple(w.strip() for w in world.split(",") if w.strip())
        names = METHODS if methods.strip() == "all" else tuple(m.strip() for m in methods.split(",") if m.strip())
        execution = _flight_stack(corridor=corridor, corridor_check=corridor_check, check_memory=check_memory,
                                  unchecked_corridor=unchecked_corridor,
                                  memory=memory, subgoal_speed=subgoal_speed, turn_toward_open=turn_toward_open,
                                  route_after=route_after, follow=follow, keep_choice=keep_choice,
                                  flown_judge=flown_judge, shift=shift, speed=speed, search_speed=search_speed,
                                  turn_accel=turn_accel, turn_min_speed=turn_min_speed, stop_decel=stop_decel,
                                  v_max=v_max, a_max=a_max)
        config = EvalConfig(worlds=worlds, pairs=pairs, seed=seed, methods=names, min_distance=min_distance,
                            stacks=parse_stacks(stacks),
                            untrained_seeds=parse_untrained_seeds(untrained_seeds),
                            workers=workers, scheduler=scheduler, record_plans=record_plans, record_judge=record_judge,
                            judge_history=judge_history, execution=execution, vehicle=vehicle, gimbal=gimbal,
                            loop=LoopConfig(pilot=PilotConfig(
                                replan_interval=replan_interval, horizon=horizon, respect_eta=not ignore_eta,
                                on_reject=on_reject, plan_latency=plan_latency, final_approach=final_approach,
                                look_ahead=look_ahead),
                                faults=Faults(drop=drop_frames, delay=depth_delay, pose_noise=pose_noise, seed=seed)))
        config.validate()
    result = evaluate(run_dir, output, config, overwrite=overwrite)
    s, lat = result.summary["success"], result.summary["latency"]
    cols = [*config.worlds, "overall"]
    width = max(18, *(len(m) + 2 for m in s))
    click.echo(f"{'method':<{width}}" + "".join(f"{c:>10}" for c in cols) + f"{'effort':>12}{'latency':>11}")
    for m in s:  # every run, in report order
        eff = s[m]["overall"]["control_effort"]["median"]
        ms = lat[m]["overall"]["mean_ms"]
        click.echo(f"{m:<{width}}" + "".join(f"{100 * (s[m][c]['success_rate'] or 0):>9.1f}%" for c in cols)
                   + (f"{eff:>12.4g}" if eff is not None else f"{'–':>12}") + (f"{ms:>9.2f}ms" if ms is not None else ""))
    click.echo("effort: median ∫‖snap‖² dt (m²/s⁷) of the successful flights")
    if result.ablation is not None:
        click.echo("\n".join(comparison_lines(result.ablation)))
    recorded = [name for name, asked in (("plans.npz", record_plans), ("judge.npz", record_judge)) if asked]
    click.echo(f"wrote {output}/results.json, latency.json, report.md, trajectories.npz and "
               f"{sum(p.suffix == '.png' for p in result.files)} PNGs" + (f" (and {', '.join(recorded)})" if recorded else ""))


def _flight_stack(*, corridor: float, corridor_check: bool, check_memory: bool, unchecked_corridor: float, memory: float,
                  subgoal_speed: float | None, turn_toward_open: bool, route_after: float, follow: float,
                  keep_choice: float, flown_judge: bool, shift: bool, speed: float,
                  search_speed: float | None, turn_accel: float, turn_min_speed: float, stop_decel: float,
                  v_max: float, a_max: float) -> Execution:
    """The flight stack the options describe, layer by layer (0 turns a layer or a limit off)."""
    from mapkit._choices import CANDIDATE_SHIFTS
    from mapkit.flight import Corridor, Execution, Memory, RouteConfig, SpeedProfile

    return Execution(
        corridor=Corridor(width=corridor or None, check=corridor_check, check_memory=check_memory,
                          unchecked_width=unchecked_corridor or None),
        memory=Memory(seconds=memory, subgoal_speed=subgoal_speed, turn_toward_open=turn_toward_open) if memory else None,
        route=None if route_after == 0 else RouteConfig(after=route_after),
        follow=follow,
        keep_choice=keep_choice or None,
        flown_judge=flown_judge,
        shift=CANDIDATE_SHIFTS if shift else (),
        speed=SpeedProfile(cruise=speed or None, search_speed=search_speed, turn_accel=turn_accel or None,
                           turn_min_speed=turn_min_speed, stop_decel=stop_decel or None, v_max=v_max or None,
                           a_max=a_max or None))
