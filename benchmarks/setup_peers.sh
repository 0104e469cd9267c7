#!/usr/bin/env bash
# Build .venv-peers: a separate environment holding the peer libraries that
# benchmarks/bench_trajopt.py compares mapkit.trajopt against (qpth, cvxpylayers).
# qpth pins numpy<2, so it must never be installed into the project's own .venv.
#
# Usage: bash benchmarks/setup_peers.sh [PYTHON]     (default python: python3)
# Re-running is safe; it reuses an existing .venv-peers.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${1:-python3}"
VENV=.venv-peers
TORCH_SPEC="torch==2.13.0"
# Prefer the local CPU wheel (a plain PyPI pin would pull the CUDA build).
for w in /opt/wheels/torch-2.13.0*cpu*.whl; do
  if [ -f "$w" ]; then TORCH_SPEC="$w"; fi
done
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
"$VENV/bin/python" -m pip install -q "$TORCH_SPEC" "numpy<2" "scipy"
"$VENV/bin/python" -m pip install -q "$TORCH_SPEC" "numpy<2" qpth
# cvxpylayers is optional: the bench reports it as missing when this fails.
if ! "$VENV/bin/python" -m pip install -q "$TORCH_SPEC" "numpy<2" cvxpylayers; then
  echo "setup_peers: cvxpylayers did not install; the bench will skip it" >&2
fi
"$VENV/bin/python" - <<'PY'
import numpy, torch
print("peers venv ready: numpy", numpy.__version__, "torch", torch.__version__)
try:
    import qpth; print("qpth", getattr(qpth, "__version__", "ok"))
except Exception as e:  # noqa: BLE001
    print("qpth missing:", e)
try:
    import cvxpylayers; print("cvxpylayers", getattr(cvxpylayers, "__version__", "ok"))
except Exception as e:  # noqa: BLE001
    print("cvxpylayers missing:", e)
PY
