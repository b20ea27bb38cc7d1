"""Saved models, `evaluate`, and the pixel-budget study (equivalent pixel counts, resuming)."""

from __future__ import annotations

import json
import math

import pytest
import torch
from conftest import ROOT, SAMPLES

from layoutwarp.cli import main
from layoutwarp.experiments.mnist import MnistNet
from layoutwarp.experiments.models import FORMAT, load_model, save_model
from layoutwarp.experiments.study import equivalent_pixels, study_table, summarise_study, write_summary
from layoutwarp.experiments.tasks import TASKS
from layoutwarp.layoutfile import load_layout

MNIST = TASKS["mnist"]


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
    recs = [
        {"family": "uniform", "size_hw": [s, s], "seed": k, "scores": {"accuracy": 40 + 10 * s + k}}
        for s in (2, 4, 8)
        for k in (0, 1)
    ]
    recs += [
        {"family": "curv", "size_hw": [4, 4], "seed": k, "scores": {"accuracy": 70.5 + 2 * k}} for k in (0, 1)
    ]
    summary = summarise_study(MNIST, recs)
    row = next(r for r in summary["rows"] if r["family"] == "curv")
    # uniform: 60.5 at 4 px, 80.5 at 16 px; curv 71.5 ± 1.41 at 16 px → log-interpolated
    t = (71.5 - 60.5) / 20
    assert row["equivalent_pixels"] == pytest.approx(math.exp(math.log(4) + t * math.log(4)))
    assert row["saving"] < 1  # this made-up curv is worse than uniform at equal pixels
    assert row["saving"] == pytest.approx(row["equivalent_pixels"] / 16)
    lo, hi = row["saving_interval"]
    assert lo < row["saving"] < hi
    assert "| curv | 4x4 | 16 |" in study_table(summary)
    # an end of the interval past the uniform curve is a bound, marked as the saving's own is (the
    # mark was dropped: "> 1.00x [1.00, 1.00]", an upper end read as a value)
    recs += [
        {"family": "rect", "size_hw": [4, 4], "seed": k, "scores": {"accuracy": 119.0 + 4 * k}}
        for k in (0, 1)
    ]
    summary = summarise_study(MNIST, recs)
    row = next(r for r in summary["rows"] if r["family"] == "rect")  # 121 ± 2.83: past 120.5, its top end too
    assert row["interval_bounds"] == ["=", ">"] and row["bound"] == ">"
    lo, hi = row["saving_interval"]
    assert f"| > 64 | > 4.00x [{lo:.2f}, > 4.00] |" in study_table(summary)


def test_model_files_refuse_other_tasks_and_formats(tmp_path):
    (tmp_path / "junk.pt").write_bytes(b"not a model")
    with pytest.raises(
        ValueError, match=r"junk.pt: not a readable layoutwarp model file \(torch.load cannot read it\)$"
    ):
        load_model(tmp_path / "junk.pt")
    torch.save({"format": "layoutwarp.model/9", "task": "mnist"}, tmp_path / "new.pt")
    with pytest.raises(
        ValueError, match=f"format 'layoutwarp.model/9'; this layoutwarp reads .* and '{FORMAT}'"
    ):
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
    assert list((out / "checkpoints").iterdir()) == []  # each run's checkpoint goes once it is kept
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "runs").iterdir()}
    (out / "runs" / "rect_3x3_seed0.json").unlink()  # as if killed during this run
    capsys.readouterr()
    assert main(argv) == 0
    assert "4 runs, 3 already done" in capsys.readouterr().out
    for name, stamp in stamps.items():  # finished runs were not repeated
        if name != "rect_3x3_seed0.json":
            assert (out / "runs" / name).stat().st_mtime_ns == stamp
    # resumed with other training settings, its curves would mix two trainings: refused, untouched
    before = {p.name: p.stat().st_mtime_ns for p in (out / "runs").iterdir()}
    assert main([*argv, "--epochs", "2"]) == 2
    assert "argument --out: " in (err := capsys.readouterr().err) and "trained with epochs 1, not 2" in err
    assert {p.name: p.stat().st_mtime_ns for p in (out / "runs").iterdir()} == before
    # a saved model scores the same through `evaluate`
    record = json.loads((out / "runs" / "density_3x3_seed0.json").read_text())
    capsys.readouterr()
    model = out / "models" / "density_3x3_seed0.pt"
    assert main(["evaluate", "mnist", "--model", str(model), "--data", str(SAMPLES / "mnist")]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["accuracy"] == pytest.approx(record["scores"]["accuracy"], abs=1e-9)
    assert scores["n"] == 1000 and scores["layout"]["family"] == "grid"
    # every run integrates at the plan's tolerance, not the experiment's (changed) default
    assert load_model(model)[1]["sensor"]["tol"] == MNIST.study.tol != MNIST.defaults.tol
    assert main(["evaluate", "camvid", "--model", str(model), "--data", str(SAMPLES / "camvid")]) == 2
    assert "a 'mnist' model, not a 'camvid' model" in capsys.readouterr().err
    # shipping: results, every learned layout, the best model per family and learned size
    ship = tmp_path / "ship"
    assert main([*argv, "--ship", str(ship)]) == 0
    assert json.loads((ship / "study.json").read_text())["rows"] == summary["rows"]
    assert sorted(p.name for p in (ship / "layouts").iterdir()) == [
        "density_3x3_seed0.json",
        "rect_3x3_seed0.json",
    ]
    layout, info = load_layout(ship / "layouts" / "rect_3x3_seed0.json")
    assert layout.family == "rect" and info["size_hw"] == [3, 3]
    assert sorted(p.name for p in (ship / "models").iterdir()) == [
        f"{f}_3x3_seed0.pt" for f in ("density", "rect", "uniform")
    ]
    assert (ship / "layouts_mnist.png").stat().st_size > 5000
    capsys.readouterr()
    assert (
        main(
            [
                "evaluate",
                "mnist",
                "--model",
                str(ship / "models" / "rect_3x3_seed0.pt"),
                "--data",
                str(SAMPLES / "mnist"),
            ]
        )
        == 0
    )
    half = json.loads(capsys.readouterr().out)["accuracy"]
    full = json.loads((out / "runs" / "rect_3x3_seed0.json").read_text())["scores"]["accuracy"]
    assert half == pytest.approx(full, abs=0.5)  # float16 weights: at most a few of 1000 digits change
    # without models (a network too large to commit): results, layouts and figures alone
    bare = tmp_path / "bare"
    assert main([*argv, "--ship", str(bare), "--weights", "none"]) == 0
    assert sorted(p.name for p in bare.iterdir()) == sorted(
        p.name for p in ship.iterdir() if p.name not in ("models", "samples_scores.json")
    )
    assert (bare / "layouts" / "rect_3x3_seed0.json").read_bytes() == (
        ship / "layouts" / "rect_3x3_seed0.json"
    ).read_bytes()
    assert main(["study", "mnist", "--quick", "--out", str(tmp_path / "none"), "--ship", str(ship)]) == 2
    assert "no study in" in capsys.readouterr().err


def test_a_study_or_landscape_resumes_only_with_the_settings_its_runs_trained_with(tmp_path):
    from dataclasses import replace

    from layoutwarp.checks import ArgumentError
    from layoutwarp.experiments.runs import RunOptions, check_resumed, keep_settings

    opts, out = RunOptions.of(MNIST.defaults, epochs=3), tmp_path / "s"
    check_resumed(out, replace(opts, epochs=5), "study")  # nothing there: any settings
    keep_settings(out, opts)  # the first run begins
    assert json.loads((out / "settings.json").read_text())["training"]["epochs"] == 3
    check_resumed(out, replace(opts, epochs=5), "study")  # no run finished or stopped: nothing mixes
    (out / "checkpoints").mkdir()
    (out / "checkpoints" / "rect_3x3_seed0.pt").write_bytes(b"")  # a stopped run
    with pytest.raises(ArgumentError, match=r"s holds a study whose runs trained with epochs 3, not 5: use"):
        check_resumed(out, replace(opts, epochs=5), "study")
    check_resumed(out, replace(opts, device="cuda"), "study")  # where the runs train may change
    with pytest.raises(ArgumentError, match=rf"trained with tol {opts.sensor['tol']!r}, not 0.001"):
        check_resumed(out, replace(opts, sensor=opts.sensor | {"tol": 1e-3}), "study")
    # a sensor option the runs did not have (sensor physics added on resuming): refused too, and
    # the reverse (it was accepted: the folder's record lacked the key, so it was not compared)
    physics = {"physics": {"photons_per_um2": 5.0}}
    with pytest.raises(ArgumentError, match=r"trained with physics None, not \{'photons_per_um2': 5.0\}"):
        check_resumed(out, replace(opts, sensor=opts.sensor | physics), "study")
    keep_settings(out, replace(opts, epochs=5))  # a folder's settings are written once
    assert json.loads((out / "settings.json").read_text())["training"]["epochs"] == 3
    # a folder of an earlier version (no settings.json): its first finished run's
    old = tmp_path / "old"
    (old / "runs").mkdir(parents=True)
    (old / "runs" / "a.json").write_text(json.dumps({"training": opts.record(), "sensor": opts.sensor}))
    with pytest.raises(ArgumentError, match=r"a landscape whose runs trained with epochs 3, not 4"):
        check_resumed(old, replace(opts, epochs=4), "landscape")
    check_resumed(old, opts, "landscape")
    # a setting an earlier version did not record is not held against the folder
    rec = json.loads((old / "runs" / "a.json").read_text())
    del rec["training"]["weight_decay"]
    (old / "runs" / "a.json").write_text(json.dumps(rec))
    check_resumed(old, replace(opts, weight_decay=0.5), "landscape")
    # an earlier version's stopped first run: a checkpoint, no run, no settings: nothing to hold
    older = tmp_path / "older"
    (older / "checkpoints").mkdir(parents=True)
    (older / "checkpoints" / "x.pt").write_bytes(b"")
    check_resumed(older, opts, "study")
    # a first run stopped before its first checkpoint leaves settings that do not bind: the next
    # first run writes its own, and its resumption is held to them
    fresh = tmp_path / "fresh"
    keep_settings(fresh, replace(opts, epochs=7))  # stopped before anything was kept
    check_resumed(fresh, opts, "study")
    keep_settings(fresh, opts)
    (fresh / "runs").mkdir()
    (fresh / "runs" / "rect_3x3_seed0.json").write_text("{}")
    check_resumed(fresh, opts, "study")
    with pytest.raises(ArgumentError, match="trained with epochs 3, not 7"):
        check_resumed(fresh, replace(opts, epochs=7), "study")


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
    assert len(scores["iou"]) == 11 and scores["split"] == "val" and scores["n"] == 3
    assert scores["units"] == "percent" and res["units"] == "percent"


def test_camvid_summary_has_per_class_iou_changes_and_counts_planned_runs(gen):
    rng = gen
    iou = {f: torch.rand(3, 11, generator=rng).mul(100).tolist() for f in ("uniform", "curv")}
    iou["curv"][0][6] = None  # a class absent from one seed's val split: left out of its mean
    recs = [
        {"family": f, "size_hw": [36, 48], "seed": k, "scores": {"miou": 50.0 + k, "iou": iou[f][k]}}
        for f in ("uniform", "curv")
        for k in range(3)
    ]
    recs += [
        {
            "family": "uniform",
            "size_hw": [18, 24],
            "seed": 0,
            "scores": {"miou": 40.0, "iou": iou["uniform"][0]},
        }
    ]
    summary = summarise_study(TASKS["camvid"], recs) | {"planned": 51}
    curv = next(r for r in summary["rows"] if r["family"] == "curv")
    uni = next(r for r in summary["rows"] if r["family"] == "uniform" and r["pixels"] == 36 * 48)
    assert curv["iou"][6] == pytest.approx((iou["curv"][1][6] + iou["curv"][2][6]) / 2)
    assert uni["iou"][0] == pytest.approx(sum(v[0] for v in iou["uniform"]) / 3)
    assert curv["scores"] == {"miou": 51.0}  # every scalar score, averaged
    table = study_table(summary)
    assert "7 of 51 planned runs finished so far." in table
    sky = curv["iou"][0] - uni["iou"][0]
    assert f"| curv | 48x36 | {sky:+.1f} |" in table


def test_a_one_size_study_keeps_each_seeds_score_and_draws_theta_over_the_epochs(tmp_path, gen):
    runs = tmp_path / "runs"
    runs.mkdir()
    scores = {}
    for f in ("uniform", "rect"):
        for k in (2, 0, 1):  # written out of order: the summary lists the seeds in order
            miou = float(torch.rand((), generator=gen)) * 100
            scores[f, k] = miou
            hist = torch.rand(6, 2, generator=gen).tolist() if f == "rect" else [[]] * 6
            rec = {"family": f, "size_hw": [72, 96], "seed": k, "scores": {"miou": miou}}
            rec |= {"theta": hist[-1], "theta_history": hist, "area_ratio_history": [1.0 + k] * 6}
            (runs / f"{f}_96x72_seed{k}.json").write_text(json.dumps(rec))
    summary = write_summary(TASKS["camvid"], tmp_path, planned=9)
    for row in summary["rows"]:
        assert row["values"] == [scores[row["family"], k] for k in range(3)]
    # rect against uniform: the difference of the means and Welch's two-sided p, by its formula
    from scipy.stats import t as student_t

    (u,), (r,) = ([x for x in summary["rows"] if x["family"] == f] for f in ("uniform", "rect"))
    vu, vr = u["std"] ** 2 / 3, r["std"] ** 2 / 3
    t = (r["mean"] - u["mean"]) / math.sqrt(vu + vr)
    df = (vu + vr) ** 2 / (vu**2 / 2 + vr**2 / 2)
    assert r["vs_uniform"] == pytest.approx(r["mean"] - u["mean"], abs=1e-12)
    assert r["welch_p"] == pytest.approx(2 * student_t.sf(abs(t), df), rel=1e-9)
    assert f"| {r['vs_uniform']:+.2f} (p = {r['welch_p']:.2f}) |" in study_table(summary)
    assert json.loads((tmp_path / "study.json").read_text())["rows"] == summary["rows"]
    assert (tmp_path / "study_camvid.png").stat().st_size > 5000
    assert (tmp_path / "theta_camvid.png").stat().st_size > 5000
    # no learned θ, no θ figure
    (tmp_path / "uniform_only" / "runs").mkdir(parents=True)
    for k in range(2):
        name = f"uniform_96x72_seed{k}.json"
        (tmp_path / "uniform_only" / "runs" / name).write_text((runs / name).read_text())
    write_summary(TASKS["camvid"], tmp_path / "uniform_only")
    assert not (tmp_path / "uniform_only" / "theta_camvid.png").exists()


SHIPPED = sorted((ROOT / "examples" / "study").glob("*/models/*.pt"))
#: far above chance (MNIST 10 %, faces' majority classes about 48 % on average, CamVid a few %)
ABOVE = {"mnist": 60.0, "faces": 60.0, "camvid": 25.0}


def test_the_study_ships_models():
    assert {p.parents[1].name for p in SHIPPED} >= {"mnist", "faces", "camvid"}


@pytest.mark.slow
@pytest.mark.parametrize("path", SHIPPED, ids=[f"{p.parents[1].name}/{p.stem}" for p in SHIPPED])
def test_shipped_models_evaluate_on_the_bundled_samples(path, capsys):
    """``evaluate`` reproduces the scores recorded when the model was shipped, on the bundled
    slice (most bundled faces were training faces, so its scores are not the test's)."""
    task = json.loads((path.parents[1] / "study.json").read_text())["task"]  # folder names vary
    data = SAMPLES / {"mnist": "mnist", "camvid": "camvid", "faces": "faces/utkface_subset"}[task]
    assert main(["evaluate", task, "--model", str(path), "--data", str(data), "--device", "cpu"]) == 0
    scores = json.loads(capsys.readouterr().out)
    recorded = json.loads((path.parents[1] / "samples_scores.json").read_text())[path.name]
    metric = TASKS[task].metric
    assert scores[metric] == pytest.approx(recorded[metric], abs=1e-9)
    assert scores[metric] > ABOVE[task]


def test_model_weights_precisions_round_trip(tmp_path, gen):
    torch.manual_seed(int(torch.randint(0, 2**31, (), generator=gen)))
    net = MnistNet("curv", (4, 4), **MNIST.defaults.sensor())
    with torch.no_grad():
        net.sensor.layout.rho.copy_(torch.rand(2, generator=gen) - 0.5)
    x = torch.rand(32, 1, 28, 28, generator=gen)
    net.eval()
    with torch.no_grad():
        ref = net(x)
    sizes, formats = {}, {}
    for weights, rel in (("float32", 0.0), ("float16", 2e-3), ("int8", 3e-2)):
        path = save_model(
            tmp_path / f"{weights}.pt",
            "mnist",
            net,
            sensor=MNIST.defaults.sensor(),
            training={},
            weights=weights,
        )
        back = load_model(path, "mnist")[0]
        assert torch.equal(back.sensor.theta, net.sensor.theta)  # θ is never rounded
        with torch.no_grad():
            out = back(x)
        assert float((out - ref).norm() / ref.norm()) <= rel
        sizes[weights], formats[weights] = path.stat().st_size, torch.load(path, weights_only=True)["format"]
    assert formats == {"float32": "layoutwarp.model/1", "float16": "layoutwarp.model/1", "int8": FORMAT}
    assert sizes["int8"] < 0.3 * sizes["float32"] and sizes["float16"] < 0.55 * sizes["float32"]
    with pytest.raises(ValueError, match="weights must be one of 'float32', 'float16', 'int8'; got 'int4'"):
        save_model(tmp_path / "x.pt", "mnist", net, sensor={}, training={}, weights="int4")


def test_a_study_runs_seed_by_seed_so_a_stopped_one_has_every_configurations_first_seeds():
    from layoutwarp.experiments.protocols import StudyPlan
    from layoutwarp.experiments.study import study_runs

    plan = StudyPlan(uniform_sizes=((6, 8), (9, 12)), learned_sizes=((6, 8),), families=("rect", "curv"))
    runs = study_runs(plan, 3)
    expected = {("uniform", s, k) for s in plan.uniform_sizes for k in range(3)}
    expected |= {(f, (6, 8), k) for f in plan.families for k in range(3)}
    assert len(runs) == len(expected) and set(runs) == expected
    assert [k for _, _, k in runs] == sorted(k for _, _, k in runs)  # every seed 0 before any seed 1
    seed0 = [("uniform", (6, 8), 0), ("uniform", (9, 12), 0), ("rect", (6, 8), 0), ("curv", (6, 8), 0)]
    assert runs[: len(runs) // 3] == seed0  # within a seed: the uniform curve, then the learned layouts
    # uniform among the families: its learned size is a point of the uniform curve, planned once
    # (it was planned twice: a finished study said 2 of 3 planned runs, and every rerun 1 to do)
    uniform = study_runs(
        StudyPlan(uniform_sizes=((6, 8),), learned_sizes=((6, 8),), families=("uniform",)), 2
    )
    assert uniform == [("uniform", (6, 8), 0), ("uniform", (6, 8), 1)]


def test_study_takes_size_as_every_training_command_does(tmp_path, monkeypatch, capsys):
    # --size sets where every family is trained; the uniform curve gains those sizes
    import layoutwarp.experiments.study as study

    plans = []

    def fake_run_study(task, folder, out, *, plan, seeds, options):
        plans.append(plan)
        raise ValueError("stopped after the plan")  # the command ends in its one-line error

    monkeypatch.setattr(study, "run_study", fake_run_study)
    argv = ["study", "mnist", "--quick", "--out", str(tmp_path / "s"), "--no-progress"]
    assert main([*argv, "--size", "5x5", "--size", "2x3"]) == 2
    assert "stopped after the plan" in capsys.readouterr().err
    (plan,) = plans
    assert plan.learned_sizes == ((5, 5), (3, 2))
    quick_uniform = MNIST.study.uniform_sizes[:2]
    assert set(plan.uniform_sizes) == set(quick_uniform) | {(5, 5), (3, 2)}
    assert [h * w for h, w in plan.uniform_sizes] == sorted(h * w for h, w in plan.uniform_sizes)
    with pytest.raises(SystemExit) as info:  # argparse's own error
        main([*argv, "--size", "0x3"])
    assert info.value.code == 2 and "--size" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("family", "theta"), [("curv", (-0.8, -0.8)), ("elliptic", (0.8, -0.6)), ("rect", (0.3, 0.2))]
)
def test_a_runs_area_ratio_is_of_its_pixel_polygons_not_of_their_corners(family, theta):
    # every pixel's boundary sampled densely along φ, its area by shapely: the corners' quads
    # alone gave 5.30 for curv's 8.61 (the bulge of its pixels)
    import shapely

    from layoutwarp.experiments.runs import _area_ratios
    from layoutwarp.layouts import make_layout

    layout, n, s = (
        make_layout(family, theta, learn=True),
        4,
        torch.linspace(0, 1, 2001, dtype=torch.float64)[:-1],
    )
    g = torch.linspace(-1, 1, n + 1, dtype=torch.float64)
    areas = []
    for i in range(n):
        for j in range(n):
            (x0, x1), (y0, y1) = g[j : j + 2], g[i : i + 2]
            sides = [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]
            pts = torch.cat(
                [torch.stack([a[0] + (b[0] - a[0]) * s, a[1] + (b[1] - a[1]) * s], -1) for a, b in sides]
            )
            with torch.no_grad():
                areas.append(
                    shapely.Polygon(layout.phi(pts, torch.tensor(theta, dtype=torch.float64)).numpy()).area
                )
    ratios = _area_ratios(layout, (n, n), [theta, theta])  # the bound: each area within 1e-4
    assert ratios[0] == ratios[1] == pytest.approx(max(areas) / min(areas), rel=2e-4)
