"""Tasks: each of the paper's experiments as one registered object.

A task is everything that differs between experiments: its name and data folder, how its
data is read and split, its network, its loss on a batch, its scores, its defaults and what
``--quick`` changes, and the plan of its pixel-budget study. Everything else (the training
loop, run records, results files, model files, figures, the study and the command line) is
written once and looks tasks up by name in [`TASKS`][], as layout families are looked up in
[`FAMILIES`][layoutwarp.FAMILIES].

A new task is one file: subclass [`Task`][], fill in its class attributes and methods and
decorate it with [`register_task`][]; ``layoutwarp train NAME``, ``study``, ``evaluate`` and
the model files then know it.
"""

from __future__ import annotations

import argparse
import copy
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch
from torch import nn

from ..density import edge_density, layout_from_density
from ..layouts import Layout
from .training import BatchLoss

__all__ = ["TASKS", "StudyPlan", "Task", "TaskData", "TaskDefaults", "get_task", "register_task"]


@dataclass(frozen=True)
class TaskDefaults:
    """A task's training settings: what ``layoutwarp train TASK`` runs without options.

    Attributes:
        families: the layout families compared (``"uniform"`` is the fixed baseline).
        sizes: sensor sizes ``(H, W)``.
        seeds: number of seeds.
        epochs: training epochs.
        batch_size: samples per step.
        lr: the network's Adam learning rate.
        theta_lr: the sensor's (θ's) learning rate (the same as ``lr``: plain Adam).
        freeze_epochs: epochs with θ frozen at the start (the paper's protocol).
        schedule: the learning rates over the epochs: ``"constant"``, ``"cosine"`` (annealed to
            0) or ``"poly"`` (PSPNet's: ``(1 − epoch/epochs)^0.9``).
        optimizer: ``"adam"``, or ``"sgd"`` (momentum 0.9, PSPNet's); θ has a group of its own
            (``theta_lr``, no weight decay) in either.
        weight_decay: the network's weight decay (PSPNet: 1e-4).
        tol: the exact integrator's tolerance, pinned so that runs compare.
    """

    families: tuple[str, ...]
    sizes: tuple[tuple[int, int], ...]
    seeds: int
    epochs: int
    batch_size: int
    lr: float
    theta_lr: float
    tol: float
    freeze_epochs: int = 0
    schedule: str = "constant"
    optimizer: str = "adam"
    weight_decay: float = 0.0

    def sensor(self) -> dict[str, Any]:
        """The sensor options of the task unless the caller gives its own."""
        return {"method": "exact", "tol": self.tol}


@dataclass(frozen=True)
class StudyPlan:
    """What a task's pixel-budget study trains (see [`study`][layoutwarp.experiments.study]).

    Attributes:
        uniform_sizes: sensor sizes ``(H, W)`` of the uniform curve.
        learned_sizes: sizes at which every other family is trained.
        families: the other families (``"density"``: the unlearned baseline).
        seeds: seeds per configuration.
        tol: the exact integrator's tolerance of every run (``None``: the task's default).
    """

    uniform_sizes: tuple[tuple[int, int], ...]
    learned_sizes: tuple[tuple[int, int], ...]
    families: tuple[str, ...] = ("rect", "curv", "fovea", "spline", "grid", "density")
    seeds: int = 3
    tol: float | None = None


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
    """One experiment. Subclasses set the class attributes and write the methods below.

    Class attributes:
        name: the task's name (``layoutwarp train NAME``).
        folder: its folder under a data root (see [`data`][layoutwarp.experiments.data]).
        description: one line for the command line's help.
        metrics: the scores of a run, in percent; the first is the headline (higher is better).
        metric_label: the headline metric as figures and tables name it.
        report_split: the split scores are reported on (``"test"``, ``"val"``).
        image_size: the task's images' size ``(H, W)``; with sensor physics, the sensor's extent
            in µm unless given (1 µm a source pixel).
        defaults: [`TaskDefaults`][].
        quick: what ``--quick`` changes in the defaults (it always uses the bundled samples,
            one seed, the first size and no frozen epochs).
        study: the [`StudyPlan`][] of its pixel-budget study.
    """

    name: ClassVar[str]
    folder: ClassVar[str]
    description: ClassVar[str]
    metrics: ClassVar[tuple[str, ...]]
    metric_label: ClassVar[str]
    report_split: ClassVar[str]
    image_size: ClassVar[tuple[int, int]]
    defaults: ClassVar[TaskDefaults]
    quick: ClassVar[dict[str, Any]] = {}
    study: ClassVar[StudyPlan]
    #: The networks ``--net`` selects, each to the attributes above its training protocol
    #: changes (``defaults``, ``study``, ``quick``); the first is the task's default network, with
    #: none. Empty: the task has one network. See [`with_net`][].
    nets: ClassVar[dict[str, dict[str, Any]]] = {}
    #: This instance's network (a key of [`nets`][]; ``""`` where there are none).
    net: str = ""

    def __init__(self) -> None:
        if self.nets and not self.net:
            self.net = next(iter(self.nets))

    def with_net(self, net: str | None) -> Task:
        """This task with network ``net`` and its protocol's defaults (``None``: this task).

        Raises:
            ValueError: ``net`` is not one of [`nets`][].
        """
        if net is None or net == self.net:
            return self
        if net not in self.nets:
            known = ", ".join(map(repr, self.nets)) or "none (one network)"
            raise ValueError(f"net of task {self.name!r} must be one of {known}; got {net!r}")
        variant = copy.copy(self)
        variant.net = net
        for name, value in self.nets[net].items():
            setattr(variant, name, value)
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
        self, layout: str | Layout, size: tuple[int, int], learn: bool = True, **sensor: Any
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

    # -- command line ----------------------------------------------------------------
    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Options of this task alone (their values reach [`batches`][] as ``options``)."""

    # -- derived ---------------------------------------------------------------------
    @property
    def extra_dests(self) -> tuple[str, ...]:
        """The names of the options [`add_arguments`][] adds (as ``options`` keys)."""
        parser = argparse.ArgumentParser(add_help=False)
        self.add_arguments(parser)
        return tuple(a.dest for a in parser._actions)

    @property
    def metric(self) -> str:
        """The headline metric."""
        return self.metrics[0]

    def quick_defaults(self) -> TaskDefaults:
        """The defaults ``--quick`` runs with."""
        d = self.defaults
        return replace(d, seeds=1, sizes=d.sizes[:1], freeze_epochs=0, **self.quick)

    def density_layout(self, data: TaskData, size: tuple[int, int]) -> Layout:
        """The unlearned ``density`` baseline: a control grid from the training set's edges."""
        return layout_from_density(edge_density(self.density_images(data)), size, "grid", dtype=torch.float32)


#: Every registered task by name (see [`register_task`][]).
TASKS: dict[str, Task] = {}
_T = TypeVar("_T", bound=type[Task])


def register_task(cls: _T) -> _T:
    """Class decorator declaring a task under ``cls.name`` (one instance serves every run)."""
    if not (isinstance(cls, type) and issubclass(cls, Task)) or not getattr(cls, "name", ""):
        raise TypeError(f"register_task needs a Task subclass with a 'name', got {cls!r}")
    TASKS[cls.name] = cls()
    return cls


def get_task(name: str) -> Task:
    """The registered task ``name``; ``ValueError`` naming the known ones otherwise."""
    if name not in TASKS:
        raise ValueError(f"task must be one of {', '.join(map(repr, TASKS))}; got {name!r}")
    return TASKS[name]
