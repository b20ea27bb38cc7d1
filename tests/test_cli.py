"""The command line as a user meets it: every bad input ends in one line naming the flag, the
value and what is allowed, with exit status 2 and no traceback; the help reads the same way
everywhere."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import ROOT, SAMPLES

import layoutwarp as lw
from layoutwarp.cli import Terminated, build_parser, main, parse_wxh
from layoutwarp.experiments.demo import demo_outputs

CAMVID_VAL = str(SAMPLES / "camvid" / "val")
MASK = ["--size", "4x4", "--sensor-um", "40x40"]
PRE = ["preprocess", CAMVID_VAL, "{tmp}/out", "--family", "uniform", "--size", "8x6"]


def test_parse_wxh_is_width_by_height():
    assert parse_wxh("257x129") == (129, 257)
    with pytest.raises(Exception, match="WIDTHxHEIGHT"):
        parse_wxh("257")


@pytest.fixture
def files(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "empty.json").write_text("{}")
    (tmp_path / "range.json").write_text(
        json.dumps({"format": "layoutwarp.layout/1", "family": "rect", "theta": [1.5, 0]})
    )
    (tmp_path / "afile").write_text("")
    (tmp_path / "list.json").write_text("[1, 2]")
    light = {"sensor_um": [60, 80], "photons_per_um2": 5}
    (tmp_path / "extra.json").write_text(json.dumps(light | {"exposure": 2}))
    (tmp_path / "fill.json").write_text(json.dumps(light | {"fill_factor": 1.5}))
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "a.png").write_bytes((SAMPLES / "photos" / "kodim20.png").read_bytes())
    (tmp_path / "noimages").mkdir()  # a folder with no images
    (tmp_path / "noimages" / "notes.txt").write_text("not an image")
    lay = {"format": "layoutwarp.layout/2", "family": "curv"}
    (tmp_path / "notheta.json").write_text(json.dumps(lay))
    (tmp_path / "bound10.json").write_text(json.dumps(lay | {"theta": [5, 0.2], "bound": 10}))
    (tmp_path / "curv.json").write_text(json.dumps(lay | {"theta": [0.3, 0.2], "size_hw": [4, 4]}))
    jpg = (SAMPLES / "photos" / "kodim20.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(jpg[: len(jpg) // 2])
    return tmp_path


# (argv with {tmp} for the temporary folder, substrings the one error line must contain)
CASES = {
    "layout file missing": (
        ["export", "--layout", "{tmp}/missing.json", *MASK, "--out", "{tmp}/x.svg"],
        ["--layout", "missing.json", "no such layout file"],
    ),
    "layout file not JSON": (
        ["export", "--layout", "{tmp}/bad.json", *MASK, "--out", "{tmp}/x.svg"],
        ["--layout", "bad.json", "not a readable layout JSON"],
    ),
    "layout file {}": (
        ["preprocess", CAMVID_VAL, "{tmp}/out", "--layout", "{tmp}/empty.json", "--size", "8x6"],
        ["--layout", "empty.json", "expected format 'layoutwarp.layout/2'"],
    ),
    "layout file θ out of range": (
        ["export", "--layout", "{tmp}/range.json", *MASK, "--out", "{tmp}/x.svg"],
        ["--layout", "range.json", "theta[0] = 1.5", "|θ| < bound = 1.0"],
    ),
    "theta nan": (
        ["export", "--family", "curv", "--theta", "nan,0", *MASK, "--out", "{tmp}/x.svg"],
        ["--theta", "'nan,0'", "finite with |θ| < 1"],
    ),
    "DST a file": (
        ["preprocess", CAMVID_VAL, "{tmp}/afile", "--family", "uniform", "--size", "8x6"],
        ["DST", "afile", "is a file"],
    ),
    "DST under a file": (
        ["preprocess", CAMVID_VAL, "{tmp}/afile/sub", "--family", "uniform", "--size", "8x6"],
        ["DST", "afile/sub", "which is a file"],
    ),
    "mnist without data": (
        ["train", "mnist", "--data", "{tmp}/nothing"],
        ["argument --data", "no such folder", "nothing"],
    ),
    "output folder under a file": (
        ["train", "faces", "--quick", "--out", "{tmp}/range.json/out"],
        ["argument --out", "must be a folder", "range.json', which is a file"],
    ),
    "study output folder under a file": (
        ["study", "mnist", "--quick", "--out", "{tmp}/range.json/out"],
        ["argument --out", "must be a folder"],
    ),
    "demo output folder is a file": (
        ["demo", "--out", "{tmp}/range.json"],
        ["argument --out", "must be a folder", "is a file"],
    ),
    "epochs 0": (["train", "mnist", "--quick", "--epochs", "0"], ["--epochs", "'0'", "integer >= 1"]),
    "epochs negative": (
        ["train", "camvid", "--quick", "--epochs", "-3"],
        ["--epochs", "'-3'", "integer >= 1"],
    ),
    "seeds 0": (["train", "faces", "--quick", "--seeds", "0"], ["--seeds", "'0'", "integer >= 1"]),
    "samples 0": (["train", "mnist", "--quick", "--samples", "0"], ["--samples", "'0'", "integer >= 1"]),
    "bench image missing": (
        ["bench", "--image", "{tmp}/missing.png"],
        ["--image", "missing.png", "no such file"],
    ),
    "huge size": (
        [
            "export",
            "--family",
            "uniform",
            "--size",
            "100000x100000",
            "--sensor-um",
            "1x1",
            "--out",
            "{tmp}/x.svg",
        ],
        ["--size", "100000x100000", "needs at least", "TiB", "available"],
    ),
    "huge size in train": (
        ["train", "camvid", "--quick", "--size", "100000x100000"],
        ["--size", "100000x100000", "needs at least"],
    ),
    "layout and family": (
        [
            "export",
            "--layout",
            "{tmp}/range.json",
            "--family",
            "curv",
            "--theta",
            "0.1,0.1",
            *MASK,
            "--out",
            "{tmp}/x.svg",
        ],
        ["--layout", "or --family/--theta, not both"],
    ),
    "family without theta": (
        ["export", "--family", "curv", *MASK, "--out", "{tmp}/x.svg"],
        ["--family", "'curv'", "needs --theta TX,TY"],
    ),
    "theta for uniform": (
        ["export", "--family", "uniform", "--theta", "0.1,0", *MASK, "--out", "{tmp}/x.svg"],
        ["--theta", "no parameters", "(0.1, 0.0)"],
    ),
    "format and suffix disagree": (
        [
            "export",
            "--family",
            "curv",
            "--theta",
            "0.3,0.3",
            *MASK,
            "--format",
            "svg",
            "--out",
            "{tmp}/x.gds",
        ],
        ["--format", "'svg'", "x.gds", "*.svg"],
    ),
    "unknown suffix": (
        ["export", "--family", "uniform", *MASK, "--out", "{tmp}/x.jpg"],
        ["--out", "'x.jpg'", "*.gds, *.dxf, *.svg, *.png"],
    ),
    "address without dask": (
        [*PRE, "--address", "tcp://h:1"],
        ["--address", "needs engine='dask'"],
    ),
    "unknown bench row": (["bench", "--quick", "--layouts", "curv,hex"], ["--layouts", "'hex'", "fovea"]),
    "preprocess on an unknown device": (
        [*PRE, "--device", "gpu0"],
        ["--device", "'gpu0'", "torch device"],
    ),
    "physics file not JSON": (
        [*PRE, "--physics", "{tmp}/bad.json"],
        ["argument --physics", "bad.json", "Expecting property name"],
    ),
    "physics file a list": (
        [*PRE, "--physics", "{tmp}/list.json"],
        ["argument --physics", "list.json", "must hold a JSON object, got list"],
    ),
    "physics file with an unknown field": (
        [*PRE, "--physics", "{tmp}/extra.json"],
        ["argument --physics", "extra.json", "unknown sensor physics field(s) ['exposure']"],
    ),
    "physics file with a bad value": (
        [*PRE, "--physics", "{tmp}/fill.json"],
        ["argument --physics", "fill.json", "fill_factor must be a finite number in (0, 1], got 1.5"],
    ),
    "physics flag over the range": (
        [*PRE, "--photons-per-um2", "5", "--sensor-um", "80x60", "--adc-bits", "40"],
        ["argument --adc-bits", "must be an integer in [1, 32], got '40'"],
    ),
    "family without a file": (
        ["export", "--family", "spline", *MASK, "--out", "{tmp}/x.svg"],
        ["--family", "'spline'", "--layout FILE"],
    ),
    "unknown family": (
        ["export", "--family", "hex", *MASK, "--out", "{tmp}/x.svg"],
        ["--family", "'hex'", "choose from"],
    ),
}
CASES |= {
    f"mask under a file ({fmt})": (
        ["export", "--family", "uniform", *MASK, "--out", "{tmp}/afile/x." + fmt],
        ["--out", "afile/x." + fmt, "afile' is a file, not a folder"],
    )
    for fmt in ("gds", "svg")
}
CASES |= {
    "report under a file": (
        ["export", "--family", "uniform", *MASK, "--out", "{tmp}/x.svg", "--report", "{tmp}/afile/r.json"],
        ["--report", "afile/r.json", "is a file, not a folder"],
    ),
    "mask onto a folder": (
        ["export", "--family", "uniform", *MASK, "--out", "{tmp}"],
        ["--out", "must be a file", "is a folder"],
    ),
}
EXPORT = ["export", "--family", "uniform", *MASK]
CASES |= {  # what a reviewer's sweep of bad inputs found accepted, run, or ended in a traceback
    "bench threads past the pool": (
        ["bench", "--quick", "--threads", "100000"],
        ["--threads", "[1, 256]", "100000"],
    ),
    "landscape grid too large": (
        ["landscape", "mnist", "--quick", "--family", "curv", "--grid", "100000", "--out", "{tmp}/out"],
        ["--grid", "[2, 25]", "100000"],
    ),
    "landscape grid of one point": (
        ["landscape", "mnist", "--quick", "--family", "curv", "--grid", "1", "--out", "{tmp}/out"],
        ["--grid", "[2, 25]"],
    ),
    "report over the mask": (
        [*EXPORT, "--out", "{tmp}/x.svg", "--report", "{tmp}/x.svg"],
        ["--report", "also --out"],
    ),
    "report over the layout file": (
        [
            "export",
            "--layout",
            "{tmp}/curv.json",
            "--sensor-um",
            "40x40",
            "--out",
            "{tmp}/x.svg",
            "--report",
            "{tmp}/curv.json",
        ],
        ["--report", "also --layout (an input)"],
    ),
    "bench results and tables in one file": (
        ["bench", "--quick", "--json", "{tmp}/x.json", "--text", "{tmp}/x.json"],
        ["--text", "also --json (another output)"],
    ),
    "bench plot of an unknown format": (
        ["bench", "--quick", "--plot", "{tmp}/x.txt"],
        ["--plot", ".png, .pdf, .svg"],
    ),
    "shipping a study onto itself": (
        ["study", "mnist", "--quick", "--out", "{tmp}", "--ship", "{tmp}"],
        ["--ship", "no study in"],
    ),
    "weights without ship": (
        ["study", "mnist", "--quick", "--weights", "int8", "--out", "{tmp}/out"],
        ["--weights", "needs --ship"],
    ),
    "theta frozen for every epoch": (
        ["train", "mnist", "--quick", "--epochs", "1", "--freeze-epochs", "5", "--out", "{tmp}/out"],
        ["--freeze-epochs", "5 would freeze θ for all 1 epochs"],
    ),
    "preprocess a folder without images": (
        ["preprocess", "{tmp}/noimages", "{tmp}/out", "--family", "uniform", "--size", "8x6"],
        ["argument SRC", "no images", "noimages"],
    ),
    "benchmark a folder without images": (
        ["preprocess", "{tmp}/noimages", "{tmp}/out", "--family", "uniform", "--size", "8x6", "--benchmark"],
        ["argument SRC", "no images"],
    ),
    "labels that match no image": (
        [*PRE, "--labels", "{tmp}/noimages"],
        ["argument --labels", "holds no label map for any image"],
    ),
    "dask address that is not one": (
        [*PRE, "--engine", "dask", "--address", "tcp://h:port"],
        ["--address", "HOST[:PORT]"],
    ),
    "f-number without a psf": (
        [*PRE, "--photons-per-um2", "5", "--sensor-um", "80x60", "--f-number", "2"],
        ["--f-number", "needs --psf"],
    ),
    "a psf wider than the sensor": (
        [*PRE, "--photons-per-um2", "5", "--sensor-um", "80x60", "--psf", "airy", "--f-number", "1e9"],
        ["--f-number", "1e+09", "over 4 times the sensor"],
    ),
    "an extent past a kilometre": (
        [*PRE, "--photons-per-um2", "5", "--sensor-um", "1e300x1e300"],
        ["--sensor-um", "1e+09"],
    ),
    "px-per-um for an svg": ([*EXPORT, "--px-per-um", "10", "--out", "{tmp}/x.svg"], ["--px-per-um", "PNG"]),
    "gds layer past 2 bytes": (
        [*EXPORT, "--gds-layer", "70000", "--out", "{tmp}/x.gds"],
        ["--gds-layer", "[0, 32767]"],
    ),
    "the meta device": ([*PRE, "--device", "meta"], ["--device", "'meta' holds no data"]),
    "layout file without theta": (
        ["export", "--layout", "{tmp}/notheta.json", *MASK, "--out", "{tmp}/x.svg"],
        ["--layout", "'theta' is missing"],
    ),
    "layout file with a bound past 1": (
        ["export", "--layout", "{tmp}/bound10.json", *MASK, "--out", "{tmp}/x.svg"],
        ["--layout", "bound must be a finite number in (0, 1], got 10"],
    ),
    "a demo photo cut short": (
        ["demo", "--image", "{tmp}/cut.png", "--out", "{tmp}/out"],
        ["--image", "truncated PNG"],
    ),
    "an unknown flag of a command": (
        ["doctor", "--bogus"],
        ["layoutwarp doctor: error: unrecognized arguments: --bogus"],
    ),
}
CASES |= {
    "labels folder missing": (
        [*PRE, "--labels", "{tmp}/nolabels", "--label-rule", "majority"],
        ["argument --labels", "no such folder", "nolabels"],
    ),
    "label rule without labels": (
        [*PRE, "--label-rule", "majority"],
        ["--label-rule", "needs --labels", "majority"],
    ),
    "preprocess onto its own source": (
        [
            "preprocess",
            "{tmp}/photos",
            "{tmp}/photos",
            "--family",
            "curv",
            "--theta",
            "0.5,0.3",
            "--size",
            "32x24",
        ],
        ["argument DST", "is the source folder", "photos"],
    ),
    "bench results under a file": (
        ["bench", "--quick", "--json", "{tmp}/afile/x.json"],
        ["--json", "afile' is a file"],
    ),
    "bench table under a file": (
        ["bench", "--quick", "--text", "{tmp}/afile/x.md"],
        ["--text", "afile' is a file"],
    ),
    "bench plot onto a folder": (
        ["bench", "--quick", "--plot", "{tmp}"],
        ["--plot", "must be a file", "is a folder"],
    ),
    "raster mask too fine to hold": (
        ["export", "--family", "uniform", *MASK, "--px-per-um", "100000", "--out", "{tmp}/x.png"],
        ["--px-per-um", "100000", "raster mask", "of memory", "available"],
    ),
    "raster mask too fine to draw": (
        [
            "export",
            "--family",
            "uniform",
            "--size",
            "4x4",
            "--sensor-um",
            "4000x40",
            "--px-per-um",
            "1e5",
            "--out",
            "{tmp}/x.png",
        ],
        ["--px-per-um", "400000000x4000000 raster mask", "a side OpenCV draws"],
    ),
}
CASES["demo photo a folder"] = (["demo", "--image", "{tmp}/photos"], ["--image", "photos' is a folder"])
CASES["bench photo no image"] = (
    ["bench", "--image", "{tmp}/bad.json"],
    ["--image", "cannot read", "bad.json"],
)
CASES["gds of a sensor under its grid"] = (
    ["export", "--family", "curv", "--theta", "0.3,0.2", "--size", "4x4", "--sensor-um", "1e-6x1e-6",
     "--out", "{tmp}/x.gds"],
    ["--sensor-um", "1e-06x1e-06", "pitch 1.75e-07", "GDSII's 0.001 µm grid"],
)  # fmt: skip
CASES["a θ learning rate that diverges"] = (
    ["train", "mnist", "--quick", "--family", "curv", "--theta-lr", "1e9", "--out", "{tmp}/out"],
    ["argument --theta-lr", "training diverged", "is no layout", "lower --theta-lr"],
)
CASES["export report over its index mask"] = (
    ["export", "--family", "uniform", *MASK, "--out", "{tmp}/x.png", "--report", "{tmp}/x_index.png"],
    ["--report", "x_index.png", "--out (its index mask)"],
)
CASES |= {
    f"grid coarser than a pixel ({fmt})": (
        ["export", "--family", "uniform", *MASK, "--grid-um", "20", "--out", "{tmp}/x." + fmt],
        ["--grid-um", "20", "not finer than the smallest pixel", "pitch 10"],
    )
    for fmt in ("gds", "dxf", "svg", "png")
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_ends_in_one_line_naming_flag_value_and_range(case, files, capsys):
    argv, needles = CASES[case]
    argv = [a.replace("{tmp}", str(files)) for a in argv]
    with pytest.raises(SystemExit) as exit_info:  # argparse's own errors exit; ours return
        sys.exit(main(argv))
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err, captured.err
    assert lines[0].startswith("layoutwarp ") and ": error: " in lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert not any(files.glob("x.*")) and not (files / "out").exists()  # nothing written


@pytest.mark.parametrize("command", ["train", "study"])
def test_without_data_the_error_says_where_data_comes_from(command, monkeypatch, capsys):
    monkeypatch.delenv("LAYOUTWARP_DATA", raising=False)
    assert main([command, "camvid", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    for needle in ("no camvid data", "--data DIR", "LAYOUTWARP_DATA", "camvid/", "--quick"):
        assert needle in err, (needle, err)
    monkeypatch.setenv("LAYOUTWARP_DATA", "/nonexistent/root")
    assert main([command, "camvid", "--no-progress"]) == 2
    assert "no camvid data at '/nonexistent/root/camvid'" in capsys.readouterr().err


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0 and capsys.readouterr().out.strip() == f"layoutwarp {lw.__version__}"


def _subparsers(parser, prefix=""):
    """``("train mnist", parser)`` for every (nested) command."""
    for action in parser._actions:
        if hasattr(action, "choices") and isinstance(action.choices, dict):
            for name, sub in action.choices.items():
                yield prefix + name, sub
                yield from _subparsers(sub, prefix + name + " ")


def test_every_command_has_a_description_and_shows_defaults_the_same_way():
    parser = build_parser()
    assert "`" not in parser.description and "\n" not in parser.description
    subs = dict(_subparsers(parser))
    tasks = {f"{c} {t}" for c in ("train", "study") for t in ("mnist", "camvid", "faces")}
    assert {"demo", "bench", "preprocess", "export", "evaluate", "train", "study"} | tasks <= set(subs)
    for name, sub in subs.items():
        assert sub.description and "\n" not in sub.description.strip(), name
        help_text = sub.format_help()
        assert "(default: None)" not in help_text and "(default: False)" not in help_text
        formatter = sub.formatter_class("x")
        for action in sub._actions:
            if not action.help or action.option_strings == ["-h", "--help"]:
                continue
            shown = formatter._expand_help(action)
            if action.default not in (None, False):  # a default is shown once, as argparse holds it
                assert shown.count("default") == 1 and "(default: " in shown, (name, action.dest, shown)
                assert "(" not in str(action.default) or "WIDTH" not in shown, (name, action.dest, shown)
    assert (
        "--family" in subs["train mnist"].format_help()
        and "--layout" not in subs["train mnist"].format_help()
    )
    for name in ("export", "preprocess"):
        assert "--layout FILE" in subs[name].format_help() and "--family" in subs[name].format_help()


def test_each_task_takes_the_same_options_and_shows_its_own_defaults():
    from layoutwarp.experiments.tasks import TASKS

    subs = dict(_subparsers(build_parser()))
    common = None
    for task in TASKS.values():
        d, q = task.defaults, task.quick_defaults()
        text = " ".join(subs[f"train {task.name}"].format_help().split())
        assert f"epochs (default: {d.epochs}; {q.epochs} with --quick)" in text
        assert f"seeds (default: {d.seeds}; 1 with --quick)" in text
        sizes = " and ".join(f"{w}x{h}" for h, w in d.sizes)
        assert f"(default: {sizes}; the first with --quick)" in text
        flags = {o for a in subs[f"train {task.name}"]._actions for o in a.option_strings}
        flags -= {o for dest in task.extra_dests for o in ("--" + dest.replace("_", "-"),)}
        if task.nets:  # a task with several networks: which one, and its backbone's start
            assert {"--net", "--backbone-weights"} <= flags, task.name
            flags -= {"--net", "--backbone-weights"}
        assert common is None or flags == common, task.name  # the same options, less the task's own
        common = flags
    assert {"--size", "--freeze-epochs", "--theta-lr", "--data", "--quick"} <= common


def test_demo_writes_figures_and_numbers(tmp_path):
    image = str(SAMPLES / "photos" / "kodim03.png")
    assert main(["demo", "--image", image, "--size", "16x12", "--out", str(tmp_path)]) == 0
    numbers = json.loads((tmp_path / "demo.json").read_text())
    assert {d["family"] for d in numbers["layouts"].values()} == {"uniform", "rect", "curv", "spline", "grid"}
    assert (tmp_path / "layouts.png").stat().st_size > 10_000
    assert sorted(tmp_path.iterdir()) == sorted(demo_outputs(tmp_path))  # what it says it writes
    # a photo among those files is refused before anything is written over it
    kept = (tmp_path / "layouts.png").read_bytes()
    again = ["demo", "--image", str(tmp_path / "layouts.png"), "--size", "16x12", "--out", str(tmp_path)]
    assert main(again) == 2 and (tmp_path / "layouts.png").read_bytes() == kept
    # the layouts fitted to the photo's edges are not uniform
    assert numbers["layouts"]["grid from edges"]["pixel_area_ratio_max_over_min"] > 1.5


def test_python_dash_m_entry_point():
    res = subprocess.run([sys.executable, "-m", "layoutwarp", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "demo" in res.stdout


@pytest.mark.slow
@pytest.mark.parametrize(
    "script", ["quickstart.py", "kornia_pipeline.py", "preprocess_and_export.py", "route_of_a_step.py"]
)
def test_examples_run(script):
    cmd = [sys.executable, str(ROOT / "examples" / script)]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]


def test_a_negative_value_after_its_flag_is_the_flags_value(tmp_path, capsys):
    """``--theta -0.5,0.5`` works as ``--theta=-0.5,0.5`` does (argparse alone read a value that
    starts with a minus as a flag and said 'expected one argument'); a flag followed by a flag stays."""
    from layoutwarp.cli import join_negative_values, main

    argv = ["export", "--theta", "-0.5,0.5", "--size", "-4x4", "--manhattan", "--range", "-.8,.8", "-o", "x"]
    assert join_negative_values(argv) == [
        "export",
        "--theta=-0.5,0.5",
        "--size=-4x4",
        "--manhattan",
        "--range=-.8,.8",
        "-o",
        "x",
    ]
    out = tmp_path / "neg.svg"
    common = ["--sensor-um", "40x40", "--out", str(out)]
    assert main(["export", "--family", "curv", "--theta", "-0.5,0.5", "--size", "4x4", *common]) == 0
    assert out.is_file()
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:  # argparse's own refusal of the value, as for any bad value
        main(["export", "--family", "curv", "--theta", "-0.5,0.5", "--size", "-4x4", *common])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.endswith("argument --size: width and height must be >= 1, got '-4x4'")


@pytest.mark.parametrize(
    "argv, status",
    [
        (["--help"], 0),
        (["--version"], 0),
        ([], 2),
        (["frobnicate"], 2),
        (["doctor", "--bogus"], 2),
        (["bench", "--threads", "0"], 2),
        (["demo", "--size", "4"], 2),
        (["train", "mnist", "--help"], 0),
        (["train", "camvid", "--net", "unet"], 2),
        (["study", "faces", "--epochs", "0"], 2),
        (["landscape", "mnist", "--family", "fovea"], 2),
        (["export", "--size", "-4x4"], 2),
        (["evaluate", "nope", "--model", "m", "--data", "d"], 2),
        (["preprocess", "--help"], 0),
    ],
)
def test_help_and_argument_errors_import_no_torch(argv, status):
    """Every help and every argument error answers before torch (or numba) is imported: the
    parser lists tasks and families from the torch-free task protocols and family names."""
    code = (
        "import sys\nfrom layoutwarp.cli import main\n"
        f"try:\n    main({argv!r})\nexcept SystemExit as exc:\n    print('status', exc.code)\n"
        "print('heavy', sorted(m for m in ('torch', 'numba') if m in sys.modules))"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert f"status {status}" in res.stdout and "heavy []" in res.stdout, res.stdout + res.stderr


def test_save_layout_under_a_file_says_so_in_one_line(files):
    with pytest.raises(
        lw.checks.ArgumentError, match=r"cannot write .*afile/x\.json': .*afile' is a file, not a folder"
    ):
        lw.save_layout(lw.CurvLayout((0.3, 0.1)), files / "afile" / "x.json")
    with pytest.raises(lw.checks.ArgumentError, match=r"must be a file; .* is a folder"):
        lw.save_layout(lw.CurvLayout((0.3, 0.1)), files)


def test_the_torch_free_catalogues_are_the_registered_tasks_and_families():
    """What the parser lists without torch (experiments.protocols, layoutwarp.catalog) is what
    the registries hold once torch is loaded."""
    from layoutwarp.catalog import BUILTIN_FAMILIES, TWO_PARAMETER_FAMILIES
    from layoutwarp.experiments.protocols import SPECS, UINT8_TOLERANCE
    from layoutwarp.experiments.tasks import TASKS
    from layoutwarp.integrators import data_tolerance

    assert list(SPECS) == list(TASKS) and all(TASKS[n].spec is SPECS[n] for n in SPECS)
    assert list(lw.FAMILIES)[: len(BUILTIN_FAMILIES)] == list(BUILTIN_FAMILIES)  # a user's come after
    two = [n for n, cls in lw.FAMILIES.items() if cls.num_params == 2 and cls().num_params == 2]
    assert list(TWO_PARAMETER_FAMILIES) == two
    assert UINT8_TOLERANCE == data_tolerance(np.uint8)[0]


def test_the_decoders_lines_are_kept_off_and_everything_else_passes_as_it_comes(capfd):
    import os
    import time

    from layoutwarp.cli.common import quiet_decoders

    with quiet_decoders() as dropped:
        os.write(2, b"\rbar 1/3")  # a progress bar's partial line: shown after a moment
        time.sleep(0.3)
        os.write(2, b"\rbar 2/3]libpng error: IDAT: CRC error\n")  # a library's line after the bar
        os.write(2, b"[ WARN:0@1.2] global loadsave.cpp (1) imread_ x\nour own line\n")
        os.write(2, b"Corrupt JPEG data: 2 extraneous bytes before marker 0xd9\n\rbar 3/3]\n")
    assert capfd.readouterr().err == "\rbar 1/3\rbar 2/3]our own line\n\rbar 3/3]\n"
    assert dropped == [
        "libpng error: IDAT: CRC error",
        "[ WARN:0@1.2] global loadsave.cpp (1) imread_ x",
        "Corrupt JPEG data: 2 extraneous bytes before marker 0xd9",
    ]


def test_a_size_is_ascii_digits_an_x_and_ascii_digits():
    assert parse_wxh("257x129") == (129, 257) and parse_wxh("8X6") == (6, 8)
    for text in ("8 x 6", "8_0x6", "８x６", "8x6x2", "0x1p-2", " 8x6"):
        with pytest.raises(Exception, match="WIDTHxHEIGHT"):
            parse_wxh(text)
    with pytest.raises(Exception, match=">= 1"):
        parse_wxh("-4x4")


def test_the_decoders_filter_ends_at_once_and_loses_nothing(capfd):
    import os
    import time

    from layoutwarp.cli.common import quiet_decoders

    t = time.perf_counter()
    with quiet_decoders():
        os.write(2, b"a partial line")  # still waiting for its end when the context closes
    assert capfd.readouterr().err == "a partial line" and time.perf_counter() - t < 5
    held = [os.open(os.devnull, os.O_RDONLY) for _ in range(1100)]  # the pipe's descriptors past 1023
    try:
        with quiet_decoders() as dropped:
            os.write(2, b"libpng warning: iCCP: known incorrect sRGB profile\nkept\n")
    finally:
        for fd in held:
            os.close(fd)
    assert capfd.readouterr().err == "kept\n" and dropped == [
        "libpng warning: iCCP: known incorrect sRGB profile"
    ]


def test_a_folder_a_command_writes_into_is_not_another_commands(tmp_path, capsys):
    # a landscape's runs written among a study's, or a study shipped into its own runs/, were
    # read as the other's runs (a study summed a landscape's points into its own numbers)
    study = tmp_path / "st"
    (study / "runs").mkdir(parents=True)
    land = ["landscape", "mnist", "--quick", "--family", "rect", "--study", study, "--out"]
    for argv, needle in [
        ([*land, study], "is --study"),
        ([*land, study / "runs"], "lies inside --study"),
        (["study", "mnist", "--quick", "--out", study, "--ship", study / "runs"], "lies inside --out"),
    ]:
        assert main([str(a) for a in argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0], err
    assert sorted(p.name for p in study.rglob("*")) == ["runs"]  # nothing written


def test_a_run_record_of_another_kind_is_refused_in_one_line(tmp_path):
    from layoutwarp.experiments.runs import read_runs, run_name

    def name(r: dict) -> str:
        return run_name(r["family"], r["size_hw"], r["seed"])

    (tmp_path / "runs").mkdir()
    record = {"family": "curv", "size_hw": [4, 4], "seed": 0, "scores": {}}
    (tmp_path / "runs" / "curv_4x4_seed0.json").write_text(json.dumps(record))
    assert read_runs(tmp_path, name, "a study") == [record]
    strays = {
        "study.json": json.dumps({"planned": 3}),  # a summary copied there
        "curv_4x4_tx+0_ty+0_seed0.json": json.dumps(record),  # a landscape's point
        "torn.json": '{"family": "cu',
    }
    for stray, text in strays.items():
        (tmp_path / "runs" / stray).write_text(text)
        with pytest.raises(ValueError, match=re.escape(f"{stray} is no run of a study")):
            read_runs(tmp_path, name, "a study")
        (tmp_path / "runs" / stray).unlink()
    # a writer's temporary file (another rank's write under way, or one a killed process left)
    # is no record: it was read as one, and refused the folder until removed by hand
    (tmp_path / "runs" / ".curv_4x4_seed0.json.q8w1z0cd.json").write_text('{"family": "cu')
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / ".curv_4x4_seed1.pt.k2j3h4.pt").write_bytes(b"")
    assert read_runs(tmp_path, name, "a study") == [record]
    from layoutwarp.experiments.runs import _made

    (tmp_path / "runs" / "curv_4x4_seed0.json").unlink()
    assert not _made(tmp_path)


@pytest.mark.parametrize(
    ("error", "status", "line"),
    [
        (PermissionError(13, "Permission denied", "/no/demo.json"), 1, "Permission denied: '/no/demo.json'"),
        (ImportError("plots need matplotlib: pip install 'layoutwarp[plot]'"), 1,
         "plots need matplotlib: pip install 'layoutwarp[plot]'"),
        (KeyboardInterrupt(), 130, "interrupted"),
        (Terminated(), 143, "terminated"),
    ],
)  # fmt: skip
def test_an_unwritable_file_or_a_ctrl_c_ends_in_one_line(error, status, line, tmp_path, monkeypatch, capsys):
    def fail(*args, **kwargs):
        (tmp_path / "a" / "b" / "out").mkdir(parents=True)  # made, as a command makes its --out
        raise error

    monkeypatch.setattr("layoutwarp.experiments.demo.run_demo", fail)
    assert main(["demo", "--size", "8x6", "--out", str(tmp_path / "a" / "b" / "out")]) == status
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"layoutwarp demo: {'error: ' if status == 1 else ''}{line}"]
    assert not (tmp_path / "a").exists()  # the empty folders it made are gone (those above --out too)


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (Linux's /proc)."""
    kids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError):
                stat = open(f"/proc/{entry}/stat").read()
                if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                    kids.append(int(entry))
    return kids


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the processes from /proc")
def test_sigterm_stops_a_command_as_ctrl_c_does_and_its_compiles_with_it(tmp_path):
    # SIGTERM (torchrun ending a rank, a scheduler) killed the command without its cleanup (a
    # rank's temporary folder left, no manifest), and `doctor --compile` left its compiling
    # children running; a Ctrl-C there still started the units not begun
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}  # empty: everything compiles
    proc = subprocess.Popen(
        [sys.executable, "-m", "layoutwarp", "doctor", "--compile"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    deadline = time.monotonic() + 60
    while not (kids := _children(proc.pid)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert kids, "no compile started"
    proc.send_signal(signal.SIGTERM)
    try:  # at once: the compiles under way killed, the units not begun never begun (the code
        _, err = proc.communicate(timeout=20)  # before waited for every unit: 30-90 s)
    finally:
        proc.kill()
    assert proc.returncode == 143 and err.strip().endswith("terminated"), err[-2000:]
    time.sleep(0.5)
    assert not [k for k in kids if os.path.exists(f"/proc/{k}")]  # its compiles stopped with it


def test_a_process_group_that_fails_ends_in_one_line(tmp_path, monkeypatch, capsys):
    # a rank gone (killed, failed): the others' collectives raised the backend's RuntimeError,
    # printed as a 30-line traceback per rank; any other RuntimeError (out of memory, a bug of
    # ours) keeps its traceback, in a process group or not
    import torch.distributed as dist

    errors = []

    def fail(*args, **kwargs):
        raise errors[-1]

    monkeypatch.setattr("layoutwarp.experiments.demo.run_demo", fail)
    argv = ["demo", "--size", "8x6", "--out", str(tmp_path / "out")]
    gone = RuntimeError("[../gloo/transport/tcp/pair.cc:534] Connection closed by peer\nmore lines")
    for joined in (True, False):
        monkeypatch.setattr(dist, "is_initialized", lambda joined=joined: joined)
        errors.append(gone)
        if joined:
            assert main(argv) == 1
            assert capsys.readouterr().err.strip().splitlines() == [
                "layoutwarp demo: error: the process group failed (did another rank stop?): "
                "[../gloo/transport/tcp/pair.cc:534] Connection closed by peer"
            ]
        else:
            with pytest.raises(RuntimeError, match="Connection closed by peer"):
                main(argv)
        errors.append(RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB"))
        with pytest.raises(RuntimeError, match="CUDA out of memory"):
            main(argv)


@pytest.mark.parametrize(
    ("task", "model", "line"),
    [
        ("faces", "faces/models/density_8x8_seed0.pt",
         "argument --split: a faces folder has no splits (every face in labels.csv is scored), got split"),
        ("camvid", "camvid/models/uniform_48x36_seed1.pt", "argument --split: no CamVid images in "),
    ],
)  # fmt: skip
def test_evaluate_names_a_bad_split_once_and_as_the_split(task, model, line, capsys):
    # faces said "argument --split: --split: ..."; camvid blamed an unknown split on --data
    argv = [
        "evaluate",
        task,
        "--model",
        str(ROOT / "examples" / "study" / model),
        "--data",
        str(SAMPLES / task),
    ]
    assert main([*argv, "--split", "nope"]) == 2
    assert capsys.readouterr().err.startswith(f"layoutwarp evaluate: error: {line}")
