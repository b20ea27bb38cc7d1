"""The paper's experiments, the speed-vs-error benchmark and the figures, beside the library.

Nothing in [`layoutwarp`][] imports this subpackage; the command line loads it on demand.

* [`protocols`][] — every task's protocol as data, without torch (its defaults, study plan,
  networks and options: what the command line lists); [`tasks`][] — a task as a registered
  object ([`TASKS`][tasks.TASKS]); [`mnist`][], [`camvid`][], [`faces`][], `cityscapes`, `celeba`
  — one file per task (its network, data, loss and scores), loaded with `tasks`;
* [`data`][] — data roots, the bundled samples and the dataset readers; [`nets`][] —
  shared network blocks;
* [`training`][] — the training loop (devices, AMP, torchrun); `runs` — one run, its
  record, the results file and the experiment loop; `models` — model files and
  ``evaluate``; `study` — the pixel-budget study;
* `bench` and `scene` — speed against error, and the images it measures on;
* `plots` and `demo` — figures.
"""
