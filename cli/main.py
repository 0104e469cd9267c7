"""The ``mapkit`` entry point: the command group of :mod:`mapkit.cli._group` with every command registered.

The group, the error boundary (:func:`library_call`) and the option types live in :mod:`mapkit.cli._group`,
which the command modules import; this module imports the command modules (each registers its commands on
`main` when imported) and re-exports the group's names for callers (`mapkit.cli.main:main` is the script).
"""

from mapkit.cli._group import (
    COUNT,
    FINITE,
    FRACTION,
    INDEX,
    NONNEGATIVE,
    POSITIVE,
    STORE_PATH,
    WIDTHS,
    Number,
    StorePath,
    Widths,
    library_call,
    main,
    refuse_url,
    workspace_option,
)

# isort: split
# Bound above first: a command module may import these names from here while this module is importing it.
from mapkit.cli import batch as _batch  # noqa: F401 - registers its commands on main
from mapkit.cli import config as _config  # noqa: F401 - registers its commands on main
from mapkit.cli import dataset as _dataset  # noqa: F401 - registers its commands on main
from mapkit.cli import eval as _eval  # noqa: F401 - registers its commands on main
from mapkit.cli import exchange as _exchange  # noqa: F401 - registers its commands on main
from mapkit.cli import export as _export  # noqa: F401 - registers its commands on main
from mapkit.cli import fly as _fly  # noqa: F401 - registers its commands on main
from mapkit.cli import ingest as _ingest  # noqa: F401 - registers its commands on main
from mapkit.cli import mapping as _mapping  # noqa: F401 - registers its commands on main
from mapkit.cli import plan as _plan  # noqa: F401 - registers its commands on main
from mapkit.cli import simulate as _simulate  # noqa: F401 - registers its commands on main
from mapkit.cli import stores as _stores  # noqa: F401 - registers its commands on main
from mapkit.cli import train as _train  # noqa: F401 - registers its commands on main
from mapkit.cli import view as _view  # noqa: F401 - registers its commands on main

__all__ = [
    "COUNT",
    "FINITE",
    "FRACTION",
    "INDEX",
    "NONNEGATIVE",
    "POSITIVE",
    "STORE_PATH",
    "WIDTHS",
    "Number",
    "StorePath",
    "Widths",
    "library_call",
    "main",
    "refuse_url",
    "workspace_option",
]
