"""The pixel-budget study: how many uniform pixels is a learned layout worth?

For one task, the uniform layout is trained at several sensor sizes (the *uniform curve*: the
task metric against the number of sensor pixels) and every other family at some of them;
each learned result is then read back through the uniform curve: its *equivalent uniform pixel
count* is the pixel count at which the (log-linearly interpolated) uniform curve reaches the
learned metric, and the *pixel saving factor* is that count over the learned sensor's pixels.
The interval maps the learned metric's mean ± one seed standard deviation the same way.

``density`` is the unlearned baseline :func:`~layoutwarp.layout_from_density` on the training
set's statistics (mean edge strength of the images; of the label maps for CamVid).

Every run writes its record (``runs/<family>_<W>x<H>_seed<s>.json``) and model file
(``models/…pt``) when it finishes, atomically; a restarted study skips finished runs, so it can
be stopped at any time. Nothing is chosen on the report split: fixed epochs, no early stopping.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..density import edge_density, layout_from_density
from ..files import atomic_write
from ..layouts import Layout
from .models import run_name, save_model

__all__ = [
    "PLANS",
    "StudyPlan",
    "equivalent_pixels",
    "run_study",
    "ship_study",
    "study_runs",
    "summarise_study",
    "write_summary",
]


@dataclass(frozen=True)
class StudyPlan:
    """What a task's study trains.

    Attributes:
        metric: the score read from each run (higher is better) and its label.
        uniform_sizes: sensor sizes ``(H, W)`` of the uniform curve.
        learned_sizes: sizes at which every other family is trained.
        families: the other families (``"density"``: the unlearned baseline).
        seeds: seeds per configuration.
        tol: the exact integrator's tolerance of every run (``None``: the experiment's default).
    """

    metric: str
    label: str
    uniform_sizes: tuple[tuple[int, int], ...]
    learned_sizes: tuple[tuple[int, int], ...]
    families: tuple[str, ...] = ("rect", "curv", "fovea", "spline", "grid", "density")
    seeds: int = 3
    tol: float | None = None


#: The uniform curve reaches past the largest learned size, so that a learned layout that beats
#: uniform there gets an equivalent pixel count and not just a bound.
PLANS = {
    "mnist": StudyPlan(
        "accuracy",
        "test accuracy (%)",
        ((2, 2), (3, 3), (4, 4), (5, 5), (6, 6), (7, 7)),
        ((3, 3), (4, 4)),
        tol=1e-5,  # the experiment's default when the study was run; kept so its runs compare
    ),
    "camvid": StudyPlan(
        "miou",
        "val mIoU (%)",
        ((18, 24), (27, 36), (36, 48), (54, 72), (72, 96), (90, 120)),
        ((36, 48), (72, 96)),
    ),
    "faces": StudyPlan(
        "mean", "mean test accuracy (%)", ((4, 4), (6, 6), (8, 8), (12, 12), (16, 16)), ((6, 6), (8, 8))
    ),
}


def study_runs(plan: StudyPlan, seeds: int) -> list[tuple[str, tuple[int, int], int]]:
    """Every ``(family, size, seed)`` of a plan, uniform curve first."""
    runs = [("uniform", s, k) for s in plan.uniform_sizes for k in range(seeds)]
    runs += [(f, s, k) for s in plan.learned_sizes for f in plan.families for k in range(seeds)]
    return runs


class _Task:
    """Loads a task's data once and trains one configuration of it."""

    def __init__(
        self,
        task: str,
        data_dir: Path,
        epochs: int | None,
        tol: float | None,
        progress: bool,
        device: str,
        amp: bool,
    ) -> None:
        self.task, self.progress, self.device, self.amp = task, progress, device, amp
        if task == "mnist":
            from .data import load_mnist
            from .mnist import DEFAULTS

            self.data = load_mnist(data_dir)
            stats = torch.from_numpy(self.data["train_images"][:4000]).float()
        elif task == "camvid":
            from .camvid import DEFAULTS
            from .data import load_camvid

            self.train_set, self.val_set = load_camvid(data_dir, "train"), load_camvid(data_dir, "val")
            stats = torch.from_numpy(self.train_set[1]).float()  # label boundaries
        else:
            from .data import load_faces
            from .faces import DEFAULTS

            self.data = load_faces(data_dir)
            n = len(self.data["images"])
            order = np.random.default_rng(1234).permutation(n)  # the experiment's fixed split
            n_test = max(1, round(n * 0.2))
            self.test_idx, self.train_idx = np.sort(order[:n_test]), np.sort(order[n_test:])
            stats = torch.from_numpy(self.data["images"][self.train_idx[:1000]]).float().permute(0, 3, 1, 2)
        self.defaults = DEFAULTS
        self.epochs = epochs or DEFAULTS.epochs
        self.sensor = DEFAULTS.sensor() | ({"tol": tol} if tol is not None else {})
        self.density = edge_density(stats)

    def layout(self, family: str, size: tuple[int, int]) -> str | Layout:
        if family == "density":
            return layout_from_density(self.density, size, "grid", dtype=torch.float32)
        return family

    def train(self, family: str, size: tuple[int, int], seed: int) -> tuple[dict, torch.nn.Module, list]:
        layout = self.layout(family, size)
        kw = {"seed": seed, "epochs": self.epochs, "progress": self.progress, "sensor": self.sensor}
        kw |= {"device": self.device, "amp": self.amp}
        if self.task == "mnist":
            from .mnist import train_mnist

            res, model = train_mnist(self.data, layout, size=size, **kw)
            return {"accuracy": res.test_accuracy}, model, res.theta
        if self.task == "camvid":
            from .camvid import train_camvid

            freeze = min(self.defaults.freeze_epochs, max(self.epochs - 1, 0))
            run, model = train_camvid(self.train_set, self.val_set, layout, size, freeze_epochs=freeze, **kw)
            return run.scores, model, run.theta
        from .faces import train_faces

        run, model = train_faces(self.data, self.train_idx, self.test_idx, layout, size, **kw)
        return run.scores, model, run.theta


def run_study(
    task: str,
    data_dir: str | Path,
    out: str | Path,
    *,
    plan: StudyPlan | None = None,
    seeds: int | None = None,
    epochs: int | None = None,
    progress: bool = True,
    device: str = "cpu",
    amp: bool = False,
    say: Callable[[str], None] = print,
) -> dict:
    """Run (or resume) a task's study; write ``study.json``, ``study.md`` and ``study_<task>.png``.

    Returns:
        the summary written to ``study.json``.
    """
    plan = plan or PLANS[task]
    out = Path(out)
    seeds = seeds or plan.seeds
    todo = study_runs(plan, seeds)
    done = sum((out / "runs" / f"{run_name(*r)}.json").exists() for r in todo)
    say(f"{task} study: {len(todo)} runs, {done} already done, in {out}")
    runner = None
    for k, (family, size, seed) in enumerate(todo):
        name = run_name(family, size, seed)
        record = out / "runs" / f"{name}.json"
        if record.exists():
            continue
        runner = runner or _Task(task, Path(data_dir), epochs, plan.tol, progress, device, amp)
        t0 = time.perf_counter()
        scores, model, theta = runner.train(family, size, seed)
        seconds = time.perf_counter() - t0
        save_model(
            out / "models" / f"{name}.pt",
            task,
            model,
            sensor=runner.sensor,
            training={"seed": seed, "epochs": runner.epochs, "family": family, "scores": scores},
        )
        rec = {"family": family, "size_hw": list(size), "seed": seed, "scores": scores}
        rec |= {
            "theta": list(theta),
            "epochs": runner.epochs,
            "seconds": seconds,
            "device": device,
            "amp": amp,
        }
        atomic_write(record, json.dumps(rec, indent=2))
        say(f"  [{k + 1}/{len(todo)}] {name}: {plan.metric} {scores[plan.metric]:.2f}  [{seconds:.0f} s]")
        write_summary(task, out, plan, planned=len(todo))  # a stopped study still has its figures
    return write_summary(task, out, plan, planned=len(todo))


def write_summary(
    task: str, out: str | Path, plan: StudyPlan | None = None, planned: int | None = None
) -> dict:
    """Summarise the runs a study folder holds so far into ``study.json``, ``study.md`` and
    ``study_<task>.png``; returns the summary."""
    plan = plan or PLANS[task]
    out = Path(out)
    records = [json.loads(p.read_text()) for p in sorted((out / "runs").glob("*.json"))]
    if not records:
        raise FileNotFoundError(f"no finished runs in {out / 'runs'}")
    summary = summarise_study(task, plan, records) | {"planned": planned}
    atomic_write(out / "study.json", json.dumps(summary, indent=2))
    atomic_write(out / "study.md", study_table(summary))
    study_figure(summary, out / f"study_{task}.png")
    return summary


def equivalent_pixels(curve: Sequence[tuple[float, float]], metric: float) -> tuple[float, str]:
    """The pixel count at which the uniform ``curve`` ((pixels, metric) points) reaches ``metric``.

    The curve is made non-decreasing (running maximum) and interpolated linearly in
    ``log(pixels)``. Outside its range the nearest end is returned with ``"<"`` or ``">"`` (a
    bound, not a value); inside, ``"="``.
    """
    pts = sorted(curve)
    pixels = [float(p) for p, _ in pts]
    px = np.log(pixels)
    m = np.maximum.accumulate([v for _, v in pts])
    if metric <= m[0]:
        return pixels[0], "<" if metric < m[0] else "="
    if metric > m[-1]:
        return pixels[-1], ">"
    k = int(np.searchsorted(m, metric))  # first point with m >= metric
    if m[k] == metric or m[k] == m[k - 1]:
        return pixels[k], "="
    t = (metric - m[k - 1]) / (m[k] - m[k - 1])
    return float(math.exp(px[k - 1] + t * (px[k] - px[k - 1]))), "="


def summarise_study(task: str, plan: StudyPlan, records: list[dict]) -> dict:
    """Mean ± std per family and size, the uniform curve, and every learned result's equivalent
    uniform pixel count and saving factor (with the interval from the seed spread)."""
    groups: dict[tuple[str, tuple[int, int]], list[dict]] = {}
    for r in records:
        groups.setdefault((r["family"], tuple(r["size_hw"])), []).append(r["scores"])
    rows = []
    for (family, size), scores in sorted(
        groups.items(), key=lambda kv: (kv[0][1][0] * kv[0][1][1], kv[0][0])
    ):
        v = np.array([float(s[plan.metric]) for s in scores])
        row = {
            "family": family,
            "size_hw": list(size),
            "pixels": size[0] * size[1],
            "mean": float(v.mean()),
            "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "n": len(v),
            "scores": {  # every scalar score, averaged over the seeds
                k: float(np.mean([s[k] for s in scores]))
                for k, x in scores[0].items()
                if isinstance(x, int | float)
            },
        }
        if "iou" in scores[0]:  # CamVid: per-class IoU averaged over the seeds (None: class absent)
            iou = np.array([[np.nan if x is None else x for x in s["iou"]] for s in scores], dtype=float)
            row["iou"] = [None if np.isnan(x) else float(x) for x in np.nanmean(iou, 0)] if iou.size else []
        rows.append(row)
    curve = [(r["pixels"], r["mean"]) for r in rows if r["family"] == "uniform"]
    for r in rows:
        if r["family"] == "uniform" or len(curve) < 2:
            continue
        eq, rel = equivalent_pixels(curve, r["mean"])
        lo, _ = equivalent_pixels(curve, r["mean"] - r["std"])
        hi, _ = equivalent_pixels(curve, r["mean"] + r["std"])
        r |= {"equivalent_pixels": eq, "bound": rel, "saving": eq / r["pixels"]}
        r |= {"saving_interval": [lo / r["pixels"], hi / r["pixels"]]}
    return {"task": task, "metric": plan.metric, "label": plan.label, "rows": rows, "runs": len(records)}


def study_table(summary: dict) -> str:
    """The study as a Markdown table."""
    lines = [
        f"| family | sensor | pixels | {summary['label']} | equivalent uniform pixels | pixel saving |",
        "|---|---|---|---|---|---|",
    ]
    for r in summary["rows"]:
        h, w = r["size_hw"]
        eq = sav = "—"
        if "equivalent_pixels" in r:
            mark = {"=": "", "<": "< ", ">": "> "}[r["bound"]]
            eq = f"{mark}{r['equivalent_pixels']:.0f}"
            lo, hi = r["saving_interval"]
            sav = f"{mark}{r['saving']:.2f}x [{lo:.2f}, {hi:.2f}]"
        score = f"{r['mean']:.2f} ± {r['std']:.2f} (n={r['n']})"
        lines.append(f"| {r['family']} | {w}x{h} | {r['pixels']} | {score} | {eq} | {sav} |")
    if summary.get("planned") and summary["runs"] < summary["planned"]:
        lines.append(f"\n{summary['runs']} of {summary['planned']} planned runs finished so far.")
    return "\n".join(lines) + "\n" + class_table(summary)


def class_table(summary: dict) -> str:
    """CamVid: each family's per-class IoU change against uniform at the same size (points);
    empty for tasks without per-class scores."""
    from .data import CAMVID_CLASSES

    rows = [r for r in summary["rows"] if r.get("iou")]
    uniform = {tuple(r["size_hw"]): r["iou"] for r in rows if r["family"] == "uniform"}
    rows = [r for r in rows if r["family"] != "uniform" and tuple(r["size_hw"]) in uniform]
    if not rows:
        return ""
    names = CAMVID_CLASSES[: len(rows[0]["iou"])]
    lines = [
        "\nPer-class IoU change against uniform at the same size (points, mean over seeds):\n",
        "| family | sensor | " + " | ".join(names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for r in rows:
        base = uniform[tuple(r["size_hw"])]
        cells = [
            "—" if a is None or b is None else f"{a - b:+.1f}" for a, b in zip(r["iou"], base, strict=False)
        ]
        lines.append(f"| {r['family']} | {r['size_hw'][1]}x{r['size_hw'][0]} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def study_figure(summary: dict, path: str | Path) -> Path:
    """Metric against sensor pixels (log scale): uniform as a line with error bars, the other
    families as points."""
    from .plots import family_color, figure, save_figure

    fig, ax = figure(figsize=(6.4, 4.4))
    rows = summary["rows"]
    uni = [r for r in rows if r["family"] == "uniform"]
    ax.errorbar(
        [r["pixels"] for r in uni],
        [r["mean"] for r in uni],
        [r["std"] for r in uni],
        color="black",
        marker="o",
        capsize=3,
        label="uniform",
    )
    families = list(dict.fromkeys(r["family"] for r in rows if r["family"] != "uniform"))
    for k, fam in enumerate(families):
        pts = [r for r in rows if r["family"] == fam]
        jitter = 1 + 0.03 * (k - (len(families) - 1) / 2)  # side by side at equal pixel counts
        ax.errorbar(
            [r["pixels"] * jitter for r in pts],
            [r["mean"] for r in pts],
            [r["std"] for r in pts],
            color=family_color(fam) if fam != "density" else "tab:gray",
            marker="s",
            ls="none",
            capsize=3,
            label=fam,
        )
    ax.set_xscale("log")
    sizes = {r["pixels"]: r["size_hw"] for r in rows}
    ax.set_xticks(sorted(sizes), [f"{p}\n{sizes[p][1]}x{sizes[p][0]}" for p in sorted(sizes)])
    ax.minorticks_off()
    ax.set_xlabel("sensor pixels")
    ax.set_ylabel(summary["label"])
    ax.set_title(f"{summary['task']}: metric against pixel budget")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def study_scene(task: str, data_dir: str | Path) -> np.ndarray:
    """The image learned layouts are drawn over: the mean test digit (MNIST), the mean
    training face (faces), the first validation frame (CamVid); HW or HWC in ``[0, 1]``."""
    if task == "mnist":
        from .data import load_mnist_split

        return load_mnist_split(data_dir, "test")[0][:2000].mean(0) / 255
    if task == "camvid":
        from .data import load_camvid

        return load_camvid(data_dir, "val", limit=1)[0][0] / 255
    from .data import load_faces

    return load_faces(data_dir, limit=500)["images"].mean(0) / 255


def ship_study(
    task: str,
    out: str | Path,
    dest: str | Path,
    scene: np.ndarray | None = None,
    models: bool = True,
    weights: str = "float16",
    samples: str | Path | None = None,
    planned: int | None = None,
) -> dict:
    """Copy what a study folder holds so far into a small folder to commit and share.

    Writes ``dest/study.json``, ``study.md``, ``study_<task>.png``; ``layouts/<run>.json``, the
    layout file of every run with a non-uniform layout; with ``models``,
    ``models/<run>.pt`` (in ``weights`` precision, see :func:`~.models.save_model`) of each
    family's best seed at each learned size;
    with a ``scene``, ``layouts_<task>.png``: those best layouts drawn over it; with
    ``samples`` (a small data folder, e.g. the bundled ``data_samples/``),
    ``samples_scores.json``: each shipped model's scores there, read back from its shipped
    file (so anyone can check that ``evaluate`` reproduces them). ``planned``: the number of
    runs the study plans (default: as the study last wrote it).

    Returns:
        the summary.
    """
    from ..layoutfile import save_layout
    from .models import evaluate_model, load_model

    out, dest = Path(out), Path(dest)
    previous = out / "study.json"
    if planned is None and previous.exists():
        planned = json.loads(previous.read_text()).get("planned")
    summary = write_summary(task, out, planned=planned)
    for name in ("study.json", "study.md", f"study_{task}.png"):
        atomic_write(dest / name, (out / name).read_bytes())
    records = [json.loads(p.read_text()) for p in sorted((out / "runs").glob("*.json"))]
    learned = set(PLANS[task].learned_sizes)
    best: dict[tuple[str, tuple[int, int]], dict] = {}
    for r in records:
        name, size = run_name(r["family"], r["size_hw"], r["seed"]), tuple(r["size_hw"])
        if r["family"] == "uniform" and size not in learned:
            continue  # no layout to ship and never a shipped model: not worth loading
        net, info = load_model(out / "models" / f"{name}.pt", task)
        if r["family"] != "uniform":
            extra = {"task": task, "run": name, "scores": r["scores"]}
            save_layout(net.sensor.layout, dest / "layouts" / f"{name}.json", size, **extra)
        key = (r["family"], size)
        if size in learned and (key not in best or r["scores"][PLANS[task].metric] > best[key]["score"]):
            best[key] = {"score": r["scores"][PLANS[task].metric], "name": name, "net": net, "info": info}
    sample_scores = {}
    for b in best.values() if models else ():
        path = save_model(
            dest / "models" / f"{b['name']}.pt",
            task,
            b["net"],
            sensor=b["info"]["sensor"],
            training=b["info"]["training"],
            weights=weights,
        )
        if samples is not None:
            shipped, _ = load_model(path, task)
            sample_scores[path.name] = evaluate_model(task, shipped, samples)
    if sample_scores:
        atomic_write(dest / "samples_scores.json", json.dumps(sample_scores, indent=2, sort_keys=True))
    layouts = {k: b["net"].sensor.layout for k, b in best.items() if k[0] != "uniform"}
    if scene is not None and layouts:
        layouts_figure(scene, layouts, dest / f"layouts_{task}.png")
    return summary


def layouts_figure(
    scene: np.ndarray, layouts: dict[tuple[str, tuple[int, int]], Layout], path: str | Path
) -> Path:
    """Learned layouts over a scene: one row per sensor size, one column per family."""
    from .plots import draw_layout, family_color, figure, save_figure

    sizes = sorted({s for _, s in layouts}, key=lambda s: s[0] * s[1])
    families = list(dict.fromkeys(f for f, _ in sorted(layouts, key=lambda k: k[0])))
    fig, axes = figure(
        len(sizes), len(families), figsize=(2.6 * len(families), 2.6 * len(sizes)), squeeze=False
    )
    for i, size in enumerate(sizes):
        for j, fam in enumerate(families):
            ax = axes[i, j]
            if (fam, size) in layouts:
                color = family_color(fam) if fam != "density" else "tab:gray"
                draw_layout(ax, layouts[fam, size], size, image=scene, color=color, lw=0.5)
                ax.set_title(f"{fam} {size[1]}x{size[0]}", fontsize=9)
            else:
                ax.axis("off")
    return save_figure(fig, path)
