"""`mapkit config COMMAND`: every setting of a command as TOML, for its --config."""

from __future__ import annotations

import click

from mapkit.cli._config import SPECS, render
from mapkit.cli._group import PIPELINE_ORDER, main


def _commands() -> list[str]:
    """The commands with settings, in pipeline order."""
    rank = {name: i for i, name in enumerate(PIPELINE_ORDER)}
    return sorted(SPECS, key=lambda name: (rank.get(name.split()[0], len(rank)), name))


@main.command("config")
@click.argument("command", nargs=-1, required=True)
def config_cmd(command: tuple[str, ...]) -> None:
    """Print every setting of COMMAND (eval, train, batch, lab tune-timing, ...) at its default, each with
    its docstring as a comment: TOML to edit and pass as COMMAND --config FILE.toml."""
    name = " ".join(command)
    spec = SPECS.get(name) or SPECS.get(f"lab {name}")
    if spec is None:
        raise click.UsageError(f"{name!r} is not a command with settings; use one of: {', '.join(_commands())}")
    click.echo(render(spec), nl=False)
