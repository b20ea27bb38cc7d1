"""The paper's curvilinear family φ_curv: pixels are curvilinear quads, the unit circle fixed.

``φ_j(p) = p_j (θ_j − 1) / (2 θ_j ‖p‖ − θ_j − 1)`` for ``‖p‖ < 1``; the functional forms take θ
explicitly and [`CurvLayout`][] wraps them.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .arith import denom, promote, safe_norm
from .base import register_family
from .centered import CenteredLayout, side_scale

__all__ = [
    "CurvLayout",
    "phi_curv",
    "phi_curv_dtheta",
    "phi_curv_inverse",
    "phi_curv_jacobian",
    "phi_curv_jacobian_det",
]


def phi_curv(p: Tensor, theta: Tensor) -> Tensor:
    """φ_curv: ``φ_j(p) = p_j (θ_j − 1) / (2 θ_j ‖p‖ − θ_j − 1)`` for ``‖p‖ < 1``, else ``p``.

    The unit circle is fixed pointwise (a kink there) and so is everything outside it,
    including the sensor corners. Pixels are curvilinear quadrilaterals.

    Args:
        p: points ``(..., 2)`` in sensor coordinates.
        theta: ``(2,)`` deformation strengths in ``(-1, 1)``.
    """
    p, theta = promote(p, theta)
    r = safe_norm(p)[..., None]
    return torch.where(r < 1, p * (1 - theta) / denom(r.clamp(max=1), theta), p)


def phi_curv_inverse(q: Tensor, theta: Tensor) -> Tensor:
    """Closed-form inverse of [`phi_curv`][].

    With ``p_j = q_j D_j(r) / (1 − θ_j)``, ``D_j(r) = (1 + θ_j) − 2θ_j r`` linear in
    ``r = ‖p‖``, the constraint ``r² = Σ p_j²`` is a quadratic ``a r² + b r + c = 0`` with
    exactly one root in ``[0, 1)`` for ``‖q‖ < 1`` (``f(0) = c >= 0``, ``f(1) = ‖q‖² − 1 < 0``).
    It is solved with the cancellation-free form of the quadratic formula and polished by
    one Newton step.
    """
    q, theta = promote(q, theta)
    inside = (q * q).sum(-1, keepdim=True) < 1
    qi = torch.where(inside, q, torch.zeros_like(q))
    alpha, beta = 1 + theta, 2 * theta
    c2 = (qi / (1 - theta)) ** 2
    a = (c2 * beta**2).sum(-1) - 1
    b = -2 * (c2 * alpha * beta).sum(-1)
    c = (c2 * alpha**2).sum(-1)
    disc = (b * b - 4 * a * c).clamp(min=0)
    sq = torch.sqrt(torch.where(disc > 0, disc, torch.ones_like(disc))) * (disc > 0)
    s = -0.5 * (b + torch.where(b >= 0, sq, -sq))  # |s| = (|b| + √Δ)/2, no cancellation
    s_safe = torch.where(s != 0, s, torch.ones_like(s))
    a_safe = torch.where(a != 0, a, torch.ones_like(a))
    r1 = torch.where(s != 0, c / s_safe, 0.0)  # root c / s
    r2 = torch.where(a != 0, s / a_safe, 2.0)  # root s / a (absent when a = 0)
    ok1 = (r1 >= 0) & (r1 <= 1)
    r = torch.where(ok1, r1, r2).clamp(0, 1)
    # One Newton step on f(r) = Σ c2 (α − βr)² − r² removes the last rounding error.
    f = (c2 * (alpha - beta * r[..., None]) ** 2).sum(-1) - r * r
    df = (-2 * c2 * beta * (alpha - beta * r[..., None])).sum(-1) - 2 * r
    df_safe = torch.where(df != 0, df, torch.ones_like(df))
    r = torch.where((df != 0) & (c > 0), r - f / df_safe, r).clamp(0, 1)
    p = qi * denom(r[..., None], theta) / (1 - theta)
    return torch.where(inside, p, q)


def phi_curv_jacobian(p: Tensor, theta: Tensor) -> Tensor:
    """Spatial Jacobian ``∂φ_i/∂p_j`` of [`phi_curv`][], shape ``(..., 2, 2)``.

    ``∂φ_i/∂p_j = δ_ij s_i + p_i s_i'(r) p_j / r`` with ``s_i = (1 − θ_i)/D_i(r)`` and
    ``s_i' = 2θ_i(1 − θ_i)/D_i²``; the second term vanishes at the origin (limit) and the
    identity is returned outside the unit circle (one-sided value on it).
    """
    p, theta = promote(p, theta)
    r = safe_norm(p).clamp(max=1)[..., None]
    inside = ((p * p).sum(-1) < 1)[..., None, None]
    d = denom(r, theta)
    s = (1 - theta) / d
    ds = 2 * theta * (1 - theta) / d**2
    r_safe = torch.where(r > 0, r, torch.ones_like(r))
    u = torch.where(r > 0, p / r_safe, 0.0)  # unit direction, 0 at the origin
    jac = torch.diag_embed(s) + (p * ds)[..., :, None] * u[..., None, :]
    eye = torch.eye(2, dtype=p.dtype, device=p.device).expand_as(jac)
    return torch.where(inside, jac, eye)


def phi_curv_jacobian_det(p: Tensor, theta: Tensor) -> Tensor:
    """``det ∂φ/∂p`` of [`phi_curv`][], shape ``(...)``, in closed form.

    The Jacobian is ``diag(s) + a uᵀ`` with ``a = p s'(r)`` and ``u = p / r``, so by the matrix
    determinant lemma ``det = s_x s_y + (s_y s_x' p_x² + s_x s_y' p_y²) / r``; 1 outside the unit
    circle.
    """
    p, theta = promote(p, theta)
    r2 = (p * p).sum(-1)
    r = safe_norm(p).clamp(max=1)[..., None]
    d = denom(r, theta)
    s = (1 - theta) / d
    ds = 2 * theta * (1 - theta) / d**2
    r_safe = torch.where(r > 0, r, torch.ones_like(r))[..., 0]
    sx, sy, dsx, dsy = s[..., 0], s[..., 1], ds[..., 0], ds[..., 1]
    px2, py2 = p[..., 0] ** 2, p[..., 1] ** 2
    det = sx * sy + (sy * dsx * px2 + sx * dsy * py2) / r_safe
    return torch.where(r2 < 1, det, 1.0)


def phi_curv_dtheta(p: Tensor, theta: Tensor) -> Tensor:
    """``∂φ_i/∂θ_j`` of [`phi_curv`][], shape ``(..., 2, 2)`` (diagonal).

    ``∂φ_j/∂θ_j = 2 p_j (r − 1) / D_j(r)²`` (the reference code's formula for this is wrong).
    """
    p, theta = promote(p, theta)
    r = safe_norm(p).clamp(max=1)[..., None]
    inside = (p * p).sum(-1, keepdim=True) < 1
    d = torch.where(inside, 2 * p * (r - 1) / denom(r, theta) ** 2, 0.0)
    return torch.diag_embed(d)


def _circle_crossings(a: Tensor, d: Tensor, lo: Tensor, hi: Tensor, scale: Tensor) -> Tensor:
    """Parameters ``t ∈ (lo, hi)`` where ``Σ_j ((a_j + t d_j) / scale_j)² = 1``: ``(E, 2)``, NaN for none."""
    ds, as_ = d / scale, a / scale
    qa = (ds * ds).sum(-1)
    qb = 2 * (as_ * ds).sum(-1)
    qc = (as_ * as_).sum(-1) - 1
    disc = qb * qb - 4 * qa * qc
    sq = torch.sqrt(torch.where(disc > 0, disc, torch.ones_like(disc))) * (disc > 0)  # NaN-free gradient
    qa_safe = torch.where(qa > 0, qa, torch.ones_like(qa))
    t = torch.stack([(-qb - sq) / (2 * qa_safe), (-qb + sq) / (2 * qa_safe)], -1)
    ok = (disc > 0)[:, None] & (qa > 0)[:, None] & (t > lo[:, None]) & (t < hi[:, None])
    return torch.where(ok, t, torch.full_like(t, float("nan")))


@register_family
class CurvLayout(CenteredLayout):
    """The curvilinear layout φ_curv of the paper (radial, fixed outside the unit circle), about
    a movable centre (see [`CenteredLayout`][]: ``center``, ``learn_center``)."""

    family = "curv"
    kernel_map = "curv"

    def _fixed(self, p: Tensor, u: Tensor) -> Tensor:
        return (p.abs() >= 1) | ((u * u).sum(-1, keepdim=True) >= 1)  # outside the adapted circle

    def _phi0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_curv(p, theta)

    def _inverse0(self, q: Tensor, theta: Tensor) -> Tensor:
        return phi_curv_inverse(q, theta)

    def _jacobian0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_curv_jacobian(p, theta)

    def _det0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_curv_jacobian_det(p, theta)

    def _dtheta0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_curv_dtheta(p, theta)

    def edge_breakpoints(self, a: Tensor, b: Tensor, theta: Tensor | None = None) -> Tensor:
        """Where the segment crosses the (adapted) unit circle, the kink of φ_curv, and, off the
        centre, the lines ``x = c_x`` and ``y = c_y`` (differentiable in a learned centre). None
        on the sensor's sides, where φ is the identity (the circle touches them: a double root
        whose rounding would add or drop pieces there as θ moves)."""
        d = b - a
        border = ((a.abs() >= 1) & (d == 0)).any(-1, keepdim=True)
        return torch.where(border, float("nan"), self._kinks(a, d, theta))

    def _kinks(self, a: Tensor, d: Tensor, theta: Tensor | None) -> Tensor:
        _, c = self._split(self.theta.detach() if theta is None else theta)
        if c is None:
            lo, hi = torch.zeros_like(d[:, 0]), torch.ones_like(d[:, 0])
            return _circle_crossings(a, d, lo - 1, hi + 1, torch.ones_like(d))
        c = c.to(a)
        nan = torch.full_like(d, float("nan"))
        dsafe = torch.where(d != 0, d, torch.ones_like(d))
        cut = torch.where(d != 0, (c - a) / dsafe, nan)
        cut = torch.where((cut > 0) & (cut < 1), cut, nan)
        one = torch.ones_like(d[:, :1])
        bounds = torch.cat([0 * one, torch.where(cut.isnan(), 1.0, cut).sort(1).values, one], 1)
        out = [cut]
        for k in range(3):  # the crossings on each piece between the cuts, in local scale
            lo, hi = bounds[:, k], bounds[:, k + 1]
            mid = a + ((lo + hi) / 2)[:, None].detach() * d
            out.append(_circle_crossings(a - c, d, lo, hi, side_scale(mid, c)))
        return torch.cat(out, 1)
