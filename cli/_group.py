"""The ``mapkit`` command group and the error boundary and option types shared by every command.

Command modules import these from here and register their commands on :func:`main`; :mod:`mapkit.cli.main` imports every command module (so the group knows all its commands) and is the entry point.
"""

from __future__ import annotations

import errno
import functools
import logging
import math
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click

from mapkit import __version__
from mapkit.errors import MapkitError

_OUTPUTS = ("output", "out", "workspace")
"""Command arguments naming where a command writes: an OSError without a file name (a full disk
seen by a C library) names that place instead."""


def library_call(func: Callable[..., Any]) -> Callable[..., Any]:
    """Run a command body; a MapkitError, or an OSError from the file system (no space, no permission,
    not a directory, read-only), becomes ``error: <message>`` on stderr and exit 1."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except MapkitError as exc:
            click.echo("error: " + " ".join(str(exc).split()), err=True)  # one line, whatever a library said
            sys.exit(1)
        except OSError as exc:
            path = exc.filename or next((kwargs[k] for k in _OUTPUTS if kwargs.get(k)), None)
            where = f": {path}" if path else ""
            fix = "; free space there or write elsewhere" if exc.errno == errno.ENOSPC else ""
            click.echo(f"error: {exc.strerror or exc}{where}{fix}", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            click.echo("interrupted", err=True)
            sys.exit(130)

    return wrapper


@contextmanager
def option_values() -> Iterator[None]:
    """The block turns a command's option values into configs (parsing and checking them, e.g. with
    their ``validate()``): a value the library refuses there is a usage error, exit 2 like a bad number
    that click refuses, in the library's one line (it names the option, the value and the fix). What
    depends on the inputs' contents or the machine belongs outside the block (exit 1)."""
    try:
        yield
    except MapkitError as exc:
        raise click.UsageError(" ".join(str(exc).split()), click.get_current_context(silent=True)) from None


class Number(click.ParamType):
    """A finite number within bounds, for every numeric option: NaN, ±inf and out-of-range values are
    usage errors naming the option, before any work starts."""

    def __init__(self, low: float | None = None, high: float | None = None, *, low_open: bool = False,
                 high_open: bool = False, integer: bool = False) -> None:
        self.low, self.high, self.low_open, self.high_open, self.integer = low, high, low_open, high_open, integer
        self.name = "integer" if integer else "number"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            number: float = value
        else:
            try:
                number = int(value) if self.integer else float(value)
            except ValueError:
                self.fail(f"{value!r} is not {'an integer' if self.integer else 'a number'}", param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value} is not a finite number", param, ctx)
        if self.low is not None and (number <= self.low if self.low_open else number < self.low):
            self.fail(f"{value} must be {'>' if self.low_open else '>='} {self.low}", param, ctx)
        if self.high is not None and (number >= self.high if self.high_open else number > self.high):
            self.fail(f"{value} must be {'<' if self.high_open else '<='} {self.high}", param, ctx)
        return number


FINITE = Number()
"""Any finite number."""
POSITIVE = Number(0.0, low_open=True)
"""A finite number > 0."""
NONNEGATIVE = Number(0.0)
"""A finite number >= 0."""
FRACTION = Number(0.0, 1.0)
"""A finite number in [0, 1]."""
COUNT = Number(1, integer=True)
"""An integer >= 1."""
INDEX = Number(0, integer=True)
"""An integer >= 0."""


class Widths(click.ParamType):
    """Layer widths separated by commas (``256,256,256``), each an integer >= 1."""

    name = "widths"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, tuple):
            return value
        parts = [p.strip() for p in str(value).split(",")]
        if not all(p.isdigit() and int(p) >= 1 for p in parts):
            self.fail(f"{value!r} is not widths >= 1 separated by commas (e.g. 256,256,256)", param, ctx)
        return tuple(int(p) for p in parts)


WIDTHS = Widths()
"""Layer widths, e.g. ``256,256,256``."""


class StorePath(click.ParamType):
    """A local path (a :class:`~pathlib.Path`, as before) or an fsspec URL such as ``s3://bucket/ws``
    (kept as text: click's path type would fold its ``//``)."""

    name = "path_or_url"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        from mapkit._stores import is_url

        if isinstance(value, Path) or not is_url(str(value)):
            return Path(value)
        return str(value)


STORE_PATH = StorePath()
"""A local path or an fsspec URL (docs/stores.md)."""


def refuse_url(ctx: click.Context, option: str, value: Any, why: str) -> None:
    """One line, exit 1, when a command that needs local files gets a URL for `option`."""
    from mapkit._stores import is_url

    if isinstance(value, str) and is_url(value):
        raise click.ClickException(
            f"mapkit {ctx.info_name}: {option} {value} is a URL, but this command needs a local folder ({why}); "
            "run it in a local workspace and copy the stores over with `mapkit copy-store` (docs/stores.md)"
        )


def current_folder() -> Path:
    """The current directory as the workspace when -w is not given, announced on stderr."""
    click.echo(f"workspace: {Path.cwd()} (the current directory; -w chooses another)", err=True)
    return Path(".")


def workspace_option(help: str, *, urls: bool = False,
                     local_reason: str = "it reads or writes files outside the zarr stores"
                     ) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``-w/--workspace``, by default the current directory (as git works in the one it is run in), so
    ``mapkit fuse flight.mcap`` then ``mapkit esdf --voxel 0.1`` work in sequence; the default is
    announced on stderr. With ``urls`` it may be an fsspec URL (docs/stores.md); otherwise a URL is
    refused in one line giving `local_reason`."""

    def resolve(ctx: click.Context, param: click.Parameter, value: Path | str | None) -> Path | str:
        if value is not None:
            if not urls:
                refuse_url(ctx, "-w/--workspace", value, local_reason)
            return value
        return current_folder()

    more = " A local folder or an fsspec URL (s3://, gs://, memory://)." if urls else ""
    return click.option("-w", "--workspace", type=STORE_PATH, default=None, callback=resolve,
                        help=f"{help}{more} Default: the current directory.")


PIPELINE_ORDER = ("info", "ingest", "fuse", "fuse-world", "esdf", "slice", "export", "batch", "simulate", "dataset",
                  "train", "eval", "plan", "fly", "replay", "view", "export-foxglove", "export-rerun", "copy-store", "config", "lab")
"""`mapkit --help` lists the commands along the pipeline (recordings → maps → training data → a
planner → its flights → looking at the results), not alphabetically; the tools come last."""


class OrderedGroup(click.Group):
    """A group whose commands are listed in ``order`` (any other after them, by name)."""

    order: tuple[str, ...] = ()

    def list_commands(self, ctx: click.Context) -> list[str]:
        names = super().list_commands(ctx)
        return [n for n in self.order if n in names] + [n for n in names if n not in self.order]


class _Group(OrderedGroup):
    """Usage errors (unknown option, bad value) as one line, like every other error: ``error:
    <command>: <what> (see mapkit <command> --help)``, exit 2. Commands in pipeline order."""

    order = PIPELINE_ORDER

    def main(self, *args: Any, **kwargs: Any) -> Any:
        kwargs["standalone_mode"] = False
        # Ctrl-C stops every command, also when the parent started it with SIGINT ignored (a background
        # job of a script, some test runners): Python keeps an inherited "ignore" otherwise.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            return super().main(*args, **kwargs)
        except click.UsageError as exc:
            where = exc.ctx.command_path if exc.ctx is not None else "mapkit"
            click.echo(f"error: {where}: {exc.format_message()} (see {where} --help)", err=True)
            sys.exit(exc.exit_code)
        except click.ClickException as exc:
            click.echo(f"error: {exc.format_message()}", err=True)
            sys.exit(exc.exit_code)
        except click.exceptions.Abort:
            click.echo("interrupted", err=True)
            sys.exit(130)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, "--version", prog_name="mapkit")
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug).")
def main(verbose: int) -> None:
    """mapkit: UAV depth + pose recordings → maps, training data and a learned planner.

    Every command that reads or writes a workspace takes -w/--workspace.
    """
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")



class _Lab(OrderedGroup):
    order = ("tune-timing", "tune-judge")


@main.group("lab", cls=_Lab)
def lab() -> None:
    """Research tools: the shipped recipe runs them for you (`mapkit train --recipe pretrained -o DIR`)."""
