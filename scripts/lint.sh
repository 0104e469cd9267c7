#!/usr/bin/env bash
# `make lint`: ruff, then mypy (settings in pyproject.toml); both run, and any finding fails it.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
VENV=${VENV:-.venv}
case $VENV in /*) ;; *) VENV=$root/$VENV ;; esac

status=0
"$VENV/bin/ruff" check . || status=1

# cli/ and viewer/ install as mapkit.cli and mapkit.viewer (pyproject's package-dir), a mapping mypy
# cannot read; it checks a tree of links laid out as the installed package, and the paths it prints
# are mapped back to the files in this repository.
tree=build/typecheck
rm -rf "$tree"
mkdir -p "$tree/mapkit"
for entry in mapkit/*; do ln -s "$root/$entry" "$tree/mapkit/"; done
ln -s "$root/cli" "$tree/mapkit/cli"
ln -s "$root/viewer" "$tree/mapkit/viewer"
cd "$tree"
"$VENV/bin/mypy" --config-file "$root/pyproject.toml" --cache-dir "$root/build/mypy_cache" -p mapkit \
  | sed -e 's#^mapkit/cli/#cli/#' -e 's#^mapkit/viewer/#viewer/#' || status=1
exit $status
