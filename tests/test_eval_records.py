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
       "peak_acceleration": 3.1, "peak_jerk": 9.0, "climb": 0.1, "tracking_error_mean": 0.02, "tracking_error_max": 0.05,
       "reference_peak_speed": 1.4, "reference_peak_acceleration": 2.5, "stack": "full"}
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


def test_effort_at_time_is_the_snap_of_the_same_path_flown_in_another_time() -> None:
    import torch

    from mapkit.evaluation import effort_at_time
    from mapkit.trajopt import min_snap

    # Rest to rest, the minimum-snap path does not depend on the pace: 2× the durations is the same path
    # flown at half speed, and one segment over d in T costs 100800·d²/T⁷.
    wp = torch.tensor([[[0.0, 0.0, 1.0], [2.0, 1.0, 1.2], [3.0, 3.0, 1.0]]], dtype=torch.float64)
    T = torch.tensor([[1.3, 0.9]], dtype=torch.float64)
    fast, slow = (float(min_snap(wp, k * T).snap_cost()[0]) for k in (1.0, 2.0))
    assert effort_at_time(fast, 2.2, 4.4) == pytest.approx(slow, rel=1e-9)
    assert fast == pytest.approx(slow * 2 ** 7, rel=1e-9)
    assert effort_at_time(100800 * 4.0 / 3.0 ** 7, 3.0, 1.5) == pytest.approx(100800 * 4.0 / 1.5 ** 7)
    with pytest.raises(ValueError, match="> 0 s"):
        effort_at_time(1.0, 0.0, 2.0)


def test_compare_effort_counts_the_pairs_both_reached_at_equal_flight_time() -> None:
    from mapkit.evaluation import compare_effort

    def row(method: str, pair: int, effort: float, time_s: float, outcome: str = "success") -> EpisodeRecord:
        return EpisodeRecord.from_dict(ROW | {"method": method, "pair": pair, "control_effort": effort,
                                              "time_s": time_s, "outcome": outcome})

    rows = [row("oracle", 0, 100.0, 10.0), row("learned", 0, 100.0 * 2 ** 7, 5.0),  # same cost at equal time
            row("oracle", 1, 50.0, 8.0), row("learned", 1, 300.0, 8.0),  # 6× at equal time
            row("oracle", 2, 60.0, 8.0), row("learned", 2, 1.0, 8.0, "timeout"),  # not both reached
            row("learned", 3, 5.0, 8.0)]  # the oracle did not fly it
    c = compare_effort(rows, "learned", "oracle")
    assert c is not None and c.pairs == 2
    assert c.equal_time_ratio == pytest.approx(3.5)  # median of 1 and 6
    assert c.median_a == pytest.approx((12800 + 300) / 2) and c.median_b == pytest.approx(75.0)
    assert c.time_a == pytest.approx(6.5) and c.time_b == pytest.approx(9.0)
    assert compare_effort(rows, "learned", "straight") is None
    s = summarise(rows, ["office"], ["oracle"])["oracle"]["overall"]
    assert s["time_s"]["median"] == pytest.approx(8.0)  # over its three successful flights


def test_success_by_detour_bins_pairs_by_the_oracles_route() -> None:
    from mapkit.evaluation import OutcomeCounts, success_by_detour
    from mapkit.evaluation._report import _detour_table

    def row(method: str, pair: int, outcome: str, path_length: float = 10.0, world: str = "office") -> EpisodeRecord:
        return EpisodeRecord.from_dict(ROW | {"method": method, "pair": pair, "outcome": outcome, "distance": 10.0,
                                              "path_length": path_length, "world": world})

    rows = [row("oracle", 0, "success", 9.6), row("learned", 0, "success"),  # stopped 0.4 m short: ratio 0.96
            row("oracle", 1, "success", 10.5), row("learned", 1, "collision"),
            row("oracle", 2, "success", 12.0), row("learned", 2, "timeout"),  # 1.2: the 1.1–1.3 bin
            row("oracle", 3, "success", 25.0), row("learned", 3, "success"),  # 2.5: beyond the last edge
            row("oracle", 4, "timeout", 30.0), row("learned", 4, "timeout"),
            row("oracle", 0, "success", 13.0, "garage"),  # the same pair index in another world: its own pair
            row("learned", 9, "success")]  # a pair the oracle did not fly is left out
    bins = success_by_detour(rows)
    assert [(b.low, b.high, b.pairs) for b in bins] == [(0.0, 1.1, 2), (1.1, 1.3, 1), (1.3, 1.6, 1),
                                                        (2.0, float("inf"), 1), (None, None, 1)]
    assert bins[0].counts["learned"] == OutcomeCounts(success=1, collision=1)
    assert bins[1].counts["learned"] == OutcomeCounts(timeout=1)
    assert bins[2].counts == {"oracle": OutcomeCounts(success=1)}  # the garage pair, no learned flight there
    assert bins[4].counts["oracle"] == OutcomeCounts(timeout=1)
    assert success_by_detour(rows, reference="straight") == []
    table = _detour_table({"methods": ["learned", "oracle"]}, rows)
    assert "| < 1.1 | 2 | 50.0 (1 / 0) |" in table and "| 1.3–1.6 | 1 | – |" in table
    assert "| ≥ 2 | 1 | 100.0 (0 / 0) |" in table and "| oracle failed | 1 | 0.0 (0 / 1) |" in table
