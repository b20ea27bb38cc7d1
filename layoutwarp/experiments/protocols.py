"""Every task's protocol as data: what it trains by default, what ``--quick`` changes, its study
plan, its networks and its own options, without importing torch, so that the command line's help
and argument errors answer at once. A task's implementation ([`Task`][layoutwarp.experiments.tasks.Task]:
data, network, loss, scores) lives in its module and reads its protocol from here
([`SPECS`][]).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, replace
from typing import Any

__all__ = [
    "PSPNET_TRAINING",
    "SPECS",
    "UINT8_TOLERANCE",
    "StudyPlan",
    "TaskDefaults",
    "TaskSpec",
]


@dataclass(frozen=True)
class TaskDefaults:
    """A task's training settings: what ``layoutwarp train TASK`` runs without options.

    Attributes:
        families: the layout families compared (``"uniform"`` is the fixed baseline).
        sizes: sensor sizes ``(H, W)``.
        seeds: number of seeds.
        epochs: training epochs.
        batch_size: samples per step.
        lr: the network's learning rate.
        theta_lr: the sensor's (θ's) learning rate (the same as ``lr``: plain Adam).
        tol: the exact integrator's tolerance, pinned so that runs compare.
        freeze_epochs: epochs with θ frozen at the start (the paper's protocol).
        schedule: the learning rates over the epochs: ``"constant"``, ``"cosine"`` (annealed to
            0) or ``"poly"`` (PSPNet's: ``(1 − epoch/epochs)^0.9``).
        optimizer: ``"adam"``, or ``"sgd"`` (momentum 0.9, PSPNet's); θ has a group of its own
            (``theta_lr``, no weight decay) in either.
        weight_decay: the network's weight decay (PSPNet: 1e-4).
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
    """What a task's pixel-budget study trains (see [`layoutwarp.experiments.study`][]).

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


@dataclass(frozen=True)
class TaskSpec:
    """One task's protocol (what [`Task`][layoutwarp.experiments.tasks.Task] reads as its
    attributes).

    Attributes:
        name: the task's name (``layoutwarp train NAME``).
        module: the module of ``layoutwarp.experiments`` that implements it.
        folder: its folder under a data root (see [`layoutwarp.experiments.data`][]).
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
        nets: the networks ``--net`` selects, each to the attributes its protocol changes
            (``defaults``, ``study``, ``quick``); the first is the default network, with none.
            Empty: the task has one network.
        options: the task's own command-line options, ``(flags, argparse keywords)`` each
            (their values reach its batches as ``options``).
        net: which of ``nets`` this protocol is (``""`` where there are none).
    """

    name: str
    module: str
    folder: str
    description: str
    metrics: tuple[str, ...]
    metric_label: str
    report_split: str
    image_size: tuple[int, int]
    defaults: TaskDefaults
    study: StudyPlan
    quick: dict[str, Any] = field(default_factory=dict)
    nets: dict[str, dict[str, Any]] = field(default_factory=dict)
    options: tuple[tuple[tuple[str, ...], dict[str, Any]], ...] = ()
    net: str = ""

    def __post_init__(self) -> None:
        if self.nets and not self.net:
            object.__setattr__(self, "net", next(iter(self.nets)))

    def with_net(self, net: str | None) -> TaskSpec:
        """This protocol with network ``net`` and its changes (``None``: this one).

        Raises:
            ValueError: ``net`` is not one of [`nets`][layoutwarp.experiments.protocols.TaskSpec.nets].
        """
        if net is None or net == self.net:
            return self
        if net not in self.nets:
            known = ", ".join(map(repr, self.nets)) or "none (one network)"
            raise ValueError(f"net of task {self.name!r} must be one of {known}; got {net!r}")
        return replace(self, net=net, **self.nets[net])

    def quick_defaults(self) -> TaskDefaults:
        """The defaults ``--quick`` runs with."""
        d = self.defaults
        return replace(d, seeds=1, sizes=d.sizes[:1], freeze_epochs=0, **self.quick)

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Add the task's own options to ``parser``."""
        for flags, keywords in self.options:
            parser.add_argument(*flags, **keywords)

    @property
    def extra_dests(self) -> tuple[str, ...]:
        """The names of the task's own options (as ``options`` keys)."""
        parser = argparse.ArgumentParser(add_help=False)
        self.add_arguments(parser)
        return tuple(a.dest for a in parser._actions)

    @property
    def metric(self) -> str:
        """The headline metric."""
        return self.metrics[0]


#: [`data_tolerance`][layoutwarp.tolerance.data_tolerance] of uint8 images (a quarter of one
#: level), written out so that the protocols need no torch (tests check the two agree).
UINT8_TOLERANCE = 0.25 / 255

#: PSPNet's training (Zhao et al.), which the paper keeps but for a batch of 4: SGD with momentum
#: 0.9, learning rate 0.01 with poly decay, weight decay 1e-4 (θ: the same rate, no decay).
PSPNET_TRAINING: dict[str, Any] = {
    "batch_size": 4,
    "lr": 0.01,
    "theta_lr": 0.01,
    "schedule": "poly",
    "optimizer": "sgd",
    "weight_decay": 1e-4,
}

#: The PSP protocol on CamVid (``--net psp``): the paper's optimiser, schedule and batch, and its θ
#: frozen for the first 5 % of the epochs (10 of 200); 20 epochs, about an hour a run on 2 CPU
#: cores at 96x72 (a training epoch 2–4 minutes), where the paper trains 200 on Cityscapes.
PSP_CAMVID = TaskDefaults(
    families=("uniform", "rect", "curv"),
    sizes=((72, 96),),
    seeds=3,
    epochs=20,
    tol=1e-3,
    freeze_epochs=1,
    **PSPNET_TRAINING,
)
#: The paper's CelebA protocol for ResNet-18 (Adam 1e-3, batch 64, 15 epochs), on UTKFace.
RESNET18_FACES = TaskDefaults(
    families=("uniform", "rect"),
    sizes=((8, 8), (16, 16)),
    seeds=3,
    epochs=15,
    batch_size=64,
    lr=1e-3,
    theta_lr=1e-3,
    tol=1e-3,
)
#: The paper's Cityscapes protocol (Sec. 5.3): PSPNet's, batch 4, 200 epochs, θ frozen for 10.
CITYSCAPES_PAPER = TaskDefaults(
    families=("uniform", "curv", "rect"),
    sizes=((65, 129), (129, 257), (257, 513)),
    seeds=1,
    epochs=200,
    tol=1e-3,
    freeze_epochs=10,
    **PSPNET_TRAINING,
)

_SPECS = (
    TaskSpec(
        name="mnist",
        module="mnist",
        folder="mnist",
        description="MNIST digits from a tiny sensor (the paper's 4x4 experiment)",
        metrics=("accuracy",),
        metric_label="test accuracy (%)",
        report_split="test",
        image_size=(28, 28),
        defaults=TaskDefaults(
            families=("uniform", "curv", "rect"),
            sizes=((4, 4),),
            seeds=3,
            epochs=14,
            batch_size=64,
            lr=0.01,
            theta_lr=0.01,
            tol=UINT8_TOLERANCE,  # MNIST is 8-bit: a quarter of one level
        ),
        quick={"epochs": 3},
        study=StudyPlan(
            ((2, 2), (3, 3), (4, 4), (5, 5), (6, 6), (7, 7)),
            ((3, 3), (4, 4)),
            tol=1e-5,  # the default when the study was run; kept so its runs compare
        ),
    ),
    TaskSpec(
        name="camvid",
        module="camvid",
        folder="camvid",
        description="CamVid street-scene segmentation, back-warped to full resolution",
        metrics=("miou", "pixel_accuracy"),
        metric_label="val mIoU (%)",
        report_split="val",
        image_size=(360, 480),
        defaults=TaskDefaults(
            families=("uniform", "curv", "rect"),
            sizes=((36, 48), (72, 96)),
            seeds=2,
            epochs=12,
            batch_size=8,
            lr=2e-3,
            theta_lr=0.01,
            tol=1e-3,
            freeze_epochs=3,
            schedule="cosine",
        ),
        quick={"epochs": 1},
        study=StudyPlan(((18, 24), (27, 36), (36, 48), (54, 72), (72, 96), (90, 120)), ((36, 48), (72, 96))),
        nets={
            "small": {},
            "psp": {
                "defaults": PSP_CAMVID,
                "study": StudyPlan(((72, 96),), ((72, 96),), families=("rect", "curv")),
                "quick": {"epochs": 1},
            },
        },
        options=(
            (
                ("--class-weights",),
                {
                    "choices": ["none", "median"],
                    "help": "loss class weights: none or median-frequency balancing (default: median with "
                    "the small network, none with psp, as PSPNet trains)",
                },
            ),
        ),
    ),
    TaskSpec(
        name="faces",
        module="faces",
        folder="faces/utkface_subset",
        description="UTKFace gender, age group and race from a small sensor",
        metrics=("mean", "gender", "age_group", "race"),
        metric_label="mean test accuracy (%)",
        report_split="test",
        image_size=(200, 200),
        defaults=TaskDefaults(
            families=("uniform", "rect"),
            sizes=((8, 8), (16, 16)),
            seeds=3,
            epochs=30,
            batch_size=64,
            lr=2e-3,
            theta_lr=0.01,
            tol=1e-3,
            schedule="cosine",
        ),
        quick={"epochs": 2},
        study=StudyPlan(((4, 4), (6, 6), (8, 8), (12, 12), (16, 16)), ((6, 6), (8, 8))),
        nets={"small": {}, "resnet18": {"defaults": RESNET18_FACES}},
    ),
    TaskSpec(
        name="cityscapes",
        module="cityscapes",
        folder="cityscapes",
        description="Cityscapes street scenes (19 classes), PSPNet, back-warped to the labels' resolution",
        metrics=("miou", "pixel_accuracy"),
        metric_label="val mIoU (%)",
        report_split="val",
        image_size=(1024, 2048),
        defaults=CITYSCAPES_PAPER,
        quick={"epochs": 1},
        study=StudyPlan(CITYSCAPES_PAPER.sizes, CITYSCAPES_PAPER.sizes, families=("rect", "curv"), seeds=1),
    ),
    TaskSpec(
        name="celeba",
        module="celeba",
        folder="celeba",
        description="CelebA's 40 face attributes from a small sensor, ResNet-18",
        metrics=("mean",),
        metric_label="mean test accuracy (%)",
        report_split="test",
        image_size=(218, 178),
        defaults=TaskDefaults(
            families=("uniform", "rect"),
            sizes=((8, 8), (16, 16)),
            seeds=1,
            epochs=15,
            batch_size=64,
            lr=1e-3,
            theta_lr=1e-3,
            tol=1e-3,
        ),
        quick={"epochs": 2, "batch_size": 8},
        study=StudyPlan(((4, 4), (8, 8), (16, 16)), ((8, 8), (16, 16)), families=("rect",), seeds=1),
    ),
)
#: Every task's protocol by name, in the order the command line lists them.
SPECS: dict[str, TaskSpec] = {spec.name: spec for spec in _SPECS}
