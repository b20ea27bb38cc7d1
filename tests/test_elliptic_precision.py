"""The elliptic family's φ in float64 against a 700-digit evaluation of its definition
(E⁻¹ ∘ φ_curv ∘ E, E the elliptical grid mapping): a few ulps over the whole square, the axes,
edges and corners included, where the closed form's differences of two roots once lost digits
(8e-9 relative near the axes, 1e-8 absolute at 1e-12 from a corner)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from layoutwarp.layouts import EllipticLayout

F64 = torch.float64

mp = pytest.importorskip("mpmath")


def reference(x: float, y: float, theta: tuple[float, float]) -> tuple[float, float]:
    """φ at the float inputs, evaluated as written (the direct difference of roots) in 700 digits."""
    with mp.workdps(700):
        x, y = mp.mpf(x), mp.mpf(y)
        u, v = x * mp.sqrt(1 - y * y / 2), y * mp.sqrt(1 - x * x / 2)
        r = mp.sqrt(u * u + v * v)
        if r < 1:
            u, v = (
                c * (1 - mp.mpf(t)) / ((1 + mp.mpf(t)) - 2 * mp.mpf(t) * r)
                for c, t in zip((u, v), theta, strict=True)
            )
        r2, a, b = 2 * mp.sqrt(2), 2 + u * u - v * v, 2 - u * u + v * v
        return (
            float((mp.sqrt(a + r2 * u) - mp.sqrt(a - r2 * u)) / 2),
            float((mp.sqrt(b + r2 * v) - mp.sqrt(b - r2 * v)) / 2),
        )


def test_elliptic_phi_is_within_a_few_ulps_of_a_700_digit_reference_over_the_square(seed):
    rng = np.random.default_rng(seed)
    layout = EllipticLayout(tuple(rng.uniform(-0.6, 0.6, 2)), dtype=torch.float64)
    theta = tuple(float(t) for t in layout.theta)
    n = 150
    inner = rng.uniform(-1, 1, (n, 2))
    tiny = rng.choice([1e-300, -1e-200, 1e-12, -1e-8, 1e-6, 0.0], n)  # on and beside the axes
    axes = np.concatenate(
        [np.stack([rng.uniform(-1, 1, n), tiny], 1), np.stack([tiny, rng.uniform(-1, 1, n)], 1)]
    )
    edges = np.stack([rng.choice([1 - 1e-12, -1 + 1e-9, 1 - 1e-4], n), rng.uniform(-0.9, 0.9, n)], 1)
    corners = rng.choice([-1, 1], (n, 2)) * (1 - 10 ** rng.uniform(-12, -2, (n, 2)))
    points = np.concatenate([inner, axes, edges, edges[:, ::-1], corners])
    out = layout.phi(torch.from_numpy(points), layout.theta.double()).numpy()
    ref = np.array([reference(x, y, theta) for x, y in points])
    err = np.abs(out - ref)
    ulps = err / np.spacing(np.maximum(np.abs(ref), np.finfo(float).tiny))
    worst = int(ulps.max())  # corners included, where E⁻¹'s derivative is infinite
    assert worst <= 16, (worst, points[ulps.max(1).argmax()], theta)
    assert (out[ref == 0] == 0).all()  # on an axis, exactly on it
    back = layout.phi_inverse(torch.from_numpy(out), layout.theta.double()).numpy()
    near_corner = (np.abs(points) > 0.9).all(1)
    assert np.abs(back - points)[~near_corner].max() <= 1e-14  # and the inverse takes φ back


def definition(p: np.ndarray, theta: np.ndarray, family: str) -> np.ndarray:
    """φ as its definition reads, in plain float64 numpy (the elliptic family: the elliptical grid
    mapping to the disk, φ_curv, and back by the difference of two roots)."""
    x, y = p[:, 0], p[:, 1]
    if family == "rect":
        return np.stack(
            [c * (t - 1) / (2 * t * np.abs(c) - t - 1) for c, t in zip((x, y), theta, strict=True)], 1
        )
    if family == "curv":
        r = np.hypot(x, y)[:, None]
        return np.where(r < 1, p * (theta - 1) / (2 * theta * r - theta - 1), p)
    u, v = x * np.sqrt(1 - y * y / 2), y * np.sqrt(1 - x * x / 2)
    r = np.hypot(u, v)
    u, v = (c * (t - 1) / (2 * t * r - t - 1) for c, t in zip((u, v), theta, strict=True))
    s, a, b = 2 * np.sqrt(2), 2 + u * u - v * v, 2 - u * u + v * v
    return np.stack([np.sqrt(a + s * u) - np.sqrt(a - s * u), np.sqrt(b + s * v) - np.sqrt(b - s * v)], 1) / 2


@pytest.mark.parametrize("family", ["elliptic", "curv", "rect"])
def test_phi_in_float64_is_its_definition_whatever_dtype_the_layout_was_made_in(family, seed):
    # a layout made in float32 (torch's default) used to evaluate φ at its θ's float32 rounding:
    # 8e-9 off the definition at (0.72196, −0.00266) for θ = (0.45, 0.3)
    from layoutwarp.layouts import make_layout

    rng = np.random.default_rng(seed)
    n = 2000
    band = rng.uniform(-0.05, 0.05, n)
    for theta in [
        np.array([0.45, 0.3]),
        np.array([0.2, 0.2]),
        np.array([-0.5, 0.1]),
        *rng.uniform(-0.9, 0.9, (12, 2)),
    ]:
        points = np.concatenate(
            [rng.uniform(-0.999, 0.999, (n, 2)), np.stack([rng.uniform(-0.999, 0.999, n), band], 1)]
        )
        points = np.concatenate([points, points[n:, ::-1], [[0.72196, -0.00266], [-0.6003, -0.0041]]])
        p, ref = torch.from_numpy(points), definition(points, theta, family)
        made = {
            "float32": make_layout(family, tuple(theta)),
            "float64": make_layout(family, tuple(theta), dtype=torch.float64),
            "float32 then .double()": make_layout(family, tuple(theta)).double(),
            "float64 then .float()": make_layout(family, tuple(theta), dtype=torch.float64).float(),
            "learnable float64": make_layout(family, tuple(theta), learn=True, dtype=torch.float64),
        }
        for what, layout in made.items():
            got = {
                "layout(p)": layout(p).detach(),
                "phi at theta_as(float64)": layout.phi(p, layout.theta_as(F64)).detach(),
            }
            if layout.dtype == F64:
                got["phi at theta"] = layout.phi(p, layout.theta).detach()
            for how, out in got.items():
                err = float((out - torch.from_numpy(ref)).abs().max())
                assert err <= 5e-14, (what, how, theta.tolist(), err)
        assert made["float32"].theta.dtype == torch.float32 and made["float32 then .double()"].dtype == F64
        assert made["float64 then .float()"].theta.dtype == torch.float32


def test_the_float32_inverse_is_the_float64_one_rounded_and_stays_in_the_square(seed):
    # E⁻¹ near the corners lost 4e-5 in float32 (and left the square by 1e-5): the inverse of a
    # float32 layout is now the float64 one rounded once
    rng = np.random.default_rng(seed)
    near = 1 - 10.0 ** rng.uniform(-7, -1, (4000, 2))  # towards the corners and edges
    q = np.concatenate([rng.uniform(-1, 1, (20000, 2)), near * rng.choice([-1, 1], (4000, 2))])
    q32 = torch.from_numpy(q).float()
    theta = (0.9, -0.9)
    got = EllipticLayout(theta).inverse(q32)
    ref = EllipticLayout(theta, dtype=torch.float64).inverse(q32.double())
    assert got.dtype == torch.float32
    assert float((got.double() - ref).abs().max()) <= 2 * 2.0**-24  # one rounding of ref, at most 1
    assert float(got.abs().max()) <= 1.0
