"""Names shared by the writer and the readers of mapkit's result files, in one light module (no
torch, no open3d) so the evaluation runner, ``mapkit.viz`` and the viewer agree without importing
each other."""

from __future__ import annotations

from typing import Literal, get_args

EVAL_FORMAT = "mapkit-eval/1"
"""``format`` of a `mapkit eval` folder's results.json and latency.json."""

Outcome = Literal["success", "collision", "timeout"]
"""How a closed-loop flight ended."""
OUTCOMES: tuple[Outcome, ...] = get_args(Outcome)
