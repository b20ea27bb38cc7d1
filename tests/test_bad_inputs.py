"""Bad arguments to the Python API end in one line that names the argument, the value and what is
allowed: never a raw torch, numpy or OpenCV message, never a silent wrong result (the cases a
reviewer's sweep of bad inputs found)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

import layoutwarp as lw
from layoutwarp.checks import ArgumentError

L = lw.CurvLayout((0.3, 0.2))
IMG = torch.rand(1, 3, 48, 64, generator=torch.Generator().manual_seed(0))
PHYS = {"sensor_um": [60.0, 80.0], "photons_per_um2": 50.0}
MEAN, AREAS = torch.rand(1, 6, 8), torch.full((6, 8), 4 / 48)


def _spread(layout):
    with torch.no_grad():  # as a training step with a large learning rate may leave it
        layout.rho[2:] = torch.tensor([30.0, -30.0, 0.0])
    return layout


def _resampler(**kwargs):
    return lw.AreaResampler(L, (6, 8), (48, 64), **kwargs)


# name: (call, the argument named, a substring of the one-line message)
CASES = {
    "a bound past 1 folds the layout": (
        lambda: lw.CurvLayout((5, 0.2), bound=10),
        "bound",
        "in (0, 1], got 10",
    ),
    "an integer dtype would truncate θ": (
        lambda: lw.CurvLayout((0.1, 0.2), dtype=torch.int32),
        "dtype",
        "floating-point torch.dtype",
    ),
    "a dtype given as text": (lambda: lw.CurvLayout((0.1, 0.2), dtype="float32"), "dtype", "got 'float32'"),
    "a complex θ": (lambda: lw.CurvLayout(torch.tensor([0.1 + 1j, 0])), "theta", "2 numbers"),
    "a θ of shape (1, 2)": (lambda: lw.CurvLayout(np.array([[0.1, 0.2]])), "theta", "2 numbers"),
    "learn as text": (lambda: lw.CurvLayout((0.1, 0.2), learn="yes"), "learn", "True or False, got 'yes'"),
    "allow_nonfinite as text": (
        lambda: lw.simulate(IMG, L, (6, 8), allow_nonfinite="no"),
        "allow_nonfinite",
        "True or False",
    ),
    "a generator that is not one": (
        lambda: lw.simulate(IMG, L, (6, 8), "montecarlo", generator="x"),
        "generator",
        "torch.Generator",
    ),
    "spline logits spread past what float64 resolves": (
        lambda: lw.SplineLayout([20.0, -20.0, 0.0, 0.0], knots=(2, 2)),
        "theta",
        "the x knot logits spread from -20 to 20, so a piece is narrower than float64 resolves",
    ),
    "a learnable spline a step spread past what float64 resolves": (
        lambda: lw.simulate(IMG, _spread(lw.SplineLayout(knots=(2, 3), learn=True)), (6, 8)),
        "theta",
        "the y knot logits spread from -30 to 30",
    ),
    "a seed and a generator (simulate)": (
        lambda: lw.simulate(IMG, L, (6, 8), "montecarlo", seed=1, generator=torch.Generator()),
        "generator",
        "generator and seed are two sources of the call's random draws",
    ),
    "a seed and a generator (layer)": (
        lambda: lw.SensorLayer((6, 8), L, "montecarlo", seed=1, generator=torch.Generator()),
        "generator",
        "pass one of them",
    ),
    "a seed and a generator (sample points)": (
        lambda: lw.maps.sample_points((6, 8), 2, jitter=True, seed=1, generator=torch.Generator()),
        "generator",
        "pass one of them",
    ),
    "a seed and a generator (measure)": (
        lambda: lw.measurement.measure(MEAN, AREAS, PHYS, generator=torch.Generator(), seed=torch.tensor(1)),
        "generator",
        "pass one of them",
    ),
    "a seed and a generator (resampler)": (
        lambda: _resampler().apply(IMG[0], PHYS, generator=torch.Generator(), seed=torch.tensor(1)),
        "generator",
        "pass one of them",
    ),
    "a seed past torch's 64 bits": (
        lambda: lw.simulate(IMG, L, (6, 8), "montecarlo", seed=2**63),
        "seed",
        "integer in [0, 9223372036854775807] or None, got 9223372036854775808",
    ),
    "a seed that is text": (
        lambda: lw.simulate(IMG, L, (6, 8), "montecarlo", seed="a"),
        "seed",
        "integer in [0, 9223372036854775807]",
    ),
    "a family name for a layout (maps)": (
        lambda: lw.forward_maps("curv", (6, 8), (48, 64)),
        "layout",
        "make_layout('curv'",
    ),
    "a family name for a layout (back-warp)": (
        lambda: lw.backwarp(torch.rand(1, 1, 6, 8), "curv", (48, 64)),
        "layout",
        "layoutwarp Layout",
    ),
    "a family name for a layout (export)": (
        lambda: lw.export_layout("curv", (6, 8), "m.svg", (60, 80)),
        "layout",
        "Layout",
    ),
    "a family name for a layout (resampler)": (
        lambda: lw.AreaResampler("curv", (6, 8), (48, 64)),
        "layout",
        "Layout",
    ),
    "save_layout with its arguments swapped": (
        lambda: lw.save_layout("x.json", L),
        "layout",
        "Layout, got str",
    ),
    "a size given as text to save_layout": (lambda: lw.save_layout(L, "x.json", size="8x6"), "size", "size"),
    "NaN in a layout file's extras": (
        lambda: lw.save_layout(L, "x.json", acc=float("nan")),
        "extra",
        "JSON numbers",
    ),
    "a size given as text": (
        lambda: lw.simulate(IMG, L, "34"),
        "size",
        "pair (H, W) of positive integers, got '34'",
    ),
    "a size of text numbers": (lambda: lw.simulate(IMG, L, ("3", "4")), "size", "positive integers"),
    "a grid's min_det outside (0, 1)": (lambda: lw.GridLayout(min_det=5), "min_det", "in (0, 1), got 5"),
    "a grid's min_det as text": (lambda: lw.GridLayout(min_det="a"), "min_det", "got 'a'"),
    "a grid size against its control points": (
        lambda: lw.GridLayout(lw.coords.uniform_corners((4, 4)), grid=(3, 3)),
        "grid",
        "disagrees with the control points' grid (4, 4)",
    ),
    "a resampler on a device torch does not know": (
        lambda: _resampler(device="nonsense"),
        "device",
        "torch device",
    ),
    "a resampler for a dtype that is not one": (
        lambda: _resampler(dtype="bogus"),
        "dtype",
        "numpy or torch dtype",
    ),
    "a resampler given a tensor": (lambda: _resampler()(IMG), "image", "use apply()"),
    "a resampler given complex pixels": (
        lambda: _resampler()(np.ones((48, 64, 3), np.complex64)),
        "image",
        "real numbers",
    ),
    "a resampler given NaN": (
        lambda: _resampler()(np.full((48, 64, 3), np.nan, np.float32)),
        "image",
        "NaN or Inf",
    ),
    "a mask of fractional line width": (
        lambda: lw.export_layout(L, (6, 8), "m.png", (60, 80), line_width=2.5),
        "line_width",
        "integer >= 1",
    ),
    "an empty GDSII cell name": (
        lambda: lw.export_layout(L, (6, 8), "m.gds", (60, 80), cell=""),
        "cell",
        "non-empty",
    ),
    "a GDSII layer past 2 bytes": (
        lambda: lw.export_layout(L, (6, 8), "m.gds", (60, 80), layer=70000),
        "layer",
        "[0, 32767]",
    ),
    "physics text that is not JSON": (
        lambda: lw.SensorPhysics.from_json("not json"),
        "text",
        "must be JSON text",
    ),
    "a PRNU of 500 %": (lambda: lw.SensorPhysics(**PHYS, prnu=5), "prnu", "in [0, 1], got 5"),
    "an extent past a kilometre": (
        lambda: lw.SensorPhysics((1e300, 1e300), 50),
        "sensor_um",
        "in (0, 1e+09]",
    ),
    "an f-number that blurs everything": (
        lambda: lw.SensorPhysics(**PHYS, psf="airy", f_number=1e9),
        "f_number",
        "over 4 times the sensor's 80 µm",
    ),
    "the meta device": (
        lambda: lw.AreaResampler(L, (6, 8), (48, 64), device="meta"),
        "device",
        "'meta' holds no data",
    ),
    # the compiled product reads each image's (H, W) cells: another size read past it (values of
    # memory that is not the image) or a part of it, silently
    "images smaller than the resampler's source": (
        lambda: _resampler().apply(torch.ones(2, 7, 7)),
        "images",
        "(N, 48, 64) tensor, got shape (2, 7, 7)",
    ),
    "images larger than the resampler's source": (
        lambda: _resampler().apply(torch.ones(1, 96, 128)),
        "images",
        "(N, 48, 64) tensor, got shape (1, 96, 128)",
    ),
    "one image without its batch": (
        lambda: _resampler().apply(torch.ones(48, 64)),
        "images",
        "got shape (48, 64)",
    ),
    "a gradient of another sensor size": (
        lambda: _resampler().adjoint(torch.ones(1, 3, 3)),
        "grad",
        "(N, 6, 8) tensor, got shape (1, 3, 3)",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_argument_is_named_in_one_line(case, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing a case might write lands in the checkout
    call, argument, needle = CASES[case]
    with pytest.raises(ArgumentError) as info:
        call()
    message = str(info.value)
    assert info.value.argument == argument and needle in message and "\n" not in message, message
    assert not any(tmp_path.iterdir())  # refused before anything was written


@pytest.mark.parametrize(
    ("value", "dtype", "learn"),
    [(1e307, torch.float64, False), (1e307, torch.float64, True), (1e38, torch.float32, True)],
)
def test_a_finite_image_whose_sums_overflow_is_refused_in_one_line(value, dtype, learn):
    # its means came back NaN without a word: the check looked for NaN/Inf in the input alone
    img = torch.full((1, 1, 16, 64), value, dtype=dtype)
    with pytest.raises(
        ValueError, match=r"image's values are finite, but the integrator's sums .* overflow"
    ) as info:
        lw.simulate(img, lw.CurvLayout((0.5, -0.3), learn=learn, dtype=dtype), (3, 4))
    assert "\n" not in str(info.value)
    out = lw.simulate(img, lw.CurvLayout((0.5, -0.3), learn=learn, dtype=dtype), (3, 4), allow_nonfinite=True)
    assert not bool(out.isfinite().all())  # let through where asked


def test_preprocessing_refuses_what_it_cannot_do_before_writing(tmp_path, monkeypatch):
    import cv2

    src = tmp_path / "src"
    src.mkdir()
    cv2.imwrite(str(src / "a.png"), np.zeros((48, 64, 3), np.uint8))
    bad = {
        "files": dict(files=["nothere.png"]),
        "device": dict(device="nonsense"),
        "tol": dict(tol=-1),
        "workers": dict(workers=100000),
    }
    for argument, kwargs in bad.items():
        with pytest.raises(ArgumentError) as info:
            lw.preprocess_folder(src, tmp_path / "dst", L, (6, 8), progress=False, **kwargs)
        assert info.value.argument == argument, (argument, str(info.value))
    (tmp_path / "empty").mkdir()
    with pytest.raises(ArgumentError, match="holds no images"):
        lw.preprocess_folder(tmp_path / "empty", tmp_path / "x", L, (6, 8))
    assert not (tmp_path / "dst").exists() and not (tmp_path / "x").exists()
    res = lw.preprocess_folder(
        src, tmp_path / "dst", L, (6, 8), progress=False, physics=PHYS
    )  # a dict, as files hold it
    assert res.processed == 1 and not res.failed
    # a float image holding NaN (as a float TIFF decodes; older OpenCVs write float TIFFs otherwise)
    import layoutwarp.preprocess as pre

    cv2.imwrite(str(src / "nan.png"), np.zeros((48, 64, 3), np.uint8))
    read = pre.read_image

    def nan_for_nan_png(path, *args):
        img = read(path, *args)
        return np.full(img.shape, np.nan, np.float32) if path.name == "nan.png" else img

    monkeypatch.setattr(pre, "read_image", nan_for_nan_png)
    res = lw.preprocess_folder(src, tmp_path / "dst2", L, (6, 8), progress=False)
    assert [f["file"] for f in res.failed] == ["nan.png"] and "NaN or Inf" in res.failed[0]["error"]


def _stepped_to(family: str, rho: list[float], dtype: torch.dtype = torch.float64) -> lw.Layout:
    """A learnable layout whose ρ a training step moved to ``rho`` (in place, as an optimiser
    does: nothing checks it there)."""
    layout = lw.make_layout(family, (0.2, -0.1), learn=True, dtype=dtype)
    with torch.no_grad():
        layout.rho.copy_(torch.tensor(rho))
    return layout


@pytest.mark.parametrize(
    ("family", "rho", "dtype", "theta"),
    [
        ("curv", [float("nan"), 0.1], torch.float64, "theta[0] = nan"),
        ("curv", [0.1, 20.0], torch.float64, "theta[1] = 1.0"),  # tanh(20) rounds to 1
        ("rect", [-20.0, 0.1], torch.float64, "theta[0] = -1.0"),
        ("elliptic", [0.1, float("inf")], torch.float32, "theta[1] = 1.0"),
        ("curv", [12.0, 0.1], torch.float32, "theta[0] = 1.0"),  # in float32 from about 9
    ],
)
@pytest.mark.parametrize("method", ["exact", "point", "montecarlo"])
def test_a_learnable_theta_a_step_made_no_layout_is_refused_in_one_line(family, rho, dtype, theta, method):
    # NaN sample points crashed torch's grid_sample backward (SIGSEGV) for point and Monte Carlo;
    # exact gave NaN, rect at ρ = -20 a torch error about negative repeats
    layout = _stepped_to(family, rho, dtype)
    img = IMG.to(dtype).requires_grad_(True)
    with pytest.raises(
        ArgumentError, match=rf"^{re.escape(theta)} \(rho\[\d\] = .*is no layout.*bound = 1"
    ) as e:
        lw.simulate(img, layout, (6, 8), method, seed=0)
    assert e.value.argument == "theta" and "\n" not in str(e.value)
    with pytest.raises(ArgumentError, match="is no layout"):  # back-warping takes the same check
        lw.backwarp(torch.rand(1, 1, 6, 8), layout, (48, 64), mode="bilinear")


def test_a_state_dict_whose_theta_is_no_layout_is_refused_before_it_loads():
    layer = lw.SensorLayer((6, 8), "curv", "point")
    before = layer.layout.rho.detach().clone()
    state = layer.state_dict()
    state["layout.rho"] = torch.tensor([float("nan"), 0.1])
    with pytest.raises(ArgumentError, match=r"theta\[0\] = nan \(rho\[0\] = nan\) is no layout"):
        layer.load_state_dict(state)
    assert torch.equal(layer.layout.rho.detach(), before)  # nothing taken
    fixed = lw.CurvLayout((0.3, 0.2))
    state = fixed.state_dict() | {"fixed_theta": torch.tensor([0.3, 1.0], dtype=torch.float64)}
    with pytest.raises(ArgumentError, match=r"theta\[1\] = 1.0 is no layout"):
        fixed.load_state_dict(state)
    assert fixed.theta_as(torch.float64).tolist() == [0.3, 0.2]


def test_a_folded_theta_is_refused_on_the_evaluation_path_too_and_nowhere_values_cannot_be_read():
    from torch._subclasses.fake_tensor import FakeTensorMode

    layout = _stepped_to("curv", [float("nan"), 0.1], torch.float32)
    with torch.no_grad(), pytest.raises(ArgumentError, match="is no layout"):  # the kept weights' path
        lw.simulate(IMG, layout, (6, 8))
    # fake tensors (shape propagation) read no values: the call is traced as before
    usable = lw.SensorLayer((6, 8), "curv", learn=True)
    with FakeTensorMode(allow_non_fake_inputs=True) as mode:
        out = usable(mode.from_tensor(IMG))
    assert out.shape == (1, 3, 6, 8)


def test_a_bfloat16_layout_is_checked_at_the_precision_it_is_computed_in():
    # θ = tanh(3.5) rounds to 1 in bfloat16, not in the float32 the integrators compute it in
    layout = _stepped_to("curv", [3.5, 0.1], torch.bfloat16)
    out = lw.simulate(IMG, layout, (6, 8))
    assert torch.isfinite(out).all()


def test_the_largest_seed_runs_where_a_call_derives_seeds_from_it():
    from layoutwarp.checks import SEED_MAX

    physics = lw.SensorPhysics(sensor_um=(40.0, 40.0), photons_per_um2=50.0)
    assert lw.simulate(IMG, L, (6, 8), physics=physics, seed=SEED_MAX).shape == (1, 3, 6, 8)
    learn = lw.CurvLayout((0.3, 0.2), learn=True)
    out = lw.simulate(IMG, learn, (6, 8), "montecarlo", seed=SEED_MAX, grad="reynolds")
    out.sum().backward()
    assert torch.isfinite(learn.rho.grad).all()
