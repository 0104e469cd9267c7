"""The examples in the library's docstrings run and print what they show.

Only modules under mapkit/ whose source holds a ``>>>`` are imported, so collecting these tests
costs nothing for the rest; the viewer's examples need a browser and are all marked ``+SKIP``.
"""

import doctest
import importlib
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mapkit"
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def modules_with_examples() -> list[str]:
    """Dotted names of the modules under mapkit/ whose source contains a doctest prompt."""
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if ">>>" in path.read_text(encoding="utf-8"):
            parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
            names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


MODULES = modules_with_examples()


def test_some_modules_have_examples():
    assert {"mapkit.esdf", "mapkit.trajopt"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name, capsys):
    module = importlib.import_module(name)
    failed, attempted = doctest.testmod(module, optionflags=FLAGS)
    report = capsys.readouterr().out
    assert failed == 0, f"{failed} of {attempted} examples in {name} failed:\n{report}"
