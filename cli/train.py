"""`mapkit train` and the research tools of `mapkit lab` (tune-timing, tune-judge)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from mapkit._choices import PRESET_NAMES
from mapkit.cli._config import ConfigSpec, Settings, config_options, field_option
from mapkit.cli._group import (
    COUNT,
    INDEX,
    POSITIVE,
    STORE_PATH,
    current_folder,
    lab,
    library_call,
    main,
    option_values,
)

if TYPE_CHECKING:
    from mapkit.train import JudgeTuneConfig, TimingTuneConfig, TrainConfig


def _train_defaults() -> TrainConfig:
    from mapkit.train import TrainConfig, preset

    name = TrainConfig().preset
    return preset(name, name=name)  # a run is named after its preset unless --name says otherwise


TRAIN = ConfigSpec("train", (("", _train_defaults),), hidden=frozenset({"preset"}), example="planner.accel=1.5",
                   note="The defaults are the cpu preset's; with --preset paper the paper preset's are the base.")


@main.command("train")
@click.option("-w", "--workspace", "workspaces", multiple=True, type=STORE_PATH,
              help="Workspace with tuples.zarr and map.zarr (a local folder or an fsspec URL); repeat to train on "
                   "several. Default: the current directory, unless --dataset is given.")
@click.option("--dataset", "dataset_root", type=click.Path(path_type=Path), default=None,
              help="A `mapkit dataset` directory: train on its worlds (added to any -w).")
@click.option("--val-worlds", type=INDEX, default=None,
              help="With --dataset: hold out the last N worlds whole for validation (default: an eighth, at least 1).")
@click.option("--val-workspace", "val_workspaces", multiple=True, type=STORE_PATH,
              help="Held-out workspace for validation (repeatable); without one, each store's own split validates.")
@field_option("--preset", spec=TRAIN, key="preset", type=click.Choice(PRESET_NAMES),
              help="Named configuration the settings start from.")
@click.option("--name", default=None, help="Run name (default: the preset's name).")
@click.option("--runs-dir", type=STORE_PATH, default=None, help="Where runs go, a local folder or an fsspec URL (default: first WS/runs).")
@field_option("--epochs", spec=TRAIN, key="epochs", type=COUNT, show=lambda v: f"the preset's; cpu: {v}")
@field_option("--device", spec=TRAIN, key="device")
@field_option("--seed", spec=TRAIN, key="seed", type=INDEX)
@field_option("--init", spec=TRAIN, key="init", metavar="MODEL",
              help="Start from this model's weights (run directory, model.pt or 'pretrained'): fine-tuning "
                   "(--set only=tan or only=judge trains that part alone).")
@click.option("--resume", is_flag=True, help="Continue the run after its last completed epoch.")
@click.option("--overwrite", is_flag=True, help="Restart an existing run from scratch.")
@click.option("--recipe", default=None, metavar="NAME|FILE.toml",
              help="Make a model from nothing by a declared recipe ('pretrained': the shipped model, about 2 h on 2 "
                   "cores) into -o DIR; resumable: run it again to go on.")
@click.option("-o", "--output", "recipe_dir", type=click.Path(path_type=Path), default=None,
              help="With --recipe: the folder it works in; DIR/model.pt is the result.")
@click.option("--force", is_flag=True, help="With --recipe: resume a folder another mapkit version started.")
@config_options(TRAIN)
@library_call
def train_cmd(workspaces: tuple[Path | str, ...], dataset_root: Path | None, val_worlds: int | None,
              val_workspaces: tuple[Path | str, ...], preset: str | None, name: str | None,
              runs_dir: Path | str | None, epochs: int | None, device: str | None, seed: int | None, init: str | None,
              resume: bool, overwrite: bool, recipe: str | None, recipe_dir: Path | None, force: bool,
              settings: Settings) -> None:
    """Train the self-supervised planner on WS/tuples.zarr (+ map.zarr) → runs/NAME, or make a model
    from nothing by a recipe (--recipe pretrained -o DIR).

    Everything else is a setting (`mapkit config train`), e.g. --set max_steps=200, --set lr=2e-4,
    --set planner.accel=1.5, --set loss.gamma_time=0. Multi-GPU / multi-node: torchrun
    --nproc-per-node N -m mapkit.cli train ...
    """
    if recipe is not None or recipe_dir is not None:
        if settings.file or settings.sets:
            raise click.UsageError("--config/--set configure one training run; a recipe declares the settings of "
                                   "each of its steps: drop them, or edit a copy of the recipe")
        _recipe(recipe, recipe_dir, force)
        return
    from mapkit.train import TrainConfig, train
    from mapkit.train import preset as make_preset

    chosen = preset or TrainConfig().preset
    with option_values():  # unknown planner/loss fields too
        overrides = settings.nested({"name": name, "epochs": epochs, "device": device, "seed": seed, "init": init})
        overrides.setdefault("name", chosen)
        config = make_preset(chosen, **overrides)
        config.validate()
    if val_worlds is not None and dataset_root is None:
        raise click.UsageError("--val-worlds needs --dataset")
    # -w defaults to the current directory, as for every command with a workspace; --dataset alone
    # trains on the dataset's worlds only
    train_ws: list[Path | str] = list(workspaces) or ([] if dataset_root is not None else [current_folder()])
    val_ws: list[Path | str] = list(val_workspaces)
    if dataset_root is not None:
        from mapkit.dataset import dataset_workspaces, split_worlds

        n_val = val_worlds if val_worlds is not None else max(1, len(dataset_workspaces(dataset_root)) // 8)
        more_train, more_val = split_worlds(dataset_root, n_val)
        train_ws, val_ws = [*more_train, *train_ws], [*val_ws, *more_val]
    if runs_dir is None and dataset_root is not None:
        runs_dir = dataset_root / "runs"
    s = train(train_ws, config, runs_dir=runs_dir, resume=resume, overwrite=overwrite, progress=True,
              val_workspaces=val_ws)
    _summary(s)


def _summary(s: Any) -> None:
    """The run's one-line summary (and a warning when no goal taught avoidance)."""
    if s.blocked_goals == 0:
        click.echo("warning: no training goal is blocked in its map (0 of the samples): the planner cannot learn to "
                   "steer around obstacles; re-export with hidden goals (mapkit export --set goal_mix=0.2,0.4,0.4)",
                   err=True)
    if s.last:
        v, b = s.last["val"], s.baseline
        click.echo(
            f"run {s.run_dir}: {s.epochs_done} epochs, {s.steps} steps, {s.seconds:.0f} s ({s.samples_per_second:.1f} samples/s); "
            f"{s.threads} torch thread(s); model.pt from epoch {s.best_epoch}; "
            f"val obstacle {v['obstacle']:.4f} collision {v['collision_rate']:.3f}, blocked goals: reach "
            f"{v.get('blocked_reach', 0):.3f} collision {v.get('blocked_collision', 0):.3f}"
            + (f" (untrained {b['val']['obstacle']:.4f} / {b['val']['collision_rate']:.3f}, straight "
               f"{b['straight']['obstacle']:.4f} / {b['straight']['collision_rate']:.3f}, straight on blocked goals: reach "
               f"{b['straight'].get('blocked_reach', 0):.3f} collision {b['straight'].get('blocked_collision', 0):.3f})"
               if b else "")
        )


def _recipe(recipe: str | None, out: Path | None, force: bool) -> None:
    from mapkit.recipe import RecipeError, load_recipe, run_recipe

    if recipe is None or out is None:
        raise click.UsageError("--recipe and -o go together: mapkit train --recipe pretrained -o DIR")
    try:
        chosen = load_recipe(recipe)
    except RecipeError as exc:  # the option's value: a usage error
        raise click.UsageError(str(exc)) from None
    run_recipe(chosen, out, force=force)


def _timing_defaults() -> TimingTuneConfig:
    from mapkit.train import TimingTuneConfig

    return TimingTuneConfig()


def _judge_defaults() -> JudgeTuneConfig:
    from mapkit.train import JudgeTuneConfig

    return JudgeTuneConfig()


TIMING = ConfigSpec("lab tune-timing", (("", _timing_defaults),), example="tan_hidden=256,256,256",
                    hidden=frozenset({"boundary_scale", "objective", "first_weight"}))
"""tune-timing's settings; the objective and its weights are the recipe's (mapkit/flight/pretrained/recipe.toml)."""
JUDGE = ConfigSpec("lab tune-judge", (("", _judge_defaults),), example="positive_weight=2")
PLANS_HELP = ("An eval folder with plans.npz (repeatable): what the model's time allocation was given in flight "
              "(the recipe's flights steps record them; the library: EvalConfig(record_plans=True)).")


@lab.command("tune-timing")
@click.option("--model", "model", type=click.Path(path_type=Path), default=Path("pretrained"), show_default=True,
              help="Run directory with model.pt, or \"pretrained\".")
@click.option("--plans", "plans", multiple=True, required=True, type=click.Path(path_type=Path),
              help=PLANS_HELP + " The plans to learn from.")
@click.option("--val", "val", multiple=True, required=True, type=click.Path(path_type=Path),
              help="Eval folder(s) of other seeds, likewise: the plans that choose the weights kept.")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="New run directory.")
@field_option("--steps", spec=TIMING, key="steps", type=COUNT)
@field_option("--lr", spec=TIMING, key="lr", type=POSITIVE)
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@config_options(TIMING)
@library_call
def tune_timing_cmd(model: Path, plans: tuple[Path, ...], val: tuple[Path, ...], output: Path, steps: int | None,
                    lr: float | None, overwrite: bool, settings: Settings) -> None:
    """Fine-tune the Time Allocation Net alone on plans the planner made in flight (to imitate gradient descent's split)."""
    from mapkit.train import tune_timing

    with option_values():
        config = settings.build(_timing_defaults(), {"steps": steps, "lr": lr})
        config.validate()
    s = tune_timing(model, plans, val, output, config, overwrite=overwrite)
    click.echo(f"{s.train_plans} plans to learn from, {s.val_plans} to validate; snap per plan against the "
               f"gradient-descent split (median / summed): {s.before[0]:.2f}× / {s.before[1]:.3f}× before, "
               f"{s.after[0]:.2f}× / {s.after[1]:.3f}× after (step {s.best_step})")
    click.echo(f"wrote {output}/model.pt and config.json")


@lab.command("tune-judge")
@click.option("--model", "model", type=click.Path(path_type=Path), default=Path("pretrained"), show_default=True,
              help="Run directory with model.pt, or \"pretrained\".")
@click.option("--records", "records", multiple=True, required=True, type=click.Path(path_type=Path),
              help="An eval folder with judge.npz (repeatable): the candidates to learn from (the recipe's flights "
                   "steps record them; the library: EvalConfig(record_judge=True)).")
@click.option("--val", "val", multiple=True, required=True, type=click.Path(path_type=Path),
              help="Eval folder(s) of other seeds, likewise: the candidates that choose the weights kept.")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="New run directory.")
@field_option("--steps", spec=JUDGE, key="steps", type=COUNT)
@field_option("--lr", spec=JUDGE, key="lr", type=POSITIVE)
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@config_options(JUDGE)
@library_call
def tune_judge_cmd(model: Path, records: tuple[Path, ...], val: tuple[Path, ...], output: Path, steps: int | None,
                   lr: float | None, overwrite: bool, settings: Settings) -> None:
    """Fit the flown-path head: each candidate judged by its trajectory as flown against the depth image
    (and the flight's recent frames, as many seconds as the records hold)."""
    from mapkit.train import tune_judge

    with option_values():
        config = settings.build(_judge_defaults(), {"steps": steps, "lr": lr})
        config.validate()
    s = tune_judge(model, records, val, output, config, overwrite=overwrite)
    click.echo(f"{s.train_rows} candidates to learn from, {s.val_rows} to validate ({100 * s.colliding_share:.1f} % "
               f"colliding; clearances to the image{f' and the last {s.history:g} s of frames' if s.history else ''}); "
               "caught / false alarms on the validation candidates:")
    rows = [("depth image, clearance < robot radius", s.clearance_rule), ("head as it was", s.before),
            (f"fitted head (step {s.best_step})", s.after)]
    for label, score in rows:
        if score is not None:
            click.echo(f"  {label + ':':<40} {100 * score.caught:5.1f} % / {100 * score.false_alarms:4.1f} %")
    click.echo(f"wrote {output}/model.pt and config.json")
