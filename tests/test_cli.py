"""The command line: the demo main job writes its figures and numbers."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from conftest import ROOT

from layoutwarp.cli import main, parse_wxh


def test_parse_wxh_is_width_by_height():
    assert parse_wxh("257x129") == (129, 257)
    with pytest.raises(Exception, match="WIDTHxHEIGHT"):
        parse_wxh("257")


def test_demo_writes_figures_and_numbers(tmp_path):
    assert (
        main(
            [
                "demo",
                "--image",
                str(ROOT / "data_samples" / "photos" / "kodim03.png"),
                "--size",
                "16x12",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    numbers = json.loads((tmp_path / "demo.json").read_text())
    assert set(d["family"] for d in numbers["layouts"].values()) == {"uniform", "rect", "curv"}
    assert (tmp_path / "layouts.png").stat().st_size > 10_000
    for fam in ("uniform", "rect", "curv"):
        assert (tmp_path / f"sensor_{fam}.png").exists()


def test_python_dash_m_entry_point():
    res = subprocess.run([sys.executable, "-m", "layoutwarp", "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "demo" in res.stdout


@pytest.mark.parametrize("script", ["quickstart.py", "kornia_pipeline.py", "preprocess_and_export.py"])
def test_examples_run(script):
    cmd = [sys.executable, str(ROOT / "examples" / script)]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
