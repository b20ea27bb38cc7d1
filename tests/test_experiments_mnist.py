"""The MNIST experiment: IDX reading, the shared training loop, and its quick run."""

from __future__ import annotations

import gzip
import json

import numpy as np
import pytest
import torch
from conftest import SAMPLES, SHARED

import layoutwarp as lw
from layoutwarp.cli import main
from layoutwarp.experiments.data import load_mnist, read_idx
from layoutwarp.experiments.runs import RunOptions, train_run
from layoutwarp.experiments.tasks import TASKS
from layoutwarp.layoutfile import load_layout


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


@pytest.mark.slow
def test_train_mnist_quick_writes_results_layout_and_figures(tmp_path):
    code = main(["train", "mnist", "--quick", "--epochs", "1", "--no-progress", "--out", str(tmp_path)])
    assert code == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["format"] == "layoutwarp.results/1" and res["units"] == "percent"
    assert [(r["family"], r["size_hw"]) for r in res["summary"]] == [
        ("uniform", [4, 4]),
        ("curv", [4, 4]),
        ("rect", [4, 4]),
    ]
    for s in res["summary"]:
        assert 30 < s["scores"]["accuracy"]["mean"] <= 100  # far above chance (10%) after one epoch
        if s["family"] == "uniform":
            assert s["theta_mean"] == []  # the uniform layout has no parameters
        else:
            assert any(abs(v) > 1e-3 for v in s["theta_mean"])  # θ learned
    for run in res["runs"]:  # θ and the pixel-size range after every epoch, from θ = 0
        assert len(run["theta_history"]) == len(run["area_ratio_history"]) == 2
        assert run["area_ratio_history"][0] == pytest.approx(1.0)
    assert res["run"]["layoutwarp"] == lw.__version__ and res["run"]["seeds"] == [0]
    layout, info = load_layout(tmp_path / "layout.json")  # the better of the learned layouts
    best = max(res["summary"][1:], key=lambda s: s["scores"]["accuracy"]["mean"])
    assert layout.family == best["family"] and info["size_hw"] == [4, 4]
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

    def batch_loss(idx, net):
        assert net is model  # one process: no DistributedDataParallel wrapper
        seen.append(idx.clone())
        grads.append(model.sensor.layout.rho.requires_grad)
        img = torch.rand(len(idx), 1, 12, 12, generator=gen) + torch.arange(12.0)  # θ moves pixel (0, 0)
        return model.head(model.sensor(img)[:, :, 0, 0]).pow(2).mean()

    history, seconds = fit(model, indices, batch_loss, opt, gen, epochs=3, batch_size=batch, freeze_epochs=1)
    assert seconds > 0
    per_epoch = len(sizes)
    assert [len(s) for s in seen] == sizes * 3 and len(history) == 4
    for e in range(3):
        got = torch.cat(seen[e * per_epoch : (e + 1) * per_epoch])
        assert torch.equal(got.sort().values, indices.sort().values)
    assert grads == [False] * per_epoch + [True] * 2 * per_epoch
    assert history[0] == history[1] == [0.0, 0.0] and history[2] != history[1]


def test_training_runs_on_the_device_with_mixed_precision(device):
    # the training path on the device fixture (CPU here; CUDA where present), with --amp
    task = TASKS["mnist"]
    data = task.load(SAMPLES / "mnist", limit=256)
    options = RunOptions.of(task.defaults, epochs=1, progress=False, device=str(device), amp=True)
    res, model = train_run(task, data, "curv", (4, 4), 0, options)
    assert next(model.parameters()).device.type == device.type
    assert 0 <= res.scores["accuracy"] <= 100 and len(res.theta) == 2
    assert any(abs(v) > 0 for v in res.theta)  # θ moved: gradients reached it through autocast


def test_device_flag_errors_name_the_value(capsys):
    argv = ["train", "mnist", "--quick", "--no-progress", "--device"]
    assert main([*argv, "tpu9"]) == 2
    assert (
        "argument --device must be a torch device (e.g. cpu, cuda, cuda:1), got 'tpu9'"
        in capsys.readouterr().err
    )
    if not torch.cuda.is_available():
        assert main([*argv, "cuda"]) == 2
        assert "no CUDA GPU is available here" in capsys.readouterr().err


@pytest.mark.parametrize("fails", [False, True])
def test_a_rank_other_than_0_trains_in_a_folder_its_command_removes(fails, tmp_path, monkeypatch, capsys):
    # under torchrun the ranks but 0 train into a temporary folder; it outlived every command
    # (a model and figures left in the system's temp folder per rank and run), also on errors
    import tempfile

    import layoutwarp.experiments.runs as runs
    import layoutwarp.experiments.training as training

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    monkeypatch.setattr(training, "init_distributed", lambda: (1, 2))
    seen = []

    def run_experiment(task, folder, out, **kw):  # where the rank writes, while it runs
        seen.append((out, out.is_dir(), out.parent == scratch))
        if fails:
            raise KeyboardInterrupt
        (out / "results.json").write_text("{}")
        return {"summary": {}}

    monkeypatch.setattr(runs, "run_experiment", run_experiment)
    monkeypatch.setattr(runs, "format_summary", lambda task, summary: "a summary")
    argv = ["train", "mnist", "--quick", "--family", "curv", "--out", str(tmp_path / "out")]
    assert main(argv) == (130 if fails else 0)  # a Ctrl-C: the command's one line, status 130
    assert [s[1:] for s in seen] == [(True, True)]
    assert list(scratch.iterdir()) == []  # removed, also when the run failed
    assert not (tmp_path / "out" / "results.json").exists()  # rank 0 alone writes into --out
    assert capsys.readouterr().out == ""  # and reports


@pytest.mark.parametrize("command", ["study", "landscape"])
def test_a_study_or_landscape_prints_on_rank_0_alone(command, tmp_path, monkeypatch, capsys):
    # under torchrun every rank printed the whole report (and two ranks' lines mixed in one)
    import layoutwarp.experiments.landscape as landscape
    import layoutwarp.experiments.study as study
    import layoutwarp.experiments.training as training

    ran = []
    monkeypatch.setattr(study, "run_study", lambda *a, **kw: ran.append(command) or {})
    monkeypatch.setattr(study, "study_table", lambda summary: "the table\n")
    monkeypatch.setattr(landscape, "run_landscape", lambda *a, **kw: ran.append(command) or {})
    monkeypatch.setattr(landscape, "landscape_table", lambda summary: "the table\n")
    for rank, says in ((1, ""), (0, "the table\nwrote ")):
        monkeypatch.setattr(training, "init_distributed", lambda rank=rank: (rank, 2))
        extra = ["--family", "rect"] if command == "landscape" else []
        assert main([command, "mnist", "--quick", *extra, "--out", str(tmp_path / command)]) == 0
        out = capsys.readouterr().out
        assert out.startswith(says) if says else out == ""
    assert ran == [command, command]


@pytest.mark.slow
@pytest.mark.heavy
def test_torchrun_with_two_gloo_processes_matches_one_process(tmp_path):
    # the same command under torchrun: 2 CPU ranks (gloo) split each global batch of 64 in two.
    # DistributedDataParallel averages their gradients, so each step is the one-process step up
    # to float rounding, which Adam (lr 0.01) amplifies where a gradient is near zero: after one
    # quick epoch θ agreed to 4e-3 and the accuracy to 0.6 points (stated tolerance: 1e-2, 2).
    # fit() also compares θ across the ranks after every epoch and fails the run if they differ.
    import os
    import subprocess
    import sys

    args = [
        "train",
        "mnist",
        "--quick",
        "--family",
        "curv",
        "--epochs",
        "1",
        "--seeds",
        "1",
        "--device",
        "cpu",
    ]
    args += ["--no-progress"]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]
    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK")}
    (tmp_path / "tmp").mkdir()
    env["TMPDIR"] = str(tmp_path / "tmp")  # where rank 1 trains: nothing of it is left
    res = subprocess.run(
        [*torchrun, "-m", "layoutwarp", *args, "--out", str(tmp_path / "two")],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    one = json.loads((tmp_path / "one" / "results.json").read_text())["runs"][0]
    two = json.loads((tmp_path / "two" / "results.json").read_text())["runs"][0]
    assert max(abs(a - b) for a, b in zip(one["theta"], two["theta"], strict=True)) <= 1e-2
    assert abs(one["scores"]["accuracy"] - two["scores"]["accuracy"]) <= 2.0
    assert any(abs(v) > 1e-3 for v in two["theta"])  # it learned
    assert res.stdout.count("wrote ") == 1  # rank 0 alone reports
    assert not any(p.name.startswith("layoutwarp-rank-") for p in (tmp_path / "tmp").iterdir())
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == sorted(
        p.name for p in (tmp_path / "one").iterdir()
    )


@pytest.mark.slow
def test_ranks_that_would_resume_at_different_epochs_are_refused_in_one_line(tmp_path):
    # two machines, each its own --out: rank 0 found a checkpoint and resumed at epoch 1, rank 1
    # began at 0; their collectives paired across epochs, a run was recorded, the next crashed
    import os
    import subprocess
    import sys
    import textwrap

    script = tmp_path / "start.py"
    script.write_text(
        textwrap.dedent("""
        import torch.distributed as dist
        from layoutwarp.experiments.training import _check_same_start
        dist.init_process_group("gloo")
        _check_same_start(3, "curv_4x4_seed0")  # alike: nothing said
        for first, run in ((dist.get_rank(), "a"), (0, f"run{dist.get_rank()}")):
            try:
                _check_same_start(first, run)
            except ValueError as exc:
                print(exc)
        dist.destroy_process_group()
    """)
    )
    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK")}
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]
    res = subprocess.run([*torchrun, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("the ranks would resume at epochs 0 to 1: every rank must see") == 2  # both
    # or train different runs: a record one rank found (it skipped the run) and another did not
    assert res.stdout.count("the ranks would train different runs (run") == 2
