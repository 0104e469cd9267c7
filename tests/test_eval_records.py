"""results.json rows as typed records: the runner's key order, reading back, and mapkit.viz's records."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapkit.evaluation import EVAL_FORMAT, OUTCOMES, EpisodeRecord, summarise

ROW = {"world": "office", "pair": 3, "method": "learned", "outcome": "success", "start": [0.0, 1.0, 1.2],
       "goal": [9.0, -2.0, 1.5], "distance": 9.5, "line_of_sight": False, "time_s": 6.2, "path_length": 10.1,
       "path_length_ratio": 10.1 / 9.5, "control_effort": 120.5, "min_distance": None, "collision_point": None,
       "collision_time": None, "plans": 13, "rejected_plans": 1, "plan_effort": 30.25, "peak_speed": 2.4,
       "peak_acceleration": 3.1, "peak_jerk": 9.0}
"""A row as `mapkit eval` writes it (every key, in the file's order)."""


def test_a_row_round_trips_with_its_key_order() -> None:
    record = EpisodeRecord.from_dict(ROW)
    assert record.outcome in OUTCOMES and record.pair == 3 and record.collision_point is None
    assert json.dumps(record.to_dict()) == json.dumps(ROW)  # same keys, same order: results.json unchanged


def test_a_partial_row_reads_with_none_and_a_row_without_identity_does_not() -> None:
    record = EpisodeRecord.from_dict({k: ROW[k] for k in ("world", "pair", "method", "outcome", "start", "goal")}
                                     | {"from_a_newer_version": 1})
    assert record.time_s is None and record.peak_speed is None
    with pytest.raises(KeyError, match="outcome"):
        EpisodeRecord.from_dict({k: ROW[k] for k in ("world", "pair", "method", "start", "goal")})


def test_summarise_reads_records_and_skips_fields_older_files_lack() -> None:
    old = EpisodeRecord.from_dict({k: v for k, v in ROW.items() if not k.startswith("peak_") and k != "plan_effort"})
    crash = EpisodeRecord.from_dict(ROW | {"outcome": "collision", "pair": 4, "min_distance": 0.1})
    s = summarise([EpisodeRecord.from_dict(ROW), old, crash], ["office"], ["learned"])["learned"]["overall"]
    assert s["episodes"] == 3 and s["success_rate"] == pytest.approx(2 / 3)
    assert s["collision_rate"] == pytest.approx(1 / 3) and s["timeout_rate"] == 0
    assert s["peak_speed"]["mean"] == pytest.approx(2.4) and s["plan_effort"]["median"] == pytest.approx(30.25)
    assert s["control_effort"]["mean"] == pytest.approx(120.5) and s["min_distance"]["min"] == pytest.approx(0.1)
    assert s["rejected_plan_rate"] == pytest.approx(3 / 39)


def test_viz_gives_the_rows_as_records(tmp_path: Path) -> None:
    from mapkit.viz import load_eval

    (tmp_path / "worlds").mkdir()
    (tmp_path / "results.json").write_text(json.dumps({
        "format": EVAL_FORMAT, "worlds": {"office": {"seed": 0, "world_json": "worlds/office.world.json"}},
        "methods": ["learned"], "episodes": [ROW, ROW | {"pair": 4, "outcome": "timeout"}]}))
    ev = load_eval(tmp_path)
    assert [r.to_dict() for r in ev.episodes] == json.loads((tmp_path / "results.json").read_text())["episodes"]
    assert [r.outcome for r in ev.episodes_of("office", 4)] == ["timeout"] and len(ev.episodes_of("office")) == 2
    ev.close()
