"""`mapkit info`: what a recording holds and which topics ingestion would use, and why."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from mapkit.ingest._errors import IngestError
from mapkit.ingest._reader import IngestConfig, SourcePlan, plan_source
from mapkit.ingest._sources import BagSummary, Source


@dataclass
class RecordingInfo:
    """Summary of one recording plus the ingestion plan (or the reason there is none)."""

    summary: BagSummary
    plan: SourcePlan | None
    problem: str | None


def inspect_recordings(paths: Sequence[str | Path], config: IngestConfig | None = None) -> list[RecordingInfo]:
    """Summaries and role choices for each recording; a role without a candidate is a `problem`.

    Unreadable inputs raise IngestError; a readable recording with no usable depth / camera info /
    pose is reported in `problem` so every input gets listed.
    """
    config = config or IngestConfig()
    config.validate()
    if not paths:
        raise IngestError("no input recordings given")
    out = []
    for path in paths:
        with Source(path) as source:
            try:
                plan = plan_source(source, config)
                out.append(RecordingInfo(source.summary, plan, None))
            except IngestError as exc:
                out.append(RecordingInfo(source.summary, None, str(exc)))
    return out
