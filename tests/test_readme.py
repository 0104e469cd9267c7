"""The README as a newcomer reads it: it opens with its title and the two commands, stays short, and
its Library snippet runs as pasted (from the repository's root: here a folder holding sample_data/)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def section(title: str) -> str:
    """The body of the README's ``## title`` section."""
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", README, re.S | re.M)
    assert match, f"README has no section {title!r}"
    return match.group(1)


def test_the_readme_opens_with_its_title_then_the_demo_and_test_commands():
    lines = README.splitlines()
    assert lines[0].startswith("# ")
    head = "\n".join(lines[:8])
    assert "make demo" in head and "make test" in head


def test_the_readme_and_its_planner_section_stay_short():
    assert len(README.splitlines()) <= 150
    assert len(section("How good is the planner").strip().splitlines()) <= 15


@pytest.mark.slow
def test_the_library_snippet_runs_as_pasted(tmp_path: Path):
    code = re.search(r"```python\n(.*?)```", section("Library"), re.S)
    assert code, "the Library section has no python block"
    (tmp_path / "sample_data").symlink_to(ROOT / "sample_data")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    run = subprocess.run([sys.executable, "-c", code.group(1)], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert re.search(r"^(cruising|braking|blocked|reached) ", run.stdout, re.M)
    assert (tmp_path / "ws" / "map.zarr").is_dir()
