"""The paper's protocol on CamVid (``--net psp``): the task's network variants, PSPNet's
optimiser and schedule, scale jitter for whole images, and a quick run end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from conftest import SAMPLES

from layoutwarp.cli import main
from layoutwarp.experiments.camvid import SegNet
from layoutwarp.experiments.data import VOID
from layoutwarp.experiments.models import load_model
from layoutwarp.experiments.protocols import PSP_CAMVID as PSP_DEFAULTS
from layoutwarp.experiments.resnets import IMAGENET_MEAN
from layoutwarp.experiments.segmentation import PSPSegNet, scale_jitter
from layoutwarp.experiments.tasks import TASKS, get_task
from layoutwarp.experiments.training import optimizer, schedule


def test_a_tasks_network_variant_carries_its_protocol_and_leaves_the_task_as_it_was():
    camvid = get_task("camvid")
    assert camvid.net == "small" and list(camvid.nets) == ["small", "psp"]
    psp = camvid.with_net("psp")
    assert psp.net == "psp" and psp.defaults is PSP_DEFAULTS and psp.name == "camvid"
    assert (PSP_DEFAULTS.optimizer, PSP_DEFAULTS.schedule, PSP_DEFAULTS.batch_size) == ("sgd", "poly", 4)
    assert psp.study.learned_sizes == ((72, 96),) and psp.study.families == ("rect", "curv")
    assert camvid.defaults is not PSP_DEFAULTS and TASKS["camvid"] is camvid  # unchanged
    assert camvid.with_net(None) is camvid and camvid.with_net("small") is camvid
    assert isinstance(psp.network("curv", (9, 12), learn=True), PSPSegNet)
    assert isinstance(camvid.network("curv", (9, 12), learn=True), SegNet)
    with pytest.raises(ValueError, match=r"net of task 'camvid' must be one of 'small', 'psp'; got 'unet'"):
        camvid.with_net("unet")
    with pytest.raises(
        ValueError, match=r"net of task 'mnist' must be one of none \(one network\); got 'psp'"
    ):
        get_task("mnist").with_net("psp")


def test_sgd_keeps_theta_out_of_weight_decay_and_poly_decays_to_zero():
    model = get_task("camvid").network("rect", (6, 8), learn=True)
    opt = optimizer(model, 0.01, 0.02, "sgd", 1e-4)
    assert isinstance(opt, torch.optim.SGD) and opt.defaults["momentum"] == 0.9
    net_group, theta_group = opt.param_groups
    assert (net_group["lr"], net_group["weight_decay"]) == (0.01, 1e-4)
    assert (theta_group["lr"], theta_group["weight_decay"]) == (0.02, 0.0)
    assert [id(p) for p in theta_group["params"]] == [id(p) for p in model.sensor.parameters()]
    epochs, lrs = 7, []
    sched = schedule(opt, "poly", epochs)
    for _ in range(epochs):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs == pytest.approx([0.01 * (1 - e / epochs) ** 0.9 for e in range(epochs)], rel=1e-12)
    assert opt.param_groups[0]["lr"] == 0.0 and schedule(opt, "constant", 3) is None
    with pytest.raises(ValueError, match="schedule must be one of 'constant', 'cosine', 'poly'; got 'step'"):
        schedule(opt, "step", 3)
    with pytest.raises(ValueError, match="optimizer must be one of 'adam', 'sgd'; got 'lbfgs'"):
        optimizer(model, 0.01, 0.01, "lbfgs")


def test_scale_jitter_scales_then_crops_or_pads_with_void_and_the_mean():
    h, w = 30, 40
    x = torch.rand(2, 3, h, w)
    y = torch.randint(0, 11, (2, h, w))
    seen = {"up": False, "down": False}
    for seed in range(40):
        gen = torch.Generator().manual_seed(seed)
        xs, ys = scale_jitter(x, y, gen, ignore=VOID)
        assert xs.shape == x.shape and ys.shape == y.shape and ys.dtype == y.dtype
        s = 0.5 + 1.5 * float(torch.rand((), generator=torch.Generator().manual_seed(seed)))
        sh, sw = round(h * s), round(w * s)
        if s < 1:  # padded: the frame's rest is void and the mean colour, the scaled image inside
            seen["down"] = True
            void = ys == VOID
            assert int(void[0].sum()) == h * w - sh * sw
            mean = torch.tensor(IMAGENET_MEAN).view(3, 1)
            assert torch.equal(xs[0][:, void[0]], mean.expand(3, int(void[0].sum())))
        else:  # cropped: every label is one of the originals, no void added
            seen["up"] = True
            assert not (ys == VOID).any()
        again = scale_jitter(x, y, torch.Generator().manual_seed(seed), ignore=VOID)
        assert torch.equal(again[0], xs) and torch.equal(again[1], ys)  # the generator decides
    assert seen == {"up": True, "down": True}


def test_a_scale_of_one_gives_the_images_back():
    x, y = torch.rand(1, 3, 12, 16), torch.randint(0, 11, (1, 12, 16))
    xs, ys = scale_jitter(x, y, torch.Generator().manual_seed(0), lo=1.0, hi=1.0)
    assert torch.allclose(xs, x, atol=1e-6) and torch.equal(ys, y)


@pytest.mark.slow
@pytest.mark.heavy
def test_train_camvid_psp_quick_writes_psp_models_that_evaluate_rebuilds(tmp_path, capsys):
    out = tmp_path / "psp"
    argv = [
        "train",
        "camvid",
        "--quick",
        "--net",
        "psp",
        "--family",
        "rect",
        "--no-progress",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    res = json.loads((out / "results.json").read_text())
    assert (
        res["net"] == "psp"
        and res["training"]["optimizer"] == "sgd"
        and res["training"]["schedule"] == "poly"
    )
    assert res["training"]["batch_size"] == 4 and res["training"]["lr"] == 0.01
    (row,) = res["summary"]
    assert row["family"] == "rect" and row["size_hw"] == [72, 96]
    assert any(abs(v) > 1e-5 for v in row["theta_mean"]) and not any(math.isnan(v) for v in row["theta_mean"])
    model, _ = load_model(out / "model_rect_96x72_seed0.pt", "camvid")
    assert isinstance(model, PSPSegNet) and not model.training
    capsys.readouterr()
    bad = ["train", "camvid", "--quick", "--net", "psp", "--backbone-weights", str(tmp_path / "none.pth")]
    assert main(bad) == 2
    assert "argument --backbone-weights: no such file" in capsys.readouterr().err


@pytest.mark.parametrize("physics", [None, {"sensor_um": [90.0, 120.0], "photons_per_um2": 20.0, "seed": 4}])
def test_a_run_stopped_in_its_second_epoch_resumes_from_its_checkpoint_to_the_same_values(
    tmp_path, monkeypatch, physics
):
    """fit's checkpoint: a run stopped in its second epoch (an interrupt in its first batch
    there) and resumed trains to the values of an uninterrupted run, θ history included; with a
    seeded sensor noise too (its place in the sequence is kept: the resumed run drew the first
    epoch's noise again)."""
    from layoutwarp.experiments.runs import RunOptions, train_run

    task = get_task("camvid")
    data = task.load(SAMPLES / "camvid", limit=4)
    sensor = {"method": "exact", "tol": 1e-2} | ({"physics": physics} if physics else {})
    options = RunOptions.of(task.quick_defaults(), epochs=2, batch_size=2, progress=False, sensor=sensor)
    whole, whole_model = train_run(task, data, "rect", (9, 12), 3, options)
    batches, calls = task.batches, []

    def stopping(*args):
        indices, loss = batches(*args)

        def batch_loss(idx, net):
            calls.append(1)
            if len(calls) == 3 and stop:  # two batches an epoch: the second epoch's first
                raise KeyboardInterrupt
            return loss(idx, net)

        return indices, batch_loss

    ckpt, stop = tmp_path / "run.pt", True
    monkeypatch.setattr(task, "batches", stopping)
    with pytest.raises(KeyboardInterrupt):
        train_run(task, data, "rect", (9, 12), 3, options, checkpoint=ckpt)
    state = torch.load(ckpt, weights_only=True)
    assert state["epochs_done"] == 1 and len(state["history"]) == 2 and state["seconds"] > 0
    calls.clear()
    stop = False
    resumed, resumed_model = train_run(task, data, "rect", (9, 12), 3, options, checkpoint=ckpt)
    assert len(calls) == 2  # the second epoch's batches alone: the first came from the checkpoint
    assert resumed.theta_history == whole.theta_history and resumed.scores == whole.scores
    assert resumed.seconds > state["seconds"]  # the first epoch's time counted too
    for (k, a), b in zip(whole_model.state_dict().items(), resumed_model.state_dict().values(), strict=True):
        assert torch.equal(a, b), k


class _Payload:
    """A pickled object whose loading would run code: it creates the file ``marker``."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


def test_a_checkpoint_that_would_run_code_is_refused(tmp_path):
    import pickle

    from layoutwarp.experiments.runs import RunOptions, train_run

    task = get_task("mnist")
    data = task.load(SAMPLES / "mnist", limit=8)
    options = RunOptions.of(task.quick_defaults(), epochs=1, batch_size=4, progress=False)
    ckpt, marker = tmp_path / "run.pt", tmp_path / "ran"
    torch.save({"epochs_done": 0, "model": _Payload(str(marker))}, ckpt)
    with pytest.raises(pickle.UnpicklingError, match="Weights only load failed"):
        train_run(task, data, "rect", (4, 4), 0, options, checkpoint=ckpt)
    assert not marker.exists()
