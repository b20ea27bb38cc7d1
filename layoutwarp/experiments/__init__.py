"""The paper's experiments, the speed-vs-error benchmark and the figures, beside the library.

Nothing in [`layoutwarp`][] imports this subpackage; the command line loads it on demand.

* [`tasks`][] — a task as a registered object ([`TASKS`][tasks.TASKS]), its defaults and
  study plan; [`mnist`][], [`camvid`][], [`faces`][] — one file per task (its network,
  data split, loss and scores), registered on import below;
* [`data`][] — data roots, the bundled samples and the dataset readers; [`nets`][] —
  shared network blocks;
* [`training`][] — the training loop (devices, AMP, torchrun); `runs` — one run, its
  record, the results file and the experiment loop; `models` — model files and
  ``evaluate``; `study` — the pixel-budget study;
* `bench` and `scene` — speed against error, and the images it measures on;
* `plots` and `demo` — figures.
"""

from . import camvid, celeba, cityscapes, faces, mnist  # noqa: F401  (registers the built-in tasks)
