#!/usr/bin/env bash
# Runs every benchmark in benchmarks/ and prints measured figures and peer ratios.
# Peers that must not enter the project's venv (qpth pins numpy<2) live in .venv-peers.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv-peers/bin/python ]; then
  bash benchmarks/setup_peers.sh || echo "bench: peer environment not built; peer columns will be missing" >&2
fi
for b in benchmarks/bench_*.py; do
  echo "=== $b"
  .venv/bin/python "$b"
done
