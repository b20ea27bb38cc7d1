"""The pixel-budget study: how many uniform pixels is a learned layout worth?

For one task, the uniform layout is trained at several sensor sizes (the *uniform curve*: the
task metric against the number of sensor pixels) and every other family at some of them;
each learned result is then read back through the uniform curve: its *equivalent uniform pixel
count* is the pixel count at which the (log-linearly interpolated) uniform curve reaches the
learned metric, and the *pixel saving factor* is that count over the learned sensor's pixels.
The interval maps the learned metric's mean ± one seed standard deviation the same way.

``density`` is the unlearned baseline
[`density_layout`][layoutwarp.experiments.tasks.Task.density_layout] on the training
set's statistics (mean edge strength of the images; of the label maps for CamVid). What a task's
study trains is its [`StudyPlan`][] (``task.study``); every run is one
[`train_run`][].

Every run writes its record (``runs/<family>_<W>x<H>_seed<s>.json``, a
[`RunRecord`][layoutwarp.experiments.runs.RunRecord]) and model file (``models/…pt``) when it finishes,
atomically; a
restarted study skips finished runs, so it can be stopped at any time. Nothing is chosen on the
report split: fixed epochs, no early stopping.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..doctor import run_info
from ..files import atomic_write
from ..layouts import Layout
from .models import save_model
from .protocols import StudyPlan
from .runs import RunOptions, check_resumed, keep_settings, run_name, study_run_records, train_run
from .tasks import Task

__all__ = [
    "equivalent_pixels",
    "run_study",
    "ship_study",
    "study_runs",
    "summarise_study",
    "write_summary",
]


def study_runs(plan: StudyPlan, seeds: int) -> list[tuple[str, tuple[int, int], int]]:
    """Every ``(family, size, seed)`` of a plan, seed by seed (each seed: the uniform curve, then
    the learned layouts), so a study stopped part way has every configuration's first seeds
    rather than all of some configurations' and none of others'. A configuration is planned once
    (``uniform`` among the families is the uniform curve's own)."""
    uniform = [("uniform", tuple(s)) for s in plan.uniform_sizes]
    learned = [(f, tuple(s)) for s in plan.learned_sizes for f in plan.families]
    return [(family, size, k) for k in range(seeds) for family, size in dict.fromkeys(uniform + learned)]


def study_options(task: Task, plan: StudyPlan, **changes: Any) -> RunOptions:
    """The options every run of a study trains with: the task's defaults at the plan's tolerance,
    with ``changes`` (epochs, device, ...; ``None`` keeps the default)."""
    options = RunOptions.of(task.defaults, **changes)
    if plan.tol is not None:
        options = replace(options, sensor=options.sensor | {"tol": plan.tol})
    return options


def run_study(
    task: Task,
    folder: str | Path,
    out: str | Path,
    *,
    plan: StudyPlan | None = None,
    seeds: int | None = None,
    options: RunOptions | None = None,
    say: Callable[[str], None] = print,
) -> dict:
    """Run (or resume) a task's study; write ``study.json``, ``study.md`` and ``study_<task>.png``.

    Args:
        task: the task.
        folder: its data folder.
        out: the study folder (rerun with the same folder to resume).
        plan: what to train (default: ``task.study``).
        seeds: seeds per configuration (default: the plan's).
        options: how every run trains (default: [`study_options`][]).
        say: where progress lines go.

    Returns:
        the summary written to ``study.json``.
    """
    plan = plan or task.study
    options = options or study_options(task, plan)
    out = Path(out)
    todo = study_runs(plan, seeds or plan.seeds)
    study_run_records(out)  # a folder of another kind refused before any run trains into it
    check_resumed(out, options, "study")
    done = sum((out / "runs" / f"{run_name(*r)}.json").exists() for r in todo)
    say(f"{task.name} study: {len(todo)} runs, {done} already done, in {out}")
    data = None
    for k, (family, size, seed) in enumerate(todo):
        name = run_name(family, size, seed)
        path = out / "runs" / f"{name}.json"
        if path.exists():
            continue
        data = data or task.load(Path(folder))
        keep_settings(out, options)
        checkpoint = out / "checkpoints" / f"{name}.pt"  # a stopped run resumes from its last epoch
        record, model = train_run(task, data, family, size, seed, options, checkpoint=checkpoint)
        training = options.record() | {"family": family, "seed": seed, "scores": record.scores}
        save_model(
            out / "models" / f"{name}.pt",
            task.name,
            model,
            sensor=options.sensor,
            training=training,
            net=task.net,
        )
        rec = asdict(record) | {
            "sensor": options.sensor,
            "training": options.record(),
            "run": run_info(options.device),
        }
        atomic_write(path, json.dumps(rec, indent=2))
        checkpoint.unlink(missing_ok=True)
        score = record.scores[task.metric]
        say(f"  [{k + 1}/{len(todo)}] {name}: {task.metric} {score:.2f}%  [{record.seconds:.0f} s]")
        write_summary(task, out, plan, planned=len(todo))  # a stopped study still has its figures
    return write_summary(task, out, plan, planned=len(todo))


def write_summary(
    task: Task, out: str | Path, plan: StudyPlan | None = None, planned: int | None = None
) -> dict:
    """Summarise the runs a study folder holds so far into ``study.json``, ``study.md``,
    ``study_<task>.png`` and, once a run has learned a layout, ``theta_<task>.png``
    ([`theta_figure`][layoutwarp.experiments.plots.theta_figure]); returns the summary."""
    out = Path(out)
    records = study_run_records(out)
    if not records:
        raise FileNotFoundError(f"no finished runs in {out / 'runs'}")
    summary = summarise_study(task, records) | {"planned": planned}
    atomic_write(out / "study.json", json.dumps(summary, indent=2))
    atomic_write(out / "study.md", study_table(summary))
    study_figure(summary, out / f"study_{task.name}.png")
    from .plots import learned_runs, theta_figure

    if learned_runs(records):
        theta_figure(records, out / f"theta_{task.name}.png")
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


def summarise_study(task: Task, records: list[dict]) -> dict:
    """Mean ± std per family and size, the uniform curve, and every learned result's equivalent
    uniform pixel count and saving factor (with the interval from the seed spread); where both
    have two seeds or more, its difference from uniform at the same size and Welch's t-test's
    two-sided p-value (``vs_uniform``, ``welch_p``)."""
    groups: dict[tuple[str, tuple[int, int]], list[dict]] = {}
    for r in records:
        groups.setdefault((r["family"], tuple(r["size_hw"])), []).append(r["scores"])
    rows = []
    for (family, size), scores in sorted(
        groups.items(), key=lambda kv: (kv[0][1][0] * kv[0][1][1], kv[0][0])
    ):
        v = np.array([float(s[task.metric]) for s in scores])
        row = {
            "family": family,
            "size_hw": list(size),
            "pixels": size[0] * size[1],
            "mean": float(v.mean()),
            "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
            "n": len(v),
            "values": v.tolist(),  # each seed's, in the order of the seeds
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
    uniform = {tuple(r["size_hw"]): r for r in rows if r["family"] == "uniform"}
    for r in rows:
        u = uniform.get(tuple(r["size_hw"]))
        if r["family"] != "uniform" and u is not None and min(r["n"], u["n"]) > 1:
            from scipy.stats import ttest_ind

            p = ttest_ind(r["values"], u["values"], equal_var=False).pvalue
            r |= {"vs_uniform": r["mean"] - u["mean"], "welch_p": None if math.isnan(p) else float(p)}
    for r in rows:
        if r["family"] == "uniform" or len(curve) < 2:
            continue
        eq, rel = equivalent_pixels(curve, r["mean"])
        lo, lo_rel = equivalent_pixels(curve, r["mean"] - r["std"])
        hi, hi_rel = equivalent_pixels(curve, r["mean"] + r["std"])
        r |= {"equivalent_pixels": eq, "bound": rel, "saving": eq / r["pixels"]}
        # an end past the uniform curve's is a bound too ("<" or ">"), as the saving's own
        r |= {"saving_interval": [lo / r["pixels"], hi / r["pixels"]], "interval_bounds": [lo_rel, hi_rel]}
    return {
        "task": task.name,
        "net": task.net,
        "metric": task.metric,
        "label": task.metric_label,
        "units": "percent",
        "rows": rows,
        "runs": len(records),
    }


def study_table(summary: dict) -> str:
    """The study as a Markdown table."""
    lines = [
        f"| family | sensor | pixels | {summary['label']} | vs uniform (Welch p) "
        "| equivalent uniform pixels | pixel saving |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in summary["rows"]:
        h, w = r["size_hw"]
        eq = sav = "—"
        if "equivalent_pixels" in r:
            marks = {"=": "", "<": "< ", ">": "> "}
            mark = marks[r["bound"]]
            eq = f"{mark}{r['equivalent_pixels']:.0f}"
            (lo, hi), (at_lo, at_hi) = r["saving_interval"], r.get("interval_bounds", ("=", "="))
            sav = f"{mark}{r['saving']:.2f}x [{marks[at_lo]}{lo:.2f}, {marks[at_hi]}{hi:.2f}]"
        score = f"{r['mean']:.2f} ± {r['std']:.2f} (n={r['n']})"
        vs = "—"
        if "vs_uniform" in r:
            vs = f"{r['vs_uniform']:+.2f}" + ("" if r["welch_p"] is None else f" (p = {r['welch_p']:.2f})")
        lines.append(f"| {r['family']} | {w}x{h} | {r['pixels']} | {score} | {vs} | {eq} | {sav} |")
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
    families as points; a study of one sensor size: each family's seeds side by side."""
    from .plots import family_color, figure, save_figure

    fig, ax = figure(figsize=(6.4, 4.4))
    rows = summary["rows"]
    if len({r["pixels"] for r in rows}) == 1:
        rows = sorted(rows, key=lambda r: r["family"] != "uniform")  # uniform first, the rest as they come
        for k, r in enumerate(rows):
            color = "black" if r["family"] == "uniform" else family_color(r["family"])
            label = "each seed" if k == 0 else None
            ax.plot([k] * r["n"], r["values"], "o", color=color, alpha=0.6, label=label)
            ax.errorbar(k + 0.15, r["mean"], r["std"], color=color, marker="s", capsize=3)
        ax.errorbar([], [], [], color="gray", marker="s", ls="none", capsize=3, label="mean ± std")
        ax.set_xticks(range(len(rows)), [f"{r['family']}\n(n={r['n']})" for r in rows])
        ax.set_xlim(-0.6, len(rows) - 0.4)
        h, w = rows[0]["size_hw"]
        ax.set_ylabel(summary["label"])
        name = " ".join(filter(None, (summary["task"], summary.get("net"))))
        ax.set_title(f"{name} at {w}x{h}: each family's seeds")
        ax.legend(fontsize=8)
        return save_figure(fig, path)
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


def ship_study(
    task: Task,
    out: str | Path,
    dest: str | Path,
    scene: np.ndarray | None = None,
    models: bool = True,
    weights: str = "float16",
    samples: str | Path | None = None,
    planned: int | None = None,
) -> dict:
    """Copy what a study folder holds so far into a small folder to commit and share.

    Writes ``dest/study.json``, ``study.md``, ``study_<task>.png``, ``theta_<task>.png`` (once a
    run has learned a layout); ``layouts/<run>.json``, the
    layout file of every run with a non-uniform layout; with ``models``,
    ``models/<run>.pt`` (in ``weights`` precision, see [`save_model`][]) of each
    family's best seed at each learned size;
    with a ``scene`` (e.g. [`scene`][layoutwarp.experiments.tasks.Task.scene]), ``layouts_<task>.png``:
    those best
    layouts drawn over it; with
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
    for name in ("study.json", "study.md", f"study_{task.name}.png", f"theta_{task.name}.png"):
        if (out / name).exists():
            atomic_write(dest / name, (out / name).read_bytes())
    records = study_run_records(out)
    learned = {tuple(s) for s in task.study.learned_sizes}
    best: dict[tuple[str, tuple[int, int]], dict] = {}
    for r in records:
        name, size = run_name(r["family"], r["size_hw"], r["seed"]), tuple(r["size_hw"])
        if r["family"] == "uniform" and size not in learned:
            continue  # no layout to ship and never a shipped model: not worth loading
        net, info = load_model(out / "models" / f"{name}.pt", task.name)
        if r["family"] != "uniform":
            extra = {"task": task.name, "run": name, "scores": r["scores"]}
            save_layout(net.sensor.layout, dest / "layouts" / f"{name}.json", size, **extra)
        key = (r["family"], size)
        score = r["scores"][task.metric]
        if size in learned and (key not in best or score > best[key]["score"]):
            best[key] = {"score": score, "name": name, "net": net, "info": info}
    sample_scores = {}
    for b in best.values() if models else ():
        path = save_model(
            dest / "models" / f"{b['name']}.pt",
            task.name,
            b["net"],
            sensor=b["info"]["sensor"],
            training=b["info"]["training"],
            weights=weights,
            net=task.net,
        )
        if samples is not None:
            shipped, _ = load_model(path, task.name)
            sample_scores[path.name] = evaluate_model(task.name, shipped, samples)
    if sample_scores:
        atomic_write(dest / "samples_scores.json", json.dumps(sample_scores, indent=2, sort_keys=True))
    layouts = {k: b["net"].sensor.layout for k, b in best.items() if k[0] != "uniform"}
    if scene is not None and layouts:
        layouts_figure(scene, layouts, dest / f"layouts_{task.name}.png")
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
