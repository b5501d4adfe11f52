#!/bin/sh
# Lay out build/typecheck/scopetwin as the installed package (scopetwin/ with its own subpackage cli/, plus the five
# layer folders as its subpackages), as links to the sources, so that mypy names every module scopetwin.* as an
# import does.
set -eu
cd "$(dirname "$0")/.."
tree=build/typecheck/scopetwin
rm -rf build/typecheck
mkdir -p "$tree"
for f in scopetwin/*.py; do ln -s "../../../$f" "$tree/"; done
for f in scopetwin/*/__init__.py; do ln -s "../../../${f%/__init__.py}" "$tree/"; done
for d in scenes sim recon calib instrument; do ln -s "../../../$d" "$tree/$d"; done
