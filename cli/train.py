"""`mapkit train`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from mapkit._choices import (
    BOUNDARY_SCALES,
    PRESET_NAMES,
    TIMING_OBJECTIVES,
    TRAINED_WEIGHTS,
    BoundaryScale,
    TimingObjective,
)
from mapkit.cli._group import (
    COUNT,
    FINITE,
    INDEX,
    NONNEGATIVE,
    POSITIVE,
    STORE_PATH,
    WIDTHS,
    current_folder,
    library_call,
    main,
    option_values,
)


def _pairs(values: tuple[str, ...], option: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for text in values:
        key, sep, raw = text.partition("=")
        if not sep or not key:
            raise click.UsageError(f"{option} {text!r}: expected FIELD=VALUE (VALUE as JSON, e.g. input_size=[96,160])")
        try:
            out[key] = json.loads(raw)
        except json.JSONDecodeError:
            out[key] = raw
    return out


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
@click.option("--grad-clip", type=POSITIVE, default=None, help="Override the gradient-norm clip.")
@click.option("--preset", default="cpu", show_default=True, type=click.Choice(PRESET_NAMES), help="Named configuration.")
@click.option("--name", default=None, help="Run name (default: the preset's name).")
@click.option("--runs-dir", type=STORE_PATH, default=None, help="Where runs go, a local folder or an fsspec URL (default: first WS/runs).")
@click.option("--epochs", type=COUNT, default=None, help="Override the preset's epochs.")
@click.option("--batch-size", type=COUNT, default=None, help="Override the preset's batch size.")
@click.option("--lr", type=FINITE, default=None, help="Override the preset's Adam learning rate.")
@click.option("--device", default="cpu", show_default=True, help="cpu, cuda or cuda:N.")
@click.option("--seed", type=INDEX, default=0, show_default=True, help="Seed (CPU runs are reproducible).")
@click.option("--max-steps", type=COUNT, default=None, help="Stop after this many optimiser steps.")
@click.option("--weight-decay", type=NONNEGATIVE, default=None, help="Override the Adam weight decay.")
@click.option("--corridor", type=POSITIVE, default=None, help="Flight-corridor half-width (m) for min_snap during training.")
@click.option("--val-batches", type=COUNT, default=None, help="Limit validation batches.")
@click.option("--planner", "planner_items", multiple=True, metavar="FIELD=VALUE", help="PlannerConfig field override (repeatable).")
@click.option("--loss", "loss_items", multiple=True, metavar="FIELD=VALUE", help="LossConfig field override (repeatable).")
@click.option("--init", "init", default=None, metavar="MODEL",
              help="Start from this model's weights (run directory, model.pt or 'pretrained'): fine-tuning.")
@click.option("--only", type=click.Choice(TRAINED_WEIGHTS), default="all", show_default=True,
              help="Train only the Time Allocation Net ('tan') or only the judge of the candidates ('judge': "
                   "scores and η) on the key-points of the frozen --init model.")
@click.option("--resume", is_flag=True, help="Continue the run after its last completed epoch.")
@click.option("--overwrite", is_flag=True, help="Restart an existing run from scratch.")
@click.option("--recipe", default=None, metavar="NAME|FILE.toml",
              help="Make a model from nothing by a declared recipe ('pretrained': the shipped model, about 2 h on 2 "
                   "cores) into -o DIR; resumable: run it again to go on.")
@click.option("-o", "--output", "recipe_dir", type=click.Path(path_type=Path), default=None,
              help="With --recipe: the folder it works in; DIR/model.pt is the result.")
@click.option("--force", is_flag=True, help="With --recipe: resume a folder another mapkit version started.")
@library_call
def train_cmd(workspaces: tuple[Path | str, ...], dataset_root: Path | None, val_worlds: int | None,
              val_workspaces: tuple[Path | str, ...], grad_clip: float | None, preset: str, name: str | None,
              runs_dir: Path | str | None, epochs: int | None,
              batch_size: int | None, lr: float | None, device: str, seed: int, max_steps: int | None,
              val_batches: int | None, weight_decay: float | None, corridor: float | None, planner_items: tuple[str, ...], loss_items: tuple[str, ...], init: str | None,
              only: str, resume: bool, overwrite: bool, recipe: str | None, recipe_dir: Path | None,
              force: bool) -> None:
    """Train the self-supervised planner on WS/tuples.zarr (+ map.zarr) → runs/NAME, or make a model
    from nothing by a recipe (--recipe pretrained -o DIR).

    Multi-GPU / multi-node: torchrun --nproc-per-node N -m mapkit.cli train ...
    """
    if recipe is not None or recipe_dir is not None:
        _recipe(recipe, recipe_dir, force)
        return
    from mapkit.train import preset as make_preset
    from mapkit.train import train

    overrides: dict[str, Any] = {"name": name or preset, "device": device, "seed": seed, "max_steps": max_steps,
                                 "val_batches": val_batches}
    overrides["corridor"] = corridor
    overrides["init"] = init
    overrides["only"] = only
    for key, value in (("epochs", epochs), ("batch_size", batch_size), ("lr", lr), ("weight_decay", weight_decay),
                       ("grad_clip", grad_clip)):
        if value is not None:
            overrides[key] = value
    overrides["planner"] = _pairs(planner_items, "--planner")
    overrides["loss"] = _pairs(loss_items, "--loss")
    with option_values():  # unknown --planner/--loss fields too
        config = make_preset(preset, **overrides)
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
    if s.blocked_goals == 0:
        click.echo("warning: no training goal is blocked in its map (0 of the samples): the planner cannot learn to "
                   "steer around obstacles; re-export with hidden goals (mapkit export --goal-mix 0.2 0.4 0.4)", err=True)
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


@main.command("tune-timing")
@click.option("--model", "model", type=click.Path(path_type=Path), default=Path("pretrained"), show_default=True,
              help="Run directory with model.pt, or \"pretrained\".")
@click.option("--plans", "plans", multiple=True, required=True, type=click.Path(path_type=Path),
              help="Eval folder made with `mapkit eval --methods learned --record-plans` (repeatable): the plans to learn from.")
@click.option("--val", "val", multiple=True, required=True, type=click.Path(path_type=Path),
              help="Eval folder(s) of other seeds, likewise: the plans that choose the weights kept.")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="New run directory.")
@click.option("--steps", type=COUNT, default=4000, show_default=True, help="Adam steps.")
@click.option("--lr", type=POSITIVE, default=1e-3, show_default=True, help="Learning rate.")
@click.option("--boundary-inputs", is_flag=True,
              help="Replace the TAN by a new one that also reads the start velocity, acceleration and end speed.")
@click.option("--boundary-scale", type=click.Choice(BOUNDARY_SCALES), default="limits", show_default=True,
              help="With --boundary-inputs: limits = divided by the cruise speed and acceleration; duration = "
                   "scaled by each plan's total time and path length (the same split at every --speed).")
@click.option("--tan-hidden", type=WIDTHS, default=None,
              help="Hidden widths of a new TAN trained from scratch, e.g. 256,256,256 (default: the model's TAN).")
@click.option("--lr-decay/--no-lr-decay", default=True, show_default=True,
              help="Cosine decay of the learning rate to 1 % of --lr over the steps.")
@click.option("--objective", type=click.Choice(TIMING_OBJECTIVES), default="snap", show_default=True,
              help="snap: each plan's whole snap cost; imitate: each segment's duration against the "
                   "gradient-descent split's (squared log ratio), the first segment (the one flown) weighted more.")
@click.option("--first-weight", type=POSITIVE, default=4.0, show_default=True,
              help="With --objective imitate: the first segment's weight (the others 1).")
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@library_call
def tune_timing_cmd(model: Path, plans: tuple[Path, ...], val: tuple[Path, ...], output: Path, steps: int, lr: float,
                    boundary_inputs: bool, boundary_scale: BoundaryScale, tan_hidden: tuple[int, ...] | None,
                    lr_decay: bool, objective: TimingObjective, first_weight: float, overwrite: bool) -> None:
    """Fine-tune the Time Allocation Net alone on plans the planner made in flight (lower snap per plan)."""
    from mapkit.train import TimingTuneConfig, tune_timing

    with option_values():
        config = TimingTuneConfig(steps=steps, lr=lr, boundary_inputs=boundary_inputs, boundary_scale=boundary_scale,
                                  tan_hidden=tan_hidden, lr_decay=lr_decay, objective=objective,
                                  first_weight=first_weight)
        config.validate()
    s = tune_timing(model, plans, val, output, config, overwrite=overwrite)
    click.echo(f"{s.train_plans} plans to learn from, {s.val_plans} to validate; snap per plan against the "
               f"gradient-descent split (median / summed): {s.before[0]:.2f}× / {s.before[1]:.3f}× before, "
               f"{s.after[0]:.2f}× / {s.after[1]:.3f}× after (step {s.best_step})")
    if objective == "imitate":
        click.echo(f"duration error against the gradient-descent split (weighted mean squared log ratio): "
                   f"{s.objective[0]:.4f} before, {s.objective[1]:.4f} after")
    click.echo(f"wrote {output}/model.pt and config.json")


@main.command("tune-judge")
@click.option("--model", "model", type=click.Path(path_type=Path), default=Path("pretrained"), show_default=True,
              help="Run directory with model.pt, or \"pretrained\".")
@click.option("--records", "records", multiple=True, required=True, type=click.Path(path_type=Path),
              help="Eval folder made with `mapkit eval --methods learned --record-judge` (repeatable): the candidates to learn from.")
@click.option("--val", "val", multiple=True, required=True, type=click.Path(path_type=Path),
              help="Eval folder(s) of other seeds, likewise: the candidates that choose the weights kept.")
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="New run directory.")
@click.option("--steps", type=COUNT, default=4000, show_default=True, help="Adam steps.")
@click.option("--lr", type=POSITIVE, default=1e-3, show_default=True, help="Learning rate.")
@click.option("--positive-weight", type=POSITIVE, default=1.0, show_default=True,
              help="Weight of the colliding candidates in the cross-entropy (> 1 catches more and vetoes more).")
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@library_call
def tune_judge_cmd(model: Path, records: tuple[Path, ...], val: tuple[Path, ...], output: Path, steps: int, lr: float,
                   positive_weight: float, overwrite: bool) -> None:
    """Fit the flown-path head: each candidate judged by its trajectory as flown against the depth image
    (and the flight's recent frames, as recorded with `mapkit eval --judge-history`)."""
    from mapkit.train import JudgeTuneConfig, tune_judge

    with option_values():
        config = JudgeTuneConfig(steps=steps, lr=lr, positive_weight=positive_weight)
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


@main.command("compare-timing")
@click.option("--model", "model", type=click.Path(path_type=Path), default=Path("pretrained"), show_default=True,
              help="Run directory with model.pt, or \"pretrained\".")
@click.option("--plans", "plans", multiple=True, required=True, type=click.Path(path_type=Path),
              help="Eval folder made with `mapkit eval --methods learned --record-plans` (repeatable).")
@click.option("--window", type=POSITIVE, default=0.5, show_default=True,
              help="Seconds of each plan a replanning flight flies (mapkit eval replans every 0.5 s).")
@library_call
def compare_timing_cmd(model: Path, plans: tuple[Path, ...], window: float) -> None:
    """The model's Time Allocation Net against gradient descent on the same recorded plans (Table III)."""
    from mapkit.train import compare_timing

    c = compare_timing(model, plans, window=window)
    click.echo(f"{c.plans} plans; snap of the TAN's split against gradient descent's on the same plans "
               "(summed / median / geometric mean of the per-plan ratios):")
    for label, r in (("whole plan", c.whole), (f"first {c.window:g} s (flown)", c.flown)):
        click.echo(f"  {label + ':':<20} {r.summed:.3f}× / {r.median:.3f}× / {r.geomean:.3f}×")
