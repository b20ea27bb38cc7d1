"""Layout files: round trips for every family, clear errors for bad files, old files still load."""

from __future__ import annotations

import json

import pytest
import torch
from conftest import rand_theta

import layoutwarp as lw
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


def test_files_written_by_version_0_1_still_load(tmp_path):
    # a layout file exactly as layoutwarp 0.1 wrote it
    old = {
        "format": "layoutwarp.layout/1",
        "family": "curv",
        "theta": [0.7016, 0.3129],
        "bound": 1.0,
        "size_hw": [4, 4],
        "version": "0.1.0",
        "extra": {"experiment": "mnist", "accuracy": 92.43},
    }
    (tmp_path / "old.json").write_text(json.dumps(old))
    layout, info = load_layout(tmp_path / "old.json", dtype=torch.float64)
    assert layout.family == "curv" and torch.allclose(
        layout.theta, torch.tensor([0.7016, 0.3129], dtype=torch.float64)
    )
    assert info == {
        "size_hw": [4, 4],
        "version": "0.1.0",
        "extra": {"experiment": "mnist", "accuracy": 92.43},
    }
    old |= {"family": "uniform", "theta": []}
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert load_layout(tmp_path / "old.json")[0].family == "uniform"


def test_missing_file_and_bad_size_name_the_file(tmp_path):
    with pytest.raises(ValueError, match=r"nope\.json: no such layout file"):
        load_layout(tmp_path / "nope.json")
    (tmp_path / "s.json").write_text(
        json.dumps({"format": "layoutwarp.layout/1", "family": "rect", "size_hw": [0, 3]})
    )
    with pytest.raises(ValueError, match=r"s.json: 'size_hw' must be \[H, W\]"):
        load_layout(tmp_path / "s.json")


def test_the_layout_key_follows_every_change_of_the_layout(gen):
    # kept between calls, the key must still change with θ set in place, an optimiser's step, a
    # replaced buffer and a changed setting, and match the description of the layout as it is
    from layoutwarp.layoutfile import layout_key, layout_spec

    def fresh(layout: lw.Layout) -> str:
        return json.dumps(layout_spec(layout), sort_keys=True)

    layout = lw.FoveaLayout(rand_theta(gen, 0.5), center=(0.2, -0.1))
    first = layout_key(layout)
    assert first == fresh(layout) and layout_key(layout) is first  # kept
    layout.set_theta(layout.theta.detach() * 0.5)
    assert layout_key(layout) == fresh(layout) != first
    learn = lw.CurvLayout(rand_theta(gen, 0.5), learn=True)
    before = layout_key(learn)
    opt = torch.optim.SGD(learn.parameters(), lr=0.1)
    lw.simulate(torch.rand(1, 1, 16, 16, generator=gen), learn, (3, 3)).sum().backward()
    opt.step()
    assert layout_key(learn) == fresh(learn) != before
    fixed = lw.CurvLayout((0.3, 0.2))
    before = layout_key(fixed)
    fixed.register_buffer("fixed_theta", fixed.fixed_theta.clone() * 0.5)  # a new tensor, its version 0
    assert layout_key(fixed) == fresh(fixed) != before
    before = layout_key(fixed)
    fixed.bound = 0.9
    assert layout_key(fixed) == fresh(fixed) != before
    assert layout_key(lw.CurvLayout((0.3, 0.2))) == layout_key(lw.CurvLayout((0.3, 0.2)))  # by value
