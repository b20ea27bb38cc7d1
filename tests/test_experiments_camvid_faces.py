"""CamVid segmentation and UTKFace attributes: data, metrics, training mechanics, quick runs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from conftest import SAMPLES

import layoutwarp as lw
from layoutwarp.cli import main
from layoutwarp.experiments.camvid import SegNet, median_frequency_weights
from layoutwarp.experiments.data import AGE_GROUPS, age_group, load_camvid, load_faces
from layoutwarp.experiments.faces import FaceNet, split_faces
from layoutwarp.experiments.runs import RunOptions, train_run
from layoutwarp.experiments.segmentation import segmentation_scores
from layoutwarp.experiments.tasks import TASKS

CAMVID = TASKS["camvid"]


def camvid_run(family, options, seed=0):
    """One CamVid run on two bundled training frames, scored on one validation frame."""
    data = CAMVID.load(SAMPLES / "camvid", limit=2)
    data.report = tuple(a[:1] for a in data.report)
    return train_run(CAMVID, data, family, (9, 12), seed, options)


def test_segmentation_scores_against_per_class_counts(gen):
    k = 5
    gt = torch.randint(0, k, (4000,), generator=gen).numpy()
    pred = np.where(
        torch.rand(4000, generator=gen).numpy() < 0.6, gt, torch.randint(0, k, (4000,), generator=gen).numpy()
    )
    pred[gt == 4] = 0  # class 4 never predicted: IoU 0
    conf = np.zeros((k, k), np.int64)
    np.add.at(conf, (gt, pred), 1)
    s = segmentation_scores(conf)
    for c in range(k):
        inter = np.sum((gt == c) & (pred == c))
        union = np.sum((gt == c) | (pred == c))
        assert abs(s["iou"][c] - 100 * inter / union) < 1e-9
    assert abs(s["miou"] - np.mean(s["iou"])) < 1e-9 and s["iou"][4] == 0
    assert abs(s["pixel_accuracy"] - 100 * np.mean(gt == pred)) < 1e-9
    conf[3] = conf[:, 3] = 0  # a class absent from ground truth and predictions is left out
    assert segmentation_scores(conf)["iou"][3] is None


def test_age_groups_cover_all_ages():
    ages = np.array([1, 14, 15, 29, 30, 44, 45, 59, 60, 110])
    assert age_group(ages).tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    assert len(AGE_GROUPS) == 5


def test_loaders_read_the_bundled_samples():
    imgs, labels = load_camvid(SAMPLES / "camvid", "val")
    assert imgs.shape[1:] == (360, 480, 3) and labels.shape == imgs.shape[:3] and labels.max() <= 11
    faces = load_faces(SAMPLES / "faces" / "utkface_subset", limit=10)
    assert faces["images"].shape == (10, 200, 200, 3)
    assert set(faces) == {"images", "gender", "age_group", "race"} and faces["race"].max() <= 4


def test_networks_shapes_and_theta_gradient():
    seg = SegNet("curv", (23, 31), tol=1e-3)
    x = torch.rand(2, 3, 90, 120)
    out = seg(x)
    assert out.shape == (2, 11, 23, 31)
    y = torch.randint(0, 12, (2, 90, 120))
    lw.backwarp_cross_entropy(out, y, seg.sensor.layout, ignore_index=11).backward()
    g = seg.sensor.layout.rho.grad
    assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0
    face = FaceNet("rect", (8, 8))
    heads = face(torch.rand(3, 3, 64, 64))
    assert {k: v.shape for k, v in heads.items()} == {"gender": (3, 2), "age_group": (3, 5), "race": (3, 5)}


def test_theta_stays_frozen_during_freeze_epochs():
    opts = {"epochs": 2, "batch_size": 2, "progress": False}
    frozen, _ = camvid_run("rect", RunOptions.of(CAMVID.defaults, freeze_epochs=1, **opts))
    learned, _ = camvid_run("rect", RunOptions.of(CAMVID.defaults, freeze_epochs=0, **opts))
    assert frozen.theta_history[1] == [0.0, 0.0] and frozen.theta_history[2] != [0.0, 0.0]
    assert any(abs(v) > 1e-4 for v in learned.theta_history[1])
    # frozen epochs are capped at epochs - 1: θ always trains
    capped, _ = camvid_run("rect", RunOptions.of(CAMVID.defaults, freeze_epochs=5, **opts))
    assert capped.theta_history[1] == [0.0, 0.0] and capped.theta != [0.0, 0.0]
    assert 0 <= frozen.scores["miou"] <= 100


def test_median_frequency_weights_against_a_direct_count(gen):
    k, void = 6, 6
    labels = torch.randint(0, k + 1, (5, 13, 17), generator=gen).numpy()
    labels[labels == 2] = 0
    labels[3:, :2, :3] = 2  # class 2: 6 pixels in each of the last two images
    labels[labels == 4] = 1  # class 4 absent
    w = median_frequency_weights(labels, k, ignore=void)
    freq = {}
    for c in range(k):
        pixels = images_pixels = 0
        for lab in labels:
            n = int((lab == c).sum())
            if n:
                pixels += n
                images_pixels += int((lab != void).sum())
        if pixels:
            freq[c] = pixels / images_pixels
    med = float(np.median(list(freq.values())))
    for c in range(k):
        assert abs(w[c] - (med / freq[c] if c in freq else 0.0)) < 1e-6
    assert w[4] == 0 and w[2] > 1  # rare class up-weighted


def test_class_weighted_camvid_training_differs_from_plain():
    def run(cw):
        opts = RunOptions.of(
            CAMVID.defaults, epochs=1, batch_size=2, progress=False, task_options={"class_weights": cw}
        )
        return camvid_run("uniform", opts, seed=3)[1]

    p0, p1, p2 = (
        torch.cat([p.flatten() for p in run(cw).parameters()]) for cw in ("none", "median", "median")
    )
    assert torch.equal(p1, p2) and not torch.allclose(p0, p1)  # deterministic; the weights act


def test_faces_split_is_fixed_disjoint_and_a_fifth(gen):
    n = int(torch.randint(10, 200, (), generator=gen))
    faces = {"images": np.arange(n)[:, None], "gender": np.arange(n) % 2}
    train, test = split_faces(faces)
    ids = np.concatenate([train["images"][:, 0], test["images"][:, 0]])
    assert sorted(ids.tolist()) == list(range(n)) and len(test["images"]) == max(1, round(0.2 * n))
    assert np.array_equal(split_faces(faces)[1]["images"], test["images"])  # the same every time
    assert np.array_equal(test["gender"], test["images"][:, 0] % 2)  # every array split alike


@pytest.mark.slow
def test_quick_commands_write_results(tmp_path):
    assert main(["train", "camvid", "--quick", "--no-progress", "--out", str(tmp_path / "c")]) == 0
    res = json.loads((tmp_path / "c" / "results.json").read_text())
    assert [s["family"] for s in res["summary"]] == ["uniform", "curv", "rect"]
    assert (tmp_path / "c" / "camvid_layouts.png").stat().st_size > 10_000
    assert (tmp_path / "c" / "layout_curv_48x36.json").exists()
    assert main(["train", "faces", "--quick", "--no-progress", "--out", str(tmp_path / "f")]) == 0
    res = json.loads((tmp_path / "f" / "results.json").read_text())
    assert [(s["family"], s["size_hw"]) for s in res["summary"]] == [("uniform", [8, 8]), ("rect", [8, 8])]
    assert set(res["summary"][1]["scores"]) == {"gender", "age_group", "race", "mean"}
    assert (tmp_path / "f" / "faces_layouts.png").exists()


@pytest.mark.slow
@pytest.mark.parametrize("task", ["mnist", "camvid", "faces"])
def test_quick_runs_train_the_new_families(task, tmp_path):
    argv = ["train", task, "--quick", "--epochs", "1", "--no-progress", "--out", str(tmp_path)]
    families = ["spline", "grid", "fovea"] if task == "mnist" else ["spline"]
    assert main([*argv, *(a for f in families for a in ("--family", f))]) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert [s["family"] for s in res["summary"]] == families
    for s in res["summary"]:
        assert any(abs(v) > 1e-4 for v in s["theta_mean"])  # the layout learned
    size = {"mnist": "4x4", "camvid": "48x36", "faces": "8x8"}[task]
    for family in families:
        layout, _ = lw.load_layout(tmp_path / f"layout_{family}_{size}.json")
        assert layout.family == family and layout.check_foldover().ok
