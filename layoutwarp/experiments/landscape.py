"""θ-landscapes: does end-to-end learning find the best layout of a two-parameter family?

The task's network trains with θ *frozen* at every point of an ``N × N`` grid over ``(θx, θy)``
(one seed a point; three at θ = 0, the uniform layout, and at the best grid point), with the same
data, split, epochs and training options as the pixel-budget study; each learned θ of a study
(``--study DIR``: its runs of the family at the size) is rerun frozen too, so that learned-jointly
and best-frozen compare on equal terms (a network from scratch either way). Every point is one
[`train_run`][], recorded when it finishes (``runs/*.json``), so a stopped landscape
resumes where it stopped; it writes ``landscape.json``, ``landscape.md`` and
``landscape_<task>_<family>.png`` (the metric as a heat map over θ, uniform, the learned θ and
the best grid point marked).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from ..doctor import run_info
from ..files import atomic_write
from ..layouts import FAMILIES, make_layout
from .runs import RunOptions, check_resumed, keep_settings, read_runs, study_run_records, train_run
from .tasks import Task

__all__ = ["grid_points", "point_name", "run_landscape", "summarise_landscape"]


def grid_points(n: int, lo: float, hi: float) -> list[tuple[float, float]]:
    """The ``n × n`` grid of ``(θx, θy)`` over ``[lo, hi]²`` (row-major: θy slow), rounded to 1e-6;
    a centre that rounds to -0.0 is 0 (the uniform layout's θ, named as its other runs are)."""
    axis = np.round(np.linspace(lo, hi, n), 6) + 0.0  # -0.0 + 0.0 is +0.0
    return [(float(tx), float(ty)) for ty in axis for tx in axis]


def point_name(
    family: str, size: tuple[int, int], theta: tuple[float, float], seed: int, tag: str = ""
) -> str:
    """A run's name: ``<family>_<W>x<H>_tx<θx>_ty<θy>[_<tag>]_seed<s>``."""
    tx, ty = (f"{v:+.6f}".rstrip("0").rstrip(".") for v in theta)
    return f"{family}_{size[1]}x{size[0]}_tx{tx}_ty{ty}" + (f"_{tag}" if tag else "") + f"_seed{seed}"


def study_records(study: Path, family: str, size: tuple[int, int]) -> dict[int, dict]:
    """The jointly learned runs of ``family`` at ``size`` in a study folder, by seed: their
    ``theta`` and ``scores``, from its run records or, in a shipped study (``--ship``), from the
    layout files it keeps of every run."""
    out = {
        int(r["seed"]): {"theta": r["theta"], "scores": r["scores"]}
        for r in study_run_records(study)
        if r["family"] == family and tuple(r["size_hw"]) == tuple(size)
    }
    if not out:
        for p in sorted((study / "layouts").glob(f"{family}_{size[1]}x{size[0]}_seed*.json")):
            data = json.loads(p.read_text())
            seed = int(p.stem.rsplit("seed", 1)[1])
            out[seed] = {"theta": data["theta"], "scores": (data.get("extra") or {}).get("scores", {})}
    return out


def learned_thetas(study: Path, family: str, size: tuple[int, int]) -> list[tuple[int, tuple[float, float]]]:
    """``(seed, θ)`` of a study's runs of ``family`` at ``size`` (jointly learned θ)."""
    return [
        (seed, (float(r["theta"][0]), float(r["theta"][1])))
        for seed, r in study_records(study, family, size).items()
    ]


def run_landscape(
    task: Task,
    folder: str | Path,
    out: str | Path,
    *,
    family: str,
    size: tuple[int, int],
    n: int,
    lo: float,
    hi: float,
    options: RunOptions,
    study: str | Path | None = None,
    repeats: int = 3,
    say: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run (or resume) a θ-landscape; returns the summary written to ``landscape.json``.

    Args:
        task: the task.
        folder: its data folder.
        out: the landscape folder (rerun with the same folder to resume).
        family: a registered two-parameter family (``curv``, ``rect``, ``elliptic``).
        size: sensor size ``(H, W)``.
        n, lo, hi: the ``n × n`` grid over ``[lo, hi]²``.
        options: how every run trains (θ is frozen at its point whatever they say).
        study: a study folder whose learned θ of ``family`` at ``size`` are rerun frozen.
        repeats: seeds at θ = 0 and at the best grid point.
        say: where progress lines go.
    """
    cls = FAMILIES.get(family)
    if cls is None or cls().num_params != 2:
        raise ValueError(f"family must be a two-parameter family (e.g. curv, rect, elliptic), got {family!r}")
    out = Path(out)
    _records(out)  # a folder of another kind refused before any run trains into it
    check_resumed(out, options, "landscape")
    data = None

    def point(theta: tuple[float, float], seed: int, tag: str = "") -> dict:
        nonlocal data
        name = point_name(family, size, theta, seed, tag)
        path = out / "runs" / f"{name}.json"
        if path.exists():
            return json.loads(path.read_text())
        data = data or task.load(Path(folder))
        keep_settings(out, options)
        layout = make_layout(family, theta)  # fixed: θ frozen at the point
        record, _ = train_run(task, data, family, size, seed, options, layout=layout)
        rec = asdict(record) | {"theta_point": list(theta), "tag": tag, "run": run_info(options.device)}
        rec |= {"sensor": options.sensor, "training": options.record()}
        atomic_write(path, json.dumps(rec, indent=2))
        say(f"  {name}: {task.metric} {record.scores[task.metric]:.2f}%  [{record.seconds:.0f} s]")
        return rec

    grid = grid_points(n, lo, hi)
    say(f"{task.name} landscape of {family} at {size[1]}x{size[0]}: {len(grid)} grid points in {out}")
    for theta in grid:
        point(theta, 0)
    for seed in range(1, repeats):
        point((0.0, 0.0), seed)
    best = max(grid, key=lambda t: _score(out, family, size, t, task.metric))
    for seed in range(1, repeats):
        point(best, seed)
    for seed, theta in learned_thetas(Path(study), family, size) if study else []:
        point(theta, seed, "learned")
    summary = summarise_landscape(task, out, family, size, grid, study)
    atomic_write(out / "landscape.json", json.dumps(summary, indent=2))
    atomic_write(out / "landscape.md", landscape_table(summary))
    landscape_figure(summary, out / f"landscape_{task.name}_{family}.png")
    return summary


def _records(out: Path) -> list[dict]:
    """The records of a landscape folder's finished points."""

    def name(r: dict) -> str:
        return point_name(r["family"], r["size_hw"], r["theta_point"], r["seed"], r["tag"])

    return read_runs(out, name, "a landscape")


def _score(out: Path, family: str, size: tuple[int, int], theta: tuple[float, float], metric: str) -> float:
    path = out / "runs" / f"{point_name(family, size, theta, 0)}.json"
    return float(json.loads(path.read_text())["scores"][metric])


def summarise_landscape(
    task: Task, out: Path, family: str, size: tuple[int, int], grid: list, study: str | Path | None
) -> dict[str, Any]:
    """The grid's metric, uniform's and the best point's mean ± std over their seeds, the learned θ
    (jointly, from the study) and their frozen reruns, and the gaps: of the runs of ``family`` at
    ``size`` (a folder that also holds another family's or size's, resumed with other flags,
    mixed their scores into this one's)."""
    recs = [r for r in _records(out) if r["family"] == family and list(r["size_hw"]) == list(size)]

    def scores(theta, tag=""):
        return [
            float(r["scores"][task.metric])
            for r in recs
            if tuple(r["theta_point"]) == tuple(theta) and r.get("tag", "") == tag
        ]

    values = [scores(t)[0] if scores(t) else None for t in grid]
    done = [(t, v) for t, v in zip(grid, values, strict=True) if v is not None]
    best_theta, _ = max(done, key=lambda tv: tv[1])

    def stats(v: list[float]) -> dict:
        return {
            "mean": float(np.mean(v)),
            "std": float(np.std(v, ddof=1)) if len(v) > 1 else 0.0,
            "n": len(v),
        }

    uniform, best = stats(scores((0.0, 0.0))), stats(scores(best_theta))
    learned = []
    if study:
        joint = study_records(Path(study), family, size)
        for r in recs:
            if r.get("tag") == "learned" and int(r["seed"]) in joint:
                j = joint[int(r["seed"])]
                learned.append(
                    {
                        "seed": int(r["seed"]),
                        "theta": r["theta_point"],
                        "joint": float(j["scores"][task.metric]),
                        "frozen": float(r["scores"][task.metric]),
                        "distance_to_best": float(np.hypot(*(np.subtract(r["theta_point"], best_theta)))),
                    }
                )
    beats = best["mean"] - best["std"] > uniform["mean"] + uniform["std"] and best_theta != (0.0, 0.0)
    return {
        "task": task.name,
        "family": family,
        "size_hw": list(size),
        "metric": task.metric,
        "label": task.metric_label,
        "units": "percent",
        "grid": [list(t) for t in grid],
        "values": values,
        "uniform": uniform,
        "best_theta": list(best_theta),
        "best": best,
        "learned": learned,
        "best_beats_uniform_beyond_seed_noise": bool(beats),
        "runs": len(recs),
    }


def landscape_table(summary: dict) -> str:
    """The landscape's reading as Markdown."""
    u, b = summary["uniform"], summary["best"]
    h, w = summary["size_hw"]
    lines = [
        f"{summary['task']} {summary['family']} at {w}x{h}, {summary['label']}:",
        "",
        "| what | θ | metric |",
        "|---|---|---|",
        f"| uniform (θ = 0) | (0, 0) | {u['mean']:.2f} ± {u['std']:.2f} (n={u['n']}) |",
        f"| best frozen grid point | ({summary['best_theta'][0]:+.2f}, {summary['best_theta'][1]:+.2f}) "
        f"| {b['mean']:.2f} ± {b['std']:.2f} (n={b['n']}) |",
    ]
    for r in summary["learned"]:
        lines.append(
            f"| learned jointly, seed {r['seed']} (its θ rerun frozen) "
            f"| ({r['theta'][0]:+.2f}, {r['theta'][1]:+.2f}) "
            f"| {r['joint']:.2f} ({r['frozen']:.2f}); {r['distance_to_best']:.2f} from the best θ |"
        )
    verdict = "beats" if summary["best_beats_uniform_beyond_seed_noise"] else "does not beat"
    lines.append(f"\nThe best frozen θ {verdict} uniform beyond the seeds' spread.")
    return "\n".join(lines) + "\n"


def landscape_figure(summary: dict, path: str | Path) -> Path:
    """The metric as a heat map over θ, with uniform, the best grid point and the learned θ."""
    from .plots import figure, save_figure

    grid = np.array(summary["grid"])
    n = round(len(grid) ** 0.5)
    values = np.array([np.nan if v is None else v for v in summary["values"]]).reshape(n, n)
    lo, hi = float(grid[:, 0].min()), float(grid[:, 0].max())
    step = (hi - lo) / max(n - 1, 1)
    fig, ax = figure(figsize=(5.6, 4.6))
    im = ax.imshow(
        values,
        origin="lower",
        extent=(lo - step / 2, hi + step / 2, lo - step / 2, hi + step / 2),
        cmap="viridis",
    )
    fig.colorbar(im, ax=ax, label=summary["label"])
    ax.plot(0, 0, "w+", ms=12, mew=2, label="uniform")
    ax.plot(*summary["best_theta"], "r*", ms=14, label="best frozen")
    for k, r in enumerate(summary["learned"]):
        ax.plot(*r["theta"], "wo", mfc="none", ms=9, label="learned jointly" if k == 0 else None)
    ax.set_xlabel("θx")
    ax.set_ylabel("θy")
    h, w = summary["size_hw"]
    ax.set_title(f"{summary['task']}: {summary['family']} {w}x{h}, θ frozen at each point", fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    return save_figure(fig, path)
