"""Layouts: closed forms against float64 finite differences, inverses, bijectivity, errors."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from conftest import rand_theta

import layoutwarp as lw
from layoutwarp.layouts import (
    phi_curv,
    phi_curv_dtheta,
    phi_curv_jacobian,
    phi_rect,
    phi_rect_dtheta,
    phi_rect_jacobian,
)

F64 = torch.float64
FAMILIES = [lw.RectLayout, lw.CurvLayout]


def rand_points(gen, n=4000):
    return torch.rand(n, 2, generator=gen, dtype=F64) * 2 - 1


@pytest.mark.parametrize("cls", FAMILIES)
def test_inverse_round_trip_up_to_0999(cls, gen):
    for _ in range(40):
        theta = rand_theta(gen, 0.999)
        layout = cls(theta, dtype=F64)
        p = rand_points(gen)
        assert (layout.inverse(layout(p)) - p).abs().max() < 1e-9
        assert (layout(layout.inverse(p)) - p).abs().max() < 1e-9
    for theta in ([0.999, -0.999], [-0.999, 0.999], [0.999, 0.999], [0.0, 0.0]):
        layout = cls(theta, dtype=F64)
        p = rand_points(gen)
        assert (layout.inverse(layout(p)) - p).abs().max() < 1e-9
        assert (layout(layout.inverse(p)) - p).abs().max() < 1e-9


def test_rect_inverse_is_phi_of_minus_theta(gen):
    theta = rand_theta(gen)
    p = rand_points(gen)
    layout = lw.RectLayout(theta, dtype=F64)
    assert torch.equal(layout.inverse(p), phi_rect(p, -layout.theta))


@pytest.mark.parametrize("cls", FAMILIES)
def test_theta_rho_round_trip(cls, gen):
    theta = rand_theta(gen, 0.999)
    layout = cls(theta, dtype=F64)
    assert (layout.theta - theta).abs().max() < 1e-12
    layout = cls(theta, bound=0.5 + 0.5, dtype=F64)
    layout.set_theta(-theta)
    assert (layout.theta + theta).abs().max() < 1e-12


@pytest.mark.parametrize("cls", FAMILIES)
@pytest.mark.parametrize("bad", [1.0, -1.0, 1.5, math.nan, math.inf])
def test_out_of_range_theta_raises_naming_value(cls, bad):
    with pytest.raises(ValueError, match=r"theta\[1\] = " + ("nan" if bad != bad else "")):
        cls((0.1, bad))


def test_theta_count_and_bound_errors():
    with pytest.raises(ValueError, match="2 values"):
        lw.RectLayout((0.1, 0.2, 0.3))
    with pytest.raises(ValueError, match="bound"):
        lw.CurvLayout((0.1, 0.2), bound=0.0)
    with pytest.raises(ValueError, match=r"\|θ\| < bound = 0.5"):
        lw.CurvLayout((0.6, 0.2), bound=0.5)
    with pytest.raises(ValueError, match=r"family must be one of 'uniform', 'rect', 'curv'.*got 'hex'"):
        lw.make_layout("hex")


def test_points_shape_errors():
    layout = lw.RectLayout()
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 2\)"):
        layout(torch.zeros(4, 3))
    with pytest.raises(TypeError, match="floating-point"):
        layout(torch.zeros(4, 2, dtype=torch.long))
    with pytest.raises(ValueError, match="q must have shape"):
        layout.inverse(torch.zeros(3))


def central_jacobian(fn, p, h=1e-6):
    cols = [(fn(p + h * e) - fn(p - h * e)) / (2 * h) for e in torch.eye(2, dtype=F64)]
    return torch.stack(cols, -1)


def away_from_kinks(p, curv: bool, margin=1e-4):
    """Points where φ is smooth within ``margin``: off the unit circle (curv), off |p_j| = 1 (rect)."""
    if curv:
        return (p.norm(dim=-1) - 1).abs() > margin
    return ((p.abs() - 1).abs() > margin).all(-1)


@pytest.mark.parametrize("curv", [False, True])
def test_jacobian_and_dtheta_against_finite_differences(curv, gen):
    phi, jac, dth = (
        (phi_curv, phi_curv_jacobian, phi_curv_dtheta)
        if curv
        else (phi_rect, phi_rect_jacobian, phi_rect_dtheta)
    )
    for _ in range(10):
        theta = rand_theta(gen, 0.95)
        p = rand_points(gen, 2000)
        p = p[away_from_kinks(p, curv)]
        fd = central_jacobian(lambda q, t=theta: phi(q, t), p)
        assert (jac(p, theta) - fd).abs().max() < 1e-6 * (1 + fd.abs().max())
        fdt = torch.stack(
            [(phi(p, theta + 1e-6 * e) - phi(p, theta - 1e-6 * e)) / 2e-6 for e in torch.eye(2, dtype=F64)],
            -1,
        )
        assert (dth(p, theta) - fdt).abs().max() < 1e-6 * (1 + fdt.abs().max())


def test_curv_dtheta_is_not_the_reference_code_formula(gen):
    # DESIGN.md §3(b): the correct derivative is 2 p_j (r − 1)/(2θ_j r − θ_j − 1)².
    theta = rand_theta(gen, 0.9)
    p = rand_points(gen, 500) * 0.7
    r = p.norm(dim=-1, keepdim=True)
    expected = 2 * p * (r - 1) / (2 * theta * r - theta - 1) ** 2
    got = torch.diagonal(phi_curv_dtheta(p, theta), dim1=-2, dim2=-1)
    assert (got - expected).abs().max() < 1e-12


@pytest.mark.parametrize("cls", FAMILIES)
@pytest.mark.parametrize("at_zero", [False, True])
def test_module_derivatives_match_autograd(cls, at_zero, gen):
    # θ = 0 exactly is where the paper starts training: autograd through φ must not take a
    # zero subgradient of |θ| there
    layout = cls((0.0, 0.0) if at_zero else rand_theta(gen), dtype=F64, learn=True)
    p = rand_points(gen, 500)
    p = p[away_from_kinks(p, cls is lw.CurvLayout)]
    assert (layout.jacobian(p) - lw.Layout.phi_jacobian(layout, p, layout.theta)).abs().max() < 1e-12
    assert (layout.dtheta(p) - lw.Layout.phi_dtheta(layout, p, layout.theta)).abs().max() < 1e-12
    (g,) = torch.autograd.grad((layout(p) * p.flip(-1)).sum(), layout.rho)
    expected = (layout.dtheta(p) * p.flip(-1)[..., None]).sum((0, 1)) * (1 - layout.theta.detach() ** 2)
    assert torch.allclose(g, expected, atol=1e-12)


@pytest.mark.parametrize("cls", FAMILIES)
def test_centre_pixel_shrink_factor(cls, gen):
    theta = rand_theta(gen, 0.99)
    jac = cls(theta, dtype=F64).jacobian(torch.zeros(1, 2, dtype=F64))[0]
    assert torch.allclose(torch.diagonal(jac), (1 - theta) / (1 + theta), rtol=1e-13, atol=0)


@pytest.mark.parametrize("cls", FAMILIES)
def test_finite_values_and_gradients_at_special_points(cls):
    a = 1 / math.sqrt(2)
    special = torch.tensor(
        [[0.0, 0.0], [1.0, 0.0], [0.0, -1.0], [a, a], [0.6, -0.8], [1.0, 1.0], [-1.0, 0.3], [0.3, 1.0]],
        dtype=F64,
    )
    for theta in ([0.999, -0.999], [0.0, 0.0], [1 - 1e-6, 1 - 1e-6], [-0.5, 0.7]):
        layout = cls(theta, dtype=F64, learn=True)
        for fn in (layout, layout.inverse):
            p = special.clone().requires_grad_(True)
            q = fn(p)
            assert torch.isfinite(q).all()
            g_p, g_rho = torch.autograd.grad(q.sum(), (p, layout.rho))
            assert torch.isfinite(g_p).all() and torch.isfinite(g_rho).all()
        assert torch.isfinite(layout.jacobian(special)).all()
        # both fix the centre and every border coordinate; curv also the unit circle and beyond
        q = layout(special).detach()
        border = special.abs() == 1
        assert torch.equal(q[0], special[0])
        assert torch.allclose(q[border], special[border], rtol=0, atol=1e-15)
        if cls is lw.CurvLayout:  # a point a rounding inside the circle moves by ~ 2θ/(1 − θ) ulp
            t = max(abs(v) for v in theta)
            assert torch.allclose(q[1:], special[1:], rtol=0, atol=4e-16 * (1 + 2 * t / (1 - t)))
        else:  # rect moves the inner coordinate of a border point (here 0.3) unless θ = 0
            moved = (q[6:, :] - special[6:, :]).abs().max()
            assert (moved > 1e-3) == (abs(theta[0]) + abs(theta[1]) > 0)


def test_rect_fixes_border_and_curv_fixes_circle(gen):
    theta = rand_theta(gen)
    ang = torch.rand(100, generator=gen, dtype=F64) * 2 * math.pi
    circle = torch.stack([ang.cos(), ang.sin()], -1)
    # |p| = 1 ± 1 ulp on the circle; the formula's conditioning there is 2|θ|/(1 − |θ|)
    assert (lw.CurvLayout(theta, dtype=F64)(circle) - circle).abs().max() < 1e-13
    t = torch.rand(100, generator=gen, dtype=F64) * 2 - 1
    border = torch.cat([torch.stack([t, torch.ones_like(t)], -1), torch.stack([-torch.ones_like(t), t], -1)])
    q = lw.RectLayout(theta, dtype=F64)(border)
    assert torch.equal(q[:100, 1], border[:100, 1]) and torch.equal(q[100:, 0], border[100:, 0])


@pytest.mark.parametrize("cls", FAMILIES)
def test_no_foldovers_on_dense_grid(cls):
    values = (-0.99, -0.9, -0.5, 0.0, 0.5, 0.9, 0.99)
    for tx in values:
        for ty in values:
            report = cls((tx, ty), dtype=F64).check_foldover(201 if (tx, ty) != (0.99, 0.99) else 401)
            assert report.ok and report.min_det > 0, (tx, ty, report)


class Cubic(lw.Layout):
    """A user layout that writes only φ: φ_j(p) = p_j + θ_j p_j (1 − p_j²)/2 (bijective for |θ| < 1)."""

    family = "cubic"

    def phi(self, p, theta):
        theta = theta.to(p.dtype)
        return p + theta * p * (1 - p * p) / 2


class Folding(lw.Layout):
    """A 'layout' that folds over: φ(p) = p − 2θ p(1 − p²) with θ = 0.9."""

    def phi(self, p, theta):
        return p - 2 * theta.to(p.dtype) * p * (1 - p * p)


def test_user_layout_generic_fallbacks(gen):
    theta = rand_theta(gen, 0.9)
    layout = Cubic(theta, dtype=F64, learn=True)
    p = rand_points(gen, 1000)
    q = layout(p).detach()
    assert (layout.inverse(q) - p).abs().max() < 1e-10
    fd = central_jacobian(layout, p)
    assert (layout.jacobian(p) - fd).abs().max() < 1e-7
    fdt = torch.stack(
        [
            (layout.phi(p, theta + 1e-6 * e) - layout.phi(p, theta - 1e-6 * e)) / 2e-6
            for e in torch.eye(2, dtype=F64)
        ],
        -1,
    )
    assert (layout.dtheta(p) - fdt).abs().max() < 1e-7
    assert layout.check_foldover(101).ok
    # the numerical inverse is differentiable (implicit function theorem)
    pinv = layout.inverse(q[:50])
    g = torch.autograd.grad(pinv[:, 0].sum(), layout.rho)[0]
    h = 1e-6
    num = []
    for e in torch.eye(2, dtype=F64):
        lp, lm = Cubic(theta + h * e, dtype=F64), Cubic(theta - h * e, dtype=F64)
        num.append(float((lp.inverse(q[:50])[:, 0].sum() - lm.inverse(q[:50])[:, 0].sum()) / (2 * h)))
    assert torch.allclose(g / (1 - theta**2), torch.tensor(num, dtype=F64), atol=1e-6)


def test_foldover_is_reported():
    report = Folding((0.9, 0.9), dtype=F64).check_foldover(101)
    assert not report.ok and report.num_nonpositive > 0 and report.min_det < 0


def test_uniform_layout_is_identity(gen):
    p = rand_points(gen)
    u = lw.UniformLayout()
    assert torch.equal(u(p), p) and torch.equal(u.inverse(p), p)
    assert u.theta.numel() == 0 and list(u.parameters()) == []


class TestRegistry:
    def test_smoke(self):
        assert set(lw.FAMILIES) == {"uniform", "rect", "curv", "fovea", "spline", "grid", "elliptic"}
        assert all(lw.FAMILIES[name].family == name for name in lw.FAMILIES)

    @pytest.mark.parametrize("theta", [None, (), (0.0, 0.0), [0, 0], torch.zeros(2)])
    def test_uniform_accepts_empty_or_zero_theta(self, theta):
        assert lw.make_layout("uniform", theta).theta.numel() == 0
        assert lw.make_layout("UNIFORM", theta, learn=True).family == "uniform"

    def test_exception(self):
        with pytest.raises(ValueError, match="no parameters; theta must be empty or zeros, got"):
            lw.make_layout("uniform", (0.1, 0.0))
        with pytest.raises(TypeError, match="needs a Layout subclass with its own 'family'"):
            lw.register_family(Cubic.__base__)
        with pytest.raises(TypeError, match="Layout subclass"):
            lw.register_family(int)

    def test_a_registered_family_is_known_everywhere(self, tmp_path):
        from layoutwarp.cli import build_parser

        cls = lw.register_family(type("Cubic2", (Cubic,), {"family": "cubic2"}))
        try:
            layout = lw.make_layout("cubic2", (0.2, -0.1), dtype=F64)
            lw.save_layout(layout, tmp_path / "c.json", (3, 4))
            back, _ = lw.load_layout(tmp_path / "c.json", dtype=F64)
            assert isinstance(back, cls) and torch.allclose(back.theta, layout.theta, atol=1e-15)
            args = build_parser().parse_args(
                ["export", "--family", "cubic2", "--sensor-um", "1x1", "--out", "x.svg"]
            )
            assert args.family == "cubic2"
        finally:
            del lw.FAMILIES["cubic2"]


class TestLearn:
    @pytest.mark.parametrize("cls", FAMILIES)
    def test_fixed_unless_asked(self, cls, gen):
        layout = cls(rand_theta(gen))
        assert not layout.learnable and list(layout.parameters()) == []
        out = lw.simulate(torch.rand(1, 1, 20, 24, generator=gen), layout, (5, 6))
        assert not out.requires_grad and out.numpy().shape == (1, 1, 5, 6)
        assert cls(rand_theta(gen), learn=True).learnable
        assert lw.SensorLayer((5, 6), cls.family).layout.learnable  # the sensor layer learns by default

    def test_config_round_trip(self, gen):
        bound = 0.5 + 0.5 * float(torch.rand(1, generator=gen))
        layout = lw.CurvLayout(rand_theta(gen, bound), bound=bound, dtype=F64)
        back = lw.CurvLayout.from_config(layout.to_config(), dtype=F64)
        assert back.bound == layout.bound and torch.allclose(back.theta, layout.theta, rtol=0, atol=1e-15)
        with pytest.raises(ValueError, match="'theta' must be a list of numbers"):
            lw.CurvLayout.from_config({"theta": "0.1,0.2"})
        for family in ("rect", "curv", "fovea", "elliptic", "spline", "grid"):  # never the uniform layout
            with pytest.raises(ValueError, match="is missing: the layout's description must give it"):
                lw.FAMILIES[family].from_config({})
        with pytest.raises(ValueError, match="bound must be a finite number in \\(0, 1\\], got 10"):
            lw.CurvLayout.from_config({"theta": [5, 0.2], "bound": 10})


@pytest.mark.parametrize("cls", [*FAMILIES, Cubic])
def test_jacobian_determinant_closed_forms(cls, gen):
    a = 1 / math.sqrt(2)
    special = torch.tensor([[0.0, 0.0], [a, a], [1.0, 0.0], [0.6, -0.8], [-1.0, 1.0]], dtype=F64)
    p = torch.cat([rand_points(gen, 2000), special])
    for theta in (rand_theta(gen, 0.99), torch.zeros(2, dtype=F64)):
        layout = cls(theta, dtype=F64)
        expected = torch.linalg.det(layout.phi_jacobian(p, layout.theta))
        assert (layout.phi_jacobian_det(p, layout.theta) - expected).abs().max() < 1e-12


def test_a_state_dict_of_another_family_or_bound_is_refused_in_one_line(gen):
    """A layer's state says its layout's family (and the bound that makes ρ θ): a curv layer's
    state loaded into a rect layer (same shapes) is refused in one line, as a learnable ρ of
    another bound is; the same family loads (θ equal), and a state written before layouts said
    their family (no ``kind``) loads as it did, strictly; the state stays tensors only."""
    curv = lw.SensorLayer((4, 5), "curv", theta=(0.3, -0.2))
    for other in (lw.SensorLayer((4, 5), "rect"), lw.SensorLayer((4, 5), "curv", bound=0.9)):
        with pytest.raises(ValueError, match="the state dict holds") as err:
            other.load_state_dict(curv.state_dict())
        assert "\n" not in str(err.value)
    same = lw.SensorLayer((4, 5), "curv")
    same.load_state_dict(curv.state_dict())
    assert torch.equal(same.layout.theta, curv.layout.theta)
    assert all(isinstance(v, torch.Tensor) for v in curv.state_dict().values())
    old = {k: v for k, v in curv.state_dict().items() if not k.endswith(".kind")}
    fresh = lw.SensorLayer((4, 5), "curv")
    fresh.load_state_dict(old)  # strict: nothing missing
    assert torch.equal(fresh.layout.theta, curv.layout.theta)
    fixed = lw.SensorLayer((4, 5), lw.CurvLayout((0.1, 0.2), bound=0.9))  # θ itself in the state
    lw.SensorLayer((4, 5), lw.CurvLayout()).load_state_dict(fixed.state_dict())


def test_a_learnable_theta_within_rounding_of_the_bound_is_refused_in_one_line():
    """A learnable float32 layout cannot hold θ = 0.9999999999 (bound · tanh(ρ) rounds to the
    bound, where the layout folds): refused in one line naming θ, as a fixed layout refuses θ = 1;
    float64 holds it, and so does float32 a little further in."""
    for make in (
        lambda: lw.CurvLayout((0.9999999999, 0.1), learn=True),
        lambda: lw.SensorLayer((4, 5), "curv", theta=(0.9999999999, 0.1)),
        lambda: lw.CurvLayout((1.0, 0.1)),
    ):
        with pytest.raises(ValueError, match=r"theta\[0\]") as err:
            make()
        assert "\n" not in str(err.value)
    assert lw.CurvLayout((0.9999999999, 0.1), learn=True, dtype=torch.float64).theta[0] < 1
    assert lw.CurvLayout((0.99999, 0.1), learn=True).theta[0] < 1


def test_a_grid_checkpoint_taken_after_a_folding_step_loads_to_the_same_layer():
    """A learnable grid's state saved right after a step that folds it (the layer guards that step
    from its last valid grid at the next forward) loads into a fresh layer that guards it the same
    way: equal outputs (the last valid grid is saved with ρ). A fixed grid refuses a folded state
    in one line, as its constructor does."""
    x = torch.rand(1, 1, 16, 16, generator=torch.Generator().manual_seed(0))
    layer = lw.SensorLayer((4, 4), lw.GridLayout(grid=(2, 2), learn=True))
    with torch.no_grad():
        layer.layout.rho[2] = 0.5  # a valid step
    layer(x)  # the guard records it as the last valid grid
    with torch.no_grad():
        layer.layout.rho[2] = 1.2  # the next step folds the grid
    fresh = lw.SensorLayer((4, 4), lw.GridLayout(grid=(2, 2), learn=True))
    fresh.load_state_dict(copy.deepcopy(layer.state_dict()))
    assert torch.equal(fresh(x), layer(x))
    assert torch.equal(fresh.layout.rho, layer.layout.rho)
    fixed = lw.SensorLayer((4, 4), lw.GridLayout(grid=(2, 2)))
    folded = {k: v.clone() for k, v in fixed.state_dict().items()}
    folded["layout.fixed_theta"][2] = 1.2
    with pytest.raises(ValueError, match="fold") as err:
        fixed.load_state_dict(folded)
    assert "\n" not in str(err.value)
