"""Saved models, `evaluate`, and the pixel-budget study (equivalent pixel counts, resuming)."""

from __future__ import annotations

import json
import math

import pytest
import torch
from conftest import SAMPLES

from layoutwarp.cli import main
from layoutwarp.experiments.models import FORMAT, load_model
from layoutwarp.experiments.study import PLANS, equivalent_pixels, study_table, summarise_study


def test_equivalent_pixels_interpolates_in_log_pixels():
    curve = [(16, 70.0), (4, 50.0), (64, 90.0)]
    assert equivalent_pixels(curve, 60.0) == (pytest.approx(8.0), "=")  # halfway in log: sqrt(4 * 16)
    assert equivalent_pixels(curve, 85.0) == (pytest.approx(16 * 4**0.75), "=")
    assert equivalent_pixels(curve, 95.0) == (64.0, ">")  # beyond the curve: a bound
    assert equivalent_pixels(curve, 40.0) == (4.0, "<")
    # a noisy, non-monotone curve is read through its running maximum
    assert equivalent_pixels([(4, 50.0), (9, 72.0), (16, 70.0), (25, 80.0)], 71.0)[0] == pytest.approx(
        math.exp(math.log(4) + (21 / 22) * (math.log(9) - math.log(4)))
    )


def test_summary_gives_saving_factors_with_intervals():
    plan = PLANS["mnist"]
    recs = [
        {"family": "uniform", "size_hw": [s, s], "seed": k, "scores": {"accuracy": 40 + 10 * s + k}}
        for s in (2, 4, 8)
        for k in (0, 1)
    ]
    recs += [
        {"family": "curv", "size_hw": [4, 4], "seed": k, "scores": {"accuracy": 70.5 + 2 * k}} for k in (0, 1)
    ]
    summary = summarise_study("mnist", plan, recs)
    row = next(r for r in summary["rows"] if r["family"] == "curv")
    # uniform: 60.5 at 4 px, 80.5 at 16 px; curv 71.5 ± 1.41 at 16 px → log-interpolated
    t = (71.5 - 60.5) / 20
    assert row["equivalent_pixels"] == pytest.approx(math.exp(math.log(4) + t * math.log(4)))
    assert row["saving"] < 1  # this made-up curv is worse than uniform at equal pixels
    assert row["saving"] == pytest.approx(row["equivalent_pixels"] / 16)
    lo, hi = row["saving_interval"]
    assert lo < row["saving"] < hi
    assert "| curv | 4x4 | 16 |" in study_table(summary)


def test_model_files_refuse_other_tasks_and_formats(tmp_path):
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="not a readable layoutwarp model file"):
        load_model(tmp_path / "junk.pt")
    torch.save({"format": "layoutwarp.model/9", "task": "mnist"}, tmp_path / "new.pt")
    with pytest.raises(ValueError, match=f"format 'layoutwarp.model/9'; this layoutwarp reads '{FORMAT}'"):
        load_model(tmp_path / "new.pt")
    with pytest.raises(ValueError, match="no such model file"):
        load_model(tmp_path / "missing.pt")


@pytest.mark.slow
def test_quick_study_resumes_and_its_models_evaluate(tmp_path, capsys):
    out = tmp_path / "s"
    argv = ["study", "mnist", "--quick", "--no-progress", "--out", str(out)]
    assert main(argv) == 0
    summary = json.loads((out / "study.json").read_text())
    assert summary["runs"] == 4  # uniform at 2x2 and 3x3, rect and density at 3x3
    assert {r["family"] for r in summary["rows"]} == {"uniform", "rect", "density"}
    assert (out / "study.md").read_text().startswith("| family |")
    assert (out / "study_mnist.png").stat().st_size > 5000
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "runs").iterdir()}
    (out / "runs" / "rect_3x3_seed0.json").unlink()  # as if killed during this run
    capsys.readouterr()
    assert main(argv) == 0
    assert "4 runs, 3 already done" in capsys.readouterr().out
    for name, stamp in stamps.items():  # finished runs were not repeated
        if name != "rect_3x3_seed0.json":
            assert (out / "runs" / name).stat().st_mtime_ns == stamp
    # a saved model scores the same through `evaluate`
    record = json.loads((out / "runs" / "density_3x3_seed0.json").read_text())
    capsys.readouterr()
    model = out / "models" / "density_3x3_seed0.pt"
    assert main(["evaluate", "mnist", "--model", str(model), "--data", str(SAMPLES / "mnist")]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["accuracy"] == pytest.approx(record["scores"]["accuracy"], abs=1e-9)
    assert scores["n"] == 1000 and scores["layout"]["family"] == "grid"
    assert main(["evaluate", "camvid", "--model", str(model), "--data", str(SAMPLES / "camvid")]) == 2
    assert "a 'mnist' model, not a 'camvid' model" in capsys.readouterr().err


@pytest.mark.slow
def test_train_saves_camvid_models_that_evaluate_to_the_reported_scores(tmp_path, capsys):
    out = tmp_path / "c"
    argv = ["train", "camvid", "--quick", "--family", "spline", "--no-progress", "--out", str(out)]
    assert main(argv) == 0
    res = json.loads((out / "results.json").read_text())
    capsys.readouterr()
    model = out / "model_spline_48x36_seed0.pt"
    assert main(["evaluate", "camvid", "--model", str(model), "--data", str(SAMPLES / "camvid")]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["miou"] == pytest.approx(res["runs"][0]["scores"]["miou"], abs=1e-9)
    assert len(scores["iou"]) == 11 and scores["split"] is None and scores["n"] == 3
