#!/usr/bin/env bash
# Regenerate the sample recordings (run from the repository root). Deterministic: the same
# mapkit version gives the same files.
set -euo pipefail
cd "$(dirname "$0")/.."
MAPKIT=${MAPKIT:-.venv/bin/mapkit}
$MAPKIT simulate --world forest --seed 1 -o sample_data/forest --set width=160 --set height=120 --set rate=30 --duration 10 --set noise=none --overwrite
$MAPKIT simulate --world office --seed 1 -o sample_data/office --set width=160 --set height=120 --set rate=30 --duration 10 --set noise=realsense --overwrite
$MAPKIT simulate --world garage --seed 1 -o sample_data/garage --set width=160 --set height=120 --set rate=30 --duration 10 --set noise=none --overwrite
