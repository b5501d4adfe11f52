"""Package layout: the five layer folders at the repository root install as subpackages of ``scopetwin``.

The folders ``scenes/``, ``sim/``, ``recon/``, ``calib/`` and ``instrument/`` stay where they are (the project's
layout); the wheel holds one top-level package, ``scopetwin``, with ``scopetwin.scenes`` ... ``scopetwin.instrument``
mapped onto them beside its own subpackage, the command line ``scopetwin.cli``. The folders ``rigs/`` (the rig TOMLs
and their Micro-Manager ``.cfg``) and ``examples/`` (dataset configs, an MDA sequence) travel with it as package
data, ``scopetwin/rigs/`` and ``scopetwin/examples/`` (:mod:`scopetwin.shipped` finds them), so that the documented
commands work from an installed wheel too. Everything else is declared in ``pyproject.toml``.
"""

from pathlib import Path

from setuptools import find_packages, setup

LAYERS = ("scenes", "sim", "recon", "calib", "instrument")
#: Data folders at the repository root shipped as package data (no Python in them): scopetwin.<folder>
SHIPPED = ("rigs", "examples")

package_dir = {"scopetwin": "scopetwin"}
packages = ["scopetwin", *(f"scopetwin.{sub}" for sub in find_packages("scopetwin"))]  # and scopetwin.cli
for layer in LAYERS:
    package_dir[f"scopetwin.{layer}"] = layer
    packages += [f"scopetwin.{layer}", *(f"scopetwin.{layer}.{sub}" for sub in find_packages(layer))]

for folder in SHIPPED:  # each folder and its subfolders (examples/datasets, examples/mda) a package of data
    package_dir[f"scopetwin.{folder}"] = folder
    packages.append(f"scopetwin.{folder}")
    packages += [f"scopetwin.{folder}.{sub.name}" for sub in sorted(Path(folder).iterdir()) if sub.is_dir()]

setup(packages=packages, package_dir=package_dir)
