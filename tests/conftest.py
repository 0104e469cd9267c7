"""The test suite: `make test` runs all of it, about 4 min on 2 idle cores (3.5 min in a clean-clone
`.ci/run`, 2026-11-29; 8 min at a load of 3, 13–16 min while other suites shared the cores). `pytest -m "not slow"` skips the tests marked slow
(each over 5 s: end-to-end training, evaluation, datasets, kill -9, the pipelines on analytic
scenes, gradient checks, examples/) and takes about 1 min (2.5 min shared); mark a new test that
takes over 5 s `@pytest.mark.slow`."""

import sys
from pathlib import Path

# Test helpers (tests/recordings.py) import as plain modules.
sys.path.insert(0, str(Path(__file__).parent))
