"""sim: synthetic truth — surfaces, measurement simulation, datasets and studies.

By job, each layer using only the public API of the ones before it:

* :mod:`scopetwin.sim.surfaces` (§1.9 height maps), :mod:`scopetwin.sim.truth` (exact marker images),
  :mod:`scopetwin.sim.scan_time`
  (the scan-time models of §7.2-7.4, §8.2.2);
* :mod:`scopetwin.sim.measurement` — render and write one measurement (image, truth, preview, provenance) and
  :class:`~scopetwin.sim.measurement.StagedOutput`, the one stage-then-rename helper for output folders;
* :mod:`scopetwin.sim.datasets` — synthetic datasets (config, seeding, one module per sample kind, the store, the
  runner);
* :mod:`scopetwin.sim.studies` — accuracy studies against rendered truth (tables, tasks, one module per study, the
  runner);
* :mod:`scopetwin.sim.pipeline` (the end-to-end ``scopetwin run``), :mod:`scopetwin.sim.cmu_unit` (the four-channel
  unit's analyses),
  :mod:`scopetwin.sim.figures` (marker overlays, spot diagrams).

The ``scopetwin`` command line that calls them is :mod:`scopetwin.cli`, beside the Python front door.
"""

if __name__ == "sim":  # the bare folder, from the checkout's root: a second copy of scopetwin.sim
    raise ImportError(
        "sim is part of scopetwin: import scopetwin.sim (install with `make setup` or `pip install -e .`)"
    )
