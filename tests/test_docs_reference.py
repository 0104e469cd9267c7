"""docs/commands.md covers every mapkit command and option; README.md and docs/ link only to files that exist.

docs/commands.md is generated from the click definitions (`make docs`, scripts/cli_reference.py). When
a command or an option is added without re-running it, these tests name what is missing.
"""

import re
from pathlib import Path

import click
import pytest

from mapkit.cli.main import main as MAPKIT

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "docs" / "commands.md"
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")])
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def commands() -> list[tuple[str, click.Command]]:
    """(`mapkit ...` path, command) for the group and every command and subcommand below it."""
    found: list[tuple[str, click.Command]] = []

    def walk(command: click.Command, ctx: click.Context) -> None:
        found.append((ctx.command_path, command))
        if isinstance(command, click.Group):
            for name in command.list_commands(ctx):
                sub = command.get_command(ctx, name)
                if sub is not None and not sub.hidden:
                    walk(sub, click.Context(sub, info_name=name, parent=ctx))

    walk(MAPKIT, click.Context(MAPKIT, info_name="mapkit"))
    return found


def sections(text: str) -> dict[str, str]:
    """The reference's sections by command path: heading "## `mapkit eval`" → the text up to the next."""
    parts = re.split(r"^## `([^`]+)`\s*$", text, flags=re.M)
    return {parts[i]: parts[i + 1] for i in range(1, len(parts) - 1, 2)}


def long_names(command: click.Command) -> list[str]:
    """Every long option name of a visible option (`--corridor-check` and `--no-corridor-check`)."""
    names = []
    for p in command.params:
        if isinstance(p, click.Option) and not p.hidden:
            names += [n for n in [*p.opts, *p.secondary_opts] if n.startswith("--")]
    return names


def missing(text: str) -> list[str]:
    """What the reference `text` lacks: commands without a section, options absent from theirs."""
    found = sections(text)
    problems = []
    for path, command in commands():
        if path not in found:
            problems.append(f"no section for `{path}`")
            continue
        problems += [f"`{path}` lacks {name}" for name in long_names(command)
                     if not re.search(rf"[`/]{re.escape(name)}[`/]", found[path])]
    return problems


def test_the_walk_finds_every_command():
    paths = {path for path, _ in commands()}
    assert {"mapkit", "mapkit info", "mapkit fuse", "mapkit esdf", "mapkit export", "mapkit train",
            "mapkit eval", "mapkit view"} <= paths


def test_every_command_and_option_is_in_the_reference():
    problems = missing(REFERENCE.read_text())
    assert not problems, "docs/commands.md is out of date (run `make docs`): " + "; ".join(problems)


def test_the_check_fails_without_a_section_or_an_option():
    text = REFERENCE.read_text()
    without_eval = re.sub(r"^## `mapkit eval`$.*?(?=^## )", "", text, flags=re.S | re.M)
    assert "no section for `mapkit eval`" in missing(without_eval)
    without_voxel = sections(text)["mapkit esdf"].replace("`--voxel`", "`--vox`")
    assert "`mapkit esdf` lacks --voxel" in missing(text.replace(sections(text)["mapkit esdf"], without_voxel))


def links(page: Path) -> list[str]:
    return LINK.findall(FENCE.sub("", page.read_text()))


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_point_at_existing_files(page):
    for target in links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
            continue  # external links and anchors on the same page: tests/test_docs.py checks those
        path = target.partition("#")[0]
        assert (page.parent / path).exists(), f"{page.relative_to(ROOT)}: {target} does not exist"
