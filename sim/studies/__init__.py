"""Accuracy studies against rendered truth, run on Dask like the datasets (docs/contract.md, "Scale").

A study is a function of a :class:`~scopetwin.sim.studies.context.StudyContext` that fans its work out as
independent tasks (on the same Dask client the datasets use, or in this process), tabulates the errors
against the truth, and returns :class:`~scopetwin.sim.studies.tables.Table` objects, plots and a JSON summary;
:func:`~scopetwin.sim.studies.runner.run_study` writes ``report.md``, ``results.json`` and the PNG plots into the
output folder (staged, moved into place on success).

* ``thesis`` — every table of Part I of the thesis side by side: §1.10 (both height distributions),
  Tables 2.2-2.4 and 2.8 (one-shot calibration on exact marker images), Tables 2.5-2.7 (setup
  calibration from renders, and the reconstruction with calibrated data), plus Part III's §8.3
  figures of the GRIN objectives.
* ``noise`` — centroid and calibration error against the exposure (EMVA sensor model), on a
  generated dataset of calibration views.
* ``angle`` — centroid and calibration error against the viewing angle (thesis §2.8.2), on a
  generated dataset of calibration views.
* ``surface`` — reconstruction error against the surface's correlation length and range, and
  against the density of the shifted basis (thesis §1.8), on a generated deflectometry dataset.

Each study names the modules it needs; when one is not in this installation the study stops with a
:class:`~scopetwin.sim.studies.context.StudyError` naming the missing capability, before any work.

The package: :mod:`~scopetwin.sim.studies.tables` (seed | ours | ratio tables, plots),
:mod:`~scopetwin.sim.studies.context` (where
tasks run, what a study returns), :mod:`~scopetwin.sim.studies.tasks` (worker tasks shared by the studies), one module
per
study (:mod:`~scopetwin.sim.studies.thesis`, :mod:`~scopetwin.sim.studies.noise`, :mod:`~scopetwin.sim.studies.angle`,
:mod:`~scopetwin.sim.studies.surface`) and :mod:`~scopetwin.sim.studies.runner`
(:func:`~scopetwin.sim.studies.runner.run_study`, the report).
"""
