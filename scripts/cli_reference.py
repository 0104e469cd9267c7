"""Write docs/commands.md, the reference of every mapkit command, from the click definitions.

Usage: python scripts/cli_reference.py > docs/commands.md   (what `make docs` runs)

It walks the `mapkit` click group recursively and prints, for every command and subcommand, its usage
line, its help text and a table of its options (names, help, default). tests/test_docs_reference.py
fails when a command or an option is missing from docs/commands.md, so re-run this after changing a
command.
"""

from __future__ import annotations

import inspect
import sys
from collections.abc import Iterator

import click

from mapkit.cli.main import main as MAPKIT


def walk(command: click.Command, ctx: click.Context) -> Iterator[tuple[click.Command, click.Context]]:
    """`command` and every command below it, depth first, subcommands in name order."""
    yield command, ctx
    if isinstance(command, click.Group):
        for name in sorted(command.list_commands(ctx)):
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
    text = param.help or ""
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
    if isinstance(command, click.Group):
        subs = [n for n in sorted(command.list_commands(ctx)) if not getattr(command.get_command(ctx, n), "hidden", False)]
        lines += ["Commands: " + ", ".join(f"[`{n}`](#{anchor(f'{path} {n}')})" for n in subs) + ".", ""]
    return lines


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
        "Generated from the click definitions by `scripts/cli_reference.py` (`make docs`); do not edit by",
        "hand. Every command also takes `-h`/`--help`. The guides per stage say which options matter and why.",
        "",
    ]
    for command, ctx in walk(MAPKIT, root):
        out += section(command, ctx)
    return "\n".join(out).rstrip() + "\n"


if __name__ == "__main__":
    sys.stdout.write(reference())
