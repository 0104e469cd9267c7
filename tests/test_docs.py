"""The README and docs/ link only inside the repository, and every link resolves."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The repository's own pages (not workspaces, caches or the venv a checkout may hold).
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "sample_data").glob("*.md"),
                *(ROOT / "mapkit").glob("**/*.md")])
# [text](target) and ![alt](target); the alt text may span lines.
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """The anchors a page's headings make (outside code fences)."""
    body = FENCE.sub("", page.read_text())
    return {slug(m.group(1)) for m in re.finditer(r"^#+\s+(.*)$", body, re.M)}


def links(page: Path) -> list[str]:
    """Every link target on a page (outside code fences)."""
    return LINK.findall(FENCE.sub("", page.read_text()))


def test_pages_found():
    names = {p.relative_to(ROOT).as_posix() for p in PAGES}
    assert {"README.md", "docs/README.md", "docs/evaluation.md"} <= names


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_links_stay_inside_and_resolve(page):
    for target in links(page):
        assert not re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I), f"{page.name}: external link {target}"
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        assert resolved.is_relative_to(ROOT), f"{page.name}: {target} leaves the repository"
        assert resolved.exists(), f"{page.name}: {target} does not exist"
        if anchor:
            assert resolved.suffix == ".md", f"{page.name}: anchor into a non-markdown file {target}"
            assert anchor in anchors(resolved), f"{page.name}: no heading for #{anchor} in {resolved.name}"


def test_no_paths_outside_the_repository():
    # CI has ../shared beside the clone, a user's checkout does not.
    for page in PAGES:
        assert "../shared" not in page.read_text(), f"{page.name} points outside the repository"


def test_package_docstring_lists_every_stage():
    import mapkit

    stages = sorted(d.name for d in (ROOT / "mapkit").iterdir() if (d / "__init__.py").exists())
    listed = set(re.findall(r"``mapkit\.(\w+)``", mapkit.__doc__ or ""))
    assert set(stages) <= listed, f"mapkit/__init__.py does not list {sorted(set(stages) - listed)}"
    assert {"cli", "viewer"} <= listed
