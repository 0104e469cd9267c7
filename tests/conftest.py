"""The test suite: `make test` runs all of it, about 8 min on 2 cores (7.9 min measured 2026-11-29;
13–16 min while other jobs shared the cores). `pytest -m "not slow"` skips the tests marked slow
(each over 5 s: end-to-end training, evaluation, datasets, kill -9, the pipelines on analytic
scenes, gradient checks, examples/) and takes about 1 min (2.5 min shared); mark a new test that
takes over 5 s `@pytest.mark.slow`."""

import sys
from pathlib import Path

# Test helpers (tests/recordings.py) import as plain modules.
sys.path.insert(0, str(Path(__file__).parent))
