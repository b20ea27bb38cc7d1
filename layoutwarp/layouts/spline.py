"""Spline layouts: a separable φ whose per-axis map is a monotone spline of ``[-1, 1]``.

Each axis has ``k`` pieces over the uniform knots ``x_i = −1 + 2i/k``; the knot outputs are
``y_0 = −1``, ``y_i = −1 + 2 Σ_{m<i} softmax(ℓ)_m``, ``y_k = 1`` for ``k`` logits ``ℓ``, so every
θ is a bijection (each piece has positive width) and all-zero logits are the uniform layout; an
axis whose logits spread so far that a piece is narrower than float64 resolves (about 34 apart)
is refused in one line.
Sensor pixels are axis-aligned rectangles whose widths follow the spline's slope.

* ``kind="linear"``: piecewise-linear, pixel density piecewise constant;
* ``kind="smooth"``: monotone rational-quadratic (Gregory & Delbourgo, 1982), C¹, with knot
  slopes the harmonic means of the neighbouring secants (the secant itself at the ends).

Both have a closed-form inverse. The functional forms take the knot outputs explicitly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from ..checks import ArgumentError, check_choice, check_int, values_readable
from ..coords import cell_index
from .base import Layout, register_family
from .values import config_numbers, tensor_dtype

__all__ = ["KINDS", "SplineLayout", "knot_outputs", "spline_1d", "spline_1d_derivative", "spline_1d_inverse"]

#: The spline kinds of [`SplineLayout`][].
KINDS = ("linear", "smooth")


def knot_outputs(logits: Tensor) -> Tensor:
    """Knot outputs ``(k + 1,)`` from ``−1`` to ``1`` (both exact) for ``k`` logits.

    Examples:
        >>> knot_outputs(torch.zeros(4))
        tensor([-1.0000, -0.5000,  0.0000,  0.5000,  1.0000])
    """
    inner = 2 * torch.cumsum(torch.softmax(logits, -1), -1)[:-1] - 1
    one = torch.ones(1, dtype=logits.dtype, device=logits.device)
    return torch.cat([-one, inner, one])


def _slopes(y: Tensor) -> tuple[Tensor, Tensor]:
    """Secant slopes ``(k,)`` of the pieces and knot slopes ``(k + 1,)`` (harmonic means)."""
    k = y.numel() - 1
    s = (y[1:] - y[:-1]) * (k / 2)
    if k == 1:
        return s, torch.cat([s, s])
    inner = 2 * s[:-1] * s[1:] / (s[:-1] + s[1:])
    return s, torch.cat([s[:1], inner, s[-1:]])


def _rq_fraction(xi: Tensor, s: Tensor, d0: Tensor, d1: Tensor) -> Tensor:
    """The rational-quadratic piece's output fraction ``r(ξ) ∈ [0, 1]`` (``r(0) = 0``, ``r(1) = 1``)."""
    t = xi * (1 - xi)
    return (s * xi * xi + d0 * t) / (s + (d1 + d0 - 2 * s) * t)


def spline_1d(x: Tensor, y: Tensor, kind: str = "linear") -> Tensor:
    """The monotone spline through ``(x_i, y_i)`` (uniform ``x_i``) at ``x``; identity outside ``[-1, 1]``.

    Args:
        x: points, any shape.
        y: knot outputs ``(k + 1,)`` (see [`knot_outputs`][]).
        kind: ``"linear"`` or ``"smooth"``.
    """
    k = y.numel() - 1
    i, xi = cell_index(x, k)
    y0, y1 = y[i], y[i + 1]
    if kind == "linear":
        r = xi
    else:
        s, d = _slopes(y)
        r = _rq_fraction(xi, s[i], d[i], d[i + 1])
    return torch.where(x.abs() <= 1, y0 * (1 - r) + y1 * r, x)


def spline_1d_derivative(x: Tensor, y: Tensor, kind: str = "linear") -> Tensor:
    """``dφ/dx`` of [`spline_1d`][] (the right-hand value at a knot); 1 outside ``[-1, 1]``."""
    k = y.numel() - 1
    i, xi = cell_index(x, k)
    s, d = _slopes(y)
    si = s[i]
    if kind == "linear":
        out = si
    else:
        d0, d1 = d[i], d[i + 1]
        t = xi * (1 - xi)
        den = si + (d1 + d0 - 2 * si) * t
        out = si * si * (d1 * xi * xi + 2 * si * t + d0 * (1 - xi) ** 2) / (den * den)
    return torch.where(x.abs() <= 1, out, torch.ones_like(out))


def spline_1d_inverse(q: Tensor, y: Tensor, kind: str = "linear") -> Tensor:
    """Closed-form inverse of [`spline_1d`][]: the piece by binary search on ``y``, then the
    linear or (stable-root) quadratic solve inside it."""
    k = y.numel() - 1
    qc = q.clamp(-1, 1)
    i = (torch.searchsorted(y.detach().contiguous(), qc.detach().contiguous(), right=True) - 1).clamp(
        0, k - 1
    )
    y0, y1 = y[i], y[i + 1]
    dy = y1 - y0
    r = torch.where(dy > 0, (qc - y0) / torch.where(dy > 0, dy, torch.ones_like(dy)), 0.0).clamp(0, 1)
    if kind == "linear":
        xi = r
    else:
        s, d = _slopes(y)
        si, d0, d1 = s[i], d[i], d[i + 1]
        dd = d1 + d0 - 2 * si
        a = si - d0 + r * dd
        b = d0 - r * dd
        c = -r * si
        disc = (b * b - 4 * a * c).clamp_min(0)
        den = -b - torch.sqrt(disc)
        xi = torch.where(den != 0, 2 * c / torch.where(den != 0, den, torch.ones_like(den)), 0.0).clamp(0, 1)
    return torch.where(q.abs() <= 1, (i + xi) * (2 / k) - 1, q)


@register_family
class SplineLayout(Layout):
    """A separable layout with a monotone spline per axis (rectangular pixels).

    θ holds the ``k_x + k_y`` knot logits (x first); all zeros is the uniform layout, and every
    θ is a bijection, so training needs no constraint, but for logits spread beyond what float64
    resolves (about 34 apart), which are refused. See `layoutwarp.layouts.spline`.

    Args:
        theta: initial logits (``None``: zeros).
        knots: ``(k_x, k_y)`` pieces per axis, each ``>= 1``.
        kind: ``"linear"`` (piecewise-constant pixel density) or ``"smooth"`` (C¹).
        bound: unused (the logits are unbounded); accepted for
            [`make_layout`][layoutwarp.layouts.make_layout].
        learn: as [`Layout`][].
        dtype: as [`Layout`][].

    Examples:
        >>> layout = SplineLayout.from_knots([-1, -0.2, 1], [-1, 0.5, 1])
        >>> layout(torch.tensor([[0.0, 0.0]], dtype=torch.float64))
        tensor([[-0.2000,  0.5000]], dtype=torch.float64)
    """

    family = "spline"
    num_params: int | None = None
    unbounded = True
    separable = True
    straight_edges = True

    def __init__(
        self,
        theta: Sequence[float] | Tensor | None = None,
        *,
        knots: Sequence[int] = (8, 8),
        kind: str = "linear",
        bound: float = 1.0,
        learn: bool = False,
        dtype: torch.dtype | None = None,
    ) -> None:
        try:
            kx, ky = knots
        except (TypeError, ValueError):
            raise ValueError(f"knots must be a pair (k_x, k_y) of integers >= 1, got {knots!r}") from None
        self.knots = (check_int(kx, "knots[0]", 1), check_int(ky, "knots[1]", 1))
        self.kind = check_choice(kind, KINDS, "kind")
        self.num_params = self.knots[0] + self.knots[1]
        super().__init__(theta, bound=bound, learn=learn, dtype=dtype)

    @classmethod
    def from_knots(
        cls,
        x_knots: Sequence[float] | Tensor,
        y_knots: Sequence[float] | Tensor,
        *,
        kind: str = "linear",
        learn: bool = False,
        dtype: torch.dtype | None = None,
    ) -> SplineLayout:
        """The layout whose knot outputs are ``x_knots`` (``k_x + 1`` values) and ``y_knots``.

        Each must run strictly increasing from ``-1`` to ``1`` (the ends are checked to 1e-12).
        """
        logits = []
        for name, v in (("x_knots", x_knots), ("y_knots", y_knots)):
            t = torch.as_tensor(v, dtype=torch.float64).flatten()
            if t.numel() < 2 or abs(float(t[0]) + 1) > 1e-12 or abs(float(t[-1]) - 1) > 1e-12:
                raise ValueError(f"{name} must run from -1 to 1 with at least 2 values, got {v!r}")
            gaps = t.diff()
            if not bool((gaps > 0).all()):
                bad = int(torch.nonzero(gaps <= 0)[0])
                raise ValueError(f"{name} must be strictly increasing; {name}[{bad + 1}] <= {name}[{bad}]")
            logits.append(torch.log(gaps / 2))
        return cls(
            torch.cat(logits),
            knots=(logits[0].numel(), logits[1].numel()),
            kind=kind,
            learn=learn,
            dtype=dtype or tensor_dtype(x_knots, y_knots),
        )

    def _check_theta(self, theta: Tensor) -> None:
        super()._check_theta(theta)
        self._refuse_unresolved(theta.tolist())

    def _refuse_folded(self, theta: Tensor, rho: Tensor | None) -> None:
        super()._refuse_folded(theta, rho)
        self._refuse_unresolved(theta.detach().double().cpu().tolist())

    def check_theta_now(self) -> None:
        """As [`Layout.check_theta_now`][layoutwarp.layouts.base.Layout.check_theta_now], and the
        logits' spread: a training step may spread them until a piece is narrower than float64
        resolves."""
        super().check_theta_now()
        if self.rho.device.type == "cpu" and values_readable():
            self._refuse_unresolved(self.rho.detach().tolist())

    def _refuse_unresolved(self, logits: list[float]) -> None:
        """Raise, in one line, where an axis's logits spread so far that its narrowest piece is
        under 2 ulp of float64: its knots then round onto each other, and the layout's values and
        gradients were NaN (logits ±19, float32 and float64 layouts alike), or its smooth kind
        failed inside torch."""
        eps = torch.finfo(torch.float64).eps
        for axis, part in (("x", logits[: self.knots[0]]), ("y", logits[self.knots[0] :])):
            if not all(map(math.isfinite, part)):
                continue  # the base check names a θ that is not finite
            top = max(part)
            weights = [math.exp(v - top) for v in part]
            if min(weights) / sum(weights) < 2 * eps:
                spread = -math.log(2 * eps) - math.log(len(part))
                raise ArgumentError(
                    "theta", f"theta: the {axis} knot logits spread from {min(part):.4g} to {top:.4g}, so a "
                    f"piece is narrower than float64 resolves; keep each axis's logits within about "
                    f"{spread:.0f} of each other",
                )  # fmt: skip

    def knot_outputs(self, theta: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Knot outputs along x ``(k_x + 1,)`` and y ``(k_y + 1,)``."""
        th = self.resolve_theta(theta)
        return knot_outputs(th[: self.knots[0]]), knot_outputs(th[self.knots[0] :])

    def phi(self, p: Tensor, theta: Tensor) -> Tensor:
        dtype = torch.promote_types(p.dtype, theta.dtype)
        yx, yy = self.knot_outputs(theta.to(device=p.device, dtype=dtype))
        p = p.to(dtype)
        return torch.stack([spline_1d(p[..., 0], yx, self.kind), spline_1d(p[..., 1], yy, self.kind)], -1)

    def phi_inverse(self, q: Tensor, theta: Tensor) -> Tensor:
        dtype = torch.promote_types(q.dtype, theta.dtype)
        yx, yy = self.knot_outputs(theta.to(device=q.device, dtype=dtype))
        q = q.to(dtype)
        return torch.stack(
            [spline_1d_inverse(q[..., 0], yx, self.kind), spline_1d_inverse(q[..., 1], yy, self.kind)], -1
        )

    def phi_jacobian(self, p: Tensor, theta: Tensor) -> Tensor:
        return torch.diag_embed(self._derivatives(p, theta))

    def phi_jacobian_det(self, p: Tensor, theta: Tensor) -> Tensor:
        return self._derivatives(p, theta).prod(-1)

    def _derivatives(self, p: Tensor, theta: Tensor) -> Tensor:
        dtype = torch.promote_types(p.dtype, theta.dtype)
        yx, yy = self.knot_outputs(theta.to(device=p.device, dtype=dtype))
        p = p.to(dtype)
        dx = spline_1d_derivative(p[..., 0], yx, self.kind)
        return torch.stack([dx, spline_1d_derivative(p[..., 1], yy, self.kind)], -1)

    def to_config(self) -> dict[str, Any]:
        th = [float(v) for v in self.theta_as(torch.float64).detach().cpu()]
        return {"theta": th, "knots": list(self.knots), "kind": self.kind}

    @classmethod
    def from_config(
        cls, config: dict[str, Any], *, learn: bool = False, dtype: torch.dtype | None = None
    ) -> Layout:
        theta, knots = config_numbers(config, "theta", required=True), config_numbers(config, "knots", [8, 8])
        if not isinstance(knots, list) or len(knots) != 2:
            raise ValueError(f"'knots' must be [k_x, k_y], got {knots!r}")
        return cls(theta, knots=tuple(knots), kind=config.get("kind", "linear"), learn=learn, dtype=dtype)

    def extra_repr(self) -> str:
        return f"knots={self.knots}, kind={self.kind!r}, learn={self.learnable}"
