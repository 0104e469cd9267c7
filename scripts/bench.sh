#!/usr/bin/env bash
# Runs every benchmark in benchmarks/ and prints measured figures and peer ratios.
# Peers that must not enter the project's venv (qpth pins numpy<2) live in .venv-peers; without it
# the benchmarks still run and print their own figures (bench_trajopt notes the missing peers).
# A benchmark that fails does not stop the others: the failures are listed at the end (exit 1).
# Their smoke runs at tiny sizes are tests/test_benchmarks.py.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
if [ ! -x .venv-peers/bin/python ]; then
  bash benchmarks/setup_peers.sh || echo "bench: peer environment not built; peer columns will be missing" >&2
fi
failed=()
for b in benchmarks/bench_*.py; do
  echo "=== $b"
  "$VENV/bin/python" "$b" || failed+=("$b")
done
if [ ${#failed[@]} -gt 0 ]; then
  echo "bench: ${#failed[@]} benchmark(s) failed: ${failed[*]}" >&2
  exit 1
fi
