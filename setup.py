"""Package layout: the five layer folders at the repository root install as subpackages of ``scopetwin``.

The folders ``scenes/``, ``sim/``, ``recon/``, ``calib/`` and ``instrument/`` stay where they are (the project's
layout); the wheel holds one top-level package, ``scopetwin``, with ``scopetwin.scenes`` ... ``scopetwin.instrument``
mapped onto them. Everything else is declared in ``pyproject.toml``.
"""

from setuptools import find_packages, setup

LAYERS = ("scenes", "sim", "recon", "calib", "instrument")

package_dir = {"scopetwin": "scopetwin"}
packages = ["scopetwin"]
for layer in LAYERS:
    package_dir[f"scopetwin.{layer}"] = layer
    packages += [f"scopetwin.{layer}", *(f"scopetwin.{layer}.{sub}" for sub in find_packages(layer))]

setup(packages=packages, package_dir=package_dir)
