"""θ-landscapes: the grid, resuming, the learned θ rerun frozen, the reading."""

from __future__ import annotations

import json
import math

import pytest

from layoutwarp.cli import main
from layoutwarp.experiments.landscape import grid_points, point_name


def test_grid_points_and_names():
    pts = grid_points(3, -0.8, 0.8)
    assert pts[0] == (-0.8, -0.8) and pts[4] == (0.0, 0.0) and pts[-1] == (0.8, 0.8) and len(pts) == 9
    assert point_name("curv", (4, 4), (0.5, -0.25), 2) == "curv_4x4_tx+0.5_ty-0.25_seed2"
    assert point_name("curv", (4, 4), (0.0, 0.0), 0, "learned") == "curv_4x4_tx+0_ty+0_learned_seed0"
    # the documented -0.9 .. 0.9 by 7 put its centre at -0.0: named tx-0_ty-0 against the uniform
    # seeds' tx+0_ty+0, so a best point at θ = 0 trained and counted those seeds twice
    centre = grid_points(7, -0.9, 0.9)[24]
    assert centre == (0.0, 0.0) and all(math.copysign(1, v) == 1 for v in centre)
    assert point_name("rect", (4, 4), centre, 0) == "rect_4x4_tx+0_ty+0_seed0"


@pytest.mark.slow
def test_quick_landscape_reruns_the_learned_theta_frozen_and_resumes(tmp_path, capsys):
    study = tmp_path / "study"
    assert main(["study", "mnist", "--quick", "--family", "curv", "--no-progress", "--out", str(study)]) == 0
    argv = [
        "landscape",
        "mnist",
        "--quick",
        "--family",
        "curv",
        "--no-progress",
        "--out",
        str(tmp_path / "l"),
    ]
    assert main([*argv, "--study", str(study)]) == 0
    summary = json.loads((tmp_path / "l" / "landscape.json").read_text())
    assert len(summary["values"]) == 9 and all(v is not None for v in summary["values"])
    assert summary["uniform"]["n"] == 3 and summary["best"]["n"] == 3  # three seeds at both
    assert summary["best"]["mean"] >= max(summary["values"]) - 10  # the best point, over its seeds
    (learned,) = summary["learned"]  # the study's one curv run at 3x3, rerun with θ frozen
    joint = json.loads((study / "runs" / "curv_3x3_seed0.json").read_text())
    assert (
        learned["theta"] == pytest.approx(joint["theta"]) and learned["joint"] == joint["scores"]["accuracy"]
    )
    assert (tmp_path / "l" / "landscape_mnist_curv.png").stat().st_size > 5000
    assert "| uniform (θ = 0) | (0, 0) |" in (tmp_path / "l" / "landscape.md").read_text()
    stamps = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "l" / "runs").iterdir()}
    assert len(stamps) == 9 + 2 + 2 + 1
    capsys.readouterr()
    assert main([*argv, "--study", str(study)]) == 0  # resumes: nothing is trained again
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "l" / "runs").iterdir()} == stamps
    with pytest.raises(SystemExit) as info:  # four parameters: not a landscape over (θx, θy)
        main(["landscape", "mnist", "--quick", "--family", "fovea", "--out", str(tmp_path / "x")])
    assert info.value.code == 2 and "invalid choice: 'fovea'" in capsys.readouterr().err


def test_a_shipped_study_gives_its_learned_theta():
    from conftest import ROOT

    from layoutwarp.experiments.landscape import study_records

    recs = study_records(ROOT / "examples" / "study" / "mnist", "curv", (4, 4))
    assert sorted(recs) == [0, 1, 2]  # the shipped layout files of the three seeds
    assert all(len(r["theta"]) == 2 and 0 < r["scores"]["accuracy"] <= 100 for r in recs.values())


def test_a_study_folders_runs_are_read_as_the_study_reads_them(tmp_path):
    # the landscape takes a study's learned θ from its run records by the study's own reader:
    # a run of another family or size is passed over, a file of another kind is refused
    from layoutwarp.experiments.landscape import study_records
    from layoutwarp.experiments.runs import run_name

    runs = tmp_path / "runs"
    runs.mkdir()
    for family, size, seed, theta in [("curv", (4, 4), 3, [0.1, -0.2]), ("curv", (8, 8), 1, [0.3, 0.3])]:
        scores = {"accuracy": 90.0}
        rec = {"family": family, "size_hw": list(size), "seed": seed, "theta": theta, "scores": scores}
        (runs / f"{run_name(family, size, seed)}.json").write_text(json.dumps(rec))
    assert study_records(tmp_path, "curv", (4, 4)) == {3: {"theta": [0.1, -0.2], "scores": scores}}
    (runs / "summary.json").write_text("{}")
    with pytest.raises(ValueError, match=r"summary\.json is no run of a study"):
        study_records(tmp_path, "curv", (4, 4))


def test_landscape_seeds_are_its_repeats_at_theta_0_and_the_best_point(tmp_path, monkeypatch, capsys):
    # --seeds was accepted and ignored: θ = 0 and the best point took 3 seeds whatever it said
    import layoutwarp.experiments.landscape as landscape

    asked = []
    monkeypatch.setattr(landscape, "run_landscape", lambda *a, **kw: asked.append(kw["repeats"]) or {})
    monkeypatch.setattr(landscape, "landscape_table", lambda summary: "")
    argv = ["landscape", "mnist", "--quick", "--family", "rect", "--out", str(tmp_path / "l")]
    assert main(argv) == 0 and main([*argv, "--seeds", "2"]) == 0
    assert asked == [3, 2]


@pytest.mark.parametrize("command", ["study", "landscape"])
def test_a_folder_of_the_other_kind_is_refused_before_any_run_trains(command, tmp_path, monkeypatch, capsys):
    # study --out LANDSCAPE trained a run into the landscape's folder before refusing it (and
    # the landscape then refused its own folder); the reverse trained 13 points
    import layoutwarp.experiments.landscape as landscape
    import layoutwarp.experiments.study as study
    from layoutwarp.experiments.runs import run_name

    trained = []
    for module in (study, landscape):
        monkeypatch.setattr(module, "train_run", lambda *a, **kw: trained.append(a) or ({}, None))
    runs = tmp_path / "runs"
    runs.mkdir()
    record = {"family": "rect", "size_hw": [3, 3], "seed": 0, "theta_point": [0.0, 0.0], "tag": ""}
    other = point_name("rect", (3, 3), (0.0, 0.0), 0) if command == "study" else run_name("rect", (3, 3), 0)
    (runs / f"{other}.json").write_text(json.dumps(record))
    extra = ["--family", "rect"] if command == "landscape" else []
    assert main([command, "mnist", "--quick", *extra, "--out", str(tmp_path)]) == 2
    assert f"{other}.json is no run of a {command}" in capsys.readouterr().err
    assert trained == [] and sorted(p.name for p in runs.iterdir()) == [f"{other}.json"]


def test_a_landscape_summary_reads_its_own_family_and_size_alone(tmp_path):
    # a curv landscape's folder resumed as a rect one (the settings match) summarised curv's
    # scores as rect's: the records were taken by θ and tag alone
    from layoutwarp.experiments.landscape import summarise_landscape
    from layoutwarp.experiments.tasks import get_task

    task, grid = get_task("mnist"), [*grid_points(2, -0.5, 0.5), (0.0, 0.0)]
    (tmp_path / "runs").mkdir()
    for family, size, base in (("curv", (3, 3), 10.0), ("rect", (3, 3), 50.0), ("rect", (4, 4), 90.0)):
        for k, theta in enumerate(grid):
            for seed in (0, 1, 2) if theta == (0.0, 0.0) else (0,):
                rec = {"family": family, "size_hw": list(size), "seed": seed, "theta_point": list(theta)}
                rec |= {"tag": "", "scores": {"accuracy": base + k + seed}}
                name = point_name(family, size, theta, seed)
                (tmp_path / "runs" / f"{name}.json").write_text(json.dumps(rec))
    summary = summarise_landscape(task, tmp_path, "rect", (3, 3), grid, None)
    assert summary["values"] == [50.0, 51.0, 52.0, 53.0, 54.0]
    assert summary["uniform"]["n"] == 3 and summary["uniform"]["mean"] == 55.0
