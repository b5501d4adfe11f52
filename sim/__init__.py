"""sim: synthetic truth — surfaces, measurement simulation, datasets, studies and the command line.

By job, each layer using only the public API of the ones before it:

* :mod:`sim.surfaces` (§1.9 height maps), :mod:`sim.truth` (exact marker images), :mod:`sim.scan_time`
  (the scan-time models of §7.2-7.4, §8.2.2);
* :mod:`sim.measurement` — render and write one measurement (image, truth, preview, provenance) and
  :class:`~sim.measurement.StagedOutput`, the one stage-then-rename helper for output folders;
* :mod:`sim.datasets` — synthetic datasets (config, seeding, one module per sample kind, the store, the runner);
* :mod:`sim.studies` — accuracy studies against rendered truth (tables, tasks, one module per study, the runner);
* :mod:`sim.pipeline` (the end-to-end ``scopetwin run``), :mod:`sim.cmu_unit` (the four-channel unit's analyses),
  :mod:`sim.figures` (marker overlays, spot diagrams);
* :mod:`sim.cli` — the ``scopetwin`` command line, one module per command group; it parses and calls the above.
"""
