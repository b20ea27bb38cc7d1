"""θ-landscapes: the grid, resuming, the learned θ rerun frozen, the reading."""

from __future__ import annotations

import json

import pytest

from layoutwarp.cli import main
from layoutwarp.experiments.landscape import grid_points, point_name


def test_grid_points_and_names():
    pts = grid_points(3, -0.8, 0.8)
    assert pts[0] == (-0.8, -0.8) and pts[4] == (0.0, 0.0) and pts[-1] == (0.8, 0.8) and len(pts) == 9
    assert point_name("curv", (4, 4), (0.5, -0.25), 2) == "curv_4x4_tx+0.5_ty-0.25_seed2"
    assert point_name("curv", (4, 4), (0.0, 0.0), 0, "learned") == "curv_4x4_tx+0_ty+0_learned_seed0"


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
