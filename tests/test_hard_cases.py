"""Named hard cases for numerical stability (`pytest -k hard`).

Every case asserts finite values, finite gradients where gradients exist, and accuracy
against a reference: a closed form, an exact identity (constant in -> constant out; flux
conservation Σ I_k |A_k| = ∬ L), float64, or OpenCV.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

import layoutwarp as lw

F64 = torch.float64
EXTREME = 1 - 1e-6
FAMILIES = ["rect", "curv"]


def conserved(img: torch.Tensor, layout: lw.Layout, size, out: torch.Tensor, tol: float) -> None:
    """Σ_k I_k |A_k| / |S| equals the image mean (exact integration conserves flux)."""
    areas = lw.pixel_mesh(layout, size, tol=1e-6).areas().detach().double()
    total = (out.double() * areas).sum((-2, -1)) / 4
    assert torch.allclose(total, img.double().mean((-2, -1)), atol=tol), (total, img.mean((-2, -1)))


def finite_grads(out: torch.Tensor, layout: lw.Layout, image: torch.Tensor | None = None) -> None:
    inputs = [layout.rho] + ([image] if image is not None and image.requires_grad else [])
    grads = torch.autograd.grad((out * torch.linspace(-1, 1, out.numel()).view_as(out)).sum(), inputs)
    assert all(torch.isfinite(g).all() for g in grads)


# ---- extreme and zero θ ------------------------------------------------------------------
@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("sign", [1, -1])
def test_hard_extreme_theta_exact(family, sign):
    layout = lw.make_layout(family, (sign * EXTREME, sign * EXTREME), dtype=F64, learn=True)
    img = torch.rand(1, 2, 40, 60, dtype=F64)
    out = lw.simulate(img, layout, (7, 9), tol=1e-4)
    assert torch.isfinite(out).all()
    conserved(img[0], layout, (7, 9), out[0].detach(), 1e-9)
    finite_grads(out, layout)


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("sign", [1, -1])
def test_hard_extreme_theta_montecarlo_reynolds(family, sign):
    layout = lw.make_layout(family, (sign * EXTREME, -sign * EXTREME), dtype=F64, learn=True)
    img = torch.rand(1, 1, 40, 60, dtype=F64)
    out = lw.simulate(img, layout, (5, 6), "montecarlo", samples=3, seed=0)
    assert torch.isfinite(out).all() and float(out.detach().min()) >= 0 and float(out.detach().max()) <= 1
    finite_grads(out, layout)


@pytest.mark.parametrize("family", FAMILIES)
def test_hard_theta_exactly_zero_is_inter_area(family):
    img = torch.rand(1, 3, 56, 84)
    layout = lw.make_layout(family, (0.0, 0.0), learn=True)
    out = lw.simulate(img, layout, (8, 12))
    ref = cv2.resize(img[0].permute(1, 2, 0).numpy(), (12, 8), interpolation=cv2.INTER_AREA)
    assert np.abs(out[0].permute(1, 2, 0).detach().numpy() - ref).max() < 1e-5
    finite_grads(out, layout)


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("where", ["origin", "unit_circle", "corner", "border"])
def test_hard_special_points(family, where):
    a = 1 / math.sqrt(2)
    p0 = {"origin": [0.0, 0.0], "unit_circle": [a, a], "corner": [1.0, -1.0], "border": [-1.0, 0.25]}[where]
    for theta in ((EXTREME, -EXTREME), (0.0, 0.0), (0.5, 0.9)):
        layout = lw.make_layout(family, theta, dtype=F64, learn=True)
        p = torch.tensor([p0], dtype=F64, requires_grad=True)
        for fn in (layout, layout.inverse):
            q = fn(p)
            g = torch.autograd.grad(q.sum(), (p, layout.rho))
            assert torch.isfinite(q).all() and all(torch.isfinite(x).all() for x in g)
        assert (
            torch.isfinite(layout.jacobian(p.detach())).all()
            and torch.isfinite(layout.dtheta(p.detach())).all()
        )
        if where != "origin":  # the border (both) and the unit circle (curv) are fixed points
            if family == "curv" or where != "unit_circle":
                fixed = layout(p.detach())
                axis = slice(None) if family == "curv" else (0 if where == "border" else slice(None))
                assert torch.allclose(fixed[0, axis], p.detach()[0, axis], atol=1e-12)
        assert torch.allclose(layout(layout.inverse(p.detach())), p.detach(), atol=1e-9)


@pytest.mark.parametrize("size", [(5, 5), (7, 9), (9, 3)])
def test_hard_odd_sizes_put_a_pixel_centre_on_the_origin(size):
    layout = lw.CurvLayout((0.3, -0.4), dtype=F64, learn=True)
    img = torch.rand(1, 1, 45, 63, dtype=F64)
    for method in ("exact", "montecarlo", "point"):
        out = lw.simulate(img, layout, size, method, samples=3, seed=1)
        assert torch.isfinite(out).all()
        finite_grads(out, layout)
    # φ is odd in each axis, so the centre pixel is symmetric about the origin: its centroid
    # (of the polygon) is the origin
    poly = lw.pixel_mesh(layout, size, tol=1e-8).polygons()[(size[0] // 2) * size[1] + size[1] // 2]
    x, y = poly[:, 0], poly[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    centroid = np.array([((x + np.roll(x, -1)) * cross).sum(), ((y + np.roll(y, -1)) * cross).sum()]) / (
        3 * cross.sum()
    )
    assert np.abs(centroid).max() < 1e-12


# ---- sizes -------------------------------------------------------------------------------
@pytest.mark.parametrize("size", [(1, 1), (1, 17), (17, 1), (49, 49), (98, 49), (196, 7)])
@pytest.mark.parametrize("family", FAMILIES)
def test_hard_reference_breaking_sizes(size, family):
    layout = lw.make_layout(family, (0.6, -0.3), dtype=F64)
    img = torch.rand(1, 2, 200, 220, dtype=F64)
    out = lw.simulate(img, layout, size, tol=1e-4)
    assert out.shape == (1, 2, *size) and torch.isfinite(out).all()
    conserved(img[0], layout, size, out[0].detach(), 1e-9)


@pytest.mark.parametrize("family", FAMILIES)
def test_hard_sensor_larger_than_source(family):
    layout = lw.make_layout(family, (0.5, 0.5), dtype=F64)
    img = torch.rand(1, 1, 6, 8, dtype=F64)
    out = lw.simulate(img, layout, (30, 41), tol=1e-5)
    assert torch.isfinite(out).all()
    assert float(out.min()) >= float(img.min()) - 1e-12 and float(out.max()) <= float(img.max()) + 1e-12
    conserved(img[0], layout, (30, 41), out[0].detach(), 1e-9)


@pytest.mark.parametrize("method", ["exact", "montecarlo", "point"])
def test_hard_source_of_one_pixel(method):
    img = torch.full((1, 3, 1, 1), 0.3)
    for family in FAMILIES:
        out = lw.simulate(img, lw.make_layout(family, (0.7, -0.2)), (4, 5), method)
        assert torch.allclose(out, torch.full_like(out, 0.3), atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_hard_very_wide_image_float32_prefix_sums(family):
    # 1 x 8192 at 1000 ± 0.5: a plain float32 prefix sum reaches 8e6 (ulp 0.5) and would be
    # off by ~5e-2 after differencing; the block-local prefix must stay within a few ulp of
    # the values themselves (float32 cannot store 1000.x better than 6.1e-5). Both calls
    # share one mesh, so its tolerance does not enter the comparison (tol 1e-4 would mean 3.4M
    # vertices for these pixels, 1023 pixel widths tall, and 3 GB)
    g = torch.Generator().manual_seed(5)
    img = (1000 + torch.rand(1, 1, 1, 8192, generator=g, dtype=F64)).float()
    layout = lw.make_layout(family, (0.8, 0.0), learn=True)  # learnable: the prefix-sum path
    ref = lw.simulate(img.double(), layout, (1, 1023), tol=1e-2).detach()
    got = lw.simulate(img, layout, (1, 1023), tol=1e-2).detach()
    ulp = float(torch.finfo(torch.float32).eps) * 1001
    assert float((got.double() - ref).abs().max()) <= 4 * ulp


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("method", ["exact", "montecarlo", "point"])
def test_hard_constant_images_stay_constant(family, method):
    g = torch.Generator().manual_seed(9)
    theta = ((torch.rand(2, generator=g) * 2 - 1) * EXTREME).tolist()
    value = -7.25
    out = lw.simulate(
        torch.full((2, 1, 33, 47), value), lw.make_layout(family, theta), (6, 7), method, tol=1e-3
    )
    assert float((out - value).abs().max()) < 1e-6 * abs(value)


# ---- dtypes and memory layouts -------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float64, torch.uint8])
@pytest.mark.parametrize("family", FAMILIES)
def test_hard_input_dtypes(dtype, family):
    g = torch.Generator().manual_seed(3)
    base = torch.rand(1, 2, 40, 50, generator=g)
    img = (base * 255).round().to(torch.uint8) if dtype == torch.uint8 else base.to(dtype)
    layout = lw.make_layout(family, (0.4, 0.2))
    out = lw.simulate(img, layout, (8, 10), tol=1e-7)  # the same mesh for every dtype
    assert out.dtype == (torch.float32 if dtype == torch.uint8 else dtype) and torch.isfinite(out).all()
    ref_in = img.double() / 255 if dtype == torch.uint8 else img.double()
    ref = lw.simulate(ref_in, lw.make_layout(family, (0.4, 0.2), dtype=F64), (8, 10), tol=1e-7)
    eps = 1e-6 if dtype in (torch.float64, torch.uint8) else float(torch.finfo(dtype).eps)
    assert float((out.double() - ref).abs().max()) <= eps


@pytest.mark.parametrize("empty", ["batch", "channels"])
def test_hard_empty_batch_or_channels(empty):
    shape = (0, 3, 10, 10) if empty == "batch" else (2, 0, 10, 10)
    for family in FAMILIES:
        for method in ("exact", "montecarlo", "point"):
            out = lw.simulate(torch.rand(shape), lw.make_layout(family, (0.1, 0.1)), (3, 4), method)
            assert out.shape == (*shape[:2], 3, 4)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_hard_nonfinite_image_raises(bad):
    img = torch.rand(1, 1, 8, 8)
    img[0, 0, 2, 3] = bad
    for family in FAMILIES:
        with pytest.raises(ValueError, match="non-finite"):
            lw.simulate(img, lw.make_layout(family, (0.1, 0.1)), (2, 2))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 1.0, -1.0])
def test_hard_bad_theta_raises(bad):
    for family in FAMILIES:
        with pytest.raises(ValueError, match=r"theta\[0\]"):
            lw.make_layout(family, (bad, 0.0))
        layout = lw.make_layout(family, (0.1, 0.1))
        with pytest.raises(ValueError, match=r"theta\[1\]"):
            layout.set_theta((0.0, bad))


@pytest.mark.parametrize("family", FAMILIES)
def test_hard_non_contiguous_and_channels_last(family):
    g = torch.Generator().manual_seed(4)
    img = torch.rand(2, 3, 40, 52, generator=g)
    layout = lw.make_layout(family, (0.3, 0.5))
    ref = lw.simulate(img, layout, (7, 8))
    transposed = img.transpose(-1, -2).contiguous().transpose(-1, -2)  # non-contiguous view
    assert not transposed.is_contiguous()
    assert torch.allclose(lw.simulate(transposed, layout, (7, 8)), ref, atol=1e-6)
    cl = img.contiguous(memory_format=torch.channels_last)
    assert torch.allclose(lw.simulate(cl, layout, (7, 8)), ref, atol=1e-6)
    sliced = torch.rand(2, 3, 40, 104, generator=g)[..., ::2]  # strided
    assert torch.allclose(
        lw.simulate(sliced, layout, (7, 8)), lw.simulate(sliced.contiguous(), layout, (7, 8))
    )
    negated = torch.complex(torch.zeros_like(img), img).conj().imag  # -img as a view (negative bit)
    assert negated.is_neg()
    for options in ({}, {"tol": 1e-3}):  # the plain call and the planned one
        out = lw.simulate(negated, layout, (7, 8), **options)
        torch.testing.assert_close(out, -lw.simulate(img, layout, (7, 8), **options), rtol=0, atol=1e-6)
