"""Synthetic datasets at scale: many rendered measurements with exact truth, on Dask or in-process.

The package: :mod:`~scopetwin.sim.datasets.config` (the schema below), :mod:`~scopetwin.sim.datasets.seeding`
(per-sample
randomness), one module per sample kind (:mod:`~scopetwin.sim.datasets.part1`, :mod:`~scopetwin.sim.datasets.grin`,
:mod:`~scopetwin.sim.datasets.cmu`), :mod:`~scopetwin.sim.datasets.plan` (the validated config every worker gets),
:mod:`~scopetwin.sim.datasets.store` (the dataset folder: atomic sample writes, manifest, recovery, generation,
verification) and :mod:`~scopetwin.sim.datasets.runner` (in-process or Dask).

A dataset is described by a TOML config (``examples/datasets/*.toml``)::

    [dataset]
    kind = "deflectometry"          # deflectometry | calibration | grin | cmu
    setup = "thesis-1.10-deflectometry"   # preset name or setup TOML (relative to the config)
    count = 8
    master_seed = 1
    spp = 16
    noise = true                    # EMVA 1288 sensor model (thesis §1.11 camera class)

    [setup]                         # fixed overrides merged into the setup (any setup field)
    camera.pixels = [680, 512]

    [vary]                          # what varies from sample to sample, and how
    surface_range_um = { uniform = [20.0, 60.0] }
    camera_shift = { normal = [0.0, 0.2] }

A ``cmu`` sample (thesis Part II, §5.1-§5.2) is one image per channel of the four-channel unit
(``scenes.mitsuba.cmu``), each camera at its own refocused image distance (plus ``channel_defocus``),
offset and tilt; the splitters' modelled bows and residual seeds vary per sample; ``[cmu]`` picks the
channels, a sensor window and the tube-lens stop (:class:`CmuSection`). Keys with a ``per`` group
(``bow_*``/``residual_rms_um``: each splitter, ``channel_*``: each channel) are drawn independently
for every member, so one distribution describes e.g. all four camera offsets.

Every distribution is one of ``fixed``, ``uniform = [lo, hi]``, ``normal = [mean, std]``,
``loguniform = [lo, hi]``, ``choice = [...]`` or ``sweep = [...]``; all ``sweep`` keys form a
cartesian grid that sample i walks through (i modulo the grid size), repeated with fresh seeds.
The config is checked completely before any work starts: unknown keys, a distribution whose
support leaves the key's domain (a negative range, a viewing angle above 90 degrees) and any
sample whose setup would be invalid are rejected with a message naming the key.

Determinism: every random quantity of sample i comes from ``SeedSequence([master_seed, i,
crc32(name)])``, so sample i is the same bytes whatever worker renders it, in whatever order,
alone or with others (seed-independent of the count and of the other samples).

Layout of a dataset folder::

    DIR/dataset.json          the normalised config (what ``resume`` reads)
    DIR/manifest.jsonl        one JSON line per finished sample (hashes; worker address, host and pid of the
                              worker process that made it; time)
    DIR/.scopetwin.lock       the folder's lock (flock): host, pid, command and start of the run holding it
    DIR/samples/000000/       one folder per sample: image.exr, truth.json, surface.exr,
                              normals.exr (deflectometry), maps.exr (per-pixel truth), preview.png,
                              sample.json (hashes); 'cmu': image_<channel>.exr per channel,
                              height_<element>.exr, maps.exr

A sample folder is written under a temporary name in ``DIR/samples`` (its writer holds an ``flock`` on it)
and renamed into place when complete (atomic on POSIX file systems); sample files hold no timestamps or host
names (those are in the manifest). One run at a time holds a dataset folder (:mod:`~scopetwin.sim.datasets.lock`): a
second ``generate``/``resume`` on it is refused at once, naming the holder. ``resume`` removes the temporary
folders of dead processes (never one a live writer holds), re-lists finished samples the manifest lost (a
killed client; such lines say ``"status": "recovered"``, their maker unknown), renders only what is missing
and reports the counts; ``verify`` checks every sample against the manifest and its own hashes, validates its files
against the shipped JSON Schemas and checks their values (:mod:`~scopetwin.sim.datasets.validate`).

Reading and using a dataset: :func:`scopetwin.open_dataset` (:mod:`~scopetwin.sim.datasets.reader`), the per-pixel
truth (:mod:`~scopetwin.sim.datasets.maps`), ``dataset show`` (:mod:`~scopetwin.sim.datasets.sheet`) and
``dataset export`` (:mod:`~scopetwin.sim.datasets.export`). A run stopped
by Ctrl-C, SIGTERM or SIGHUP (:mod:`scopetwin.sim.signals`) lists every finished sample before it exits.

"""
