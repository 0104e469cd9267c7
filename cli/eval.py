"""`mapkit eval`."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from mapkit._choices import VEHICLES
from mapkit.cli._config import ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import COUNT, INDEX, library_call, main, option_values

if TYPE_CHECKING:
    from mapkit.evaluation import EvalConfig, Faults


def _defaults() -> EvalConfig:
    from mapkit.evaluation import EvalConfig

    return EvalConfig()


RESEARCH_ONLY = frozenset({
    "record_plans", "record_judge", "judge_history", "execution.flown_judge",
})
"""EvalConfig fields that served one experiment: not on the command line (the recipe, which records
plans and judgements, sets them through the library)."""

EVAL = ConfigSpec("eval", (("", _defaults),), hidden=RESEARCH_ONLY, example="loop.pilot.replan_interval=0.5")


class Faults3(click.ParamType):
    """``DROP,DELAY,NOISE``: the fraction of depth frames lost, seconds of depth lag, metres of pose noise."""

    name = "drop,delay,noise"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, tuple):
            return value
        try:
            parts = tuple(float(p) for p in str(value).split(","))
        except ValueError:
            parts = ()
        if len(parts) != 3:
            self.fail(f"{value!r} is not three numbers DROP,DELAY,NOISE (e.g. 0.1,0.05,0.02)", param, ctx)
        return parts


def _faults_text(faults: Faults) -> str:
    return f"{faults.drop:g},{faults.delay:g},{faults.pose_noise:g}"


@main.command("eval")
@click.option("--model", "run_dir", type=click.Path(path_type=Path), default=None,
              help="Run directory with model.pt, or \"pretrained\" for the model shipped with mapkit (needed by every method but straight and oracle).")
@field_option("--world", "world", spec=EVAL, key="worlds", show=lambda _: "all",
              help="forest, office, garage, all, or a comma list.")
@field_option("--pairs", spec=EVAL, key="pairs", type=COUNT)
@field_option("--seed", spec=EVAL, key="seed", type=INDEX,
              help="Seed of the evaluation worlds, the pairs and the faults (must not be a training world's seed).")
@field_option("--methods", spec=EVAL, key="methods", show=lambda _: "all",
              help="Comma list of: learned, learned+uniform, learned+poly5, learned+gradient, untrained (the model's "
                   "architecture at its initial weights), straight-keypoints (key-points on the straight line to the "
                   "goal), iplanner-style, straight, oracle.")
@field_option("--stack", "stacks", spec=EVAL, key="stacks",
              help="Comma list of flight stacks the learned methods fly under: full (every layer of `execution`: "
                   "memory, checked corridor, turn toward open space, routing, follow) and/or none (the paper's "
                   "protocol: the network's key-points through the unchecked corridor, replanned every interval). "
                   "Runs under none are labelled NAME@none.")
@field_option("--vehicle", spec=EVAL, key="vehicle", type=click.Choice(VEHICLES),
              help="What flies the pilot's references: tracker (a linear 4th-order tracker, level body; fast) or "
                   "rotorpy (rotorpy's quadrotor with rotor dynamics and drag under its SE(3) controller at 100 Hz, "
                   "the camera tilting with the airframe; --set gimbal=true levels it).")
@field_option("--faults", spec=EVAL, key="loop.faults", type=Faults3(), show=_faults_text,
              help="Fault injection: the fraction of depth frames lost, seconds by which depth (and its pose) lags, "
                   "metres of pose noise (std per axis).")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="Output folder.")
@field_option("--workers", spec=EVAL, key="workers", type=COUNT,
              help="Processes running pairs in parallel (with --scheduler local: the local Dask cluster's size).")
@field_option("--scheduler", spec=EVAL, key="scheduler", metavar="ADDRESS",
              help="Run every pair as a Dask task on the scheduler at ADDRESS (tcp://HOST:8786; its workers must read "
                   "--model at the same path), or 'local' for a Dask cluster of --workers processes here. The same results.json.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@config_options(EVAL)
@library_call
def eval_cmd(run_dir: Path | None, world: str | None, pairs: int | None, seed: int | None, methods: str | None,
             stacks: str | None, vehicle: str | None, faults: tuple[float, float, float] | None, output: Path,
             workers: int | None, scheduler: str | None, overwrite: bool, settings: Settings) -> None:
    """Closed-loop evaluation in unseen simulated worlds: success, effort, latency; report + PNGs.

    The closed loop and the flight stack are settings: `mapkit config eval` prints every one with its
    default, e.g. --set execution.speed.cruise=2.0 (the pace), --set execution.memory=none (a layer off).
    """
    from mapkit.evaluation import METHODS, WORLD_ORDER, comparison_lines, evaluate, parse_stacks

    with option_values():
        options: dict[str, Any] = {"pairs": pairs, "seed": seed, "vehicle": vehicle, "workers": workers,
                                   "scheduler": scheduler}
        if world is not None:
            options["worlds"] = WORLD_ORDER if world.strip() == "all" else tuple(w.strip() for w in world.split(",") if w.strip())
        if methods is not None:
            options["methods"] = METHODS if methods.strip() == "all" else tuple(m.strip() for m in methods.split(",") if m.strip())
        if stacks is not None:
            options["stacks"] = parse_stacks(stacks)
        if faults is not None:
            options.update(zip(("loop.faults.drop", "loop.faults.delay", "loop.faults.pose_noise"), faults, strict=True))
        config = _seeded_faults(settings.build(_defaults(), options), settings)
        config.validate()
    result = evaluate(run_dir, output, config, overwrite=overwrite)
    _report(result, config, comparison_lines)
    click.echo(f"wrote {output}/results.json, latency.json, report.md, trajectories.npz and "
               f"{sum(p.suffix == '.png' for p in result.files)} PNGs")


def _seeded_faults(config: EvalConfig, settings: Settings) -> EvalConfig:
    """The faults are drawn with the evaluation's seed unless a setting gives them their own."""
    if settings.given("loop.faults.seed") or config.loop.faults.seed == config.seed:
        return config
    loop = dataclasses.replace(config.loop, faults=dataclasses.replace(config.loop.faults, seed=config.seed))
    return dataclasses.replace(config, loop=loop)


def _report(result: Any, config: EvalConfig, comparison_lines: Any) -> None:
    """The success table per method and world, effort and latency, then the ablation's comparisons."""
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
