"""simulate() and SensorLayer: dtypes, shapes, edge sizes, errors, training behaviour."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from conftest import rand_theta

import layoutwarp as lw

F64 = torch.float64


@pytest.mark.parametrize("family", ["uniform", "rect", "curv"])
def test_batches_and_channels(family, gen, device):
    layout = lw.make_layout(family, None if family == "uniform" else rand_theta(gen)).to(device)
    img = torch.rand(3, 5, 40, 30, generator=gen).to(device)
    out = lw.simulate(img, layout, (6, 4))
    assert out.shape == (3, 5, 6, 4) and out.device == img.device
    for b in range(3):
        for c in range(5):
            single = lw.simulate(img[b : b + 1, c : c + 1], layout, (6, 4))
            assert torch.allclose(out[b, c], single[0, 0], atol=1e-6)
    assert lw.simulate(img[0], layout, (6, 4)).shape == (5, 6, 4)  # (C, H, W) accepted


@pytest.mark.parametrize("family", ["rect", "curv"])
def test_constant_image_gives_constant_output(family, gen):
    value = float(torch.rand(1, generator=gen)) * 10 - 5
    img = torch.full((1, 2, 33, 47), value, dtype=F64)
    for method in ("exact", "montecarlo", "point"):
        out = lw.simulate(img, lw.make_layout(family, rand_theta(gen, 0.999)), (9, 11), method)
        assert float((out - value).abs().max()) < 1e-6 * (1 + abs(value))


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_inputs_are_computed_in_float32(dtype, gen):
    img = torch.rand(2, 3, 64, 48, generator=gen)
    layout = lw.CurvLayout(rand_theta(gen))
    out = lw.simulate(img.to(dtype), layout, (8, 6))
    assert out.dtype == dtype
    ref = lw.simulate(img.to(dtype).float(), layout, (8, 6))
    assert torch.allclose(out.float(), ref, atol=float(torch.finfo(dtype).eps))


def test_uint8_is_scaled_to_unit_range(gen):
    img = torch.randint(0, 256, (1, 3, 30, 40), generator=gen, dtype=torch.uint8)
    out = lw.simulate(img, lw.UniformLayout(), (10, 20))
    assert out.dtype == torch.float32
    ref = cv2.resize(
        img[0].permute(1, 2, 0).numpy().astype(np.float32) / 255, (20, 10), interpolation=cv2.INTER_AREA
    )
    assert np.abs(out[0].permute(1, 2, 0).numpy() - ref).max() < 1e-6


@pytest.mark.parametrize("family", ["rect", "curv"])
@pytest.mark.parametrize("size", [(1, 1), (1, 13), (13, 1), (80, 100)])
def test_tiny_and_upsampling_sensors(family, size, gen):
    # (80, 100) is larger than the 20x30 source: sensor pixels smaller than source pixels
    layout = lw.make_layout(family, rand_theta(gen, 0.9), dtype=F64)
    img = torch.rand(1, 2, 20, 30, generator=gen, dtype=F64)
    out = lw.simulate(img, layout, size, tol=1e-5)
    assert out.shape == (1, 2, *size)
    # the areas of the mesh the integration used (another tol's polylines differ by up to tol
    # in area, which moves the weighted sum by ~1e-6 at large curv θ on a 13-pixel sensor)
    areas = lw.pixel_mesh(layout, size, tol=1e-5).areas().detach()
    # area-weighted mean of the sensor image equals the image mean (flux is conserved)
    total = (out[0] * areas).sum((-2, -1)) / 4
    assert torch.allclose(total, img[0].mean((-2, -1)), rtol=0, atol=1e-12)


def test_upsampling_uniform_is_nearest_neighbour(gen):
    img = torch.rand(1, 1, 5, 7, generator=gen)
    out = lw.simulate(img, lw.UniformLayout(), (15, 21))
    assert torch.allclose(out, img.repeat_interleave(3, -2).repeat_interleave(3, -1), atol=1e-6)


def test_empty_batch_and_channels():
    layout = lw.RectLayout((0.1, 0.2))
    assert lw.simulate(torch.rand(0, 3, 10, 10), layout, (2, 3)).shape == (0, 3, 2, 3)
    assert lw.simulate(torch.rand(2, 0, 10, 10), layout, (2, 3)).shape == (2, 0, 2, 3)
    # a learnable sensor's empty output is still in θ's (and the image's) graph, with zero gradient
    layer = lw.SensorLayer((2, 3), "curv")
    x = torch.rand(0, 1, 10, 10, dtype=torch.float64, requires_grad=True)
    out = layer(x)
    assert out.shape == (0, 1, 2, 3) and out.dtype == torch.float64 and out.requires_grad
    out.sum().backward()
    assert torch.equal(layer.layout.rho.grad, torch.zeros_like(layer.layout.rho)) and x.grad.shape == x.shape
    with torch.no_grad():
        assert not layer(torch.rand(0, 1, 10, 10)).requires_grad


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize(
    "family,method", [("curv", "exact"), ("rect", "exact"), ("curv", "montecarlo"), ("rect", "point")]
)
def test_nonfinite_input_raises_unless_allowed(bad, family, method, gen):
    img = torch.rand(2, 1, 10, 10, generator=gen)
    r, c = (int(v) for v in torch.randint(0, 10, (2,), generator=gen))
    img[1, 0, r, c] = bad
    layout = lw.make_layout(family, (0.2, 0.1))
    with pytest.raises(ValueError, match=r"1 non-finite value\(s\)"):
        lw.simulate(img, layout, (3, 3), method)
    out = lw.simulate(img, layout, (3, 3), method, allow_nonfinite=True)
    assert torch.isfinite(out[0]).all()  # the clean image is unaffected
    if method == "exact":
        assert not torch.isfinite(out[1]).all()  # the bad pixel reaches an exact output


@pytest.mark.parametrize("family", ["curv", "rect"])
def test_huge_finite_input_is_not_called_nonfinite(family, gen):
    # the output check sums the output first: a sum that overflows, of finite values, is checked
    # element by element and passes
    img = torch.full((2, 1, 10, 10), 3e38) * (1 - 0.01 * torch.rand(2, 1, 10, 10, generator=gen))
    out = lw.simulate(img, lw.make_layout(family, (0.2, 0.1)), (3, 3))
    assert torch.isfinite(out).all() and not torch.isfinite(out.sum())


def test_bad_arguments_raise_clear_errors():
    img = torch.rand(1, 1, 10, 10)
    layout = lw.CurvLayout((0.2, 0.1))
    with pytest.raises(ValueError, match="method must be one of"):
        lw.simulate(img, layout, (3, 3), "magic")
    with pytest.raises(ValueError, match="size must be a pair"):
        lw.simulate(img, layout, (0, 3))
    with pytest.raises(ValueError, match=r"shape \(B, C, H, W\)"):
        lw.simulate(torch.rand(10), layout, (3, 3))
    with pytest.raises(ValueError, match="separable layout"):
        lw.simulate(img, layout, (3, 3), "separable")
    with pytest.raises(ValueError, match="radiance='bilinear' needs method='montecarlo'"):
        lw.simulate(img, layout, (3, 3), "exact", radiance="bilinear")
    with pytest.raises(ValueError, match="tol must be"):
        lw.simulate(img, layout, (3, 3), tol=0)
    with pytest.raises(ValueError, match="samples must be an integer >= 1, got 0"):
        lw.simulate(img, layout, (3, 3), "montecarlo", samples=0)
    with pytest.raises(TypeError, match="dtype"):
        lw.simulate(torch.ones(1, 1, 4, 4, dtype=torch.int32), layout, (2, 2))
    with pytest.raises(
        ValueError, match="method must be one of 'exact', 'separable', 'montecarlo', 'point'; got 'auto'"
    ):
        lw.simulate(img, layout, (3, 3), "auto")  # "auto" was the same as "exact"
    with pytest.raises(TypeError, match="unexpected keyword argument 'channels'"):
        lw.simulate(img, layout, (3, 3), channels=1)
    with pytest.raises(TypeError, match=r"unknown simulate option\(s\) \['sample'\]"):
        lw.SensorLayer((3, 3), "curv", sample=4)
    with pytest.raises(ValueError, match="tol must be a finite number > 0, got -1"):
        lw.SensorLayer((3, 3), "curv", tol=-1)


def test_plan_models_only_what_the_scene_needs():
    assert lw.plan_simulation(lw.UniformLayout(), (9, 9), "exact").method == "separable"
    assert lw.plan_simulation(lw.RectLayout((0.5, 0.5)), (9, 9), "exact").method == "separable"
    plan = lw.plan_simulation(lw.CurvLayout((0.5, 0.5)), (9, 9), "exact", tol=1e-3)
    assert plan.method == "exact" and plan.error_bound == 1e-3
    _, plan = lw.simulate(torch.rand(1, 1, 20, 20), lw.RectLayout((0.2, 0.2)), (4, 4), return_plan=True)
    assert plan.method == "separable" and plan.error_bound == 0.0


def test_sensor_layer_learns_and_freezes(gen, device):
    img = torch.rand(4, 1, 28, 28, generator=gen).to(device)
    target = torch.rand(4, 1, 4, 4, generator=gen).to(device)
    for family in ("rect", "curv"):
        layer = lw.SensorLayer((4, 4), family).to(device)
        assert torch.equal(layer.theta.detach().cpu(), torch.zeros(2))
        opt = torch.optim.SGD(layer.parameters(), lr=0.5)
        loss = (layer(img) - target).pow(2).mean()
        loss.backward()
        assert layer.layout.rho.grad is not None and bool(layer.layout.rho.grad.abs().sum() > 0)
        opt.step()
        assert not torch.equal(layer.theta.detach().cpu(), torch.zeros(2))
        frozen = lw.SensorLayer((4, 4), family, learn=False).to(device)
        assert list(frozen.parameters()) == []
        expected = lw.simulate(img, lw.UniformLayout().to(device), (4, 4))
        assert torch.allclose(frozen(img), expected, atol=1e-6)
    assert lw.SensorLayer((4, 4), "curv", method="montecarlo").describe().method == "montecarlo"


def test_image_gradient_of_exact_is_adjoint(gen):
    # <simulate(x), y> == <x, simulate^T(y)>: the image gradient is the transpose operator
    layout = lw.CurvLayout(rand_theta(gen), dtype=F64)
    x = torch.rand(1, 1, 25, 35, generator=gen, dtype=F64, requires_grad=True)
    y = torch.rand(1, 1, 6, 8, generator=gen, dtype=F64)
    out = lw.simulate(x, layout, (6, 8))
    (g,) = torch.autograd.grad((out * y).sum(), x)
    # gradient summed over all source pixels = Σ_k y_k (each pixel's weights sum to 1)
    assert torch.allclose(g.sum(), y.sum(), atol=1e-10)
    assert bool((g >= -1e-12).all())


@pytest.mark.parametrize("family", ["uniform", "rect", "curv"])
def test_sensor_layer_saves_and_reloads_its_layout(family, gen, tmp_path):
    tol = 1e-5
    layer = lw.SensorLayer((5, 7), family, method="exact", tol=tol)
    if family != "uniform":
        with torch.no_grad():
            layer.layout.rho.copy_(torch.randn(2, generator=gen) * 0.5)
    path = layer.save_layout(tmp_path / "layer.json", note="test")
    again = lw.SensorLayer.from_layout_file(path, tol=tol)
    assert again.size == (5, 7) and again.method == "exact" and again.layout.family == family
    assert list(again.parameters()) == []  # frozen unless learn=True
    assert torch.allclose(again.theta, layer.theta.detach(), rtol=0, atol=1e-6)
    img = torch.rand(2, 3, 31, 29, generator=gen)
    # θ travels as float32 text and ρ = atanh(θ) comes back within an ulp: the float64 mesh then
    # differs at the 1e-8 level and may refine a curved edge differently, so the two outputs
    # agree within twice the error bound each keeps (tol), plus float32 rounding
    assert torch.allclose(again(img), layer(img).detach(), rtol=0, atol=2 * tol + 1e-6)
    if family != "uniform":
        assert len(list(lw.SensorLayer.from_layout_file(path, learn=True).parameters())) == 1
    assert lw.SensorLayer.from_layout_file(path, (3, 3)).size == (3, 3)
    lw.save_layout(layer.layout, tmp_path / "nosize.json")
    with pytest.raises(ValueError, match="stores no sensor size"):
        lw.SensorLayer.from_layout_file(tmp_path / "nosize.json")


class TestSimulate:
    """Kornia-style slots: smoke, exception, gradcheck (θ passed as a tensor)."""

    def test_smoke(self, device):
        out, plan = lw.simulate(
            torch.rand(2, 3, 16, 16, device=device),
            lw.CurvLayout((0.3, -0.2)).to(device),
            (4, 5),
            return_plan=True,
        )
        assert out.shape == (2, 3, 4, 5) and plan.method == "exact" and plan.error_bound == 2**-12

    def test_exception(self):
        with pytest.raises(TypeError, match="layout must be a layoutwarp Layout"):
            lw.simulate(torch.rand(1, 1, 4, 4), "curv", (2, 2))
        with pytest.raises(TypeError, match=r"image must be a torch\.Tensor"):
            lw.simulate(np.zeros((1, 1, 4, 4)), lw.UniformLayout(), (2, 2))

    @pytest.mark.parametrize("family", ["rect", "curv"])
    def test_gradcheck(self, family, gen):
        layout = lw.make_layout(family, rand_theta(gen, 0.8), dtype=F64)
        img = torch.rand(1, 2, 9, 11, generator=gen, dtype=F64).requires_grad_(True)
        assert torch.autograd.gradcheck(lambda x: lw.simulate(x, layout, (3, 4)), (img,))


@pytest.mark.parametrize(
    ("dtype", "tol", "why"),
    [
        (torch.uint8, 0.25 / 255, "a quarter of one step"),
        (torch.float32, 2**-12, "a quarter of a 10-bit step"),
        (torch.float64, 2**-12, "a quarter of a 10-bit step"),
        (torch.float16, 2**-12, "a quarter of its precision"),
        (torch.bfloat16, 2**-9, "a quarter of its precision"),
    ],
)
def test_default_tolerance_comes_from_the_data(dtype, tol, why, gen):
    img = (torch.rand(1, 1, 30, 40, generator=gen) * 200).to(dtype)
    out, plan = lw.simulate(img, lw.CurvLayout((0.5, -0.3)), (6, 8), return_plan=True)
    assert plan.error_bound == tol and why in plan.reason and plan.details["tol"] == tol
    _, given = lw.simulate(img, lw.CurvLayout((0.5, -0.3)), (6, 8), tol=1e-6, return_plan=True)
    assert given.error_bound == 1e-6 and "tol given" in given.reason
    # uint8: within a quarter level of the exact value, so rounding to 8 bit is right
    if dtype == torch.uint8:
        ref = lw.simulate(img.double() / 255, lw.CurvLayout((0.5, -0.3), dtype=F64), (6, 8), tol=1e-9)
        assert float((out.double() - ref).abs().max()) <= 0.25 / 255
    assert lw.SensorLayer((6, 8), "curv").describe(torch.uint8).error_bound == 0.25 / 255


@pytest.mark.parametrize(
    ("family", "method"), [("rect", "exact"), ("curv", "exact"), ("curv", "montecarlo"), ("grid", "point")]
)
def test_the_sensor_integrates_in_float32_under_autocast(family, method, gen, device):
    # mixed precision (--amp) runs the network in bfloat16/float16; the sensor must not follow:
    # before autocast was turned off inside simulate, CPU autocast even crashed the separable
    # path (sparse CSR products have no bfloat16 kernel)
    img = torch.rand(2, 3, 40, 56, generator=gen).to(device)
    layout = lw.make_layout(family, None if family == "grid" else rand_theta(gen, 0.7)).to(device)
    ref = lw.simulate(img, layout, (7, 9), method, seed=0)
    low = torch.bfloat16 if device.type == "cpu" else torch.float16
    with torch.autocast(device_type=device.type, dtype=low):
        out = lw.simulate(img, layout, (7, 9), method, seed=0)
        layer_out = lw.SensorLayer((7, 9), layout, method, seed=0)(img)
    assert out.dtype == torch.float32 and torch.equal(out, ref)
    assert layer_out.dtype == torch.float32 and torch.equal(layer_out, ref)


def test_a_fixed_layout_reuses_its_area_weights_in_a_bounded_cache(gen):
    from layoutwarp import resampler
    from layoutwarp.integrators import integrate_exact

    resampler.RESAMPLERS.clear()
    img = torch.rand(2, 3, 60, 80, generator=gen)
    layout = lw.CurvLayout(rand_theta(gen, 0.8))
    out = lw.simulate(img, layout, (9, 11))
    ref = integrate_exact(img.flatten(0, 1).double(), layout, (9, 11), tol=2**-12).view(2, 3, 9, 11)
    assert float((out.double() - ref).abs().max()) < 1e-5  # float32 weights; the same geometry
    assert len(resampler.RESAMPLERS) == 1 and torch.equal(lw.simulate(img, layout, (9, 11)), out)
    x = img.clone().requires_grad_(True)  # image gradients flow through the cached weights
    w = torch.rand(2, 3, 9, 11, generator=gen)
    (lw.simulate(x, layout, (9, 11)) * w).sum().backward()
    x64 = img.double().flatten(0, 1).requires_grad_(True)
    (
        integrate_exact(x64, layout, (9, 11), tol=2**-12, backend="torch") * w.flatten(0, 1).double()
    ).sum().backward()
    assert torch.allclose(x.grad.double().flatten(0, 1), x64.grad, atol=1e-6)
    for k in range(resampler.RESAMPLERS.maxsize + 2):  # bounded: least recently used out first
        lw.simulate(img, lw.CurvLayout((0.1 * k, 0.2)), (9, 11))
    assert len(resampler.RESAMPLERS) == resampler.RESAMPLERS.maxsize
    learn = lw.CurvLayout(rand_theta(gen, 0.5), learn=True)  # a learnable layout never uses it
    before = resampler.RESAMPLERS.keys()
    lw.simulate(img, learn, (9, 11)).sum().backward()
    assert resampler.RESAMPLERS.keys() == before and learn.rho.grad is not None
    with torch.no_grad():  # ... unless no gradient is wanted
        lw.simulate(img, learn, (9, 11))
    assert len(set(resampler.RESAMPLERS.keys()) - set(before)) == 1


def _plain_route_runs() -> None:
    """Skip where the plain route cannot run: no numba, or the torch path asked for."""
    if not lw.kernels.available() or lw.jit.mode() == "off":
        pytest.skip("the plain route runs the compiled product: needs numba and a mode but off")


@pytest.mark.parametrize("family", ["uniform", "rect", "curv", "fovea"])
def test_a_plain_fixed_call_skips_the_plan_and_gives_its_values(family, gen, monkeypatch):
    """A fixed layout's plain call (float32, CPU, defaults, no gradient) runs the kept weights'
    product without making a plan: the same values, bit for bit, as the planned call, the same
    errors, and the plan's route wherever anything about the call needs it."""
    from layoutwarp import resampler, sensor

    _plain_route_runs()

    layout = lw.make_layout(family, None if family == "uniform" else rand_theta(gen, 0.6))
    img = torch.rand(3, 2, 40, 52, generator=gen)
    planned = {shape: lw.simulate(img.view(shape), layout, (7, 9), return_plan=True)[0] for shape in
               [(3, 2, 40, 52), (6, 40, 52)]}  # fmt: skip
    lw.simulate(img.double(), layout, (7, 9))  # the kernels of every route below loaded (their
    lw.simulate(img.requires_grad_(True), layout, (7, 9))  # warm-ups make plans of their own)
    img.requires_grad_(False)
    plans: list[str] = []
    real_plan = sensor.plan_simulation
    monkeypatch.setattr(sensor, "plan_simulation", lambda *a, **k: plans.append("plan") or real_plan(*a, **k))
    for shape, ref in planned.items():
        out = lw.simulate(img.view(shape), layout, (7, 9))
        assert out.shape == ref.shape and torch.equal(out, ref) and not plans
    bad = img.clone()
    bad[1, 0, 3, 5] = float("nan")
    with pytest.raises(ValueError, match="1 non-finite value"):
        lw.simulate(bad, layout, (7, 9))
    assert torch.isnan(lw.simulate(bad, layout, (7, 9), allow_nonfinite=True)[1, 0]).any() and not plans
    for flag in ("return_plan", "allow_nonfinite"):  # refused as the plan refuses them
        with pytest.raises(lw.checks.ArgumentError, match=flag):
            lw.simulate(img, layout, (7, 9), **{flag: None})
    x = img.clone().requires_grad_(True)  # what the plan must decide: it does
    lw.simulate(x, layout, (7, 9)).sum().backward()
    lw.simulate(img.double(), layout, (7, 9))
    lw.simulate(img, layout, [7, 9])
    assert len(plans) == 3 and x.grad is not None
    with torch.inference_mode():  # outside it, as the plan's call is
        assert torch.equal(lw.simulate(img, layout, (7, 9)), planned[(3, 2, 40, 52)]) and len(plans) == 3
    monkeypatch.setattr(resampler.RESAMPLERS, "maxsize", 0)  # no weights kept: the walk's route
    assert torch.allclose(lw.simulate(img, layout, (7, 9)), planned[(3, 2, 40, 52)], atol=1e-6)
    assert len(plans) > 3


@pytest.mark.parametrize("family", ["rect", "curv", "fovea"])
def test_a_plain_call_without_gradient_is_the_planned_one_for_learnable_layouts_and_images(
    family, gen, monkeypatch
):
    """Without gradient, a learnable layout's plain call takes its θ as a training step computes it
    (in the layout's dtype), as the planned call does, and an image that requires grad gives what
    its detached copy gives, by either route; a warning names the caller's line."""
    from layoutwarp import checks

    _plain_route_runs()
    monkeypatch.setattr(checks, "_WARNED", set())  # a warning is said once a process
    layout = lw.make_layout(family, rand_theta(gen, 0.6), learn=True)
    img = torch.rand(2, 3, 40, 52, generator=gen)
    x = img.clone().requires_grad_(True)
    with torch.no_grad():
        plain, planned = (
            lw.simulate(img, layout, (7, 9)),
            lw.simulate(img, layout, (7, 9), return_plan=True)[0],
        )
        assert torch.equal(plain, planned)
        assert torch.equal(lw.simulate(x, layout, (7, 9)), plain)
        assert torch.equal(lw.simulate(x, layout, (7, 9), return_plan=True)[0], plain)
    with pytest.warns(UserWarning, match="more pixels along an axis") as seen:
        lw.simulate(img[..., :5, :6], layout, (7, 9))
    assert seen[0].filename == __file__


def test_a_fixed_layouts_record_is_measured_while_the_fused_measurement_is_not_loaded(gen, monkeypatch):
    """The kept weights' product with physics: fused into one compiled call where the
    measurement's unit is loaded, else the compiled product then the measurement (a process whose
    background compile has the product's unit done and not yet the measurement's); the same
    record either way."""
    from layoutwarp import jit

    layout = lw.CurvLayout(rand_theta(gen, 0.6))
    img = torch.rand(2, 3, 40, 60, generator=gen)
    camera = lw.SensorPhysics((300.0, 400.0), photons_per_um2=20, read_noise_e=2.0, adc_bits=10, seed=3)
    fused = lw.simulate(img, layout, (7, 9), physics=camera)
    ready = jit.ready

    def measure_not_loaded(group, dtype="float32", wait=False):
        return False if group == "measure" and not wait else ready(group, dtype, wait)

    monkeypatch.setattr(jit, "ready", measure_not_loaded)
    apart = lw.simulate(img, layout, (7, 9), physics=camera)
    assert torch.equal(apart, fused) and not torch.equal(apart, lw.simulate(img, layout, (7, 9)))


def test_a_resampler_applies_its_weights_to_an_empty_batch(gen):
    res = lw.AreaResampler(lw.CurvLayout(rand_theta(gen, 0.6)), (6, 8), (48, 64))
    for grad in (False, True):
        out = res.apply(torch.empty(0, 48, 64, requires_grad=grad))
        assert out.shape == (0, 6, 8) and out.dtype == torch.float32
    assert res.apply(torch.ones(1, 48, 64)).sub(1).abs().max() < 1e-6  # a constant stays itself


def test_a_cache_of_size_zero_keeps_no_weights_and_runs_the_compiled_walk(gen, monkeypatch):
    from layoutwarp import resampler
    from layoutwarp.integrators import integrate_exact

    resampler.RESAMPLERS.clear()
    monkeypatch.setattr(resampler.RESAMPLERS, "maxsize", 0)

    def refuse(*args, **kwargs):
        raise AssertionError("no weights may be built")

    monkeypatch.setattr(resampler, "AreaResampler", refuse)
    img = torch.rand(1, 3, 50, 70, generator=gen)
    layout = lw.CurvLayout(rand_theta(gen, 0.8))
    out = lw.simulate(img, layout, (8, 10))
    ref = integrate_exact(img.flatten(0, 1).double(), layout, (8, 10), tol=2**-12).view(1, 3, 8, 10)
    assert float((out.double() - ref).abs().max()) < 1e-5 and not len(resampler.RESAMPLERS)
