#!/bin/sh
# Lay out build/typecheck/scopetwin as the installed package (scopetwin/ plus the five layer folders as its
# subpackages), as links to the sources, so that mypy names every module scopetwin.* as an import does.
set -eu
cd "$(dirname "$0")/.."
tree=build/typecheck/scopetwin
rm -rf build/typecheck
mkdir -p "$tree"
for f in scopetwin/*.py; do ln -s "../../../$f" "$tree/"; done
for d in scenes sim recon calib instrument; do ln -s "../../../$d" "$tree/$d"; done
