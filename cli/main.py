"""The ``mapkit`` command group and the error boundary shared by every command."""

from __future__ import annotations

import functools
import logging
import sys
from typing import Any, Callable

import click

from mapkit import __version__
from mapkit.errors import MapkitError


def library_call(func: Callable[..., Any]) -> Callable[..., Any]:
    """Run a command body; a MapkitError, or an OSError from the file system (no space, no permission,
    not a directory, read-only), becomes ``error: <message>`` on stderr and exit 1."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except MapkitError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(1)
        except OSError as exc:
            where = f": {exc.filename}" if exc.filename else ""
            click.echo(f"error: {exc.strerror or exc}{where}", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            click.echo("interrupted", err=True)
            sys.exit(130)

    return wrapper


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, "--version", prog_name="mapkit")
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug).")
def main(verbose: int) -> None:
    """mapkit: UAV depth + pose recordings → maps, training data and a learned planner.

    Every command that reads or writes a workspace takes -w/--workspace.
    """
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")


# Command modules register themselves on `main` when imported.
from mapkit.cli import dataset as _dataset  # noqa: E402,F401
from mapkit.cli import eval as _eval  # noqa: E402,F401
from mapkit.cli import export as _export  # noqa: E402,F401
from mapkit.cli import ingest as _ingest  # noqa: E402,F401
from mapkit.cli import mapping as _mapping  # noqa: E402,F401
from mapkit.cli import plan as _plan  # noqa: E402,F401
from mapkit.cli import simulate as _simulate  # noqa: E402,F401
from mapkit.cli import train as _train  # noqa: E402,F401
from mapkit.cli import view as _view  # noqa: E402,F401
