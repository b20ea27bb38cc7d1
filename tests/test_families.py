"""The spline, grid and off-centre (fovea) layouts against independent references, and through
every path the paper's families have: simulate, SensorLayer, back-warping, Kornia, preprocessing,
export and layout files."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import kornia.augmentation as K
import numpy as np
import pytest
import shapely
import torch
from conftest import clip_reference, near_boundaries, rand_theta

import layoutwarp as lw
from layoutwarp.augment import SensorAugmentation
from layoutwarp.export import export_layout
from layoutwarp.layouts.grid import cell_corner_dets
from layoutwarp.weights import area_weights

F64 = torch.float64


def rint(gen, lo, hi):
    return int(torch.randint(lo, hi + 1, (1,), generator=gen))


def rand_spline(gen, kind="linear", knots=None, scale=1.0, **kw):
    knots = knots or (rint(gen, 1, 7), rint(gen, 1, 7))
    logits = torch.randn(sum(knots), generator=gen, dtype=F64) * scale
    return lw.SplineLayout(logits, knots=knots, kind=kind, dtype=F64, **kw)


def rand_control(gen, grid):
    """A random control grid that cannot fold: every point moves less than a quarter of a cell
    along each axis (the corner cross products then stay positive)."""
    gh, gw = grid
    ctrl = lw.coords.uniform_corners(grid).clone()
    step = torch.tensor([2 / gw, 2 / gh], dtype=F64)
    ctrl += (torch.rand(gh + 1, gw + 1, 2, generator=gen, dtype=F64) - 0.5) * 0.48 * step
    ctrl[:, 0, 0], ctrl[:, -1, 0], ctrl[0, :, 1], ctrl[-1, :, 1] = -1.0, 1.0, -1.0, 1.0  # back on the border
    return ctrl


def rand_grid(gen, grid=None, **kw):
    grid = grid or (rint(gen, 1, 5), rint(gen, 1, 5))
    return lw.GridLayout(rand_control(gen, grid), dtype=F64, **kw)


def rand_fovea(gen, family="curv", **kw):
    center = tuple((torch.rand(2, generator=gen, dtype=F64) * 1.2 - 0.6).tolist())
    return lw.make_layout(family, rand_theta(gen, 0.8), center=center, dtype=F64, **kw)


def rand_elliptic(gen, **kw):
    return lw.EllipticLayout(rand_theta(gen, 0.8), dtype=F64, **kw)


def make(name, gen, **kw):
    return {
        "elliptic": lambda: rand_elliptic(gen, **kw),
        "spline": lambda: rand_spline(gen, "linear", **kw),
        "spline-smooth": lambda: rand_spline(gen, "smooth", **kw),
        "grid": lambda: rand_grid(gen, **kw),
        "fovea-curv": lambda: rand_fovea(gen, "curv", **kw),
        "fovea-rect": lambda: rand_fovea(gen, "rect", **kw),
    }[name]()


NEW = ["spline", "spline-smooth", "grid", "fovea-curv", "fovea-rect", "elliptic"]


def box_reference(img: torch.Tensor, ex: np.ndarray, ey: np.ndarray) -> np.ndarray:
    """Box means over the rectangles ``[ex_j, ex_j+1] × [ey_i, ey_i+1]`` (source pixel units) from
    a float64 integral image: the integral of a piecewise-constant image is bilinear inside
    every cell, so bilinear interpolation of the table is exact."""
    arr = img.numpy()
    n, hs, ws = arr.shape
    table = np.zeros((n, hs + 1, ws + 1))
    table[:, 1:, 1:] = arr.cumsum(1).cumsum(2)

    def at(x, y):
        x0 = np.clip(np.floor(x).astype(int), 0, ws - 1)
        y0 = np.clip(np.floor(y).astype(int), 0, hs - 1)
        fx, fy = x - x0, y - y0
        return (
            table[:, y0, x0] * (1 - fx) * (1 - fy)
            + table[:, y0, x0 + 1] * fx * (1 - fy)
            + table[:, y0 + 1, x0] * (1 - fx) * fy
            + table[:, y0 + 1, x0 + 1] * fx * fy
        )

    x0, x1 = np.meshgrid(ex[:-1], ey[:-1])[0], np.meshgrid(ex[1:], ey[:-1])[0]
    y0, y1 = np.meshgrid(ex[:-1], ey[:-1])[1], np.meshgrid(ex[:-1], ey[1:])[1]
    total = at(x1, y1) - at(x0, y1) - at(x1, y0) + at(x0, y0)
    return total / ((x1 - x0) * (y1 - y0))


# ----------------------------------------------------------------------------------------
# Values against independent references
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["linear", "smooth"])
def test_spline_box_means_match_an_integral_image(kind, gen):
    for _ in range(3):
        layout = rand_spline(gen, kind, scale=1.5)
        src = (rint(gen, 5, 60), rint(gen, 5, 60))
        size = (rint(gen, 1, 12), rint(gen, 1, 12))
        img = torch.rand(2, *src, generator=gen, dtype=F64) * 4 - 1
        ex = lw.coords.sensor_to_pixels(
            layout(torch.stack([lw.coords.grid_lines(size[1]), torch.zeros(size[1] + 1, dtype=F64)], -1)), src
        )[:, 0]
        ey = lw.coords.sensor_to_pixels(
            layout(torch.stack([torch.zeros(size[0] + 1, dtype=F64), lw.coords.grid_lines(size[0])], -1)), src
        )[:, 1]
        ref = box_reference(img, ex.numpy(), ey.numpy())
        assert lw.plan_simulation(layout, size).method == "separable"
        sep = lw.simulate(img[None], layout, size)[0].numpy()
        ex_ = lw.integrators.integrate_exact(img, layout, size).numpy()  # the polygon path agrees too
        assert np.abs(sep - ref).max() <= 1e-9 and np.abs(ex_ - ref).max() <= 1e-9


def test_grid_values_match_shapely_clipping(gen):
    for _ in range(3):
        layout = rand_grid(gen)
        src = (rint(gen, 8, 30), rint(gen, 8, 30))
        size = (rint(gen, 1, 7), rint(gen, 1, 7))
        img = torch.rand(2, *src, generator=gen, dtype=F64)
        mesh = lw.pixel_mesh(layout, size)
        ref = clip_reference(img, mesh.polygons(), size)
        got = lw.simulate(img[None], layout, size)[0].numpy()
        assert np.abs(got - ref).max() <= 1e-9


def test_grid_from_layout_equals_the_layout_where_knots_align(gen):
    rect = lw.RectLayout(rand_theta(gen, 0.9), dtype=F64)
    size = (rint(gen, 2, 9), rint(gen, 2, 9))
    img = torch.rand(3, 31, 27, generator=gen, dtype=F64)
    grid = lw.GridLayout.from_layout(rect, grid=size, dtype=F64)
    # corners agree to rounding (a corner's cell coordinate can come out as 1 - ε instead of 0)
    assert (lw.pixel_mesh(grid, size).corners - lw.pixel_mesh(rect, size).corners).abs().max() <= 1e-14
    assert (
        np.abs((lw.simulate(img[None], grid, size) - lw.simulate(img[None], rect, size)).numpy()).max()
        <= 1e-12
    )
    # a piecewise-linear spline whose knots lie on the control lines is the same map everywhere
    spline = rand_spline(gen, "linear", knots=(3, 2))
    as_grid = lw.GridLayout.from_layout(spline, grid=(4, 6), dtype=F64)
    p = torch.rand(500, 2, generator=gen, dtype=F64) * 2 - 1
    assert (as_grid(p) - spline(p)).abs().max() <= 1e-12


@pytest.mark.parametrize("name", NEW)
def test_inverse_round_trips(name, gen):
    layout = make(name, gen)
    p = torch.rand(3000, 2, generator=gen, dtype=F64) * 2 - 1
    p[:8] = torch.tensor([[-1, -1], [1, 1], [-1, 1], [1, -1], [0, 0], [-1, 0.3], [0.2, 1], [0.999999, -0.5]])
    assert (layout.inverse(layout(p)) - p).abs().max() <= 1e-9
    assert (layout(layout.inverse(p)) - p).abs().max() <= 1e-9
    assert layout.check_foldover(101).ok


def test_fine_strongly_deformed_grid_inverts_exactly(gen):
    # a 32x32 control grid from a peaked density: points start many cells away from their own
    density = torch.rand(64, 64, generator=gen, dtype=F64) ** 8 * 50 + 0.01
    layout = lw.layout_from_density(density, (48, 64), "grid", floor=0.05)
    q = torch.rand(20000, 2, generator=gen, dtype=F64) * 2 - 1
    q[:4] = layout(layout.control_points()[[0, 5, 17, 31], [3, 9, 22, 31]])  # control points
    p = layout.inverse(q)
    assert (layout(p) - q).abs().max() <= 1e-12
    assert (p.abs() <= 1).all()
    # the cell search (the walk's fallback) finds the same cells
    gh, gw = layout.grid
    flat = layout.control_points().reshape(-1, 2)
    i, j = layout._search(flat, q[:3000])
    uv = layout._local(flat, i, j, q[:3000])
    assert ((uv >= -1e-9) & (uv <= 1 + 1e-9)).all()
    cell = ((p[:3000] + 1) * torch.tensor([gw / 2, gh / 2], dtype=F64)).floor().long()
    same = (cell[:, 0].clamp(max=gw - 1) == j) & (cell[:, 1].clamp(max=gh - 1) == i)
    assert same[4:].all()  # the control points (on the lines between cells) may go either way


@pytest.mark.parametrize("name", NEW)
def test_jacobian_and_dtheta_match_autograd(name, gen):
    layout = make(name, gen)
    p = torch.rand(200, 2, generator=gen, dtype=F64) * 1.98 - 0.99
    th = layout.theta.detach()
    assert torch.allclose(layout.phi_jacobian(p, th), lw.Layout.phi_jacobian(layout, p, th), atol=1e-10)
    assert torch.allclose(layout.phi_dtheta(p, th), lw.Layout.phi_dtheta(layout, p, th), atol=1e-10)
    det = layout.phi_jacobian_det(p, th)
    jac = layout.phi_jacobian(p, th)
    assert torch.allclose(det, torch.linalg.det(jac), atol=1e-10)


@pytest.mark.parametrize("family", ["curv", "rect"])
def test_learned_centre_dtheta_in_closed_form_matches_autograd(family, gen):
    layout = rand_fovea(gen, family, learn_center=True)
    c = layout.center.detach()
    p = torch.rand(400, 2, generator=gen, dtype=F64) * 2 - 1
    p[:40, 0] = c[0]  # on the centre lines, where the side (σ) switches
    p[40:80, 1] = c[1]
    p[80:100] = torch.tensor([[1.0, 0.4], [-1.0, -0.2], [0.3, 1.0], [0.1, -1.0]], dtype=F64).repeat(5, 1)
    th = layout.theta.detach()
    d = layout.phi_dtheta(p, th)
    assert d.shape == (400, 2, 4)
    assert (d - lw.Layout.phi_dtheta(layout, p, th)).abs().max() <= 1e-12
    assert (
        d[80:100].abs().amax(-1)[torch.tensor([[1, 0], [1, 0], [0, 1], [0, 1]]).repeat(5, 1).bool()].max()
        == 0
    )


# ----------------------------------------------------------------------------------------
# θ-gradients against central differences of the float64 exact forward
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["spline", "spline-smooth", "grid", "fovea-curv", "fovea-rect", "elliptic"])
@pytest.mark.parametrize("size", [(5, 5), (3, 7)])
def test_theta_gradients_match_central_differences(name, size, gen):
    extra = {"learn_center": True} if name.startswith("fovea") else {}
    if name == "grid":  # at least one interior point (a 1x1 grid has no parameters)
        extra = {"grid": (rint(gen, 2, 4), rint(gen, 2, 4))}
    layout = make(name, gen, **extra)
    img = torch.rand(2, 23, 19, generator=gen, dtype=F64)
    wts = torch.randn(2, *size, generator=gen, dtype=F64)
    curved = name in ("fovea-curv", "elliptic")

    def loss(t):  # the curved fovea: a fixed subdivision, so that the forward is smooth in θ
        mesh = lw.pixel_mesh(layout, size, subdivisions=6, theta=t) if curved else None
        if layout.separable:
            return (lw.integrators.integrate_separable(img, layout, size, theta=t) * wts).sum()
        return (lw.integrators.integrate_exact(img, layout, size, theta=t, mesh=mesh) * wts).sum()

    th = layout.theta.detach().clone().requires_grad_(True)
    (g,) = torch.autograd.grad(loss(th), th)

    def central(h: float) -> torch.Tensor:
        with torch.no_grad():
            steps = torch.eye(th.numel(), dtype=F64) * h
            return torch.stack([(loss(th + d) - loss(th - d)) / (2 * h) for d in steps])

    # the loss is C¹ in θ, not C²: its second derivative jumps where a vertex crosses a cell line
    # (by 220 within 1e-6 of a grid's θ, seed 1094171718), which puts a central difference off
    # by up to a quarter of the jump times the step (6e-5 at h = 1e-6): each component takes the
    # closer of two steps; a wrong gradient misses both
    fd = central(1e-6)
    err = torch.minimum((g - fd).abs(), (g - central(1e-7)).abs())
    assert float(err.max()) <= 1e-5 * max(float(fd.abs().max()), 1e-3)
    if layout.separable:  # the polygon path's gradient is the same
        (g2,) = torch.autograd.grad(
            (lw.integrators.integrate_exact(img, layout, size, theta=th) * wts).sum(), th
        )
        assert torch.allclose(g2, g, atol=1e-10)


def test_learned_centre_gradient_converges_like_the_values(gen):
    # the kinks of an off-centre fovea (its centre lines and adapted circle) move with the
    # centre, and the adaptive mesh's vertices follow them: its gradient converges like the
    # values, in proportion to tol (over 95 seeds, relative errors up to 1.0e-5 at tol 1e-6 and
    # 8e-8 at 1e-8; a decade's ratio jumps between 1 and 150 as the mesh changes, so no single
    # decade is tested). With vertices left where the kinks were it converges only like the
    # segment length, ∝ √tol (median 1.8e-5 at 1e-6, so about 2e-6 at 1e-8), and central
    # differences are too noisy here (box-image crossings, tol jumps).
    img = torch.rand(2, 60, 80, generator=gen, dtype=F64)
    size = (9, 13)
    w = torch.randn(2, *size, generator=gen, dtype=F64)
    layout = rand_fovea(gen, learn_center=True)
    th = layout.theta.detach().clone().requires_grad_(True)
    g = [
        torch.autograd.grad(
            (lw.integrators.integrate_exact(img, layout, size, tol=tol, theta=th) * w).sum(), th
        )[0]
        for tol in (1e-6, 1e-8, 1e-10)
    ]
    scale = float(g[2].abs().max())
    e6, e8 = (float((gt - g[2]).abs().max()) / scale for gt in g[:2])
    assert e6 <= 5e-5 and e8 <= 1e-6, (e6, e8)


def test_montecarlo_and_point_gradients_reach_every_parameter(gen):
    img = torch.rand(1, 1, 32, 32, generator=gen, dtype=F64)
    for layout in (
        rand_spline(gen, learn=True, knots=(3, 2)),  # one piece per axis would have no parameter to move
        rand_grid(gen, (3, 3), learn=True),
        rand_fovea(gen, learn=True, learn_center=True),
    ):
        for method, kw in (("montecarlo", {"samples": 3}), ("point", {})):
            out = lw.simulate(img, layout, (6, 6), method, **kw)
            (g,) = torch.autograd.grad(
                (out * torch.randn(out.shape, generator=gen, dtype=F64)).sum(), layout.rho
            )
            assert torch.isfinite(g).all() and bool((g != 0).any())


@pytest.mark.parametrize("name", ["spline-smooth", "grid", "fovea-curv", "elliptic"])
def test_montecarlo_reynolds_gradient_agrees_with_the_exact_one(name, gen):
    # the Reynolds estimator (needs ∂φ/∂θ and the Jacobian of each family) against the exact
    # integral's θ-gradient of the same box radiance (checked against central differences in
    # test_theta_gradients_match_central_differences). Not against central differences here:
    # a straight edge crossing a source pixel's edge is a kink of the box integral in θ, and
    # at this size one lies within h of a random θ now and then (a spline at 3.4e-8: its
    # central difference is the mean of the two one-sided slopes, 15 standard errors off)
    yy, xx = torch.meshgrid(
        torch.linspace(0, 1, 90, dtype=F64), torch.linspace(0, 1, 150, dtype=F64), indexing="ij"
    )
    img = torch.stack([torch.sin(6 * xx + 2 * yy) + xx * yy, torch.cos(5 * yy - 3 * xx * xx)])
    extra = {"grid": (3, 3)} if name == "grid" else {"learn_center": True} if name.startswith("fovea") else {}
    if name == "spline-smooth":
        extra = {"knots": (3, 2)}
    layout = make(name, gen, learn=True, **extra)
    size = (6, 8)
    wts = torch.randn(2, *size, generator=gen, dtype=F64)
    (dtheta,) = torch.autograd.grad(layout.theta.sum(), layout.rho)
    th = layout.theta.detach().clone().requires_grad_(True)

    def exact_forward(t):  # a curved family: a fixed subdivision, fine enough for the estimator's noise
        mesh = None if layout.straight_edges else lw.pixel_mesh(layout, size, subdivisions=64, theta=t)
        return lw.integrators.integrate_exact(img, layout, size, theta=t, mesh=mesh)

    jac = torch.autograd.functional.jacobian(exact_forward, th)  # (2, 6, 8, P): each pixel's θ-gradient
    exact = (jac * wts[..., None]).sum((0, 1, 2))
    scale = (jac * wts[..., None]).abs().sum((0, 1, 2))  # the same before the pixels cancel
    grads = []
    for k in range(32):  # 32 estimates of 4 samples: a standard error that is itself reliable
        out = lw.integrators.integrate_montecarlo(
            img,
            layout,
            size,
            samples=4,
            radiance="box",
            generator=torch.Generator().manual_seed(1000 * k + 7),
        )
        grads.append(torch.autograd.grad((out * wts).sum(), layout.rho)[0] / dtheta)
    g = torch.stack(grads)
    mean, se = g.mean(0), g.std(0) / 32**0.5
    # |t| > 6 with 31 degrees of freedom: about 1e-6 per component
    assert bool(((mean - exact).abs() <= 6 * se + 1e-3).all()), (mean, se, exact)
    # and the comparison means something: a standard error well below the gradient's size
    # before cancellation (at most 0.014 of it over 400 random layouts of these four families)
    assert bool((se < 0.05 * scale).all()), (se, scale)


def test_montecarlo_converges_to_exact_for_new_families(gen):
    yy, xx = torch.meshgrid(
        torch.linspace(0, 1, 64, dtype=F64), torch.linspace(0, 1, 64, dtype=F64), indexing="ij"
    )
    img = (torch.sin(6 * xx) * torch.cos(4 * yy))[None, None]
    for layout in (rand_spline(gen, "smooth"), rand_grid(gen, (4, 4)), rand_fovea(gen)):
        exact = lw.simulate(img, layout, (6, 7))
        mc = lw.simulate(img, layout, (6, 7), "montecarlo", samples=16, radiance="box")
        assert float((mc - exact).abs().max()) < 0.02


# ----------------------------------------------------------------------------------------
# The fovea: centred is the paper's layout bit for bit; off-centre is still a bijection
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("family", ["rect", "curv"])
def test_centred_fovea_is_the_paper_layout_bit_for_bit(family, gen):
    theta = rand_theta(gen)
    fn = {"rect": lw.layouts.phi_rect, "curv": lw.layouts.phi_curv}[family]
    p = torch.rand(1000, 2, generator=gen, dtype=F64) * 2.2 - 1.1
    layout = lw.make_layout(family, theta, center=(0.0, 0.0), dtype=F64)
    assert torch.equal(layout(p), fn(p, layout.theta))
    moved = lw.make_layout(family, theta, center=(0.0, 0.0), learn_center=True, dtype=F64)
    assert torch.equal(moved(p), fn(p, moved.theta[:2]))  # the general path, at c = 0


@pytest.mark.parametrize("family", ["rect", "curv"])
def test_off_centre_fovea_maps_the_square_onto_itself(family, gen):
    layout = rand_fovea(gen, family)
    c = layout.center
    assert torch.equal(layout(c[None])[0], c)  # the centre stays put
    t = torch.linspace(-1, 1, 101, dtype=F64)
    border = torch.cat([torch.stack([t, -torch.ones_like(t)], -1), torch.stack([torch.ones_like(t), t], -1)])
    out = layout(border)
    assert torch.equal(out.abs().amax(-1), torch.ones(len(border), dtype=F64))  # onto the border, exactly
    if family == "curv":
        assert torch.equal(out, border)  # fixed pointwise outside the adapted circle
    else:  # rect slides points along the border, monotonically
        assert bool((out[:101, 0].diff() > 0).all()) and bool((out[101:, 1].diff() > 0).all())
    mesh = lw.pixel_mesh(layout, (9, 11), tol=1e-7)
    assert abs(float(mesh.areas().sum()) - 4) < 1e-6 and bool((mesh.areas() > 0).all())
    if family == "curv":  # φ's kinks (the adapted circle and the centre lines) carry mesh vertices
        a, b = mesh.topology.edge_ends()
        assert layout.edge_breakpoints(a, b).isfinite().any()


@pytest.mark.parametrize("family", ["rect", "curv", "fovea"])
def test_a_learned_centre_layout_takes_its_whole_theta_as_theta_holds_it(family, gen):
    # what .theta and set_theta hold, (θ_x, θ_y, c_x, c_y), builds the same layout as θ and centre=
    whole = [*rand_theta(gen), *(torch.rand(2, generator=gen, dtype=F64) - 0.5).tolist()]
    parts = lw.make_layout(family, whole[:2], center=whole[2:], learn_center=True, dtype=F64)
    layout = lw.make_layout(family, whole, learn_center=True, dtype=F64)
    assert torch.equal(layout.theta, parts.theta) and layout.to_config() == parts.to_config()
    assert torch.equal(lw.make_layout(family, layout.theta, learn_center=True).theta, layout.theta)
    with pytest.raises(ValueError, match="center must not be given too"):
        lw.make_layout(family, whole, center=whole[2:], learn_center=True)
    with pytest.raises(ValueError, match="got 3"):
        lw.make_layout(family, whole[:3], learn_center=True)
    with pytest.raises(ValueError, match="got 4"):  # a fixed centre's θ is (θ_x, θ_y)
        lw.make_layout(family, whole, learn_center=False)


def test_learned_centre_moves_towards_the_detail():
    # a small bright dot off the centre: the brightest sensor pixel is brightest when it is
    # small and on the dot, so maximising it pulls the fovea (the smallest pixels) there
    img = torch.zeros(1, 1, 64, 64, dtype=F64)
    img[..., 14:18, 40:44] = 1.0  # around (x, y) = (0.31, -0.5)
    layer = lw.SensorLayer((5, 5), lw.FoveaLayout((0.6, 0.6), learn=True, dtype=F64))
    opt = torch.optim.Adam(layer.parameters(), lr=0.05)
    first = float(layer(img).amax().detach())
    for _ in range(40):
        loss = -layer(img).amax()
        opt.zero_grad()
        loss.backward()
        opt.step()
    cx, cy = layer.layout.center.tolist()
    # from 0.59 away to within 0.45 (measured: 0.36, a local optimum with the dot in a pixel
    # next to the centre one), and the brightest pixel 1.7x brighter
    assert ((cx - 0.31) ** 2 + (cy + 0.5) ** 2) ** 0.5 < 0.45, (cx, cy)
    assert float(layer(img).amax().detach()) > 1.5 * first


# ----------------------------------------------------------------------------------------
# Grids: construction, fold checks and the guarded step
# ----------------------------------------------------------------------------------------
def test_grid_constructors_refuse_bad_grids_with_the_cell_named():
    ctrl = lw.coords.uniform_corners((3, 3)).clone()
    ctrl[1, 1, 0] = 1 / 3 + 0.1  # past its right neighbour: the cells right of it fold
    with pytest.raises(ValueError, match=r"control grid folds: cell \(row 0, col 1\)"):
        lw.GridLayout(ctrl)
    off = lw.coords.uniform_corners((2, 2)).clone()
    off[0, 1, 1] = -0.9
    with pytest.raises(ValueError, match="top row must have y = -1"):
        lw.GridLayout(off)
    with pytest.raises(ValueError, match=r"shape \(gh \+ 1, gw \+ 1, 2\)"):
        lw.GridLayout(torch.zeros(3, 3))
    report = lw.GridLayout(grid=(2, 3)).check_foldover()
    assert report.ok and report.min_det == pytest.approx(1.0) and report.cell is None


def test_grid_close_to_folding_stays_exact(gen):
    # one cell's corner is within 1e-7 (relative) of a straight angle: still exact, finite gradients
    ctrl = lw.coords.uniform_corners((2, 2)).clone()
    ctrl[1, 1, 1] = -1 + 1e-7  # the centre point almost on the top border
    layout = lw.GridLayout(ctrl, dtype=F64, learn=True)
    assert 0 < layout.check_foldover().min_det < 1e-6
    img = torch.rand(1, 17, 19, generator=gen, dtype=F64)
    size = (4, 4)
    mesh = lw.pixel_mesh(layout, size)
    ref = clip_reference(img, mesh.polygons(), size)
    out = lw.integrators.integrate_exact(img, layout, size)
    assert np.abs(out.detach().numpy() - ref).max() <= 1e-9 * max(1.0, np.abs(ref).max())
    (g,) = torch.autograd.grad(out.sum(), layout.rho)
    assert torch.isfinite(g).all()


def test_projection_keeps_a_hard_pushed_grid_from_folding(gen):
    # the loss rewards pixel (0, 0) (pinned to the dark corner) for reaching into the bright
    # corner: its inner control point runs through its neighbours and an unguarded grid folds
    yy, xx = torch.meshgrid(
        torch.linspace(0, 1, 40, dtype=F64), torch.linspace(0, 1, 40, dtype=F64), indexing="ij"
    )
    img = (xx + yy)[None, None] ** 2  # brightest at the bottom right

    def train(guarded: bool) -> tuple[float, lw.GridLayout]:
        layout = lw.GridLayout(grid=(3, 3), learn=True, dtype=F64)
        opt = torch.optim.Adam(layout.parameters(), lr=0.3)
        worst = np.inf
        for _ in range(25):
            if guarded:
                layout.project_()
            worst = min(worst, float(cell_corner_dets(layout.control_points().detach()).min()))
            out = lw.simulate(img, layout, (3, 3), "montecarlo", samples=4, grad="autograd")
            opt.zero_grad()
            (-out[..., 0, 0].sum()).backward()
            opt.step()
        return worst, layout

    worst_free, _ = train(guarded=False)
    assert worst_free <= 0  # the task pushes hard enough to fold
    worst, layout = train(guarded=True)
    layout.project_()  # what the next forward pass would do after the last step
    assert worst >= layout.min_det - 1e-12 and layout.check_foldover().ok
    assert (
        float((layout.control_points().detach() - lw.coords.uniform_corners((3, 3))).abs().max()) > 0.1
    )  # learned


def test_sensor_layer_projects_before_every_forward():
    layout = lw.GridLayout(grid=(2, 2), learn=True, dtype=F64)
    layer = lw.SensorLayer((4, 4), layout)
    with torch.no_grad():
        layout.rho += 5.0  # an optimiser step gone wild: folds the grid
    assert float(cell_corner_dets(layout.control_points().detach()).min()) <= 0
    layer(torch.rand(1, 1, 8, 8, dtype=F64))
    assert layout.check_foldover().min_det >= layout.min_det


def test_from_maps_with_corners_and_centres(gen):
    layout = rand_grid(gen, (4, 5))
    src = (37, 41)
    ctrl = layout.control_points().detach()
    px = lw.coords.sensor_to_pixels(ctrl, src, centered=True)
    back = lw.GridLayout.from_maps(px[..., 0], px[..., 1], src, points="corners", dtype=F64)
    assert (back.control_points() - ctrl).abs().max() <= 1e-12
    back32 = lw.GridLayout.from_maps(
        px[..., 0].float().numpy(), px[..., 1].float().numpy(), src, points="corners", dtype=F64
    )
    assert (back32.control_points() - ctrl).abs().max() <= 1e-5
    # centre maps (what forward_maps writes): exact for the uniform (affine) layout
    maps = lw.forward_maps(lw.UniformLayout(), (6, 8), src)
    uni = lw.GridLayout.from_maps(maps.map_x, maps.map_y, src, dtype=F64)
    assert (
        uni.grid == (6, 8) and (uni.control_points() - lw.coords.uniform_corners((6, 8))).abs().max() <= 1e-6
    )
    # and close for a smooth one: averaging neighbouring centres is second order in the pixel
    # size (measured up to 6e-3 at 12x12 with these logits)
    spline = rand_spline(gen, "smooth", knots=(2, 2), scale=0.3)
    maps = lw.forward_maps(spline, (12, 12), src)
    approx = lw.GridLayout.from_maps(maps.map_x, maps.map_y, src, dtype=F64)
    assert (approx.control_points() - spline(lw.coords.uniform_corners((12, 12)))).abs().max() < 1.5e-2
    with pytest.raises(ValueError, match="points must be one of"):
        lw.GridLayout.from_maps(maps.map_x, maps.map_y, src, points="edges")


# ----------------------------------------------------------------------------------------
# Hard cases
# ----------------------------------------------------------------------------------------
def test_spline_piece_of_width_1e6(gen):
    x = [-1.0, -0.3, -0.3 + 2e-6, 1.0]  # the middle piece maps onto 2e-6 (1e-6 of the width 2)
    layout = lw.SplineLayout.from_knots(x, [-1, 0.1, 1], dtype=F64, learn=True)
    size, src = (6, 9), (20, 25)
    img = torch.rand(1, *src, generator=gen, dtype=F64)
    out = lw.simulate(img[None], layout, size)[0]
    ex = lw.coords.sensor_to_pixels(
        layout(torch.stack([lw.coords.grid_lines(9), torch.zeros(10, dtype=F64)], -1)), src
    )[:, 0]
    ey = lw.coords.sensor_to_pixels(
        layout(torch.stack([torch.zeros(7, dtype=F64), lw.coords.grid_lines(6)], -1)), src
    )[:, 1]
    ref = box_reference(img, ex.detach().numpy(), ey.detach().numpy())
    # the thin pixels are ~2.5e-5 source pixels wide (area ~7e-5): the integral-image reference
    # itself cancels to eps · ΣL / area ≈ 1.5e-9 there (seed 3505533219 measured 1.2e-9)
    area = np.outer(np.diff(ey.detach().numpy()), np.diff(ex.detach().numpy()))
    bound = 1e-9 + 8 * np.finfo(np.float64).eps * float(img.sum()) / area
    assert bool((np.abs(out.detach().numpy() - ref) <= bound).all())
    (g,) = torch.autograd.grad(out.sum(), layout.rho)
    assert torch.isfinite(g).all()
    p = torch.rand(2000, 2, generator=gen, dtype=F64) * 2 - 1
    with torch.no_grad():
        assert (layout.inverse(layout(p)) - p).abs().max() <= 1e-9


@pytest.mark.parametrize("name", NEW)
@pytest.mark.parametrize("size", [(1, 1), (1, 6), (5, 1)])
def test_one_pixel_and_one_row_sensors(name, size, gen):
    layout = make(name, gen)
    img = torch.rand(2, 15, 13, generator=gen, dtype=F64)
    mesh = lw.pixel_mesh(layout, size, tol=1e-8)
    ref = clip_reference(img, mesh.polygons(), size)
    got = lw.simulate(img[None], layout, size, tol=1e-8)[0].numpy()
    assert np.abs(got - ref).max() <= (1e-9 if layout.straight_edges else 1e-7)


@pytest.mark.parametrize("name", ["spline-smooth", "grid", "fovea-curv"])
@pytest.mark.parametrize("dtype", [torch.uint8, torch.float16])
def test_uint8_and_float16_inputs(name, dtype, gen):
    layout = make(name, gen)
    img = torch.randint(0, 256, (1, 3, 40, 30), generator=gen, dtype=torch.uint8)
    x = img if dtype == torch.uint8 else (img.double() / 255).to(dtype)
    out = lw.simulate(x, layout, (7, 5))
    ref = lw.simulate(x.double() / (255 if dtype == torch.uint8 else 1), layout, (7, 5), tol=1e-9)
    assert out.dtype == (torch.float32 if dtype == torch.uint8 else torch.float16)
    lsb = 1 / 255 if dtype == torch.uint8 else float(torch.finfo(torch.float16).eps)
    assert float((out.double() - ref).abs().max()) <= lsb


# ----------------------------------------------------------------------------------------
# Every path
# ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", NEW)
def test_backwarp_agrees_with_point_in_polygon_and_opencv(name, gen):
    layout = make(name, gen)
    size, target = (6, 7), (41, 37)
    index = torch.arange(size[0] * size[1]).view(1, 1, *size)
    got = lw.backwarp(index, layout, target)[0, 0].numpy()
    mesh = lw.pixel_mesh(layout, size, tol=1e-7)  # edges within ~1e-8 of the curves: far inside `near`
    polys = [shapely.Polygon(p) for p in mesh.polygons()]
    pts = shapely.points(lw.coords.pixel_centers(target).reshape(-1, 2).numpy())
    near = near_boundaries(pts, polys)
    hits = shapely.STRtree(polys).query(pts, predicate="within")
    ref = np.full(len(pts), -1)
    ref[hits[0]] = hits[1]
    assert int(((ref != got.reshape(-1)) & ~near).sum()) == 0
    arr = (torch.rand(*size, 3, generator=gen) * 255).numpy().astype(np.uint8)
    cv = lw.backwarp_numpy(arr, layout, target)
    assert np.array_equal(
        cv,
        lw.backwarp(torch.from_numpy(arr).permute(2, 0, 1)[None], layout, target)[0].permute(1, 2, 0).numpy(),
    )
    # the OpenCV-rasterised index map: the point-in-polygon pixel, except for target centres
    # within 1 / oversample (the default 3) of a target pixel from a pixel boundary
    raster = lw.maps.raster_index_map(layout, size, target).numpy().reshape(-1)
    px = [
        shapely.Polygon(lw.coords.sensor_to_pixels(torch.from_numpy(p), target, centered=True).numpy())
        for p in mesh.polygons()
    ]
    ii, jj = np.divmod(np.arange(len(pts)), target[1])
    for k in np.flatnonzero((raster != ref) & (ref >= 0)):
        assert px[ref[k]].boundary.distance(shapely.Point(jj[k], ii[k])) <= 1 / 3
    assert np.mean(raster == ref) > 0.7
    via = lw.backwarp(index, layout, target, index_method="raster")[0, 0].numpy().reshape(-1)
    assert np.array_equal(via, raster)


@pytest.mark.parametrize("name", ["spline", "grid", "fovea-curv"])
def test_kornia_container_and_keypoints(name, gen):
    extra = {"grid": (3, 2)} if name == "grid" else {"knots": (3, 2)} if name == "spline" else {}
    layout = make(name, gen, learn=True, **extra)  # at least one parameter that moves pixels
    aug = SensorAugmentation((9, 11), layout)
    img = torch.rand(2, 3, 40, 48, generator=gen)
    seq = K.AugmentationSequential(aug, data_keys=["input", "keypoints"])
    kp = torch.rand(2, 5, 2, generator=gen) * torch.tensor([47.0, 39.0])
    out, k2 = seq(img, kp)
    assert torch.allclose(out, lw.simulate(img, layout, (9, 11)), atol=1e-6)
    back = seq.inverse(out, k2, data_keys=["input", "keypoints"])[1]
    assert torch.allclose(back, kp, atol=1e-3)
    (out * torch.randn_like(out)).sum().backward()
    assert layout.rho.grad is not None and bool(layout.rho.grad.abs().sum() > 0)


def test_spline_boxes_pass_through_kornia_exactly(gen):
    layout = rand_spline(gen, "smooth")
    img = torch.rand(2, 3, 40, 48, generator=gen)
    boxes = torch.tensor([[[10.0, 5.0, 30.0, 25.0]], [[2.0, 3.0, 40.0, 33.0]]])
    seq = K.AugmentationSequential(SensorAugmentation((9, 11), layout), data_keys=["input", "bbox_xyxy"])
    out, b = seq(img, boxes)
    assert bool((b[..., 2] > b[..., 0]).all())
    assert torch.allclose(seq.inverse(out, b, data_keys=["input", "bbox_xyxy"])[1], boxes, atol=1e-3)


@pytest.mark.parametrize("name", NEW)
def test_area_weights_equal_simulate(name, gen):
    layout = make(name, gen)
    src, size = (33, 29), (7, 6)
    img = torch.rand(2, *src, generator=gen, dtype=F64)
    w = area_weights(layout, size, src, tol=1e-7)
    got = (w @ img.reshape(2, -1).T.numpy()).T.reshape(2, *size)
    with torch.no_grad():
        ref = lw.simulate(img[None], layout, size, tol=1e-7)[0].numpy()
    assert np.abs(got - ref).max() <= 1e-12


@pytest.mark.parametrize("name", ["spline-smooth", "grid", "fovea-curv"])
def test_export_tiles_the_sensor(name, gen, tmp_path):
    layout = make(name, gen)
    size, um = (5, 6), (900.0, 1200.0)
    rep = export_layout(layout, size, tmp_path / "m.svg", um, tol_um=0.05)
    assert rep.pixels == 30 and rep.max_deviation_um <= 0.05
    root = ET.parse(tmp_path / "m.svg").getroot()
    polys = [
        np.array([[float(v) for v in pt.split(",")] for pt in p.get("points").split()])
        for p in root.iter("{http://www.w3.org/2000/svg}polygon")
    ]
    shapes = [shapely.Polygon(p) for p in polys]
    assert all(s.is_valid for s in shapes)
    assert abs(sum(s.area for s in shapes) - um[0] * um[1]) < 1e-6 * um[0] * um[1]
    assert abs(shapely.union_all(shapes).area - um[0] * um[1]) < 1e-6 * um[0] * um[1]
    if layout.separable:  # Manhattan by construction: every edge is axis-aligned
        for p in polys:
            d = np.diff(np.vstack([p, p[:1]]), axis=0)
            assert bool(((np.abs(d[:, 0]) < 1e-9) | (np.abs(d[:, 1]) < 1e-9)).all())


@pytest.mark.parametrize("name", NEW)
def test_layout_files_round_trip(name, gen, tmp_path):
    layout = make(name, gen)
    lw.save_layout(layout, tmp_path / "l.json", (4, 5), note="x")
    back, info = lw.load_layout(tmp_path / "l.json", dtype=F64)
    assert type(back) is type(layout) and info["size_hw"] == [4, 5]
    p = torch.rand(300, 2, generator=gen, dtype=F64) * 2 - 1
    # θ = bound·tanh(ρ) goes through atanh and back on loading: equal to an ulp or two
    assert (back(p) - layout(p)).abs().max() <= 1e-14
    data = json.loads((tmp_path / "l.json").read_text())
    assert data["format"] == "layoutwarp.layout/2"
    data["format"] = "layoutwarp.layout/9"
    (tmp_path / "l.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match="newer than this layoutwarp reads"):
        lw.load_layout(tmp_path / "l.json")


def test_constructors_keep_a_tensor_arguments_dtype(gen):
    ctrl = lw.coords.uniform_corners((2, 2)).clone()
    ctrl[1, 1] = (torch.rand(2, generator=gen, dtype=F64) - 0.5) * 0.5
    grid = lw.GridLayout(ctrl)  # float64 control: a float64 layout, φ bilinear to the last bit
    assert grid.dtype == F64 and torch.equal(grid(torch.zeros(1, 2, dtype=F64))[0], ctrl[1, 1])
    assert lw.GridLayout(ctrl.tolist()).dtype == torch.get_default_dtype()
    assert lw.GridLayout(ctrl, dtype=torch.float32).dtype == torch.float32  # dtype= still wins
    theta = rand_theta(gen, 0.5)
    for layout in (
        lw.CurvLayout(theta),
        lw.RectLayout(theta),
        lw.FoveaLayout(theta),
        lw.SplineLayout(theta, knots=(1, 1)),
    ):
        assert layout.dtype == F64, type(layout).__name__
    assert lw.FoveaLayout(tuple(theta.tolist())).dtype == torch.get_default_dtype()
    assert lw.CurvLayout(theta.float(), center=torch.zeros(2, dtype=F64)).dtype == torch.float32
    knots = torch.tensor([-1.0, -0.2, 1.0], dtype=F64)
    assert lw.SplineLayout.from_knots(knots, knots).dtype == F64


# ----------------------------------------------------------------------------------------
# The elliptic family (the reference code's third)
# ----------------------------------------------------------------------------------------
def test_elliptic_deforms_up_to_the_corners_and_fixes_the_border(gen):
    theta = rand_theta(gen, 0.9)
    layout = lw.EllipticLayout(theta, dtype=F64)
    t = torch.rand(200, generator=gen, dtype=F64) * 2 - 1
    border = torch.cat([torch.stack([t, torch.ones_like(t)], -1), torch.stack([-torch.ones_like(t), t], -1)])
    assert torch.allclose(layout(border), border, rtol=0, atol=1e-15)
    near_corner = torch.tensor([[0.9, 0.9], [-0.95, 0.92]], dtype=F64)  # outside the unit circle
    assert float((layout(near_corner) - near_corner).abs().max()) > 1e-3  # curv leaves these alone
    assert torch.equal(lw.CurvLayout(theta, dtype=F64)(near_corner), near_corner)
    # the square-to-disk map and its inverse
    from layoutwarp.layouts import disk_to_square, square_to_disk

    p = torch.rand(500, 2, generator=gen, dtype=F64) * 2 - 1
    d = square_to_disk(p)
    assert bool((d.norm(dim=-1) < 1).all()) and torch.allclose(disk_to_square(d), p, atol=1e-12)


def test_elliptic_inverse_jacobian_and_dtheta_against_independent_references(gen):
    theta = rand_theta(gen, 0.9)
    layout = lw.EllipticLayout(theta, dtype=F64)
    p = torch.rand(300, 2, generator=gen, dtype=F64) * 1.98 - 0.99
    q = layout(p)
    assert torch.allclose(layout.inverse(q), p, atol=1e-11)  # closed form
    assert torch.allclose(lw.layouts.newton_inverse(layout.phi, q, layout.theta), p, atol=1e-10)
    h = 1e-6  # Jacobian and ∂φ/∂θ against central differences of the closed form
    for k, e in enumerate(torch.eye(2, dtype=F64)):
        fd_p = (layout.phi(p + h * e, theta) - layout.phi(p - h * e, theta)) / (2 * h)
        assert torch.allclose(layout.jacobian(p)[..., :, k], fd_p, atol=1e-7)
        fd_t = (layout.phi(p, theta + h * e) - layout.phi(p, theta - h * e)) / (2 * h)
        assert torch.allclose(layout.dtheta(p)[..., :, k], fd_t, atol=1e-7)


@pytest.mark.parametrize("tx", [-0.99, -0.9, -0.5, 0.0, 0.5, 0.9, 0.99])
def test_elliptic_does_not_fold_over_its_theta_range(tx):
    for ty in (-0.99, -0.9, -0.5, 0.0, 0.5, 0.9, 0.99):
        report = lw.EllipticLayout((tx, ty), dtype=F64).check_foldover(101)
        assert report.ok and report.min_det > 0, (tx, ty, report)


@pytest.mark.parametrize("name", ["curv", "fovea", "elliptic", "spline", "grid"])
def test_what_theta_is_made_of_makes_the_layouts_float64_theta_and_its_gradient(name, gen):
    """`Layout.theta_source` and `theta_of` (how the exact integrator's operator makes θ itself):
    a learnable float32 layout's θ in float64, bit for bit as ``theta_as(torch.float64)`` makes
    it, with the same gradient in ρ; a frozen layout's θ as it is; and the exact integrator's
    means and ρ-gradient from ρ those it gives for that θ passed in as it is."""
    from layoutwarp.integrators import integrate_exact
    from layoutwarp.layouts import theta_of

    f32 = torch.float32
    learnable = {
        "curv": lambda: lw.CurvLayout(rand_theta(gen, 0.9), learn=True, dtype=f32),
        "fovea": lambda: lw.FoveaLayout(
            rand_theta(gen, 0.8), center=(0.2, -0.3), learn=True, learn_center=True, dtype=f32
        ),
        "elliptic": lambda: lw.EllipticLayout(rand_theta(gen, 0.8), learn=True, dtype=f32),
        "spline": lambda: rand_spline(gen, learn=True).float(),
        "grid": lambda: rand_grid(gen, learn=True).float(),
    }[name]()
    param, bounds = learnable.theta_source()
    assert param is learnable.rho and bounds.dtype == F64
    made, ref = theta_of(param, bounds), learnable.theta_as(F64)
    assert made.dtype == F64 and torch.equal(made, ref)
    weights = torch.randn(made.shape, generator=gen, dtype=F64)
    (g_made,) = torch.autograd.grad((made * weights).sum(), learnable.rho)
    (g_ref,) = torch.autograd.grad((ref * weights).sum(), learnable.rho)
    assert torch.equal(g_made, g_ref)
    frozen = learnable.requires_grad_(False)
    theta, empty = frozen.theta_source()
    assert empty.numel() == 0 and torch.equal(theta, ref.detach())
    frozen.requires_grad_(True)
    if name in ("curv", "fovea"):  # the compiled mesh's families: the operator makes this θ
        img = torch.rand(2, 19, 23, generator=gen, dtype=F64)
        g = torch.randn(2, 5, 6, generator=gen, dtype=F64)
        got = integrate_exact(img, learnable, (5, 6), tol=1e-6)  # ρ and its bounds in
        (g_got,) = torch.autograd.grad((got * g).sum(), learnable.rho)
        theta = learnable.theta_as(F64)
        want = integrate_exact(img, learnable, (5, 6), tol=1e-6, theta=theta)  # θ in, as it is
        (g_want,) = torch.autograd.grad((want * g).sum(), learnable.rho)
        assert torch.equal(got.detach(), want.detach())
        assert float((g_got - g_want).abs().max()) <= 1e-6 * float(g_want.abs().max())  # ρ in float32
