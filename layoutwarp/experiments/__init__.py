"""The paper's experiments, the speed-vs-error benchmark and the figures, beside the library.

Nothing in :mod:`layoutwarp` imports this subpackage; the command line loads it on demand.

* :mod:`.data` — dataset readers (MNIST IDX files, CamVid, UTKFace);
* :mod:`.training` — the shared training loop, run records and :class:`ExperimentDefaults`;
* :mod:`.mnist`, :mod:`.camvid`, :mod:`.faces` — one module per experiment, each with its
  ``DEFAULTS``, network, training and evaluation;
* :mod:`.bench` and :mod:`.scene` — speed against error, and the images it measures on;
* :mod:`.plots` and :mod:`.demo` — figures.
"""
