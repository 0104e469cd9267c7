#!/usr/bin/env bash
# The pipeline on sample_data/, as a user runs it. Later stages append their commands here.
set -euo pipefail
cd "$(dirname "$0")/.."
WS=${1:-demo_ws}
MAPKIT=.venv/bin/mapkit
shopt -s nullglob
flights=(sample_data/*.mcap)
if [ ${#flights[@]} -eq 0 ]; then
  echo "demo: sample_data/ has no flights; regenerate them with sample_data/regenerate.sh" >&2
  exit 1
fi
for flight in "${flights[@]}"; do
  name=$(basename "$flight" .mcap)
  echo "== mapkit info $flight"
  $MAPKIT info "$flight"
  echo "== mapkit ingest $flight -w $WS/$name"
  $MAPKIT ingest "$flight" -w "$WS/$name" --overwrite
  echo "== mapkit fuse $flight -w $WS/$name   (reuses the up-to-date frames.zarr)"
  $MAPKIT fuse "$flight" -w "$WS/$name" --voxel 0.05 --mesh --overwrite
  echo "== mapkit esdf -w $WS/$name --voxel 0.1"
  $MAPKIT esdf -w "$WS/$name" --voxel 0.1 --overwrite
  echo "== mapkit slice -w $WS/$name --z 0.5 1.0 1.5"
  $MAPKIT slice -w "$WS/$name" --z 0.5 1.0 1.5 -o "$WS/$name/slices.png"
  echo "== mapkit export -w $WS/$name"
  $MAPKIT export -w "$WS/$name" --overwrite
done
echo "== mapkit train (cpu preset, a few steps on the sample flights; the shipped planner trains on mapkit dataset worlds: mapkit/flight/pretrained/REPRODUCE.md)"
$MAPKIT train -w "$WS/forest" -w "$WS/garage" -w "$WS/office" --preset cpu --name demo --set max_steps=40 --overwrite
echo "== mapkit eval of the planner shipped with mapkit (closed loop in unseen worlds; the paper's protocol is --world all --pairs 60)"
$MAPKIT eval --model pretrained --world all --pairs 2 --seed 0 \
  --methods learned,untrained,straight-keypoints,iplanner-style,straight,oracle --stack full,none -o "$WS/eval" --overwrite
echo "== mapkit export-foxglove -w $WS/forest -o $WS/forest.mcap (open it in Foxglove: flight, cloud, ESDF, plans, eval paths)"
$MAPKIT export-foxglove -w "$WS/forest" -o "$WS/forest.mcap" --model pretrained --eval "$WS/eval" --overwrite
echo "== mapkit export-rerun -w $WS/forest -o $WS/forest.rrd (the same for Rerun)"
$MAPKIT export-rerun -w "$WS/forest" -o "$WS/forest.rrd" --model pretrained --eval "$WS/eval" --overwrite
echo "demo: workspaces in $WS/ (frames.zarr, cloud.ply, mesh.ply, map.zarr, slices.png, tuples.zarr, runs/demo), eval report of the shipped planner in $WS/eval/report.md, $WS/forest.mcap for Foxglove and $WS/forest.rrd for Rerun"
echo "demo: look at it in the browser (point cloud, ESDF slices, the flight, live plans, corridors, eval paths):"
echo "  $MAPKIT view -w $WS/forest --model pretrained --eval $WS/eval"
