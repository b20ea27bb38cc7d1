"""Tasks: each of the paper's experiments as one registered object.

A task is everything that differs between experiments: its name and data folder, how its
data is read and split, its network, its loss on a batch, its scores, its defaults and what
``--quick`` changes, and the plan of its pixel-budget study. Everything else (the training
loop, run records, results files, model files, figures, the study and the command line) is
written once and looks tasks up by name in [`TASKS`][], as layout families are looked up in
[`FAMILIES`][layoutwarp.layouts.base.FAMILIES].

A new task is its protocol, a [`TaskSpec`][layoutwarp.experiments.protocols.TaskSpec] in
[`layoutwarp.experiments.protocols`][] (torch-free: the command line reads it before anything
heavy loads), and one file: subclass [`Task`][] with that ``spec``, write its methods and
decorate it with [`register_task`][]; ``layoutwarp train NAME``, ``study``, ``evaluate`` and
the model files then know it.
"""

from __future__ import annotations

import copy
import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch
from torch import nn

from ..density import edge_density, layout_from_density
from ..layouts import Layout
from .protocols import SPECS, TaskSpec
from .training import BatchLoss

__all__ = ["TASKS", "Task", "TaskData", "get_task", "register_task"]


@dataclass
class TaskData:
    """A task's data as training reads it: the training split and the split it reports on.

    Attributes:
        train, report: task-specific containers (arrays), read by the task's own methods.
        source: the folder they were read from.
    """

    train: Any
    report: Any
    source: Path
    sizes: dict[str, int] = field(default_factory=dict)


class Task:
    """One experiment: a task's implementation, which reads its protocol from [`spec`][]
    (a [`TaskSpec`][layoutwarp.experiments.protocols.TaskSpec] of
    [`SPECS`][layoutwarp.experiments.protocols.SPECS]). Subclasses set ``spec`` and write the
    methods below; the protocol's fields read as the task's attributes (``task.name``,
    ``task.defaults``, ``task.quick_defaults()``, ...).
    """

    spec: ClassVar[TaskSpec]

    def __getattr__(self, name: str) -> Any:
        # only for names the task itself lacks: the protocol's (its own, or its network's)
        if name == "spec":
            raise AttributeError(name)
        return getattr(self.spec, name)

    def with_net(self, net: str | None) -> Task:
        """This task with network ``net`` and its protocol's defaults (``None``: this task).

        Raises:
            ValueError: ``net`` is not one of the protocol's ``nets``.
        """
        spec = self.spec.with_net(net)
        if spec is self.spec:
            return self
        variant = copy.copy(self)
        variant.spec = spec
        return variant

    # -- data ------------------------------------------------------------------------
    def load(self, folder: Path, limit: int | None = None) -> TaskData:
        """Read the training and report splits from the task's data ``folder`` (``limit``: at
        most that many items of each, for smoke tests)."""
        raise NotImplementedError

    def load_split(self, folder: Path, split: str | None) -> Any:
        """Read one split of a folder laid out like the task's data (``evaluate``); ``None``: the
        report split."""
        raise NotImplementedError

    def density_images(self, data: TaskData) -> torch.Tensor:
        """Training images (or label maps) whose edge density places the ``density`` layout."""
        raise NotImplementedError

    def scene(self, data: TaskData) -> np.ndarray:
        """The image figures draw layouts over: HW or HWC in ``[0, 1]``."""
        raise NotImplementedError

    def prediction_image(self, model: nn.Module, data: TaskData) -> np.ndarray | None:
        """An RGB picture of ``model``'s prediction on [`scene`][] for figures (dense tasks),
        or ``None``."""
        return None

    def legend(self) -> dict[str, tuple[int, int, int]]:
        """Names and RGB colours of what [`prediction_image`][] draws (empty: none)."""
        return {}

    # -- model -----------------------------------------------------------------------
    def network(
        self, layout: str | Layout, size: tuple[int, int], learn: bool | None = None, **sensor: Any
    ) -> nn.Module:
        """The task's network with a [`SensorLayer`][layoutwarp.sensor.SensorLayer] in front, as
        ``.sensor``."""
        raise NotImplementedError

    def batches(
        self, model: nn.Module, train: Any, gen: torch.Generator, options: dict[str, Any]
    ) -> tuple[torch.Tensor, BatchLoss]:
        """The indices of the training items and the loss of a batch of them (on ``model``'s
        device; random augmentation draws from ``gen``). ``options``: the task's own
        command-line options ([`add_arguments`][])."""
        raise NotImplementedError

    def score(self, model: nn.Module, part: Any) -> dict[str, Any]:
        """Scores (percent) of ``model`` on a split, `metrics` among them."""
        raise NotImplementedError

    def density_layout(self, data: TaskData, size: tuple[int, int]) -> Layout:
        """The unlearned ``density`` baseline: a control grid from the training set's edges."""
        return layout_from_density(edge_density(self.density_images(data)), size, "grid", dtype=torch.float32)


#: Every registered task by name (see [`register_task`][]).
TASKS: dict[str, Task] = {}
_T = TypeVar("_T", bound=type[Task])


def register_task(cls: _T) -> _T:
    """Class decorator declaring a task under its protocol's name (one instance serves every run)."""
    spec = getattr(cls, "spec", None)
    if not (isinstance(cls, type) and issubclass(cls, Task) and isinstance(spec, TaskSpec)):
        raise TypeError(f"register_task needs a Task subclass with a 'spec' (a TaskSpec), got {cls!r}")
    TASKS[cls.spec.name] = cls()
    for name in [n for n in SPECS if n in TASKS] + [n for n in TASKS if n not in SPECS]:
        TASKS[name] = TASKS.pop(name)  # in the protocols' order, whichever module loaded first
    return cls


def get_task(name: str) -> Task:
    """The registered task ``name``; ``ValueError`` naming the known ones otherwise."""
    if name not in TASKS:
        raise ValueError(f"task must be one of {', '.join(map(repr, TASKS))}; got {name!r}")
    return TASKS[name]


# the built-in tasks register themselves when their modules load: loaded with this one
for _spec in SPECS.values():
    importlib.import_module(f"{__package__}.{_spec.module}")
