"""layoutwarp inside PyTorch 2: every kernel a registered operator (``torch.library.opcheck``),
one graph under ``torch.compile(fullgraph=True)`` for every family, integrator and physics,
``torch.export``, second derivatives exact or refused, and ``torch.func``."""

from __future__ import annotations

import copy
import json
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import layoutwarp as lw
from layoutwarp.layouts import FAMILIES
from layoutwarp.operators.areas import areas_call
from layoutwarp.operators.base import OPERATORS, SECOND_ORDER, TRANSFORMS, layout_token
from layoutwarp.operators.exact import exact_call
from layoutwarp.operators.flux import flux_call
from layoutwarp.resampler import area_call

F64 = torch.float64
CAMERA = lw.SensorPhysics(
    (200.0, 200.0), photons_per_um2=50.0, read_noise_e=1.0, adc_bits=10, full_well_per_um2=1000.0, seed=3
)


def _learnable(family: str, gen: torch.Generator, dtype: torch.dtype = torch.float32) -> lw.Layout:
    """A learnable layout of ``family`` away from the uniform one (θ random, |θ| ≲ 0.5; a grid's
    control points moved by a few hundredths)."""
    layout = lw.make_layout(family, learn=True, dtype=dtype)
    scale = 0.04 if family == "grid" else 0.25  # a grid's control points: a fold is near
    with torch.no_grad():
        if layout.rho.numel():
            layout.rho.add_(scale * torch.randn(layout.rho.shape, generator=gen, dtype=layout.rho.dtype))
    return layout


def _fixed(family: str, gen: torch.Generator) -> lw.Layout:
    """A fixed layout of ``family`` (θ random, |θ| < 0.4; a grid's control points moved a little)."""
    from layoutwarp.layoutfile import layout_from_spec, layout_spec

    return layout_from_spec(layout_spec(_learnable(family, gen)))


# ----------------------------------------------------------------------------------------
# Every operator: opcheck (schema, fake kernel, autograd registration, AOT dispatch)
# ----------------------------------------------------------------------------------------
def _cases(gen: torch.Generator) -> dict[str, tuple]:
    """Sample arguments of every operator, from a run of the forward where a backward needs it."""
    from layoutwarp.topology import MeshTopology

    img64 = torch.rand(2, 12, 14, generator=gen, dtype=F64)
    img32 = img64.float()
    curv = _learnable("curv", gen, F64)
    grid = _fixed("grid", gen)
    rho, bounds = curv.theta_source()  # the operator makes θ = bounds · tanh(ρ)
    th = rho.detach().clone().requires_grad_(True)
    theta = curv.theta.detach().clone().requires_grad_(True)
    seed = torch.tensor(5, dtype=torch.int64)
    size = (4, 5)
    fixed = lw.CurvLayout((0.3, -0.2))
    ftheta = fixed.theta_as(F64)
    call = exact_call(layout_token(curv), size, 1e-4, "auto", True, True, torch.float32)
    exact = (th, img64, bounds, call)
    means, areas, jac, held = torch.ops.layoutwarp.exact(
        *[a.detach() if torch.is_tensor(a) else a for a in exact]
    )
    grad_means, grad_areas = torch.rand_like(means), torch.rand_like(areas)
    ex = torch.tensor([0.0, 3.5, 7.2, 11.0, 14.0], dtype=F64, requires_grad=True)
    ey = torch.tensor([0.0, 2.5, 6.0, 9.5, 12.0], dtype=F64, requires_grad=True)
    sep = torch.ops.layoutwarp.separable(img64, ex.detach(), ey.detach(), True)
    value = torch.rand(2, *size, generator=gen, dtype=F64, requires_grad=True)
    vol = torch.full(size, 4 / 20, dtype=F64)
    flux = (theta, vol, img64, seed, flux_call(layout_token(curv), size, 2, "bilinear"))
    ne = MeshTopology(size).num_edges
    assert jac.shape == (3, ne, 2)
    return {
        "exact": exact,
        "exact_backward": (
            grad_means,
            grad_areas,
            th.detach(),
            img64,
            means,
            areas,
            jac,
            held,
            bounds,
            call,
            [True, False],
        ),
        "separable": (img64.clone().requires_grad_(True), ex, ey, True),
        "separable_backward": (
            torch.rand_like(sep),
            img64,
            ex.detach(),
            ey.detach(),
            sep,
            [True, True, True],
        ),
        "separable_adjoint": (torch.rand_like(sep).requires_grad_(True), ex.detach(), ey.detach(), 12, 14),
        "area": (
            img32.clone().requires_grad_(True),
            ftheta,
            seed,
            area_call(layout_token(fixed), size, 2**-12, check=True, with_areas=True),
        ),
        "area_backward": (
            torch.rand(2, *size, generator=gen),
            ftheta,
            area_call(layout_token(fixed), size, 2**-12),
            12,
            14,
        ),
        "measure": (means, areas, CAMERA.token, "dn", seed),
        "full_well": ((areas * 1000).requires_grad_(True), CAMERA.token),
        "patterns": (CAMERA.pattern_seed, *size, means),
        "draws": (torch.rand(2, *size, generator=gen, dtype=F64) * 20, seed, "poisson", True),
        "flux": (value, *flux),
        "flux_backward": (torch.rand_like(value), value.detach(), theta.detach(), *flux[1:]),
        "pixel_areas": (
            grid.theta_as(F64).clone().requires_grad_(True),
            areas_call(layout_token(grid), size, 1e-4),
        ),
        "pixel_areas_backward": (
            torch.rand_like(areas),
            grid.theta_as(F64),
            areas_call(layout_token(grid), size, 1e-4),
        ),
        "guard_finite": (value, img64, "image"),
        "uniform": (seed, [3, 4, 2], torch.empty(0, dtype=F64)),
        "seed_sequence": (torch.tensor(3, dtype=torch.int64), 11),
        "map_points": (
            torch.rand(5, 2, generator=gen, dtype=F64) * 2 - 1,
            th.detach(),
            layout_token(curv),
            True,
        ),
        "raster_index_map": (ftheta, layout_token(fixed), *size, 9, 11, 1e-4, 3),
    }


def test_every_operator_passes_opcheck(gen):
    """``torch.library.opcheck`` on every operator layoutwarp registers (its schema, its fake
    kernel against the real one, its autograd registration and AOT dispatch with dynamic shapes),
    on arguments from real runs; every operator has a case (a new one must add its own)."""
    import layoutwarp.backwarp
    import layoutwarp.sensor  # noqa: F401

    cases = _cases(gen)
    assert set(cases) == set(OPERATORS), set(OPERATORS) ^ set(cases)
    for name, args in cases.items():
        result = torch.library.opcheck(OPERATORS[name], args)
        assert all(v == "SUCCESS" for v in result.values()), (name, result)


# ----------------------------------------------------------------------------------------
# torch.compile: one graph, the eager values and gradients, nothing printed
# ----------------------------------------------------------------------------------------
def _configurations() -> list:
    configs = []
    for family in FAMILIES:
        for learn in (True, False):
            methods = ["exact", "montecarlo", "point"]
            if family in ("uniform", "rect", "spline"):
                methods.insert(1, "separable")
            for method in methods:
                for physics in (False, True):
                    name = f"{family}-{'learn' if learn else 'fixed'}-{method}{'-physics' if physics else ''}"
                    marks = [pytest.mark.slow] if physics else []  # the fast subset: half the matrix
                    configs.append(pytest.param(family, learn, method, physics, id=name, marks=marks))
    return configs


def _layer(family: str, learn: bool, method: str, physics: bool, gen: torch.Generator) -> lw.SensorLayer:
    layout = _learnable(family, gen) if learn else _fixed(family, gen)
    options = {"seed": 1} if method == "montecarlo" else {}
    return lw.SensorLayer((6, 5), layout, method, physics=CAMERA if physics else None, **options)


def _eager_and_compiled(layer: lw.SensorLayer, img: torch.Tensor, **compile_options) -> list:
    """Output and θ-gradient of ``layer`` on ``img``, eagerly and compiled in one graph."""
    results = []
    for run in (layer, torch.compile(layer, fullgraph=True, **compile_options)):
        layer.noise_calls.zero_()  # the same noise sequence for both
        out = run(img)
        grad = None
        if layer.layout.learnable:
            (grad,) = torch.autograd.grad(out.square().sum(), layer.layout.rho)
        results.append((out.detach(), grad))
    return results


@pytest.mark.parametrize(("family", "learn", "method", "physics"), _configurations())
def test_the_layer_compiles_to_one_graph_with_the_eager_values_and_gradients(
    family, learn, method, physics, gen
):
    """``torch.compile(layer, fullgraph=True)`` (AOT autograd's eager backend: the graph capture and
    autograd of the compiler, without generating code) for every family, learnable and fixed,
    every integrator the layer accepts, with and without sensor physics (a seeded noise
    sequence): it captures one graph (fullgraph raises at a graph break) whose output and
    θ-gradient are eager's, to the last bit but for the graph's own float32 rounding order."""
    torch._dynamo.reset()
    layer = _layer(family, learn, method, physics, gen)
    img = torch.rand(2, 1, 24, 20, generator=gen)
    (ref, g_ref), (out, g_out) = _eager_and_compiled(layer, img, backend="aot_eager")
    torch.testing.assert_close(out, ref, rtol=1e-6, atol=1e-6)
    if learn and g_ref is not None:
        torch.testing.assert_close(g_out, g_ref, rtol=1e-5, atol=1e-7)


def test_compiling_prints_nothing_and_simulate_backwarp_compile(gen, capfd):
    """Compiling a learnable layer, a Kornia augmentation's sensor, ``simulate`` of a fixed layout
    and ``backwarp`` (both index methods and bilinear) prints nothing and warns nothing; the
    compiled functions give eager's values."""
    torch._dynamo.reset()
    fixed = _fixed("fovea", gen)
    img = torch.rand(1, 3, 30, 26, generator=gen)
    pred = torch.rand(1, 3, 6, 5, generator=gen)
    layer = lw.SensorLayer((6, 5), "elliptic")
    augmentation = lw.SensorAugmentation((6, 5), "curv", learn=True)
    functions = {
        "layer": (layer, (img,)),
        "augmentation's sensor": (augmentation.sensor, (img,)),
        "simulate": (lambda x: lw.simulate(x, fixed, (6, 5)), (img,)),
        "backwarp": (lambda p: lw.backwarp(p, fixed, (12, 10)), (pred,)),
        "backwarp-raster": (lambda p: lw.backwarp(p, fixed, (12, 10), index_method="raster"), (pred,)),
        "backwarp-bilinear": (lambda p: lw.backwarp(p, fixed, (12, 10), mode="bilinear"), (pred,)),
    }
    for fn, args in functions.values():  # eagerly first: the kernels' first compile may speak
        fn(*args)
    capfd.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for name, (fn, args) in functions.items():
            got = torch.compile(fn, fullgraph=True, backend="aot_eager")(*args)
            torch.testing.assert_close(got, fn(*args), msg=name)
    out, err = capfd.readouterr()
    assert not caught and not out and not err, ([str(w.message) for w in caught], out, err)


def test_a_model_trains_under_compile_as_it_does_eagerly(gen):
    """A learnable curved sensor and a linear head trained five SGD steps eagerly and compiled
    (one graph, forward and backward): the same losses, θ and weights after every step."""
    torch._dynamo.reset()
    x = torch.rand(4, 1, 28, 28, generator=gen)
    y = torch.randint(0, 3, (4,), generator=gen)

    def model() -> torch.nn.Module:
        torch.manual_seed(0)
        return torch.nn.Sequential(lw.SensorLayer((6, 6), "curv"), torch.nn.Flatten(), torch.nn.Linear(36, 3))

    runs = []
    for compiled in (False, True):
        net = model()
        step_net = torch.compile(net, fullgraph=True, backend="aot_eager") if compiled else net
        opt = torch.optim.SGD(net.parameters(), lr=0.5)
        history = []
        for _ in range(5):
            opt.zero_grad()
            loss = torch.nn.functional.cross_entropy(step_net(x), y)
            loss.backward()
            opt.step()
            history.append((loss.item(), [p.detach().clone() for p in net.parameters()]))
        runs.append(history)
    for (loss_e, params_e), (loss_c, params_c) in zip(*runs, strict=True):
        assert loss_c == pytest.approx(loss_e, rel=1e-6)
        for a, b in zip(params_e, params_c, strict=True):
            torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
    assert not torch.equal(runs[0][0][1][0], runs[0][-1][1][0])  # θ moved


@pytest.mark.slow  # inductor generates and compiles C++ (tens of seconds)
def test_inductor_compiles_a_learnable_step_with_eager_values(gen):
    """The default backend (inductor, code generated and compiled) on a learnable fovea step and a
    fixed layout with physics: eager's outputs and θ-gradient."""
    torch._dynamo.reset()
    img = torch.rand(2, 1, 24, 20, generator=gen)
    for layer in (_layer("fovea", True, "exact", False, gen), _layer("curv", False, "exact", True, gen)):
        (ref, g_ref), (out, g_out) = _eager_and_compiled(layer, img)
        torch.testing.assert_close(out, ref, rtol=1e-6, atol=1e-6)
        if g_ref is not None:
            torch.testing.assert_close(g_out, g_ref, rtol=1e-5, atol=1e-7)


# ----------------------------------------------------------------------------------------
# torch.export
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("family", "method", "physics"),
    [
        ("curv", "exact", False),
        ("curv", "exact", True),
        ("rect", "exact", False),
        ("elliptic", "point", True),
    ],
)
def test_export_of_a_fixed_layer_reproduces_eager(family, method, physics, gen):
    """``torch.export.export`` of a layer with a fixed layout, with and without physics (a seeded
    noise sequence, whose count the program carries as a mutated buffer): the exported program
    gives eager's output, call after call."""
    layer = _layer(family, False, method, physics, gen)
    img = torch.rand(2, 3, 24, 20, generator=gen)
    program = torch.export.export(copy.deepcopy(layer), (img,))  # a program with its own count
    exported = program.module()
    for _ in range(2):
        torch.testing.assert_close(exported(img), layer(img), rtol=0, atol=0)
    assert any(
        node.target.namespace == "layoutwarp" for node in program.graph.nodes if node.op == "call_function"
    )


@pytest.mark.parametrize("imports", ["import torch\nimport layoutwarp", "import layoutwarp\nimport torch"])
def test_an_exported_program_loads_and_runs_in_another_process(imports, gen, tmp_path):
    """``torch.export.save`` of a fixed fovea layer with a seeded camera; a fresh process that
    does no more than ``import layoutwarp`` (before or after torch: the operators register at
    the first lookup of ``torch.ops.layoutwarp``) loads it and records, call after call, what
    the layer records here: the program carries the layout and the camera as text."""
    import subprocess
    import sys

    camera = lw.SensorPhysics((200.0, 200.0), photons_per_um2=50.0, read_noise_e=2.0, seed=5)
    layer = lw.SensorLayer((8, 8), _fixed("fovea", gen), physics=camera)
    img = torch.rand(1, 3, 40, 50, generator=gen)
    torch.export.save(torch.export.export(copy.deepcopy(layer), (img,)), tmp_path / "sensor.pt2")
    torch.save({"img": img, "want": torch.stack([layer(img), layer(img)])}, tmp_path / "case.pt")
    code = (
        f"import sys\n{imports}\nassert 'layoutwarp.sensor' not in sys.modules\n"
        "m = torch.export.load(sys.argv[1]).module()\ncase = torch.load(sys.argv[2])\n"
        "got = torch.stack([m(case['img']), m(case['img'])])\nassert torch.equal(got, case['want'])\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "sensor.pt2"), str(tmp_path / "case.pt")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-2000:]


# ----------------------------------------------------------------------------------------
# Second derivatives: exact or refused
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("family", "method", "options"),
    [
        ("curv", "exact", {}),
        ("grid", "exact", {}),
        ("rect", "exact", {}),
        ("fovea", "montecarlo", {"seed": 2}),
    ],
    ids=["exact-compiled", "exact-mesh", "separable", "montecarlo-reynolds"],
)
def test_a_second_derivative_through_a_compiled_gradient_is_refused(family, method, options, gen):
    """The exact, separable and Monte Carlo (Reynolds) θ-gradients are compiled formulas: the
    derivative of such a gradient raises in one line naming the operator, never a value that
    leaves out the second-order terms (curv's gave 2.05 against −17.44 from finite differences)."""
    layout = _learnable(family, gen, F64)
    img = torch.rand(1, 1, 24, 20, generator=gen, dtype=F64)
    out = lw.simulate(img, layout, (6, 5), method, **options)
    (g,) = torch.autograd.grad(out.square().sum(), layout.rho, create_graph=True)
    with pytest.raises(RuntimeError, match=SECOND_ORDER.format(op=".*")[:40]):
        torch.autograd.grad(g.sum(), layout.rho)


def _grid_sample_has_second_derivatives() -> bool:
    """Whether this torch differentiates ``grid_sample``'s backward (torch 2.9 does not)."""
    x = torch.rand(1, 1, 3, 3, dtype=F64, requires_grad=True)
    grid = (torch.rand(1, 2, 2, 2, dtype=F64) - 0.5).requires_grad_(True)
    (gx,) = torch.autograd.grad(F.grid_sample(x, grid, align_corners=False).sum(), x, create_graph=True)
    try:
        torch.autograd.grad((gx * gx).sum(), grid)
    except RuntimeError:
        return False
    return True


@pytest.mark.parametrize("method", ["point", "montecarlo"])
def test_second_derivatives_of_the_sampling_integrators_pass_gradgradcheck(method, gen):
    """Where the integrator is torch operations all the way (one sample at the deformed centre;
    Monte Carlo with the reparameterised gradient), second derivatives in θ and the image are exact:
    ``gradgradcheck`` in float64; refused in torch's one line where torch cannot differentiate
    ``grid_sample``'s backward."""
    layout = lw.CurvLayout((0.3, -0.2), dtype=F64)
    img = torch.rand(1, 9, 11, generator=gen, dtype=F64, requires_grad=True)
    theta = torch.tensor([0.3, -0.2], dtype=F64, requires_grad=True)
    options = {"samples": 2, "grad": "autograd", "seed": 4} if method == "montecarlo" else {}
    integrate = (
        lw.integrators.integrate_montecarlo if method == "montecarlo" else lw.integrators.integrate_point
    )

    def f(th: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return integrate(x, layout, (3, 4), theta=th, **options)

    if not _grid_sample_has_second_derivatives():
        with pytest.raises(
            RuntimeError, match="derivative for aten::grid_sampler_2d_backward is not implemented"
        ):
            torch.autograd.gradgradcheck(f, (theta, img))
        return
    assert torch.autograd.gradgradcheck(f, (theta, img))


def test_a_fixed_layouts_product_has_its_exact_second_derivative(gen):
    """A fixed layout's area weights ``W``: ``∂/∂u ⟨v, ∂⟨u, W x⟩/∂x⟩ = W v`` through the registered
    derivative of the backward (the product is linear, so this is exact)."""
    layout = lw.CurvLayout((0.4, 0.1))
    x = torch.rand(1, 2, 30, 26, generator=gen, requires_grad=True)
    u = torch.rand(1, 2, 6, 5, generator=gen, requires_grad=True)
    v = torch.rand(1, 2, 30, 26, generator=gen)
    (g,) = torch.autograd.grad((lw.simulate(x, layout, (6, 5)) * u).sum(), x, create_graph=True)
    (gg,) = torch.autograd.grad((g * v).sum(), u)
    torch.testing.assert_close(gg, lw.simulate(v, layout, (6, 5)), rtol=1e-6, atol=1e-7)


# ----------------------------------------------------------------------------------------
# torch.func
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(("family", "learn"), [("curv", True), ("rect", True), ("fovea", False)])
def test_vmap_over_simulate_is_the_loop_over_its_samples(family, learn, gen, capfd):
    """``torch.func.vmap`` over ``simulate`` (the image batched; the operators fold the batch into
    their images, or run once per sample) gives the per-sample loop's values, without a word of
    the batching fallback."""
    layout = _learnable(family, gen) if learn else _fixed(family, gen)
    imgs = torch.rand(3, 2, 24, 20, generator=gen)
    got = torch.func.vmap(lambda x: lw.simulate(x, layout, (6, 5)))(imgs)
    want = torch.stack([lw.simulate(x, layout, (6, 5)) for x in imgs])
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-7)
    assert "batching rule" not in capfd.readouterr().err


def test_vmap_refuses_noise_unless_told_its_randomness(gen):
    """A noisy camera under ``vmap``: refused in one line with ``randomness="error"`` (vmap's
    default), the same draws per sample with ``"same"``."""
    layout, img = _fixed("curv", gen), torch.rand(2, 1, 24, 20, generator=gen)
    camera = lw.SensorPhysics((200.0, 200.0), photons_per_um2=50.0)

    def record(x: torch.Tensor) -> torch.Tensor:
        return lw.simulate(x, layout, (6, 5), physics=camera, seed=7)

    with pytest.raises(RuntimeError, match="draws random numbers: pass randomness='same' or 'different'"):
        torch.func.vmap(record)(img)
    same = torch.func.vmap(record, randomness="same")(img)
    torch.testing.assert_close(same, torch.stack([record(x) for x in img]))


@pytest.mark.parametrize("transform", ["grad", "jacrev"])
def test_grad_transforms_are_refused_in_one_line(transform, gen):
    """``torch.func.grad`` and ``jacrev`` cannot enter an operator whose gradient is registered
    with autograd: one line says so and what to use."""
    layer = lw.SensorLayer((5, 6), "curv")
    img = torch.rand(1, 1, 20, 24, generator=gen)
    params = dict(layer.named_parameters())

    def loss(p: dict) -> torch.Tensor:
        return torch.func.functional_call(layer, p, (img,)).sum()

    with pytest.raises(RuntimeError, match=TRANSFORMS.format(what="grad, jacrev or vjp")[:60]):
        getattr(torch.func, transform)(loss)(params)


def test_a_compiled_grad_transform_fails_in_torchs_words_and_gives_no_value(gen):
    """Under ``torch.compile`` the one-line refusal cannot look for the transform (functorch's
    checks break the graph), so ``torch.compile(torch.func.grad(...))`` fails in torch's words (a
    custom operator's autograd formula takes no functorch transform), as docs/pytorch2.md says:
    never a value. A torch that starts to support it fails this test, and the docs change."""
    torch._dynamo.reset()
    layer = lw.SensorLayer((5, 6), "curv", learn=True)
    img = torch.rand(1, 1, 20, 24, generator=gen)

    def loss(p: dict) -> torch.Tensor:
        return torch.func.functional_call(layer, p, (img,)).sum()

    with pytest.raises(Exception, match="functorch transforms"):
        torch.compile(torch.func.grad(loss))(dict(layer.named_parameters()))


# ----------------------------------------------------------------------------------------
# What a reviewer found: inference mode, vmap's roles, copies, strides
# ----------------------------------------------------------------------------------------
def test_inference_mode_runs_and_leaves_the_caches_fit_for_autograd(gen):
    """A layer called under ``torch.inference_mode`` (learnable or fixed) gives the eager values,
    and a learnable step afterwards still gets its θ-gradient (the caches hold no inference
    tensors); a package first imported inside inference mode still turns autograd on inside its
    operators (a fresh process)."""
    import subprocess
    import sys

    img = torch.rand(2, 1, 24, 20, generator=gen)
    for layer in (_layer("grid", True, "exact", False, gen), _layer("curv", False, "exact", True, gen)):
        layer.noise_calls.zero_()
        want = layer(img).detach()
        layer.noise_calls.zero_()
        with torch.inference_mode():
            got = layer(img)
        torch.testing.assert_close(got, want)
    learn = _layer("grid", True, "exact", False, gen)
    (g,) = torch.autograd.grad(learn(img).square().sum(), learn.layout.rho)
    assert torch.isfinite(g).all() and g.abs().sum() > 0
    code = (
        "import torch\nwith torch.inference_mode():\n    import layoutwarp as lw\n"
        "layer = lw.SensorLayer((6, 5), 'curv', 'montecarlo', seed=1)\n"
        "with torch.no_grad():\n    layer.layout.rho.add_(0.05)\n"
        "(g,) = torch.autograd.grad(layer(torch.rand(2, 1, 24, 20)).square().sum(), layer.layout.rho)\n"
        "assert g.abs().sum() > 0, g\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]


@pytest.mark.parametrize("size", [(6, 5), (7, 5)], ids=["h=B·N", "h=B·N+1"])
def test_vmap_splits_outputs_by_their_role_not_their_size(size, gen):
    """A sensor whose height is the batch times the channels (or one more) under ``vmap``: the
    pixels' areas are shared by the batch, not split as if they were per image."""
    camera = lw.SensorPhysics((200.0, 200.0), photons_per_um2=50.0, read_noise_e=1.0)
    layout = _learnable("curv", gen)
    imgs = torch.rand(2, 3, 24, 20, generator=gen)

    def record(x: torch.Tensor) -> torch.Tensor:
        return lw.simulate(x, layout, size, physics=camera, seed=7)

    got = torch.func.vmap(record, randomness="same")(imgs)
    torch.testing.assert_close(got, torch.stack([record(x) for x in imgs]))


def test_a_copy_of_a_layout_of_an_unregistered_family_is_its_own(gen):
    """``copy.deepcopy`` of a layer whose layout's family is not registered (its token a handle of
    the object): the copy runs after the original is gone, with its own state."""
    import gc

    class MyCurv(lw.CurvLayout):
        pass

    layer = lw.SensorLayer((4, 5), MyCurv((0.3, -0.2)))
    clone = copy.deepcopy(layer)
    img = torch.rand(1, 1, 24, 20, generator=gen)
    want = layer(img)
    del layer
    gc.collect()
    torch.testing.assert_close(clone(img), want)


def test_compiled_gradients_of_a_strided_image_have_the_fake_kernels_strides(gen):
    """A transposed (non-contiguous) image through ``torch.compile(fullgraph=True)``: the image's
    gradient is eager's (the operators' outputs and their fake kernels agree on strides)."""
    layout = lw.CurvLayout((0.3, -0.2))
    x = torch.rand(1, 1, 20, 24, generator=gen, dtype=F64).transpose(-1, -2).detach().requires_grad_(True)

    def loss(image: torch.Tensor) -> torch.Tensor:
        return lw.simulate(image, layout, (4, 5)).square().sum()

    (want,) = torch.autograd.grad(loss(x), x)
    (got,) = torch.autograd.grad(torch.compile(loss, fullgraph=True, backend="aot_eager")(x), x)
    torch.testing.assert_close(got, want)


# ----------------------------------------------------------------------------------------
# What a compiled layer is compiled for: its layout's settings, never θ or the batch
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("family", "learn", "method"),
    [
        ("curv", True, "exact"),
        ("fovea", True, "exact"),
        ("grid", False, "exact"),
        ("rect", True, "point"),
        ("rect", False, "separable"),
        ("curv", True, "montecarlo"),
    ],
)
def test_loading_twelve_checkpoints_into_a_compiled_layer_compiles_once(family, learn, method, gen):
    """A compiled layer into which 12 checkpoints (each a new θ) are loaded in turn is compiled
    once (Dynamo's frame count; its recompile limit is 8), and gives, after each load, the
    values of an eager layer made from that checkpoint."""
    from torch._dynamo.testing import CompileCounter

    torch._dynamo.reset()
    layer = _layer(family, learn, method, False, gen)
    img = torch.rand(2, 1, 24, 20, generator=gen)
    counter = CompileCounter()
    compiled = torch.compile(layer, fullgraph=True, backend=counter)
    for _ in range(12):
        state = {k: v.clone() for k, v in _layer(family, learn, method, False, gen).state_dict().items()}
        layer.load_state_dict(state)
        eager = _layer(family, learn, method, False, gen)
        eager.load_state_dict(state)
        layer.noise_calls.zero_()
        got = compiled(img)
        torch.testing.assert_close(got, eager(img), rtol=1e-6, atol=1e-6)
    assert counter.frame_count == 1, counter.frame_count


@pytest.mark.parametrize("family", ["curv", "rect", "fovea"])
def test_a_dynamic_compile_serves_every_batch_size_with_one_graph(family, gen):
    """``torch.compile(dynamic=True)`` of a learnable layer: batches of 2 to 6 (among them the
    length of θ) run through one compiled graph, with the eager values and θ-gradients. (A batch
    of 1 compiles once more, as for any model: Dynamo specialises sizes 0 and 1.)"""
    from torch._dynamo.testing import CompileCounter

    torch._dynamo.reset()
    layer = _layer(family, True, "exact", False, gen)
    counter = CompileCounter()
    compiled = torch.compile(layer, fullgraph=True, dynamic=True, backend=counter)
    for batch in (3, 2, 4, 5, 6):
        img = torch.rand(batch, 1, 24, 20, generator=gen)
        out = compiled(img)
        (g,) = torch.autograd.grad(out.square().sum(), layer.layout.rho)
        ref = layer(img)
        (g_ref,) = torch.autograd.grad(ref.square().sum(), layer.layout.rho)
        torch.testing.assert_close(out, ref, rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(g, g_ref, rtol=1e-5, atol=1e-7)
    assert counter.frame_count == 1, counter.frame_count


@pytest.mark.parametrize("tol", ["default", "fine"])
@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("family", ["curv", "fovea", "elliptic", "rect", "grid"])
def test_vmap_over_theta_gives_the_loops_values_and_gradients(family, dtype, tol, gen):
    """``vmap`` over θ (``functional_call`` with a batch of ρ) of a learnable exact layer: the
    values and ρ's gradient of a loop over the batch. A batched ρ reports no ``requires_grad``
    inside vmap; the layer must still take the learnable path (a float32 image would otherwise
    go to a fixed layout's cached weights, and θ get no gradient), its polylines a gradient's
    (at the default tolerance a fixed θ's differed from the loop's by 1.9e-5 in float64)."""
    from torch.func import functional_call, vmap

    fine = {"default": None, "fine": 1e-10 if dtype == F64 else 1e-6}[tol]
    layer = lw.SensorLayer((4, 5), _learnable(family, gen, dtype), "exact", tol=fine)
    img = torch.rand(1, 1, 16, 20, generator=gen, dtype=dtype)
    n = layer.layout.rho.numel()
    scale = 0.03 if family == "grid" else 0.3
    rhos = layer.layout.rho.detach() + scale * torch.randn(3, n, generator=gen, dtype=dtype)
    rhos.requires_grad_(True)
    out = vmap(lambda r: functional_call(layer, {"layout.rho": r}, (img,)))(rhos)
    (g,) = torch.autograd.grad(out.square().sum(), rhos)
    ref = torch.stack([functional_call(layer, {"layout.rho": r}, (img,)) for r in rhos])
    (g_ref,) = torch.autograd.grad(ref.square().sum(), rhos)
    close = {"rtol": 0, "atol": 1e-12} if dtype == F64 else {"rtol": 0, "atol": 1e-6}
    torch.testing.assert_close(out, ref, **close)
    torch.testing.assert_close(
        g, g_ref, rtol=1e-5 if dtype == F64 else 2e-3, atol=1e-7 if dtype == F64 else 1e-4
    )
    assert g_ref.abs().max() > 1e-3  # a gradient that could be wrong


@pytest.mark.parametrize("asked", [False, True])
def test_vmap_over_theta_that_asks_no_gradient_gives_the_loops_values(asked, gen):
    """A batch of ρ that asks no gradient gives the values of a loop over it (the polylines of a
    θ that needs none), one that does those of the loop that does: what the batch wraps decides,
    not that it is batched."""
    from torch.func import functional_call, vmap

    layer = lw.SensorLayer((4, 5), _learnable("curv", gen, F64), "exact")
    img = torch.rand(1, 1, 16, 20, generator=gen, dtype=F64)
    rhos = (layer.layout.rho.detach() + 0.3 * torch.randn(3, 2, generator=gen, dtype=F64)).requires_grad_(
        asked
    )
    out = vmap(lambda r: functional_call(layer, {"layout.rho": r}, (img,)))(rhos)
    ref = torch.stack([functional_call(layer, {"layout.rho": r}, (img,)) for r in rhos])
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-14)


@pytest.mark.parametrize("learn", [False, True])
def test_a_uint8_image_compiles_to_one_graph_with_the_eager_values(learn, gen):
    """A uint8 image through ``torch.compile(fullgraph=True)`` (its tolerance is a quarter of one
    of its steps, read from the dtype without making a tensor): one graph, eager's values."""
    from torch._dynamo.testing import CompileCounter

    torch._dynamo.reset()
    layer = lw.SensorLayer((5, 6), "curv", learn=learn, theta=(0.3, -0.2))
    img = (torch.rand(1, 3, 30, 36, generator=gen) * 255).to(torch.uint8)
    counter = CompileCounter()
    got = torch.compile(layer, fullgraph=True, backend=counter)(img)
    torch.testing.assert_close(got, layer(img), rtol=1e-6, atol=1e-6)
    assert counter.frame_count == 1, counter.frame_count


def test_vmap_of_a_layer_compiles_to_one_graph(gen):
    """``torch.compile(torch.vmap(layer), fullgraph=True)`` captures one graph (the check for
    gradient transforms reads no functorch level inside a compiled graph) with the eager values."""
    from torch._dynamo.testing import CompileCounter

    torch._dynamo.reset()
    layer = lw.SensorLayer((4, 5), _fixed("curv", gen))
    imgs = torch.rand(3, 1, 1, 16, 20, generator=gen)
    counter = CompileCounter()

    def sense(x: torch.Tensor) -> torch.Tensor:  # a function: torch 2.9's vmap names its function by
        return layer(x)  # repr, which dynamo cannot trace for a module

    got = torch.compile(torch.vmap(sense), fullgraph=True, backend=counter)(imgs)
    torch.testing.assert_close(got, torch.vmap(layer)(imgs), rtol=1e-6, atol=1e-6)
    assert counter.frame_count == 1, counter.frame_count


def test_dataloader_fork_workers_simulate_after_the_parent_trained(gen):
    """The default DataLoader on Linux forks its workers: after the parent has trained a learnable
    layer (the kernels' threads started), each forked worker senses its samples and gives the
    parent's values (no threading layer that a fork breaks)."""
    import multiprocessing

    if "fork" not in multiprocessing.get_all_start_methods():
        pytest.skip("no fork start method on this platform")
    layer = lw.SensorLayer((4, 5), "curv", learn=True)
    opt = torch.optim.SGD(layer.parameters(), lr=0.1)
    for _ in range(2):
        opt.zero_grad()
        layer(torch.rand(2, 1, 32, 40, generator=gen)).square().mean().backward()
        opt.step()
    fixed = lw.CurvLayout((0.3, -0.2))
    images = torch.rand(8, 1, 32, 40, generator=gen)

    class Sensed(torch.utils.data.Dataset):
        def __len__(self) -> int:
            return len(images)

        def __getitem__(self, i: int) -> torch.Tensor:
            return lw.simulate(images[i], fixed, (4, 5))

    loader = torch.utils.data.DataLoader(
        Sensed(), batch_size=2, num_workers=2, multiprocessing_context="fork"
    )
    got = torch.cat(list(loader))
    want = torch.stack([lw.simulate(x, fixed, (4, 5)) for x in images])
    assert torch.equal(got, want)


@pytest.mark.parametrize("family", ["rect", "uniform", "curv"])
def test_an_input_gradient_penalty_through_a_fixed_layout_has_its_exact_second_derivative(family, gen):
    """A fixed layout's product is linear in the image: a penalty on the input gradient of a
    model after it (``tanh``) has its exact second derivative. float64: ``gradgradcheck`` of the
    rectangular layouts' separable path and of curv's exact walk; float32 (rect and uniform: the
    separable adjoint; curv: the cached weights): the penalty's gradient equals the one computed
    in float64 (curv's: with the same weights as a dense matrix, and by the exact walk)."""
    layout = lw.make_layout(family, None if family == "uniform" else (0.3, -0.2))
    img = torch.rand(1, 1, 12, 14, generator=gen, dtype=F64)
    w = torch.rand(1, 1, 4, 5, generator=gen, dtype=F64)

    def penalty_grad(x: torch.Tensor) -> torch.Tensor:
        x = x.clone().requires_grad_(True)
        out = torch.tanh(3 * lw.simulate(x, layout.to(x.dtype), (4, 5)))
        (g,) = torch.autograd.grad((out * w.to(x.dtype)).sum(), x, create_graph=True)
        (h,) = torch.autograd.grad(g.square().sum(), x)
        return h

    if family == "curv":  # the float64 reference: the same float32 weights, as a dense matrix
        res = lw.resampler.resampler_for(layout, (4, 5), (12, 14), lw.data_tolerance(torch.float32)[0], "cpu")
        m = torch.from_numpy(res.weights.toarray()).double()
        x = img.reshape(-1).clone().requires_grad_(True)
        out = torch.tanh(3 * (m @ x)).reshape(1, 1, 4, 5)
        (g,) = torch.autograd.grad((out * w).sum(), x, create_graph=True)
        (want,) = torch.autograd.grad(g.square().sum(), x)
        want = want.reshape(img.shape)
        walk = penalty_grad(img)  # float64: the exact walk, its image gradient's derivative exact
        torch.testing.assert_close(walk, want, rtol=1e-6, atol=1e-7)
    else:
        want = penalty_grad(img)
    fn = lambda x: torch.tanh(3 * lw.simulate(x, layout.double(), (4, 5)))  # noqa: E731
    assert torch.autograd.gradgradcheck(fn, (img.clone().requires_grad_(True),))
    got = penalty_grad(img.float())
    assert want.abs().max() > 1e-3  # a second derivative that could be wrong
    torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-5)


def test_a_calls_description_reads_back_as_written_and_compiles_to_a_constant():
    """``describe_call`` writes JSON that ``read_call`` reads back as it was written (a token with
    quotes and backslashes, sizes, a tolerance's every digit, flags, a dtype), the same as
    ``json.loads`` of it; under ``torch.compile(fullgraph=True)`` it folds into the graph; a text
    of no settings, a dtype torch does not have, a shared setting of the wrong kind (a size that is
    no pair of positive integers, a tolerance that is no positive number, a flag that is no
    boolean, ...), or a setting the operator needs and the text lacks, is refused in one line
    naming the operator."""
    from layoutwarp.operators.base import describe_call, read_call

    token = json.dumps({"family": "odd", "name": 'a "quoted" \\ path', "x": [0.1, 1e-300]}, sort_keys=True)
    text = describe_call(layout=token, size=(257, 129), tol=0.1 + 0.2, check=True, jac=False, dtype=F64)
    c = read_call(text, "exact")
    assert (c.layout, c.size, c.tol, c.check, c.jac, c.dtype) == (
        token,
        (257, 129),
        0.1 + 0.2,
        True,
        False,
        F64,
    )
    assert json.loads(text)["layout"] == token and json.loads(text)["dtype"] == "float64"
    odd = read_call(
        describe_call(a=float("inf"), b=-float("inf"), c=float("nan"), d='x\ny\t"z\\', e=np.float64(0.5)), "t"
    )
    assert (odd.a, odd.b, odd.d, odd.e) == (float("inf"), -float("inf"), 'x\ny\t"z\\', 0.5) and odd.c != odd.c

    @torch.compile(fullgraph=True, backend="eager")
    def f(x):
        return x + len(describe_call(layout=token, size=(3, 4), tol=1e-3, dtype=x.dtype))

    assert float(f(torch.zeros(()))) == len(
        describe_call(layout=token, size=(3, 4), tol=1e-3, dtype=torch.float32)
    )
    for bad, why in (
        ("[1]", "layoutwarp::exact: call must be"),
        ('{"dtype": "cuda"}', "layoutwarp::exact: call names"),
    ):
        with pytest.raises(ValueError, match="^" + why) as err:
            read_call(bad, "exact")
        assert "\n" not in str(err.value)
    for key, bad in (("size", [0, 3]), ("size", "4x5"), ("tol", -1.0), ("tol", float("nan")), ("check", "no"),
                     ("layout", 123), ("samples", 0)):  # fmt: skip
        with pytest.raises(ValueError, match=f"^layoutwarp::exact: call setting '{key}' must be ") as err:
            read_call(json.dumps({key: bad}), "exact")
        assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match=r"^layoutwarp::exact: call has no setting '\w+'$"):
        torch.ops.layoutwarp.exact(
            torch.zeros(0, dtype=F64), torch.zeros(1, 4, 4), torch.zeros(0), '{"tol": 1}'
        )


def test_raw_operators_refuse_bad_arguments_in_one_line_naming_operator_and_argument(gen):
    """``torch.ops.layoutwarp.*`` called directly with a wrong θ length, a text that is no layout's
    token, a 4-D image, an unknown backend, points that are not (..., 2), or areas of another
    shape: a ``ValueError`` in one line naming the operator and the argument."""
    curv = lw.CurvLayout((0.3, -0.2))
    token, th = layout_token(curv), curv.theta_as(F64)
    img = torch.rand(2, 12, 14, generator=gen, dtype=F64)
    empty = th.new_empty(0)

    def exact(theta=th, image=img, layout=token, backend="auto", call=None):
        call = exact_call(layout, (4, 5), 1e-3, backend, False, True, F64) if call is None else call
        return torch.ops.layoutwarp.exact(theta, image, empty, call)

    means, areas, _, _ = exact()
    cases = {
        "layoutwarp::exact: theta": lambda: exact(theta=torch.zeros(3, dtype=F64)),
        "layoutwarp::exact: layout": lambda: exact(layout="not json"),
        "layoutwarp::exact: image": lambda: exact(image=img[None]),
        "layoutwarp::exact: backend": lambda: exact(backend="banana"),
        "layoutwarp::exact: call": lambda: exact(call="[1, 2]"),
        "layoutwarp::map_points: points": lambda: torch.ops.layoutwarp.map_points(
            torch.zeros(5, 3, dtype=F64), th, token, False
        ),
        "layoutwarp::measure: areas": lambda: torch.ops.layoutwarp.measure(
            means, areas[:3], CAMERA.token, "dn", torch.tensor(1)
        ),
    }
    for start, call in cases.items():
        with pytest.raises(ValueError) as err:
            call()
        assert str(err.value).startswith(start) and "\n" not in str(err.value), str(err.value)


def _variants(args: tuple, image_at: int, variant: str) -> tuple:
    """``args`` with the image argument at ``image_at`` made non-contiguous (``"strided"``, the
    same values), rounded to float32 (``"float32"``) or emptied of its batch (``"empty"``)."""
    x = args[image_at]
    if variant == "strided":
        y = x.detach().transpose(-1, -2).contiguous().transpose(-1, -2)
    elif variant == "float32":
        y = x.detach().float()
    else:
        y = x.detach()[:0]
    y = y.requires_grad_(x.requires_grad)
    return (*args[:image_at], y, *args[image_at + 1 :])


#: Operators that take an image ``(N, H, W)``, and where it is among their arguments.
IMAGE_AT = {"exact": 1, "separable": 0, "separable_adjoint": 0, "area": 0, "guard_finite": 1}


@pytest.mark.parametrize("variant", ["strided", "float32", "empty"])
def test_the_image_operators_pass_opcheck_on_strided_float32_and_empty_images(variant, gen):
    """``torch.library.opcheck`` again on every operator that takes an image, with that image
    non-contiguous (a transposed copy's transpose), in float32 (``area`` takes nothing else), and
    with an empty batch: the fake kernels' shapes, strides and dtypes hold for them too."""
    import layoutwarp.sensor  # noqa: F401

    cases = _cases(gen)
    for name, at in IMAGE_AT.items():
        if variant == "float32" and name == "area":
            continue  # area's images are float32 already
        args = _variants(cases[name], at, variant)
        result = torch.library.opcheck(OPERATORS[name], args)
        assert all(v == "SUCCESS" for v in result.values()), (name, variant, result)


def test_a_plain_eager_fixed_forward_skips_the_dispatcher_and_gives_the_operators_values(gen):
    """A fixed layout's forward in plain eager mode calls ``layoutwarp::area``'s implementation
    directly (torch's dispatcher cost a small call most of its time) and gives the registered
    operator's values bit for bit; under anything that needs the dispatcher (autograd, vmap, fake
    tensors, compiling) the predicate sends the call through the operator."""
    from torch._subclasses.fake_tensor import FakeTensorMode

    from layoutwarp.operators.base import plain_eager

    image = torch.rand(2, 3, 40, 60, generator=gen)
    layout = lw.CurvLayout((0.3, -0.2))
    with torch.no_grad():
        direct = lw.simulate(image, layout, (5, 7))
    theta, seed = layout.theta_as(torch.float64), torch.zeros((), dtype=torch.int64)
    call = area_call(layout_token(layout), (5, 7), 2.0**-12, check=True)
    through, _ = torch.ops.layoutwarp.area(image.reshape(6, 40, 60), theta, seed, call)
    assert torch.equal(direct.reshape(6, 5, 7), through)
    assert plain_eager(image, theta)
    assert not plain_eager(image.clone().requires_grad_(), theta)
    with torch.no_grad():
        assert plain_eager(image.clone().requires_grad_(), theta)
    seen = []
    torch.vmap(lambda t: seen.append(plain_eager(t)) or t)(image)
    assert seen == [False]
    with FakeTensorMode():
        assert not plain_eager(torch.empty(3))
    assert torch.compile(lambda t: t + plain_eager(t), fullgraph=True)(torch.zeros(1)).item() == 0


@pytest.mark.parametrize("learn", [False, True])
def test_a_forward_mode_tangent_is_refused_in_one_line_not_dropped(learn, gen):
    """``torch.autograd.forward_ad``: a dual image reaching `simulate` raises one line (the
    operators have reverse-mode formulas only; torch dropped the tangent without a word), and an
    open dual level with plain inputs changes nothing."""
    import torch.autograd.forward_ad as fwad

    from layoutwarp.operators.base import FORWARD_AD

    layout = lw.CurvLayout((0.3, -0.2), learn=learn)
    img, tangent = torch.rand(1, 1, 37, 53, generator=gen), torch.rand(1, 1, 37, 53, generator=gen)
    with fwad.dual_level():
        with pytest.raises(RuntimeError, match="no forward-mode derivatives") as err:
            lw.simulate(fwad.make_dual(img, tangent), layout, (5, 7))
        assert str(err.value) == FORWARD_AD and "\n" not in FORWARD_AD
        inside = lw.simulate(img, layout, (5, 7)).detach()
    assert torch.equal(inside, lw.simulate(img, layout, (5, 7)).detach())


def test_eager_calls_do_not_import_dynamo_and_a_later_compile_traces_none_of_the_kernels():
    """torch wraps every custom operator's implementation in ``torch._dynamo.disable``, made at
    its first call (importing ``torch._dynamo``, 1–2 s). In a fresh process, a learnable step, a
    fixed forward and a call with physics import no ``torch._dynamo``; a ``torch.compile`` after
    them captures one graph (the implementations disabled from then on, as torch makes them),
    whose values and θ-gradients equal eager's."""
    import subprocess
    import sys
    import textwrap

    code = """
        import json, sys, torch, layoutwarp as lw
        g = torch.Generator().manual_seed(3)
        img = torch.rand(2, 3, 40, 56, generator=g)
        layer = lw.SensorLayer((7, 9), "curv", theta=(0.3, -0.2), learn=True)
        layer(img).sum().backward()
        eager_grad = layer.layout.rho.grad.clone()
        with torch.no_grad():
            lw.simulate(img, lw.CurvLayout((0.3, -0.1)), (7, 9))
        cam = lw.SensorPhysics((30.0, 40.0), photons_per_um2=50.0, seed=1)
        lw.simulate(img, lw.CurvLayout((0.3, -0.1)), (7, 9), physics=cam)
        before = "torch._dynamo" in sys.modules
        from torch._dynamo.testing import CompileCounter
        counter = CompileCounter()
        compiled = torch.compile(layer, fullgraph=True, backend=counter)
        layer.layout.rho.grad = None
        out = compiled(img)
        out.sum().backward()
        from layoutwarp.operators.base import OPERATORS
        impl = OPERATORS["exact"]._backend_fns[None].__wrapped__
        print(json.dumps({"before": before, "frames": counter.frame_count,
            "same": bool(torch.equal(out, layer(img))),
            "grad": float((layer.layout.rho.grad - eager_grad).abs().max()),
            "disabled": getattr(impl, "__dynamo_disable", None) is not None
                and getattr(impl, "__dynamo_disable").__name__ != "run"}))
    """
    res = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=600
    )
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["before"] is False, out
    assert out["frames"] == 1 and out["same"] and out["grad"] < 1e-6, out
    assert out["disabled"], out
