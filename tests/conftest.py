"""The test suite: `make test` runs all of it, about 4 min on 2 idle cores (3.5 min in a clean-clone
`.ci/run`, 2026-11-29; 8 min at a load of 3, 13–16 min while other suites shared the cores). `pytest -m "not slow"` skips the tests marked slow
(each over 5 s: end-to-end training, evaluation, datasets, kill -9, the pipelines on analytic
scenes, gradient checks, examples/) and takes about 1 min (2.5 min shared); mark a new test that
takes over 5 s `@pytest.mark.slow`."""

import sys
from pathlib import Path

import pytest

# Test helpers (tests/recordings.py) import as plain modules.
sys.path.insert(0, str(Path(__file__).parent))

# The slowest tests (seconds on 2 shared cores), run first so that none starts late and holds up the
# end of a parallel run; a test not named here keeps its place.
SLOW_FIRST = (
    "test_recipe.py::test_the_miniature_of_the_shipped_recipe_runs_resumes_and_flies",
    "test_fly.py::test_software_in_the_loop_in_a_fresh_interpreter",
    "test_benchmarks.py::test_benchmark_runs_at_tiny_sizes[bench_fly.py]",
    "test_cli_errors.py::test_kill_9_at_any_point_leaves_every_store_readable",
    "test_readme.py::test_the_library_snippet_runs_as_pasted",
    "test_eval_dask.py::test_pairs_on_a_dask_cluster_give_the_same_results_json_as_workers_even_when_one_dies",
    "test_judge_tune.py::test_record_judge_then_tune_judge_through_the_cli",
    "test_eval_ablation.py::test_an_ablation_run_records_the_stack_of_every_episode_and_reports_the_differences",
    "test_benchmarks.py::test_benchmark_runs_at_tiny_sizes[bench_eval_dask.py]",
    "test_benchmarks.py::test_benchmark_runs_at_tiny_sizes[bench_train.py]",
    "test_benchmarks.py::test_benchmark_runs_at_tiny_sizes[bench_pilot.py]",
    "test_eval_dask.py::test_cli_scheduler_local_starts_a_cluster_and_writes_the_same_results",
    "test_planner.py::test_winner_takes_all_keeps_the_detour_that_wins",
    "test_judge_tune.py::test_fitting_the_head_learns_what_the_image_shows_on_unseen_candidates",
    "test_timing_tune.py::test_imitation_fits_the_gradient_descent_split_on_unseen_plans",
    "test_train.py::test_held_out_worlds_validate_and_select_the_model",
    "test_eval.py::test_same_seed_gives_identical_results_json",
)


def _slow_rank(item: pytest.Item) -> int:
    name = item.nodeid.removeprefix("tests/")
    return SLOW_FIRST.index(name) if name in SLOW_FIRST else len(SLOW_FIRST)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=_slow_rank)  # stable: the rest keep pytest's order


def pytest_configure(config: pytest.Config) -> None:
    # pytest-xdist hands tests out in chunks by default: a long test could wait behind a worker's queue
    # while the other worker runs dry. Two at a time keeps the slow ones first and the workers even.
    if getattr(config.option, "numprocesses", None) and getattr(config.option, "maxschedchunk", 0) is None:
        config.option.maxschedchunk = 2


@pytest.fixture(autouse=True)
def _dask_scheduler_restored():
    """Each test starts with the process's Dask scheduler setting as it was: a distributed Client that a
    test leaves as the default (killed workers, a cluster torn down mid-test) would otherwise send a
    later test's plain `.compute()` to a client that no longer exists."""
    import dask

    before = dask.config.get("scheduler", None)
    yield
    if dask.config.get("scheduler", None) != before:
        if before is None:
            dask.config.config.pop("scheduler", None)
        else:
            dask.config.set(scheduler=before)
