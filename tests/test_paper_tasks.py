"""The paper's own experiments as tasks: Cityscapes (the official label table, the folder layout)
and CelebA (the attribute and partition lists), their bundled synthetic samples, and the
ResNet-18 network of the faces task."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from conftest import SAMPLES, SHARED

from layoutwarp.cli import main
from layoutwarp.experiments.celeba import read_attributes, read_celeba, read_partition
from layoutwarp.experiments.cityscapes import CLASSES, IGNORE, find_pairs, read_pairs, train_ids
from layoutwarp.experiments.faces import FaceResNet
from layoutwarp.experiments.models import load_model
from layoutwarp.experiments.tasks import get_task

#: cityscapesScripts' labels.py (Cordts et al.): name, id, trainId, as published.
OFFICIAL = [
    ('unlabeled', 0, 255), ('ego vehicle', 1, 255), ('rectification border', 2, 255),
    ('out of roi', 3, 255), ('static', 4, 255), ('dynamic', 5, 255), ('ground', 6, 255), ('road', 7, 0),
    ('sidewalk', 8, 1), ('parking', 9, 255), ('rail track', 10, 255), ('building', 11, 2),
    ('wall', 12, 3), ('fence', 13, 4), ('guard rail', 14, 255), ('bridge', 15, 255), ('tunnel', 16, 255),
    ('pole', 17, 5), ('polegroup', 18, 255), ('traffic light', 19, 6), ('traffic sign', 20, 7),
    ('vegetation', 21, 8), ('terrain', 22, 9), ('sky', 23, 10), ('person', 24, 11), ('rider', 25, 12),
    ('car', 26, 13), ('truck', 27, 14), ('bus', 28, 15), ('caravan', 29, 255), ('trailer', 30, 255),
    ('train', 31, 16), ('motorcycle', 32, 17), ('bicycle', 33, 18),
]  # fmt: skip


def test_label_ids_map_to_the_official_train_ids_and_everything_else_is_ignored(seed):
    expected = np.full(256, 255, np.uint8)
    for _, label_id, train_id in OFFICIAL:
        expected[label_id] = train_id
    ids = np.arange(256, dtype=np.uint8)
    assert np.array_equal(train_ids(ids), expected) and IGNORE == 255
    names = {train_id: name for name, _, train_id in OFFICIAL if train_id != 255}
    assert CLASSES == tuple(names[k] for k in range(19))
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 256, (5, 7), dtype=np.uint8)
    assert np.array_equal(train_ids(img), expected[img])  # any shape, elementwise


def test_the_bundled_cityscapes_samples_are_in_the_real_layout_and_encodings():
    root = SAMPLES / "cityscapes"
    train, val = find_pairs(root, "train"), find_pairs(root, "val")
    assert len(train) == 3 and len(val) == 2
    image, label = train[0]
    assert image.relative_to(root).parts[:3] == ("leftImg8bit", "train", "aachen")
    assert image.name.endswith("_leftImg8bit.png") and label.name.endswith("_gtFine_labelIds.png")
    x, y = read_pairs(val)
    assert x.shape == (2, 3, 1024, 2048) and x.dtype == torch.uint8 and y.shape == (2, 1024, 2048)
    present = set(torch.unique(y).tolist())
    assert {0, 1, 2, 5, 7, 10, 11, 13} <= present <= {*range(19), IGNORE}  # road .. car, and void


def test_a_cityscapes_image_without_its_label_file_is_named(tmp_path):
    folder = tmp_path / "leftImg8bit" / "val" / "bonn"
    folder.mkdir(parents=True)
    (folder / "bonn_000000_000019_leftImg8bit.png").write_bytes(b"")
    with pytest.raises(
        FileNotFoundError, match=r"bonn_000000_000019_leftImg8bit\.png' has no label file .*gtFine"
    ):
        find_pairs(tmp_path, "val")
    with pytest.raises(FileNotFoundError, match="no Cityscapes train images under"):
        find_pairs(tmp_path, "train")


def test_celeba_lists_parse_as_published(tmp_path):
    names, files, values = read_attributes(SAMPLES / "celeba" / "list_attr_celeba.txt")
    assert len(names) == 40 and names[0] == "5_o_Clock_Shadow" and names[-1] == "Young"
    assert files[:2] == ["000001.jpg", "000002.jpg"] and values.shape == (24, 40)
    assert set(np.unique(values)) <= {0, 1}
    partition = read_partition(SAMPLES / "celeba" / "list_eval_partition.txt")
    assert [sum(v == k for v in partition.values()) for k in (0, 1, 2)] == [16, 4, 4]
    test = read_celeba(SAMPLES / "celeba", "test")
    assert len(test) == 4 and test.images(slice(0, 2)).shape == (2, 3, 218, 178)
    bad = tmp_path / "list_attr_celeba.txt"
    bad.write_text("1\nA B\n000001.jpg 1 0\n")
    with pytest.raises(ValueError, match=r"list_attr_celeba\.txt:3: expected a file name and 2 values of ±1"):
        read_attributes(bad)
    with pytest.raises(ValueError, match="split must be one of train, val, test; got 'dev'"):
        read_celeba(SAMPLES / "celeba", "dev")


@pytest.mark.skipif(not (SHARED / "faces" / "celeba_sample").is_dir(), reason="needs ../shared/data")
def test_the_real_celeba_attribute_file_parses_to_its_published_first_row():
    names, files, values = read_attributes(SHARED / "faces" / "celeba_sample" / "list_attr_celeba.txt")
    first = (
        "-1  1  1 -1 -1 -1 -1 -1 -1 -1 -1  1 -1 -1 -1 -1 -1 -1  1  1"
        " -1  1 -1 -1  1 -1 -1  1 -1 -1 -1  1  1 -1  1 -1  1 -1 -1  1"
    )
    assert files[0] == "000001.jpg" and len(files) == 10
    assert values[0].tolist() == [int(v == "1") for v in first.split()]
    assert names == read_attributes(SAMPLES / "celeba" / "list_attr_celeba.txt")[0]  # the same 40 names


def test_the_faces_resnet18_gives_each_attributes_logits():
    task = get_task("faces").with_net("resnet18")
    net = task.network("rect", (8, 8), learn=True)
    assert isinstance(net, FaceResNet) and task.defaults.batch_size == 64 and task.defaults.lr == 1e-3
    out = net(torch.rand(2, 3, 40, 40))
    assert {k: tuple(v.shape) for k, v in out.items()} == {
        "gender": (2, 2),
        "age_group": (2, 5),
        "race": (2, 5),
    }
    sum(v.sum() for v in out.values()).backward()
    assert any(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in net.sensor.parameters())


@pytest.mark.slow
@pytest.mark.parametrize("task, metric", [("celeba", "mean"), ("cityscapes", "miou")])
@pytest.mark.heavy
def test_quick_runs_of_the_paper_tasks_write_models_that_evaluate(task, metric, tmp_path, capsys):
    out = tmp_path / task
    argv = ["train", task, "--quick", "--family", "rect", "--no-progress", "--out", str(out)]
    assert main(argv) == 0
    res = json.loads((out / "results.json").read_text())
    (row,) = res["summary"]
    size = {"celeba": "8x8", "cityscapes": "129x65"}[task]
    assert row["family"] == "rect" and f"{row['size_hw'][1]}x{row['size_hw'][0]}" == size
    model_file = out / f"model_rect_{size}_seed0.pt"
    model, _ = load_model(model_file, task)
    assert type(model) is type(get_task(task).network("rect", (8, 8)))  # the task's network, rebuilt
    capsys.readouterr()
    assert main(["evaluate", task, "--model", str(model_file), "--data", str(SAMPLES / task)]) == 0
    scored = json.loads(capsys.readouterr().out)
    assert scored[metric] == pytest.approx(res["runs"][0]["scores"][metric], abs=1e-9)
