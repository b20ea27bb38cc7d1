"""Saved layouts, IDX reading, and the MNIST experiment's quick mode."""

from __future__ import annotations

import gzip
import json

import numpy as np
import pytest
import torch
from conftest import SAMPLES, SHARED, rand_theta

import layoutwarp as lw
from layoutwarp.cli import main
from layoutwarp.experiments.data import load_mnist, read_idx
from layoutwarp.layoutfile import load_layout, save_layout


@pytest.mark.parametrize("family", ["uniform", "rect", "curv"])
def test_layout_json_round_trip(family, gen, tmp_path):
    theta = None if family == "uniform" else rand_theta(gen, 0.99)
    layout = lw.make_layout(family, theta, dtype=torch.float64)
    path = save_layout(layout, tmp_path / "l.json", size=(129, 257), note="x")
    back, info = load_layout(path, dtype=torch.float64)
    assert back.family == family and info["size_hw"] == [129, 257] and info["extra"] == {"note": "x"}
    assert torch.allclose(back.theta, layout.theta.detach(), atol=1e-12)
    assert not back.learnable and load_layout(path, learn=family != "uniform")[0].learnable == (
        family != "uniform"
    )


def layout_file(**kw) -> str:
    return json.dumps({"format": "layoutwarp.layout/1", **kw})


def test_bad_layout_files_raise_clear_errors(tmp_path):
    (tmp_path / "a.json").write_text("{not json")
    with pytest.raises(ValueError, match="not a readable layout JSON"):
        load_layout(tmp_path / "a.json")
    (tmp_path / "b.json").write_text(
        json.dumps({"format": "layoutwarp.layout/1", "family": "hex", "theta": [0, 0]})
    )
    with pytest.raises(ValueError, match="unknown layout family 'hex'"):
        load_layout(tmp_path / "b.json")
    (tmp_path / "c.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(ValueError, match="not a layoutwarp layout file"):
        load_layout(tmp_path / "c.json")
    (tmp_path / "d.json").write_text(
        json.dumps({"format": "layoutwarp.layout/1", "family": "rect", "theta": [2, 0]})
    )
    with pytest.raises(ValueError, match=r"theta\[0\] = 2"):
        load_layout(tmp_path / "d.json")


def test_read_idx_plain_and_gzip(tmp_path, gen):
    arr = torch.randint(0, 256, (5, 3, 4), generator=gen, dtype=torch.uint8).numpy()
    raw = bytes([0, 0, 8, 3]) + b"".join(d.to_bytes(4, "big") for d in arr.shape) + arr.tobytes()
    (tmp_path / "x-idx3-ubyte").write_bytes(raw)
    (tmp_path / "x-idx3-ubyte.gz").write_bytes(gzip.compress(raw))
    assert np.array_equal(read_idx(tmp_path / "x-idx3-ubyte"), arr)
    assert np.array_equal(read_idx(tmp_path / "x-idx3-ubyte.gz"), arr)
    (tmp_path / "bad").write_bytes(raw[:-3])
    with pytest.raises(ValueError, match="IDX header"):
        read_idx(tmp_path / "bad")


def test_data_samples_mnist_matches_the_full_set_prefix():
    small = load_mnist(SAMPLES / "mnist")
    assert small["train_images"].shape == (4000, 28, 28) and small["test_labels"].shape == (1000,)
    if not (SHARED / "mnist").exists():
        pytest.skip("full MNIST (../shared/data/mnist) not present")
    full = load_mnist(SHARED / "mnist")
    assert np.array_equal(full["train_images"][:4000], small["train_images"])
    assert np.array_equal(full["test_labels"][:1000], small["test_labels"])


def test_train_mnist_quick_writes_results_layout_and_figures(tmp_path):
    code = main(["train", "mnist", "--quick", "--epochs", "1", "--no-progress", "--out", str(tmp_path)])
    assert code == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert set(res["summary"]) == {"uniform", "curv", "rect"}
    for name, s in res["summary"].items():
        assert 30 < s["accuracy_mean"] <= 100  # far above chance (10%) after one epoch
        if name == "uniform":
            assert s["theta_mean"] == []  # the uniform layout has no parameters
        else:
            assert any(abs(v) > 1e-3 for v in s["theta_mean"])  # θ learned
    layout, info = load_layout(tmp_path / "layout.json")
    assert layout.family == "curv" and info["size_hw"] == [4, 4]
    for fig in ("mnist_layouts.png", "mnist_theta.png"):
        assert (tmp_path / fig).stat().st_size > 5000


@pytest.mark.parametrize(
    ("n", "batch", "sizes"), [(7, 3, [3, 4]), (6, 3, [3, 3]), (1, 4, [1]), (9, 4, [4, 5])]
)
def test_fit_visits_every_sample_once_per_epoch_and_freezes_theta(n, batch, sizes, gen):
    from layoutwarp.experiments.training import fit

    model = torch.nn.Module()
    model.sensor = lw.SensorLayer((3, 3), "rect")
    model.head = torch.nn.Linear(1, 1)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    indices = torch.randperm(50, generator=gen)[:n]
    seen, grads = [], []

    def batch_loss(idx):
        seen.append(idx.clone())
        grads.append(model.sensor.layout.rho.requires_grad)
        img = torch.rand(len(idx), 1, 12, 12, generator=gen) + torch.arange(12.0)  # θ moves pixel (0, 0)
        return model.head(model.sensor(img)[:, :, 0, 0]).pow(2).mean()

    history = fit(model, indices, batch_loss, opt, gen, epochs=3, batch_size=batch, freeze_epochs=1)
    per_epoch = len(sizes)
    assert [len(s) for s in seen] == sizes * 3 and len(history) == 4
    for e in range(3):
        got = torch.cat(seen[e * per_epoch : (e + 1) * per_epoch])
        assert torch.equal(got.sort().values, indices.sort().values)
    assert grads == [False] * per_epoch + [True] * 2 * per_epoch
    assert history[0] == history[1] == [0.0, 0.0] and history[2] != history[1]
