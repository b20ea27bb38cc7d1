"""What a new user trips over: giant or swapped sizes, files where folders go, warnings and
messages that must be one clear line, and the physics argument's one rule."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch
from conftest import ROOT, SAMPLES

import layoutwarp as lw
from layoutwarp.checks import ArgumentError, check_size
from layoutwarp.cli import build_parser, main
from layoutwarp.export import export_layout, report_json


def test_a_boolean_is_not_a_size():
    for size in [(True, 4), (4, np.bool_(True))]:
        with pytest.raises(ArgumentError, match=r"size must be a pair \(H, W\) of positive integers"):
            check_size(size)


def test_a_giant_sensor_is_refused_with_the_memory_it_needs_before_anything_is_allocated():
    with pytest.raises(
        ArgumentError,
        match=r"size \(H, W\) = \(100000, 100000\) is 1e\+10 sensor pixels and needs at least 1\.82 TiB",
    ):
        lw.simulate(torch.rand(1, 3, 8, 8), lw.CurvLayout((0.3, 0.1)), (100000, 100000))
    with pytest.raises(ArgumentError, match="more than the"):
        lw.SensorLayer((100000, 100000), "curv")


def test_a_sensor_finer_than_its_image_is_warned_about_once():
    img = torch.rand(1, 3, 20, 30)
    size = (21, 7)  # more rows than the image has
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            lw.simulate(img, lw.CurvLayout((0.3, 0.1)), size)
        lw.simulate(img, lw.CurvLayout((0.3, 0.1)), (10, 15))  # coarser: no warning
    finer = [w for w in caught if "more pixels along an axis than its source image" in str(w.message)]
    assert len(finer) == 1 and "(21, 7)" in str(finer[0].message) and "(20, 30)" in str(finer[0].message)


@pytest.mark.heavy
def test_preprocess_says_so_in_one_line_and_the_decoders_add_no_line_of_their_own(tmp_path):
    import cv2

    src = tmp_path / "src"
    src.mkdir()
    png = (SAMPLES / "photos" / "kodim20.png").read_bytes()
    jpg = cv2.imencode(".jpg", cv2.imread(str(SAMPLES / "photos" / "kodim20.png")))[1].tobytes()
    (src / "cut.png").write_bytes(png[:100])  # cut short
    (src / "crc.png").write_bytes(png[:100] + b"x" * 500 + png[600:])  # libpng: "IDAT: ..."
    (src / "cut.jpg").write_bytes(jpg[: len(jpg) // 2])  # libjpeg: "Premature end of JPEG file"
    (src / "gap.jpg").write_bytes(jpg[:300] + bytes(300) + jpg[600:])  # "Corrupt JPEG data", decodes
    (src / "good.png").write_bytes(png)
    cmd = [sys.executable, "-m", "layoutwarp", "preprocess", str(src), str(tmp_path / "dst")]
    cmd += ["--family", "uniform", "--size", "640x600", "--no-progress"]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 1, res.stderr  # files failed
    for noise in ("[ WARN", "[ERROR", "libpng", "JPEG data", "Premature", "Traceback"):
        assert noise not in res.stderr.replace("'libpng error", ""), (noise, res.stderr)
    warned = [line for line in res.stderr.splitlines() if line.startswith("layoutwarp: warning:")]
    assert len(warned) == 2 and "(600, 640)" in warned[0] and "(500, 500)" in warned[0], res.stderr
    assert "decoders reported 2 problem(s), e.g. 'libpng error: " in warned[1], res.stderr
    assert "2 written" in res.stdout and "3 failed" in res.stdout
    failed = sorted(line.strip() for line in res.stderr.splitlines() if line.strip().startswith("failed:"))
    assert failed == [
        "failed: crc.png: ValueError: unreadable or not an image",
        "failed: cut.jpg: ValueError: truncated JPEG file (no end-of-image marker after its scan)",
        "failed: cut.png: ValueError: truncated PNG file (no IEND chunk after its image data)",
    ]
    manifest = json.loads((tmp_path / "dst" / "manifest.json").read_text())
    lines = manifest["decoder_messages"]
    assert (
        len(lines) == 2 and lines[0].startswith("libpng error: ") and lines[1].startswith("Corrupt JPEG data")
    )


def test_a_file_given_as_a_folder_is_named_as_a_file(tmp_path, capsys):
    photo = SAMPLES / "photos" / "kodim03.png"
    assert main(["preprocess", str(photo), str(tmp_path / "out"), "--size", "8x6"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"layoutwarp preprocess: error: argument SRC: must be a folder; {str(photo)!r} is a file"
    )
    assert main(["train", "mnist", "--data", str(photo), "--out", str(tmp_path / "t")]) == 2
    assert "argument --data: must be a folder" in capsys.readouterr().err


def test_a_failed_command_leaves_no_empty_output_folder(tmp_path, capsys):
    empty = tmp_path / "no-camvid"
    empty.mkdir()
    out = tmp_path / "results" / "t"
    assert main(["train", "camvid", "--data", str(empty), "--out", str(out), "--no-progress"]) == 2
    assert "no CamVid images" in capsys.readouterr().err and not out.exists()
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png")
    assert main(["demo", "--image", str(bad), "--out", str(tmp_path / "d")]) == 2
    assert not (tmp_path / "d").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    assert main(["demo", "--image", str(bad), "--out", str(kept)]) == 2
    assert kept.is_dir()  # a folder the user had stays


def test_simulate_takes_physics_as_a_dict_as_sensor_layer_does():
    phys = lw.SensorPhysics((80.0, 80.0), photons_per_um2=20, seed=4)
    img = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(1))
    a = lw.simulate(img, lw.CurvLayout((0.3, 0.1)), (4, 4), physics=phys)
    b = lw.simulate(img, lw.CurvLayout((0.3, 0.1)), (4, 4), physics=phys.to_dict())
    assert torch.equal(a, b) and lw.SensorLayer((4, 4), "curv", physics=phys.to_dict()).physics == phys
    with pytest.raises(TypeError, match="physics must be a SensorPhysics, its dict or None, got int"):
        lw.simulate(img, lw.CurvLayout((0.3, 0.1)), (4, 4), physics=3)


def test_the_export_report_names_the_extents_order_and_says_no_full_well(tmp_path, capsys):
    phys = lw.SensorPhysics((1.0, 1.0), photons_per_um2=50)  # no full well given
    report = export_layout(
        lw.CurvLayout((0.3, 0.1)), (6, 8), tmp_path / "m.svg", (300.0, 800.0), physics=phys
    )
    data = json.loads(report_json(report))
    assert (
        data["sensor_um_hw"] == [300.0, 800.0]
        and data["sensor_um_wxh"] == "800x300"
        and "sensor_um" not in data
    )
    assert "no full well" in report.summary() and "inf" not in report.summary()
    svg = (tmp_path / "m.svg").read_text()
    assert 'width="0.8mm" height="0.3mm" viewBox="0 0 800.0 300.0"' in svg  # physical size, and scalable


def test_export_draws_progress_when_asked(tmp_path, capsys):
    export_layout(lw.CurvLayout((0.3, 0.1)), (6, 8), tmp_path / "m.svg", (300.0, 400.0), progress=True)
    err = capsys.readouterr().err
    assert "pixel outlines" in err and "writing SVG" in err
    export_layout(lw.CurvLayout((0.3, 0.1)), (6, 8), tmp_path / "n.svg", (300.0, 400.0))  # small: quiet
    assert capsys.readouterr().err == ""


def test_export_help_shows_every_default():
    (export,) = [a.choices["export"] for a in build_parser()._actions if getattr(a, "choices", None)]
    text = " ".join(export.format_help().split())
    assert "GDSII datatype (default: 0)" in text
    assert "(default: no snapping; GDSII's 1 nm for *.gds)" in text


def test_output_cut_short_by_its_reader_ends_the_command_quietly(monkeypatch):
    """``layoutwarp doctor | head -1``: the reader closes the pipe, the command ends with status 141
    and no BrokenPipeError traceback."""
    import os

    from layoutwarp.cli import run

    read, write = os.pipe()
    os.close(read)  # the reader is gone
    out = os.fdopen(write, "w")
    monkeypatch.setattr(sys, "stdout", out)
    monkeypatch.setattr(sys, "argv", ["layoutwarp", "doctor"])
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)  # run() sets its own: restored
    with pytest.raises(SystemExit) as ended:
        run()
    assert ended.value.code == 141
    out.write("more")
    out.flush()  # stdout now leads nowhere: later writes are dropped, not errors
    out.close()  # (left open, the garbage collector warned of it in a later test)


def test_a_small_sensor_is_not_checked_against_the_free_memory(monkeypatch):
    """simulate checks its size on every call: below checks.UNCHECKED_BYTES the system's memory
    figures are not read (a small fixed-layout forward costs less than reading them)."""
    import layoutwarp.checks as checks

    def unreadable() -> int:
        raise AssertionError("read the free memory for a small sensor")

    monkeypatch.setattr(checks, "available_bytes", unreadable)
    lw.simulate(torch.rand(1, 3, 16, 16), lw.CurvLayout((0.3, 0.1)), (4, 4))
    side = int((checks.UNCHECKED_BYTES / checks.BYTES_PER_SENSOR_PIXEL) ** 0.5) + 1
    with pytest.raises(AssertionError, match="read the free memory"):
        checks.check_memory((side, side))


def test_a_layout_object_with_theta_learn_or_bound_is_refused_not_ignored():
    layout = lw.CurvLayout((0.3, 0.1))
    for kwargs, first in [
        ({"theta": (0.5, 0.5)}, "theta"),
        ({"learn": False}, "learn"),
        ({"bound": 0.5, "theta": (0, 0)}, "theta"),
    ]:
        with pytest.raises(
            ArgumentError, match="set up a layout made by name; a CurvLayout brings its own"
        ) as info:
            lw.SensorLayer((4, 4), layout, **kwargs)
        assert info.value.argument == first
    layer = lw.SensorLayer((4, 4), layout)  # used as it is: fixed
    assert layer.layout is layout and not layer.layout.learnable
    named = lw.SensorLayer((4, 4), "curv", theta=(0.2, 0.1), bound=0.5)
    assert named.layout.learnable and named.layout.bound == 0.5
    assert torch.allclose(named.theta.double(), torch.tensor([0.2, 0.1], dtype=torch.float64))


def test_a_theta_that_is_not_numbers_is_named_in_our_words():
    for bad in ("ab", ["x", 1], {"a": 1}, object()):
        with pytest.raises(ArgumentError, match=r"theta must be 2 numbers \(θ_x, θ_y\), got ") as info:
            lw.CurvLayout(bad)
        assert info.value.argument == "theta" and "new()" not in str(info.value)


def test_a_layout_elsewhere_than_its_image_is_warned_about_once(monkeypatch):
    from layoutwarp import checks

    monkeypatch.setattr(checks, "_WARNED", set())
    with pytest.warns(
        UserWarning, match=r"θ is on cpu and the image on cuda:0: θ is copied to cuda:0"
    ) as rec:
        for _ in range(3):
            checks.warn_if_elsewhere(torch.device("cpu"), torch.device("cuda:0"))
    assert len(rec) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        checks.warn_if_elsewhere(torch.device("cpu"), torch.device("cpu"))
        lw.simulate(torch.rand(1, 1, 8, 8), lw.CurvLayout((0.3, 0.1)), (4, 4))  # one device: quiet


def test_a_fixed_layouts_constants_stay_float64_through_dtype_changes():
    layout = lw.CurvLayout((0.45, 0.3), center=(0.1, -0.2))
    assert layout.dtype == torch.float32 and layout.rho.dtype == torch.float64
    for convert in (
        lambda m: m.half(),
        lambda m: m.to(torch.bfloat16),
        lambda m: m.float(),
        lambda m: m.double(),
    ):
        layout = convert(layout)
        assert layout.rho.dtype == layout.fixed_center.dtype == torch.float64
        assert layout.theta.dtype == layout.dtype == layout.center.dtype
        assert layout.theta_as(torch.float64).tolist() == pytest.approx([0.45, 0.3], abs=1e-16)
        assert layout.fixed_center.tolist() == [0.1, -0.2]
    learn = lw.CurvLayout((0.45, 0.3), learn=True).double()  # a parameter: of the module's dtype
    assert learn.rho.dtype == learn.dtype == torch.float64 and isinstance(learn.rho, torch.nn.Parameter)
    state = lw.CurvLayout((0.45, 0.3)).state_dict()
    again = lw.CurvLayout()
    again.load_state_dict(state | {"rho": state["rho"].float()})  # an older float32 ρ loads too
    assert again.rho.dtype == torch.float64 and float(again.theta[0]) == pytest.approx(0.45, rel=1e-7)


def test_a_fixed_layouts_theta_comes_back_to_the_bit(tmp_path, seed):
    rng = np.random.default_rng(seed)
    for theta in rng.uniform(-0.9, 0.9, (50, 2)).tolist():
        layout = lw.CurvLayout(theta)
        assert layout.theta_as(torch.float64).tolist() == theta  # atanh and tanh do not round-trip
        again = lw.CurvLayout()
        again.load_state_dict(layout.state_dict())
        assert again.theta_as(torch.float64).tolist() == theta
        lw.save_layout(layout, tmp_path / "l.json", (4, 4))
        assert lw.load_layout(tmp_path / "l.json")[0].theta_as(torch.float64).tolist() == theta
    learn = lw.CurvLayout((0.25, -0.2), learn=True)  # a learnable layout's state: θ as it computed it
    with torch.no_grad():
        learn.rho.add_(0.01)
    fixed = lw.CurvLayout()
    fixed.load_state_dict(learn.state_dict())
    assert torch.equal(fixed.theta, learn.theta.detach())


def test_a_layouts_description_holds_its_numbers_to_the_bit():
    # θ, a centre and a grid's control points, given as Python floats, are written as given
    fovea = lw.FoveaLayout((0.5, 0.2), center=(0.3, -0.1))
    assert fovea.to_config()["theta"] == [0.5, 0.2] and fovea.to_config()["center"] == [0.3, -0.1]
    assert lw.CurvLayout((0.5, 0.2), center=(0.3, -0.1)).to_config()["center"] == [0.3, -0.1]
    ctrl = lw.coords.uniform_corners((2, 2)).tolist()
    ctrl[1][1] = [0.1, -0.2]
    assert lw.GridLayout(ctrl).to_config()["control"][1][1] == [0.1, -0.2]
    # a fixed layout whose ρ was trained anyway saves the θ it trained to
    layout = lw.RectLayout((0.3, 0.2))
    layout.rho.requires_grad_(True)
    opt = torch.optim.SGD([layout.rho], lr=1.0)
    layout.theta.sum().backward()
    opt.step()
    again = lw.RectLayout()
    again.load_state_dict(layout.state_dict())
    assert torch.allclose(again.theta.double(), layout.theta.detach().double(), atol=1e-7)


def test_a_tasks_own_freeze_epochs_is_its_protocol_not_an_error(monkeypatch, tmp_path, capsys):
    import layoutwarp.experiments.runs as runs

    seen = []

    def stop(task, folder, out, *, families, sizes, seeds, options):
        seen.append(options)
        raise ValueError("stopped")

    monkeypatch.setattr(runs, "run_experiment", stop)
    assert (
        main(["train", "camvid", "--quick", "--epochs", "1", "--out", str(tmp_path / "o"), "--no-progress"])
        == 2
    )
    assert "stopped" in capsys.readouterr().err and seen[0].epochs == 1


def test_import_layoutwarp_is_enough_for_its_subpackages():
    """``import layoutwarp`` alone gives every submodule on first use (``lw.kernels``,
    ``lw.operators``, ``lw.integrators``, ...: as the docs' blocks use them), in a fresh process."""
    import subprocess
    import sys

    code = (
        "import layoutwarp as lw\nlw.kernels.threads()\nassert 'exact' in lw.operators.OPERATORS\n"
        "assert callable(lw.integrators.integrate_exact) and callable(lw.optics.apply_psf)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
