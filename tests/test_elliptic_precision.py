"""The elliptic family's φ in float64 against a 700-digit evaluation of its definition
(E⁻¹ ∘ φ_curv ∘ E, E the elliptical grid mapping): a few ulps over the whole square, the axes,
edges and corners included, where the closed form's differences of two roots once lost digits
(8e-9 relative near the axes, 1e-8 absolute at 1e-12 from a corner)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from layoutwarp.layouts import EllipticLayout

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
