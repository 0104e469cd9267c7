#!/usr/bin/env bash
# Runs every benchmark in benchmarks/ and prints measured figures and peer ratios.
set -euo pipefail
cd "$(dirname "$0")/.."
for b in benchmarks/bench_*.py; do
  echo "=== $b"
  .venv/bin/python "$b"
done
