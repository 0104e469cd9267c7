"""Write docs/commands.md, the reference of every mapkit command, from the click definitions.

Usage: python scripts/cli_reference.py > docs/commands.md   (what `make docs` runs)

It walks the `mapkit` click group recursively (commands in the order `mapkit --help` lists them) and
prints, for every command and subcommand, its usage line, its help text, a table of its options (names,
help, default) and, for a command backed by config dataclasses, a table of its settings (key, default,
the field's docstring: what `mapkit config COMMAND` prints as TOML). tests/test_docs_reference.py
fails when a command or an option is missing from docs/commands.md, so re-run this after changing a
command.
"""

from __future__ import annotations

import inspect
import re
import sys
from collections.abc import Iterator

import click

from mapkit.cli._config import SPECS, ConfigSpec, FieldOption, plain, to_toml
from mapkit.cli.main import main as MAPKIT

INTRO = """\
Generated from the click definitions by `scripts/cli_reference.py` (`make docs`); do not edit by
hand. Every command also takes `-h`/`--help`. The guides per stage say which options matter and why.

## Options and settings

A command's options are what a run needs every time: its inputs and outputs (`-w`, `-o`, `--model`),
what to run (`--world`, `--pairs`, `--seed`, `--methods`, ...), how to run it (`--workers`,
`--scheduler`) and `--overwrite` / `--resume`. Everything else is a **setting**: a field of the
command's typed config dataclasses (`EvalConfig` with its `LoopConfig`, `PilotConfig`, `Execution`,
...; `TrainConfig` with `planner` and `loss`; `FuseConfig`, `EsdfConfig`, `ExportConfig`, ...), each
with one default, in the dataclass, and its docstring as help. Options that fill a field have no default
of their own either: `--help` shows the dataclass's.

- `mapkit config COMMAND` prints every setting of COMMAND as TOML, each at its default with its
  docstring as a comment (`mapkit config eval > eval.toml`); the tables below list the same.
- `--config FILE.toml` reads settings from such a file; keys may be left out (they keep their default).
- `--set KEY=VALUE` (repeatable) sets one. A key is a field's name; a nested dataclass is a table,
  its fields dotted keys: `--set loop.pilot.replan_interval=0.5`, `--set execution.corridor.width=0.75`,
  `--set planner.accel=1.5`. VALUE is a TOML value (`0.5`, `true`, `[256, 256, 256]`, `"text"`); a
  bare word is text (`--set vehicle=rotorpy`) and a comma list fills a list (`--set goal_mix=0.2,0.4,0.4`).
  TOML has no null: `"none"` (or `none`) stands for None, e.g. `--set execution.memory=none` turns the
  memory layer off, `--set execution.speed.cruise=none` uses the model's own speed.
- Precedence, lowest first: the dataclass defaults (`train`: its `--preset`), `--config`, the command's
  options (`--pairs 20`), `--set`. So `--config eval.toml --pairs 20 --set pairs=5` flies 5 pairs.
- Every command that reads recordings (`info`, `ingest`, `fuse`, `batch`) has the ingest settings as
  the table `ingest` (`--set ingest.stride=2`), so one file serves them all; `batch` has a table per step
  (`fuse`, `esdf`, `export`).
- Errors are usage errors (exit 2, one line, before any work): an unknown key names the closest keys and
  `mapkit config COMMAND`; a value of the wrong type names the key, what it takes and an example; a value
  the dataclass's `validate()` refuses is named by the dataclass's own message.
- Fields only the shipped recipe uses are no settings (`EvalConfig.record_plans`, `record_judge`,
  `judge_history`, `execution.flown_judge`; tune-timing's `objective`,
  `boundary_scale`, `first_weight`): the recipe (`mapkit train --recipe pretrained`) and the library set
  them. The research tools themselves are under `mapkit lab`.
"""


def walk(command: click.Command, ctx: click.Context) -> Iterator[tuple[click.Command, click.Context]]:
    """`command` and every command below it, depth first, subcommands in the group's order."""
    yield command, ctx
    if isinstance(command, click.Group):
        for name in command.list_commands(ctx):
            sub = command.get_command(ctx, name)
            if sub is None or getattr(sub, "hidden", False):
                continue
            yield from walk(sub, click.Context(sub, info_name=name, parent=ctx))


def escape(text: str) -> str:
    """Help text as markdown shows it literally: no HTML tags (`<name>`), no emphasis (`*.mcap`)."""
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace("*", "\\*")


def cell(text: object) -> str:
    """One markdown table cell: a single line, pipes escaped."""
    return escape(" ".join(str(text).split())).replace("|", "\\|")


def option_names(param: click.Option) -> str:
    names = list(param.opts)
    if param.secondary_opts and len(param.opts) == len(param.secondary_opts):
        names = [f"{a}/{b}" for a, b in zip(param.opts, param.secondary_opts, strict=True)]
    elif param.secondary_opts:
        names += param.secondary_opts
    return ", ".join(f"`{n}`" for n in names)


def unset(value: object) -> bool:
    """True for "no default": None, empty, or click's internal UNSET sentinel (click >= 8.3)."""
    return value is None or value == () or value == [] or type(value).__name__ == "Sentinel"


def default_text(param: click.Option, ctx: click.Context) -> str:
    if isinstance(param, FieldOption):  # the dataclass's default
        return param.default_text()
    if isinstance(param.show_default, str):
        return param.show_default
    if param.required:
        return "required"
    if callable(param.default) and not unset(param.default):
        return "(computed)"
    default = param.get_default(ctx, call=False)
    if param.is_flag and not param.secondary_opts:
        return "on" if default is True else "off"
    if param.is_flag:
        return param.opts[0] if default else param.secondary_opts[0]
    if unset(default):
        return ""
    if isinstance(default, (tuple, list)):
        return " ".join(str(d) for d in default)
    return str(default)


def help_text(param: click.Option) -> str:
    text = param.help or (plain(param.spec.doc(param.key)).split("\n")[0] if isinstance(param, FieldOption) else "")
    if isinstance(param.type, click.Choice):
        text = f"{text} One of: {', '.join(map(str, param.type.choices))}.".strip()
    if param.multiple:
        text = f"{text} May be given more than once.".strip()
    return text


def metavar(param: click.Parameter, ctx: click.Context) -> str:
    """`param`'s metavar (click >= 8.2 wants the context, older versions do not take it)."""
    try:
        return param.make_metavar(ctx)  # type: ignore[call-arg]
    except TypeError:
        return param.make_metavar()  # type: ignore[call-arg]


def section(command: click.Command, ctx: click.Context) -> list[str]:
    path = ctx.command_path
    lines = [f"## `{path}`", ""]
    usage = " ".join(command.collect_usage_pieces(ctx))
    lines += ["```", f"{path} {usage}".rstrip(), "```", ""]
    doc = inspect.cleandoc(command.help or "").replace("\b\n", "")
    if doc:
        lines += [escape(doc), ""]
    arguments = [p for p in command.params if isinstance(p, click.Argument)]
    if arguments:
        lines += ["Arguments: " + ", ".join(
            f"`{metavar(a, ctx)}`" + ("" if a.required else " (optional)") for a in arguments) + ".", ""]
    options = [p for p in command.params if isinstance(p, click.Option) and not p.hidden]
    if options:
        lines += ["| option | help | default |", "|---|---|---|"]
        for p in options:
            lines.append(f"| {option_names(p)} | {cell(help_text(p))} | {cell(default_text(p, ctx))} |")
        lines.append("")
    spec = SPECS.get(path.removeprefix("mapkit "))
    if spec is not None:
        lines += settings(spec)
    if isinstance(command, click.Group):
        subs = [n for n in command.list_commands(ctx) if not getattr(command.get_command(ctx, n), "hidden", False)]
        lines += ["Commands: " + ", ".join(f"[`{n}`](#{anchor(f'{path} {n}')})" for n in subs) + ".", ""]
    return lines


def first_sentence(text: str) -> str:
    """Up to the first full stop that ends a sentence (the docstrings' first lines say what a field is)."""
    match = re.search(r"[.!?](?=\s+[A-Z(`])", text)
    return text[: match.end()] if match else text.split("\n")[0]


def settings(spec: ConfigSpec) -> list[str]:
    """The table of a command's settings: key, default (as TOML), the first paragraph of its docstring."""
    lines = [f"Settings (`--set KEY=VALUE`, `--config FILE.toml`; as TOML: `mapkit config {spec.command}`)"
             + (f". {spec.note}" if spec.note else "") + ":", "", "| setting | default | what |", "|---|---|---|"]
    for key, entry in spec.entries.items():
        if entry.table is not None:
            value = spec.default(key)
            if value is not None:
                continue  # a table: its keys follow
        shown = spec.default(key)
        codec = spec.codecs.get(key)
        shown = codec.show(shown) if codec is not None and shown is not None else shown
        lines.append(f"| `{key}` | `{cell(to_toml(shown))}` | {cell(first_sentence(plain(entry.doc)))} |")
    return [*lines, ""]


def anchor(title: str) -> str:
    """The anchor GitHub gives a heading `title` (in backticks)."""
    return "".join(c for c in title.lower().replace(" ", "-") if c.isalnum() or c in "-_")


def reference() -> str:
    root = click.Context(MAPKIT, info_name="mapkit")
    out = [
        "# Command reference",
        "",
        "Part of mapkit's documentation: [README](../README.md) · [all pages](README.md).",
        "",
        INTRO,
    ]
    for command, ctx in walk(MAPKIT, root):
        out += section(command, ctx)
    return "\n".join(out).rstrip() + "\n"


if __name__ == "__main__":
    sys.stdout.write(reference())
