"""The paper's experiments, the speed-vs-error benchmark and the figures, beside the library.

Nothing in :mod:`layoutwarp` imports this subpackage; the command line loads it on demand.

* :mod:`.tasks` — a task as a registered object (:data:`~.tasks.TASKS`), its defaults and
  study plan; :mod:`.mnist`, :mod:`.camvid`, :mod:`.faces` — one file per task (its network,
  data split, loss and scores), registered on import below;
* :mod:`.data` — data roots, the bundled samples and the dataset readers; :mod:`.nets` —
  shared network blocks;
* :mod:`.training` — the training loop (devices, AMP, torchrun); :mod:`.runs` — one run, its
  record, the results file and the experiment loop; :mod:`.models` — model files and
  ``evaluate``; :mod:`.study` — the pixel-budget study;
* :mod:`.bench` and :mod:`.scene` — speed against error, and the images it measures on;
* :mod:`.plots` and :mod:`.demo` — figures.
"""

from . import camvid, celeba, cityscapes, faces, mnist  # noqa: F401  (registers the built-in tasks)
