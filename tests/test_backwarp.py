"""Back-warping: exact against point-in-polygon, OpenCV path bit-identical, loss helper."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import shapely
import torch
from conftest import near_boundaries, rand_theta

import layoutwarp as lw

F64 = torch.float64


@pytest.mark.parametrize("family", ["uniform", "rect", "curv"])
def test_backwarp_matches_point_in_polygon(family, gen):
    layout = lw.make_layout(family, None if family == "uniform" else rand_theta(gen, 0.9), dtype=F64)
    size, target = (7, 9), (41, 53)
    index = torch.arange(size[0] * size[1]).view(1, 1, *size)
    got = lw.backwarp(index, layout, target)[0, 0].numpy()
    assert got.dtype == np.int64
    # reference: which (finely subdivided) pixel polygon contains each target centre
    mesh = lw.pixel_mesh(layout, size, subdivisions=1 if family != "curv" else 512)
    polys = [shapely.Polygon(p) for p in mesh.polygons()]
    tree = shapely.STRtree(polys)
    centres = lw.coords.pixel_centers(target).reshape(-1, 2).numpy()
    pts = shapely.points(centres)
    near = near_boundaries(pts, polys)
    hits = tree.query(pts, predicate="within")
    ref = np.full(len(pts), -1)
    ref[hits[0]] = hits[1]
    mismatch = (ref != got.reshape(-1)) & ~near
    assert int(mismatch.sum()) == 0
    assert (ref >= 0).sum() + near.sum() >= len(pts)  # every centre is classified


@pytest.mark.parametrize("family", ["rect", "curv"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.float32, np.float64])
def test_opencv_path_is_bit_identical(family, dtype, gen):
    layout = lw.make_layout(family, rand_theta(gen, 0.95))
    arr = (torch.rand(13, 17, 3, generator=gen) * 200).numpy().astype(dtype)
    got = lw.backwarp_numpy(arr, layout, (90, 70))
    ref = (
        lw.backwarp(torch.from_numpy(arr).permute(2, 0, 1)[None], layout, (90, 70))[0]
        .permute(1, 2, 0)
        .numpy()
    )
    assert got.dtype == dtype and np.array_equal(got, ref)
    gray = arr[..., 0]
    assert np.array_equal(lw.backwarp_numpy(gray, layout, (90, 70)), ref[..., 0])


def test_bilinear_backwarp_converges_at_second_order(gen):
    # a smooth field sampled at the deformed pixel centres and back-warped bilinearly
    # approximates the field with error O(h²): it must fall ~4x per doubling of resolution
    layout = lw.CurvLayout(rand_theta(gen, 0.7), dtype=F64)
    q = lw.coords.pixel_centers((50, 70))
    # away from the border padding and from φ_curv's kinks (O(h) there)
    u = layout.inverse(q).detach().norm(dim=-1)  # φ_curv bends at |u| = 1 and at u = 0 (|u| terms)
    inner = (q.abs() < 0.85).all(-1) & ((u - 1).abs() > 0.15) & (u > 0.15)
    expected = torch.sin(2 * q[..., 0]) + q[..., 1] ** 2
    errs = []
    for size in ((20, 30), (40, 60), (80, 120), (160, 240)):
        c = layout(lw.coords.pixel_centers(size)).detach()
        field = (torch.sin(2 * c[..., 0]) + c[..., 1] ** 2)[None, None]
        out = lw.backwarp(field, layout, (50, 70), mode="bilinear")[0, 0]
        errs.append(float((out - expected)[inner].pow(2).mean().sqrt()))  # RMS: max-norm orders are noisy
    order = [math.log2(a / b) for a, b in itertools.pairwise(errs)]
    overall = math.log2(errs[0] / errs[-1]) / (len(errs) - 1)
    assert overall > 1.8 and min(order) > 1.5, (errs, order)  # second order
    with pytest.raises(TypeError, match="nearest"):
        lw.backwarp(torch.zeros(1, 1, 4, 4, dtype=torch.long), layout, (8, 8), mode="bilinear")


def test_backwarp_cross_entropy_equals_manual_and_has_gradients(gen):
    for layout in (lw.RectLayout(rand_theta(gen, 0.8)), lw.CurvLayout(rand_theta(gen, 0.8))):
        logits = torch.randn(2, 5, 6, 8, generator=gen, dtype=torch.float64, requires_grad=True)
        labels = torch.randint(0, 6, (2, 30, 40), generator=gen)  # 5 = ignored
        weight = torch.rand(5, generator=gen, dtype=torch.float64) + 0.5
        for w in (None, weight):
            loss = lw.backwarp_cross_entropy(logits, labels, layout, ignore_index=5, weight=w)
            up = lw.backwarp(logits, layout, (30, 40))
            ref = torch.nn.functional.cross_entropy(up, labels, ignore_index=5, weight=w)
            assert abs(float((loss - ref).detach())) < 1e-12
            (g,) = torch.autograd.grad(loss, logits)
            (g_ref,) = torch.autograd.grad(ref, logits)
            assert torch.allclose(g, g_ref, rtol=0, atol=1e-14) and bool(g.abs().sum() > 0)
    with pytest.raises(ValueError, match="labels must be in"):
        lw.backwarp_cross_entropy(logits, labels + 1, layout, ignore_index=5)


def test_backwarp_uniform_integer_ratio_is_nearest_upsampling(gen, device):
    x = torch.rand(2, 3, 4, 5, generator=gen).to(device)
    out = lw.backwarp(x, lw.UniformLayout().to(device), (12, 20))
    assert out.device == x.device and torch.equal(out, x.repeat_interleave(3, -2).repeat_interleave(4, -1))
    assert lw.backwarp(x[:, 0], lw.UniformLayout(), (12, 20)).shape == (2, 12, 20)
    layout = lw.CurvLayout(rand_theta(gen)).to(device)  # nearest and bilinear on the device
    for mode in ("nearest", "bilinear"):
        assert lw.backwarp(x, layout, (9, 11), mode=mode).device == x.device


@pytest.mark.parametrize(
    "family",
    [
        "fovea",
        "rect",
        pytest.param("elliptic", marks=pytest.mark.slow),
    ],
)
def test_bilinear_backwarp_of_a_learnable_sensor_gives_theta_its_central_difference_gradient(family, gen):
    """A float64 model: conv → learnable sensor → bilinear back-warp → conv → loss. Autograd's
    θ-gradient (through the sensor and through the sampling points φ⁻¹(q, θ) of the back-warp)
    equals central differences of the loss in ρ; without the back-warp's part it would not
    (the check that the test can fail: its share of the gradient is not small)."""
    F64 = torch.float64
    layout = lw.make_layout(family, learn=True, dtype=F64)
    with torch.no_grad():
        layout.rho.add_(0.3 * torch.randn(layout.rho.shape, generator=gen, dtype=F64))
    pre = torch.nn.Conv2d(1, 1, 3, padding=1).double()
    post = torch.nn.Conv2d(1, 1, 3, padding=1).double()
    img = torch.rand(1, 1, 24, 28, generator=gen, dtype=F64)
    target = torch.rand(1, 1, 16, 18, generator=gen, dtype=F64)

    def loss(detach_warp: bool = False) -> torch.Tensor:
        low = lw.simulate(pre(img), layout, (6, 7), tol=1e-10)
        if detach_warp:
            with torch.no_grad():
                p = lw.maps.inverse_coords(layout, (16, 18))
            up = torch.nn.functional.grid_sample(
                low, p[None].to(low), mode="bilinear", padding_mode="border", align_corners=False
            )
        else:
            up = lw.backwarp(low, layout, (16, 18), mode="bilinear")
        return (post(up) - target).square().mean()

    (g,) = torch.autograd.grad(loss(), layout.rho)
    (g_sensor_only,) = torch.autograd.grad(loss(detach_warp=True), layout.rho)
    eps, fd = 1e-6, torch.zeros_like(g)
    with torch.no_grad():
        for i in range(layout.rho.numel()):
            layout.rho[i] += eps
            up = loss()
            layout.rho[i] -= 2 * eps
            down = loss()
            layout.rho[i] += eps
            fd[i] = (up - down) / (2 * eps)
    torch.testing.assert_close(g, fd, rtol=1e-5, atol=1e-9)
    assert (g_sensor_only - fd).abs().max() > 100 * (g - fd).abs().max()


@pytest.mark.parametrize("n", [3, 5, 10, 18, 24, 129])
def test_centres_on_pixel_boundaries_go_right_and_below_every_one(n):
    # a uniform sensor of n pixels over 10 n source pixels: every sensor centre lies on a source
    # boundary (10 j + 5); target centres of a 3n/2 back-warp lie on every other sensor boundary.
    # Rounding put some just before it, and they went left or up (columns 4, 15, 25, 34, ...)
    from layoutwarp.backwarp import sensor_index_maps
    from layoutwarp.labels import source_pixels

    row, col = source_pixels(lw.UniformLayout(), (n, n + 1), (10 * n, 10 * (n + 1)))
    assert col[0].tolist() == [10 * j + 5 for j in range(n + 1)]
    assert row[:, 0].tolist() == [10 * i + 5 for i in range(n)]
    col, row = sensor_index_maps(lw.UniformLayout(), (2 * n, 2 * n), (3 * n, 3 * n))
    expected = [math.floor(2 * (t + 0.5) / 3) for t in range(3 * n)]  # exact in rationals: ties right
    assert col[0].tolist() == expected and row[:, 0].tolist() == expected
