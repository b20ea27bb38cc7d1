"""Pixel layouts: bijections φ(·, θ) of the sensor square S = [-1, 1]² onto itself.

Sensor pixel ``k`` of a layout is the image ``A_k = φ(U_k, θ)`` of the uniform cell ``U_k``
(Sommerhoff et al., "Differentiable Sensor Layouts for End-to-End Learning of Task-Specific
Camera Parameters", §3.2). Conventions used everywhere in this package:

* points are ``(..., 2)`` tensors ``(x, y)``: ``x`` along the image width (columns), ``y``
  along the height (rows, downwards), both in ``[-1, 1]``; ``-1`` is the outer edge of the
  first pixel and ``+1`` the outer edge of the last (``align_corners=False``);
* ``θ = (θ_x, θ_y)`` with each component in ``(-bound, bound)``; ``θ > 0`` puts more (smaller)
  pixels at the centre, ``θ < 0`` at the border. A learnable layout stores the unconstrained
  parameter ``ρ`` and derives ``θ = bound · tanh(ρ)``.

The functional forms ([`phi_rect`][], [`phi_curv`][], their inverses, Jacobians and
θ-derivatives) take ``θ`` explicitly; the [`Layout`][] modules wrap them.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

import torch
from torch import Tensor, nn

from .checks import ArgumentError, check_number, check_points

__all__ = [
    "FAMILIES",
    "CenteredLayout",
    "CurvLayout",
    "EllipticLayout",
    "FoldoverReport",
    "FoveaLayout",
    "Layout",
    "RectLayout",
    "UniformLayout",
    "config_numbers",
    "disk_to_square",
    "make_layout",
    "newton_inverse",
    "phi_curv",
    "phi_curv_dtheta",
    "phi_curv_inverse",
    "phi_curv_jacobian",
    "phi_curv_jacobian_det",
    "phi_rect",
    "phi_rect_dtheta",
    "phi_rect_inverse",
    "phi_rect_jacobian",
    "register_family",
    "square_to_disk",
    "tensor_dtype",
]


# ----------------------------------------------------------------------------------------
# Scalar building blocks
# ----------------------------------------------------------------------------------------
def _denom(a: Tensor, t: Tensor) -> Tensor:
    """``D(a, t) = 1 + t − 2ta`` (> 0 for ``|t| < 1``, ``0 <= a <= 1``), free of cancellation.

    For ``t >= 0`` it is summed as ``(1 − t) + 2t(1 − a)`` and for ``t < 0`` as
    ``(1 + t) + 2|t|a``: two non-negative terms either way, so the relative error stays at
    a few ulp even when ``t → ±1`` and ``a → 1``. Written as ``(1 − |t|) + 2|t| g`` with
    ``g = s + (1 − 2s) a`` (``s = [t >= 0]``, so ``g`` is ``1 − a`` or ``a``) to need only
    two fused multiply-adds on the large tensor ``a``.
    """
    s = (t >= 0).to(a.dtype)
    t_abs = t * (2 * s - 1)  # |t| whose derivative at t = 0 is the t >= 0 branch's, not 0
    g = torch.addcmul(s, 1 - 2 * s, a)
    return torch.addcmul(1 - t_abs, 2 * t_abs, g)


def _safe_norm(p: Tensor) -> Tensor:
    """``‖p‖`` over the last axis (of size 2) with a zero (not NaN) gradient at the origin."""
    x, y = p[..., 0], p[..., 1]
    r2 = x * x + y * y
    nonzero = r2 > 0
    return torch.where(nonzero, torch.sqrt(torch.where(nonzero, r2, torch.ones_like(r2))), 0.0)


def _promote(p: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    dtype = torch.promote_types(p.dtype, theta.dtype)
    return p.to(dtype), theta.to(device=p.device, dtype=dtype)


def tensor_dtype(*values: Any) -> torch.dtype:
    """The dtype a layout built from ``values`` gets unless ``dtype=`` says otherwise: that of the
    first floating-point tensor among them (as torch and Kornia keep an argument's dtype), else
    torch's default dtype."""
    for v in values:
        if isinstance(v, Tensor) and v.is_floating_point():
            return v.dtype
    return torch.get_default_dtype()


def config_numbers(
    config: dict[str, Any], key: str, default: list[float] | None = None
) -> list[float] | None:
    """``config[key]`` as a list of numbers (``default`` when absent); ``ValueError`` otherwise.

    Used by [`Layout.from_config`][] of every family to read layout files.
    """
    value = config.get(key, default)
    if value is not None and (
        not isinstance(value, list) or not all(isinstance(v, (int, float)) for v in value)
    ):
        raise ValueError(f"{key!r} must be a list of numbers, got {value!r}")
    return value


# ----------------------------------------------------------------------------------------
# Rectangular layout φ_rect (separable)
# ----------------------------------------------------------------------------------------
def phi_rect(p: Tensor, theta: Tensor) -> Tensor:
    """φ_rect: ``φ_j(p) = p_j (θ_j − 1) / (2 θ_j |p_j| − θ_j − 1)`` for ``|p_j| < 1``, else ``p_j``.

    Args:
        p: points ``(..., 2)`` in sensor coordinates.
        theta: ``(2,)`` deformation strengths in ``(-1, 1)``.

    Returns:
        ``(..., 2)`` deformed points. Separable: each deformed pixel is an axis-aligned
        rectangle. The centre pixel shrinks by ``(1 − θ)/(1 + θ)``.
    """
    p, theta = _promote(p, theta)
    a = p.abs()
    return torch.where(a < 1, p * (1 - theta) / _denom(a.clamp(max=1), theta), p)


def phi_rect_inverse(q: Tensor, theta: Tensor) -> Tensor:
    """Closed-form inverse of [`phi_rect`][]: ``φ_rect⁻¹(·, θ) = φ_rect(·, −θ)``."""
    return phi_rect(q, -theta)


def phi_rect_jacobian(p: Tensor, theta: Tensor) -> Tensor:
    """Spatial Jacobian ``∂φ_i/∂p_j`` of [`phi_rect`][], shape ``(..., 2, 2)`` (diagonal).

    ``dφ_j/dp_j = (1 − θ_j²) / D_j²`` with ``D_j = 1 + θ_j − 2θ_j|p_j|``; 1 outside S.
    """
    p, theta = _promote(p, theta)
    a = p.abs()
    d = torch.where(a < 1, (1 - theta) * (1 + theta) / _denom(a.clamp(max=1), theta) ** 2, 1.0)
    return torch.diag_embed(d)


def phi_rect_dtheta(p: Tensor, theta: Tensor) -> Tensor:
    """``∂φ_i/∂θ_j`` of [`phi_rect`][], shape ``(..., 2, 2)`` (diagonal).

    ``∂φ_j/∂θ_j = 2 p_j (|p_j| − 1) / D_j²``.
    """
    p, theta = _promote(p, theta)
    a = p.abs()
    d = torch.where(a < 1, 2 * p * (a - 1) / _denom(a.clamp(max=1), theta) ** 2, 0.0)
    return torch.diag_embed(d)


# ----------------------------------------------------------------------------------------
# Curvilinear layout φ_curv
# ----------------------------------------------------------------------------------------
def phi_curv(p: Tensor, theta: Tensor) -> Tensor:
    """φ_curv: ``φ_j(p) = p_j (θ_j − 1) / (2 θ_j ‖p‖ − θ_j − 1)`` for ``‖p‖ < 1``, else ``p``.

    The unit circle is fixed pointwise (a kink there) and so is everything outside it,
    including the sensor corners. Pixels are curvilinear quadrilaterals.

    Args:
        p: points ``(..., 2)`` in sensor coordinates.
        theta: ``(2,)`` deformation strengths in ``(-1, 1)``.
    """
    p, theta = _promote(p, theta)
    r = _safe_norm(p)[..., None]
    return torch.where(r < 1, p * (1 - theta) / _denom(r.clamp(max=1), theta), p)


def phi_curv_inverse(q: Tensor, theta: Tensor) -> Tensor:
    """Closed-form inverse of [`phi_curv`][].

    With ``p_j = q_j D_j(r) / (1 − θ_j)``, ``D_j(r) = (1 + θ_j) − 2θ_j r`` linear in
    ``r = ‖p‖``, the constraint ``r² = Σ p_j²`` is a quadratic ``a r² + b r + c = 0`` with
    exactly one root in ``[0, 1)`` for ``‖q‖ < 1`` (``f(0) = c >= 0``, ``f(1) = ‖q‖² − 1 < 0``).
    It is solved with the cancellation-free form of the quadratic formula and polished by
    one Newton step.
    """
    q, theta = _promote(q, theta)
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
    p = qi * _denom(r[..., None], theta) / (1 - theta)
    return torch.where(inside, p, q)


def phi_curv_jacobian(p: Tensor, theta: Tensor) -> Tensor:
    """Spatial Jacobian ``∂φ_i/∂p_j`` of [`phi_curv`][], shape ``(..., 2, 2)``.

    ``∂φ_i/∂p_j = δ_ij s_i + p_i s_i'(r) p_j / r`` with ``s_i = (1 − θ_i)/D_i(r)`` and
    ``s_i' = 2θ_i(1 − θ_i)/D_i²``; the second term vanishes at the origin (limit) and the
    identity is returned outside the unit circle (one-sided value on it).
    """
    p, theta = _promote(p, theta)
    r = _safe_norm(p).clamp(max=1)[..., None]
    inside = ((p * p).sum(-1) < 1)[..., None, None]
    d = _denom(r, theta)
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
    p, theta = _promote(p, theta)
    r2 = (p * p).sum(-1)
    r = _safe_norm(p).clamp(max=1)[..., None]
    d = _denom(r, theta)
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
    p, theta = _promote(p, theta)
    r = _safe_norm(p).clamp(max=1)[..., None]
    inside = (p * p).sum(-1, keepdim=True) < 1
    d = torch.where(inside, 2 * p * (r - 1) / _denom(r, theta) ** 2, 0.0)
    return torch.diag_embed(d)


# ----------------------------------------------------------------------------------------
# Modules
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FoldoverReport:
    """Result of [`Layout.check_foldover`][] on an ``n × n`` grid of S.

    Attributes:
        min_det: smallest Jacobian determinant found.
        num_nonpositive: number of grid points with ``det J <= 0`` (fold-overs).
        worst_point: ``(x, y)`` where ``det J`` is smallest.
        grid: the grid side ``n`` (0 for an exact check, e.g. [`GridLayout`][layoutwarp.grids.GridLayout]'s).
        cell: the first folded control cell ``(row, col)`` of an exact check, else ``None``.
    """

    min_det: float
    num_nonpositive: int
    worst_point: tuple[float, float]
    grid: int
    cell: tuple[int, int] | None = None

    @property
    def ok(self) -> bool:
        """``True`` when no fold-over was found."""
        return self.num_nonpositive == 0


class Layout(nn.Module):
    """Base class of pixel layouts.

    A subclass writes [`phi`][] (``φ(p, θ)`` for points ``(..., 2)`` and parameters
    ``(P,)``). Optional overrides, with generic fallbacks here:

    * [`phi_inverse`][] — default: damped Newton iteration in float64;
    * [`phi_jacobian`][] — default: autograd, ``(..., 2, 2)``;
    * [`phi_dtheta`][] — default: autograd, ``(..., 2, P)``.

    Class attributes tell the integrators what machinery a layout needs:

    * ``separable``: ``φ_x`` depends on ``x`` only and ``φ_y`` on ``y`` only, so pixels are
      axis-aligned rectangles (the fast separable integrator applies);
    * ``straight_edges``: images of the uniform grid lines are straight between the cuts of
      [`edge_breakpoints`][], so pixel edges are polylines with a vertex at each cut and are
      never subdivided further (exact meshes at any tolerance);
    * ``unbounded``: every finite θ is a valid layout, so θ is stored as it is (no ``tanh``).

    The parameter is stored unconstrained as ``rho`` with ``θ = bound · tanh(ρ)`` (families
    with unbounded parameters override `_to_theta` and `_to_rho`). A layout built
    from θ is fixed (``rho`` is a buffer) unless ``learn=True``;
    [`SensorLayer`][layoutwarp.sensor.SensorLayer] learns by default. ``num_params`` is the length of θ
    (``None`` on the class for families whose instances choose it).

    A new family subclasses this, sets ``family`` and is declared with
    [`register_family`][]: layout files, [`make_layout`][] and the command line's
    ``--family`` then know it. Families with more state than θ override [`to_config`][]
    and [`from_config`][].

    Args:
        theta: initial ``θ`` (length ``num_params``), each in ``(-bound, bound)``; a family
            without parameters accepts ``None``, ``()`` or zeros.
        bound: the open bound on ``|θ|`` (the paper uses 1).
        learn: make ``ρ`` a trainable parameter (default ``False``: a buffer, fixed layout).
        dtype: the layout's [`dtype`][]: that of θ and of what is computed from it (default: a
            tensor ``theta``'s own floating dtype, else torch's default).

    A fixed layout keeps ``ρ`` (and its other constants, e.g. a centre) in float64 whatever its
    dtype: they are a few numbers, and a float64 computation then gets the θ that was written,
    not its float32 rounding, also after ``.float()``/``.double()``; those change the layout's
    [`dtype`][] and move the constants without rounding them. [`theta_as`][] gives θ in any
    dtype; the methods that take points ([`forward`][], [`inverse`][], ...) compute at the
    points' precision when it is the finer one. A learnable layout's ``ρ`` is a parameter of its
    dtype, as every torch module's.
    """

    family: ClassVar[str] = "custom"
    num_params: int | None = 2
    separable: ClassVar[bool] = False
    straight_edges: ClassVar[bool] = False
    unbounded: ClassVar[bool] = False
    #: Buffers of a fixed layout's constants, held in float64 whatever the layout's dtype.
    exact_buffers: ClassVar[tuple[str, ...]] = ("rho",)

    def __init__(
        self,
        theta: Sequence[float] | Tensor | None = None,
        *,
        bound: float = 1.0,
        learn: bool = False,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        self.bound = check_number(bound, "bound", 0, lo_open=True)
        self._bounds_on: dict[tuple[torch.device, torch.dtype], Tensor] = {}  # _bounds() where ρ lives
        self._dtype = dtype or tensor_dtype(theta)
        rho = self._to_rho(self._validate_theta(theta, torch.float64))
        if learn and self.num_params:
            self.rho = nn.Parameter(rho.to(self._dtype))
        else:
            self.register_buffer("rho", rho)

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of [`theta`][] and of what is computed from it (``dtype`` at construction;
        ``.to(dtype)``, ``.float()``, ``.double()`` change it)."""
        return self._dtype

    def _apply(self, fn: Callable[[Tensor], Tensor], recurse: bool = True) -> Layout:
        """As `nn.Module`'s, except that a fixed layout's `exact_buffers` are moved, never rounded."""
        dtype = fn(torch.empty(0, dtype=self._dtype)).dtype  # what the conversion does to a float
        exact = {n: self._buffers[n] for n in self.exact_buffers if n in self._buffers}
        super()._apply(fn, recurse)
        for name, value in exact.items():
            if value is not None:
                self._buffers[name] = value.to(self._buffers[name].device)
        self._dtype = dtype
        return self

    @property
    def learnable_param(self) -> bool:
        """Whether ``ρ`` is a parameter (``learn=True``), trainable or frozen."""
        return isinstance(self.rho, nn.Parameter)

    # -- parameters ------------------------------------------------------------------
    def _bounds(self) -> Tensor:
        """The open bound on each entry of θ, ``(P,)`` float64 (infinite for unbounded families)."""
        value = math.inf if self.unbounded else self.bound
        return torch.full((self.num_params or 0,), value, dtype=torch.float64)

    def _to_theta(self, rho: Tensor) -> Tensor:
        """θ from the stored unconstrained ``ρ``: ``bound · tanh(ρ)``, or ``ρ`` itself for
        families whose every θ is valid (``unbounded``)."""
        if self.unbounded:
            return rho
        key = (rho.device, rho.dtype)
        if key not in self._bounds_on:  # made once per device: no copy to it every step
            self._bounds_on[key] = self._bounds().to(rho)
        return self._bounds_on[key] * torch.tanh(rho)

    def _to_rho(self, theta: Tensor) -> Tensor:
        """Inverse of `_to_theta`."""
        return theta.clone() if self.unbounded else torch.atanh(theta / self._bounds().to(theta))

    def _check_theta(self, theta: Tensor) -> None:
        """Raise ``ValueError`` naming the first entry of a (float64, CPU) θ that is not allowed."""
        for i, (v, b) in enumerate(zip(theta.tolist(), self._bounds().tolist(), strict=True)):
            if not math.isfinite(v) or abs(v) >= b:
                raise ValueError(
                    f"theta[{i}] = {v!r} is out of range: each θ must be finite with |θ| < bound = {b}"
                )

    def _validate_theta(self, theta: Sequence[float] | Tensor | None, dtype: torch.dtype) -> Tensor:
        n = self.num_params or 0
        if theta is None:
            return torch.zeros(n, dtype=dtype)
        try:
            t = torch.as_tensor(theta, dtype=torch.float64).detach().flatten().cpu()
        except (TypeError, ValueError, RuntimeError):
            what = f"{n} numbers (θ_x, θ_y)" if n == 2 else f"{n} numbers" if n else "empty or zeros"
            raise ArgumentError("theta", f"theta must be {what}, got {theta!r}") from None
        if n == 0 and bool((t == 0).all()):
            return torch.zeros(0, dtype=dtype)
        if n == 0:
            raise ValueError(
                f"the {self.family} layout has no parameters; theta must be empty or zeros, got {theta!r}"
            )
        if t.numel() != n:
            what = " (θ_x, θ_y)" if n == 2 else ""
            raise ValueError(f"theta must have {n} values{what}, got {t.numel()}: {theta!r}")
        self._check_theta(t)
        return t.to(dtype)

    @property
    def theta(self) -> Tensor:
        """The constrained parameters (``θ = bound · tanh(ρ)`` by default), shape ``(P,)``, in the
        layout's [`dtype`][]."""
        return self.theta_as(self._dtype)

    def theta_as(self, dtype: torch.dtype) -> Tensor:
        """θ in ``dtype`` (differentiable in ``ρ``): a fixed layout's from its float64 ``ρ``, so
        ``theta_as(torch.float64)`` is the θ that was set to the last bit or two."""
        return self._to_theta(self.rho).to(dtype)

    @torch.no_grad()
    def set_theta(self, theta: Sequence[float] | Tensor) -> None:
        """Set ``θ`` in place (validated like the constructor)."""
        t = self._validate_theta(theta, torch.float64)
        self.rho.copy_(self._to_rho(t).to(self.rho))

    @property
    def learnable(self) -> bool:
        """Whether ``ρ`` is a trainable parameter that currently requires grad."""
        return self.learnable_param and self.rho.requires_grad

    def resolve_theta(self, theta: Tensor | None = None) -> Tensor:
        """The θ a computation uses: ``theta`` when given (e.g. a tensor that
        ``torch.autograd.gradcheck`` varies), else the layout's own [`theta`][]."""
        return self.theta if theta is None else theta

    def _theta_for(self, p: Tensor) -> Tensor:
        """θ for a computation on points ``p``: at their precision when it is finer than the layout's."""
        return self.theta_as(
            torch.promote_types(p.dtype, self._dtype) if p.is_floating_point() else self._dtype
        )

    def project_(self) -> bool:
        """Pull the parameters back into the valid set after an optimiser step.

        Families whose every θ is a bijection (the default) have nothing to do; others (e.g.
        [`GridLayout`][layoutwarp.grids.GridLayout]) undo the part of a step that would fold the layout.
        [`SensorLayer`][layoutwarp.sensor.SensorLayer] calls this before each forward pass.

        Returns:
            whether the parameters were changed.
        """
        return False

    # -- files -----------------------------------------------------------------------
    def to_config(self) -> dict[str, Any]:
        """The JSON-able constructor arguments that rebuild this layout (see [`from_config`][])."""
        return {"theta": [float(v) for v in self.theta_as(torch.float64).detach().cpu()], "bound": self.bound}

    @classmethod
    def from_config(
        cls, config: dict[str, Any], *, learn: bool = False, dtype: torch.dtype | None = None
    ) -> Layout:
        """Rebuild a layout from [`to_config`][]'s dict (raises ``ValueError`` on bad values)."""
        theta = config_numbers(config, "theta")
        return cls(theta, bound=config.get("bound", 1.0), learn=learn, dtype=dtype)

    # -- the map ---------------------------------------------------------------------
    def phi(self, p: Tensor, theta: Tensor) -> Tensor:
        """``φ(p, θ)`` for points ``(..., 2)``. Subclasses must implement this."""
        raise NotImplementedError(f"{type(self).__name__} must implement phi(p, theta)")

    def phi_inverse(self, q: Tensor, theta: Tensor) -> Tensor:
        """``φ⁻¹(q, θ)``; generic fallback: [`newton_inverse`][]."""
        return newton_inverse(self.phi, q, theta)

    def phi_jacobian(self, p: Tensor, theta: Tensor) -> Tensor:
        """``∂φ_i/∂p_j``, shape ``(..., 2, 2)``; generic fallback by autograd."""
        with torch.enable_grad():
            pp = p if p.requires_grad else p.detach().requires_grad_(True)
            q = self.phi(pp, theta)
            rows = [
                torch.autograd.grad(q[..., i].sum(), pp, create_graph=True, allow_unused=True)[0]
                for i in range(2)
            ]
        rows = [torch.zeros_like(p) if g is None else g for g in rows]
        return torch.stack(rows, dim=-2)

    def phi_jacobian_det(self, p: Tensor, theta: Tensor) -> Tensor:
        """``det ∂φ/∂p``, shape ``(...)``: the local area scale (Monte Carlo weights); generic
        fallback from [`phi_jacobian`][] in closed 2x2 form."""
        j = self.phi_jacobian(p, theta)
        return j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0]

    def phi_dtheta(self, p: Tensor, theta: Tensor) -> Tensor:
        """``∂φ_i/∂θ_j``, shape ``(..., 2, P)``; generic fallback by autograd.

        Each column is a Jacobian-vector product, computed as the derivative of a
        vector-Jacobian product with respect to its (dummy) cotangent.
        """
        if theta.numel() == 0:
            return p.new_zeros(*p.shape, 0)
        with torch.enable_grad():
            th = theta.detach().requires_grad_(True)
            out = self.phi(p.detach(), th)
            u = torch.zeros_like(out, requires_grad=True)
            (vjp,) = torch.autograd.grad(out, th, u, create_graph=True, allow_unused=True)
            if vjp is None or not vjp.requires_grad:  # φ does not depend on θ here
                return out.new_zeros(*out.shape, theta.numel())
            eye = torch.eye(theta.numel(), dtype=vjp.dtype, device=vjp.device)
            cols = [torch.autograd.grad(vjp, u, e, retain_graph=True, allow_unused=True)[0] for e in eye]
        return torch.stack([torch.zeros_like(out) if c is None else c for c in cols], dim=-1)

    def edge_breakpoints(self, a: Tensor, b: Tensor, theta: Tensor | None = None) -> Tensor:
        """Parameters ``t ∈ (0, 1)`` where φ is not smooth along the segments ``a + t (b − a)``.

        Where the kinks move with θ (e.g. a learned fovea centre), the parameters are
        differentiable in ``theta``, so that mesh vertices follow the kinks and θ-gradients stay
        as accurate as values.

        Args:
            a: ``(E, 2)`` segment starts in uniform sensor coordinates.
            b: ``(E, 2)`` segment ends.
            theta: the θ the mesh is built for (default: the layout's own, without gradient).

        Returns:
            ``(E, K)`` parameters (NaN where there are fewer than ``K``); the mesh puts a
            polyline vertex on each. Default: none (``K = 0``).
        """
        return a.new_zeros(a.shape[0], 0)

    def forward(self, p: Tensor) -> Tensor:
        """``φ(p, θ)`` for points ``p`` of shape ``(..., 2)``; differentiable in ``p`` and ``θ``.
        Computed at the finer of the points' and the layout's precisions."""
        check_points(p)
        return self.phi(p, self._theta_for(p))

    def inverse(self, q: Tensor) -> Tensor:
        """``φ⁻¹(q, θ)`` for points ``q`` of shape ``(..., 2)``."""
        check_points(q, "q")
        return self.phi_inverse(q, self._theta_for(q))

    def jacobian(self, p: Tensor) -> Tensor:
        """Spatial Jacobian ``∂φ_i/∂p_j`` at ``p``, shape ``(..., 2, 2)``."""
        check_points(p)
        return self.phi_jacobian(p, self._theta_for(p))

    def dtheta(self, p: Tensor) -> Tensor:
        """Parameter derivative ``∂φ_i/∂θ_j`` at ``p``, shape ``(..., 2, P)``."""
        check_points(p)
        return self.phi_dtheta(p, self._theta_for(p))

    @torch.no_grad()
    def check_foldover(self, n: int = 401) -> FoldoverReport:
        """Look for fold-overs: ``det J <= 0`` on an ``n × n`` grid of S (float64).

        A valid layout is a bijection, so ``det J > 0`` everywhere (almost everywhere for
        layouts with kinks). Use this to vet a user-written φ.
        """
        if n < 2:
            raise ValueError(f"n must be >= 2, got {n}")
        t = torch.linspace(-1, 1, n, dtype=torch.float64)
        grid = torch.stack(torch.meshgrid(t, t, indexing="xy"), -1)
        theta = self.theta_as(torch.float64).detach()
        with torch.enable_grad():
            jac = self.phi_jacobian(grid, theta).detach()
        det = torch.linalg.det(jac)
        k = int(torch.argmin(det))
        worst = grid.reshape(-1, 2)[k]
        return FoldoverReport(
            min_det=float(det.min()),
            num_nonpositive=int((det <= 0).sum()),
            worst_point=(float(worst[0]), float(worst[1])),
            grid=n,
        )

    def extra_repr(self) -> str:
        th = ", ".join(f"{v:.4g}" for v in self.theta.detach().tolist())
        return f"theta=({th}), bound={self.bound:g}, learn={self.learnable}"


FAMILIES: dict[str, type[Layout]] = {}
"""Every registered layout family by name: ``uniform``, ``rect``, ``curv``, ``fovea`` and
``elliptic`` (this module), ``spline`` and ``grid`` (their modules, loaded with this one), and any
a user adds with [`register_family`][]. Each family registers itself when its module loads, so
the dict is filled on import (the source reads ``{}``)."""
_L = TypeVar("_L", bound=type[Layout])


def register_family(cls: _L) -> _L:
    """Class decorator declaring a layout family under ``cls.family``.

    Registration is what layout files, [`make_layout`][] and the command line's ``--family``
    read, so a new family is added in one place.
    """
    if not (isinstance(cls, type) and issubclass(cls, Layout)) or cls.family in ("", "custom"):
        raise TypeError(f"register_family needs a Layout subclass with its own 'family' name, got {cls!r}")
    FAMILIES[cls.family] = cls
    return cls


@register_family
class UniformLayout(Layout):
    """The uniform layout ``φ(p) = p`` (no parameters): the classical sensor."""

    family = "uniform"
    num_params = 0
    separable = True
    straight_edges = True

    def phi(self, p: Tensor, theta: Tensor) -> Tensor:
        return p

    def phi_inverse(self, q: Tensor, theta: Tensor) -> Tensor:
        return q

    def phi_jacobian(self, p: Tensor, theta: Tensor) -> Tensor:
        return torch.eye(2, dtype=p.dtype, device=p.device).expand(*p.shape, 2).clone()

    def phi_jacobian_det(self, p: Tensor, theta: Tensor) -> Tensor:
        return torch.ones_like(p[..., 0])

    def phi_dtheta(self, p: Tensor, theta: Tensor) -> Tensor:
        return p.new_zeros(*p.shape, 0)

    def to_config(self) -> dict[str, Any]:
        return {}

    def extra_repr(self) -> str:
        return ""


def _side_scale(p: Tensor, center: Tensor) -> Tensor:
    """Per-axis half-width of the side of ``center`` that ``p`` lies on: ``1 − c`` or ``1 + c``."""
    return torch.where(p >= center, 1 - center, 1 + center)


class CenteredLayout(Layout):
    """Base of the paper's two families: a centred map φ0 deformed about a movable centre
    ``c = (c_x, c_y)``, ``|c_j| < 1``. Not a family itself: subclasses ([`RectLayout`][],
    [`CurvLayout`][]) write the centred map's ``_phi0``, ``_inverse0``, ``_jacobian0``,
    ``_det0`` and ``_dtheta0``.

    The square is mapped onto itself by the per-axis piecewise-affine ``T(p)_j = (p_j − c_j) /
    s_j`` with ``s_j = 1 − c_j`` right of (below) the centre and ``1 + c_j`` left of (above) it:
    ``T`` sends ``c`` to the origin and each of the four rectangles between ``c`` and a sensor
    corner onto a quadrant of S. The layout is ``T⁻¹ ∘ φ ∘ T``; φ keeps every point in its
    quadrant, so this is again a bijection of S fixing its border, and ``c = (0, 0)`` gives the
    centred layout bit for bit. The unit circle of φ_curv becomes four quarter-ellipses through
    ``c ± (s_x, 0)`` and ``c ± (0, s_y)``, touching the sensor's sides; the unit interval of
    φ_rect stays the whole side, with its density peak (``θ > 0``) at ``c``. Off the centre,
    φ is not smooth across the lines ``x = c_x`` and ``y = c_y`` (the scale changes there).

    Args:
        theta: ``(θ_x, θ_y)``.
        center: the centre ``(c_x, c_y)`` in sensor coordinates.
        learn_center: make the centre part of θ, which becomes ``(θ_x, θ_y, c_x, c_y)`` (each
            centre entry bounded by 1), so that it is learned with θ (``learn=True``).
        bound: as [`Layout`][].
        learn: as [`Layout`][].
        dtype: as [`Layout`][].
    """

    num_params: int | None = 2
    exact_buffers: ClassVar[tuple[str, ...]] = ("rho", "fixed_center")

    def __init__(
        self,
        theta: Sequence[float] | Tensor | None = None,
        *,
        center: Sequence[float] | Tensor = (0.0, 0.0),
        learn_center: bool = False,
        bound: float = 1.0,
        learn: bool = False,
        dtype: torch.dtype | None = None,
    ) -> None:
        c = torch.as_tensor(center, dtype=torch.float64).detach().flatten().cpu()
        if c.numel() != 2 or not bool(torch.isfinite(c).all()) or bool((c.abs() >= 1).any()):
            raise ValueError(f"center must be (c_x, c_y) with |c| < 1 each, got {center!r}")
        dtype = dtype or tensor_dtype(theta, center)
        self.learn_center = bool(learn_center)
        self.num_params = 4 if learn_center else 2
        self._centred = not learn_center and bool((c == 0).all())
        if learn_center:
            t = torch.zeros(2, dtype=torch.float64) if theta is None else torch.as_tensor(theta).double()
            if t.numel() != 2:
                raise ValueError(f"theta must have 2 values (θ_x, θ_y), got {t.numel()}: {theta!r}")
            theta = torch.cat([t.flatten().cpu(), c])
        super().__init__(theta, bound=bound, learn=learn, dtype=dtype)
        self.register_buffer("fixed_center", c)  # float64, as ρ (Layout.exact_buffers)

    def _bounds(self) -> Tensor:
        b = torch.full((self.num_params or 0,), self.bound, dtype=torch.float64)
        if self.learn_center:
            b[2:] = 1.0
        return b

    @property
    def center(self) -> Tensor:
        """The centre ``(c_x, c_y)`` the deformation is about."""
        return self.theta[2:] if self.learn_center else self.fixed_center.to(self._dtype)

    @property
    def centred(self) -> bool:
        """Whether φ is the centred map itself: a fixed centre at the origin (no affine step)."""
        return self._centred

    def _split(self, theta: Tensor) -> tuple[Tensor, Tensor | None]:
        """``(θ_x, θ_y)`` and the centre (``None`` for the centred fast path)."""
        if theta.numel() == 4:
            return theta[:2], theta[2:]
        return theta, None if self._centred else self.fixed_center.to(theta)

    # the centred functions of the family
    def _phi0(self, p: Tensor, theta: Tensor) -> Tensor:
        raise NotImplementedError

    def _inverse0(self, q: Tensor, theta: Tensor) -> Tensor:
        raise NotImplementedError

    def _jacobian0(self, p: Tensor, theta: Tensor) -> Tensor:
        raise NotImplementedError

    def _det0(self, p: Tensor, theta: Tensor) -> Tensor:
        raise NotImplementedError

    def _dtheta0(self, p: Tensor, theta: Tensor) -> Tensor:
        raise NotImplementedError

    def _local(self, p: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
        p, c = _promote(p, c)
        s = _side_scale(p, c)
        return (p - c) / s, s

    def _fixed(self, p: Tensor, u: Tensor) -> Tensor:
        """Where the centred map is the identity (coordinate-wise mask): on and outside the border."""
        return p.abs() >= 1

    def phi(self, p: Tensor, theta: Tensor) -> Tensor:
        th, c = self._split(theta)
        if c is None:
            return self._phi0(p, th)
        u, s = self._local(p, c)
        p = p.to(u)  # points φ fixes keep their exact coordinates (no rounding through T)
        return torch.where(self._fixed(p, u), p, c.to(u) + s * self._phi0(u, th))

    def phi_inverse(self, q: Tensor, theta: Tensor) -> Tensor:
        th, c = self._split(theta)
        if c is None:
            return self._inverse0(q, th)
        u, s = self._local(q, c)
        q = q.to(u)
        return torch.where(self._fixed(q, u), q, c.to(u) + s * self._inverse0(u, th))

    def phi_jacobian(self, p: Tensor, theta: Tensor) -> Tensor:
        th, c = self._split(theta)
        if c is None:
            return self._jacobian0(p, th)
        u, s = self._local(p, c)
        return self._jacobian0(u, th) * s[..., :, None] / s[..., None, :]

    def phi_jacobian_det(self, p: Tensor, theta: Tensor) -> Tensor:
        th, c = self._split(theta)
        return self._det0(p if c is None else self._local(p, c)[0], th)

    def phi_dtheta(self, p: Tensor, theta: Tensor) -> Tensor:
        """``∂φ/∂θ`` in closed form, ``(..., 2, P)``. For a learned centre, with ``σ_j = ±1``
        the side of ``c_j`` that ``p_j`` lies on (``∂s_j/∂c_j = −σ_j``, ``∂u_j/∂c_j =
        (σ_j u_j − 1)/s_j``): ``∂φ_i/∂c_j = δ_ij (1 − σ_i φ0_i(u)) + s_i J0_ij(u) (σ_j u_j −
        1)/s_j``; coordinates φ keeps fixed have zero derivative."""
        th, c = self._split(theta)
        if c is None:
            return self._dtheta0(p, th)
        u, s = self._local(p, c)
        d = s[..., :, None] * self._dtheta0(u, th)
        if theta.numel() < 4:
            return d
        sigma = torch.where(p.to(u) >= c.to(u), 1.0, -1.0)
        eye = torch.eye(2, dtype=u.dtype, device=u.device)
        dc = eye * (1 - sigma * self._phi0(u, th))[..., :, None]
        dc = dc + s[..., :, None] * self._jacobian0(u, th) * ((sigma * u - 1) / s)[..., None, :]
        d = torch.cat([d, dc], -1)
        return torch.where(self._fixed(p.to(u), u)[..., :, None], torch.zeros_like(d), d)

    def to_config(self) -> dict[str, Any]:
        th = self.theta_as(torch.float64).detach().cpu()
        c = self.center.detach().double().cpu()
        return {
            "theta": [float(v) for v in th[:2]],
            "bound": self.bound,
            "center": [float(v) for v in c],
            "learn_center": self.learn_center,
        }

    @classmethod
    def from_config(
        cls, config: dict[str, Any], *, learn: bool = False, dtype: torch.dtype | None = None
    ) -> Layout:
        theta = config_numbers(config, "theta")
        center = config_numbers(config, "center", [0.0, 0.0])
        return cls(
            theta,
            center=center,
            learn_center=bool(config.get("learn_center", False)),
            bound=config.get("bound", 1.0),
            learn=learn,
            dtype=dtype,
        )

    def extra_repr(self) -> str:
        th = ", ".join(f"{v:.4g}" for v in self.theta.detach()[:2].tolist())
        c = ", ".join(f"{v:.4g}" for v in self.center.detach().tolist())
        return f"theta=({th}), center=({c}), bound={self.bound:g}, learn={self.learnable}"


@register_family
class RectLayout(CenteredLayout):
    """The rectangular layout φ_rect of the paper (separable; pixels are rectangles), about a
    movable centre (see [`CenteredLayout`][]: ``center``, ``learn_center``).

    Examples:
        >>> layout = RectLayout(theta=(0.3, -0.2))
        >>> q = layout(torch.tensor([[0.5, 0.5]]))
        >>> torch.allclose(layout.inverse(q), torch.tensor([[0.5, 0.5]]), atol=1e-6)
        True
        >>> RectLayout((0.5, 0.5), center=(0.25, -0.5))(torch.tensor([[0.25, -0.5]]))
        tensor([[ 0.2500, -0.5000]])
    """

    family = "rect"
    separable = True
    straight_edges = True

    def _phi0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_rect(p, theta)

    def _inverse0(self, q: Tensor, theta: Tensor) -> Tensor:
        return phi_rect_inverse(q, theta)

    def _jacobian0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_rect_jacobian(p, theta)

    def _det0(self, p: Tensor, theta: Tensor) -> Tensor:
        return torch.diagonal(phi_rect_jacobian(p, theta), dim1=-2, dim2=-1).prod(-1)

    def _dtheta0(self, p: Tensor, theta: Tensor) -> Tensor:
        return phi_rect_dtheta(p, theta)


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
            out.append(_circle_crossings(a - c, d, lo, hi, _side_scale(mid, c)))
        return torch.cat(out, 1)


@register_family
class FoveaLayout(CurvLayout):
    """φ_curv about a learnable centre: [`CurvLayout`][] with ``learn_center=True``, so θ is
    ``(θ_x, θ_y, c_x, c_y)`` and a learned layout moves its fovea to where the task needs it.

    Examples:
        >>> FoveaLayout((0.5, 0.2), center=(0.3, -0.1)).theta
        tensor([ 0.5000,  0.2000,  0.3000, -0.1000])
    """

    family = "fovea"

    def __init__(
        self, theta: Sequence[float] | Tensor | None = None, *, learn_center: bool = True, **kwargs: Any
    ) -> None:
        super().__init__(theta, learn_center=learn_center, **kwargs)


# ----------------------------------------------------------------------------------------
# The reference code's third family: curvilinear in a disk that fills the square
# ----------------------------------------------------------------------------------------
def _sqrt0(x: Tensor) -> Tensor:
    """``√max(x, 0)`` with a zero (not infinite) gradient where the argument is 0."""
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


def square_to_disk(p: Tensor) -> Tensor:
    """The elliptical grid mapping of the square onto the unit disk: ``u = x √(1 − y²/2)``,
    ``v = y √(1 − x²/2)`` (points ``(..., 2)``; the square's border goes to the unit circle)."""
    x, y = p[..., 0], p[..., 1]
    return torch.stack([x * _sqrt0(1 - y * y / 2), y * _sqrt0(1 - x * x / 2)], -1)


def disk_to_square(q: Tensor) -> Tensor:
    """The inverse of [`square_to_disk`][]: ``x = ½√(2 + u² − v² + 2√2 u) − ½√(2 + u² − v² − 2√2 u)``
    and likewise ``y`` with ``u`` and ``v`` exchanged, evaluated as ``x = √2 u / (√(…+…) + √(…−…))``
    (the two roots' difference is ``4√2 u`` over their sum): the difference of two nearly equal
    roots lost all but a few digits of a small ``x`` (near the axes, 8e-9 relative); the quotient
    keeps them."""
    u, v = q[..., 0], q[..., 1]
    r2 = 2 * math.sqrt(2)
    a, b = 2 + u * u - v * v, 2 - u * u + v * v
    return torch.stack([_root_difference(a, r2 * u), _root_difference(b, r2 * v)], -1)


def _root_difference(a: Tensor, t: Tensor) -> Tensor:
    """``(√(a + t) − √(a − t)) / 2`` as ``t / (√(a + t) + √(a − t))``, without cancellation (0
    where both roots are 0)."""
    total = _sqrt0(a + t) + _sqrt0(a - t)
    return torch.where(
        total > 0, t / torch.where(total > 0, total, torch.ones_like(total)), torch.zeros_like(t)
    )


@register_family
class EllipticLayout(Layout):
    """The curvilinear map in a disk that fills the square: ``φ = E⁻¹ ∘ φ_curv ∘ E`` with ``E`` the
    elliptical square-to-disk mapping ([`square_to_disk`][]).

    The paper's φ_curv deforms only inside the unit circle, so the sensor's corners keep uniform
    pixels (§5: "restricted to a circular region"); the paper's public code has this third family,
    which first maps the whole square onto the disk, applies φ_curv there and maps back, so the
    deformation reaches the corners. ``E`` is a bijection of the open square onto the open disk
    sending the border onto the unit circle, which φ_curv fixes pointwise, so φ is again a
    bijection of S that fixes its border; it is smooth inside the square (φ_curv's kink lies on
    the circle, which is the square's border here), so pixel edges are curved but have no kinks.
    The inverse is closed form: ``E⁻¹ ∘ φ_curv⁻¹ ∘ E``. ``θ > 0`` puts more pixels at the centre;
    θ = 0 is the uniform layout. Jacobian and ∂φ/∂θ come from autograd through the closed forms.

    Examples:
        >>> layout = EllipticLayout((0.5, 0.3), dtype=torch.float64)
        >>> p = torch.tensor([[0.9, -0.95], [0.2, 0.1]], dtype=torch.float64)
        >>> torch.allclose(layout.inverse(layout(p)), p, atol=1e-12)
        True
    """

    family = "elliptic"

    def phi(self, p: Tensor, theta: Tensor) -> Tensor:
        return _elliptic_phi(p, theta)

    def phi_inverse(self, q: Tensor, theta: Tensor) -> Tensor:
        return _through_disk(phi_curv_inverse, q, theta)


def _elliptic_phi(p: Tensor, theta: Tensor) -> Tensor:
    """``E⁻¹ ∘ φ_curv ∘ E`` evaluated to a few ulps everywhere in the open square (the identity
    on and outside its border). Written out, each coordinate is a difference of two roots
    ``(√A₊ − √A₋)/2``; near a corner ``A₋`` is a difference of nearly equal numbers, so a rounding
    of ``E(p)`` of one ulp moved φ by ``√ε`` (1e-8 at 1e-12 from a corner). Here every small
    quantity is formed from ``x`` and ``y`` directly, by the identities (``c_x = 1 − x²``,
    ``c_y = 1 − y²``, coordinates taken as ``|x|, |y|`` and the signs restored, ``u, v = E(p)``):
    ``1 − ‖E(p)‖ = c_x c_y / (1 + ‖E(p)‖)``; φ_curv's change ``Δu = −2θ (1 − r) u / (1 − θ + 2θ(1 − r))``;
    ``(√2 − u)² − v² = (√(2 − y²) − x)²`` with ``√(2 − y²) − x = (c_x + c_y) / (√(2 − y²) + x)``; so
    ``A₋ = m² − 2(√2 − u)Δu − 2vΔv + Δu² − Δv²``, and the coordinate is ``2√2 u' / (√A₊ + √A₋)``."""
    p, theta = _promote(p, theta)
    inside = (p.abs() < 1).all(-1, keepdim=True)
    q = torch.where(inside, p, torch.zeros_like(p))
    ax, ay = q[..., 0].abs(), q[..., 1].abs()
    cx, cy = (1 - ax) * (1 + ax), (1 - ay) * (1 + ay)
    sx, sy = torch.sqrt(1 + cy), torch.sqrt(1 + cx)  # √(2 − y²), √(2 − x²)
    h = math.sqrt(2)
    u, v = ax * sx / h, ay * sy / h
    r = _safe_norm(torch.stack([u, v], -1))
    gap = cx * cy / (1 + r)  # 1 − r
    tx, ty = theta[..., 0], theta[..., 1]
    du = -2 * tx * gap * u / ((1 - tx) + 2 * tx * gap)
    dv = -2 * ty * gap * v / ((1 - ty) + 2 * ty * gap)
    u2, v2 = u + du, v + dv
    mx, my = (cx + cy) / (sx + ax), (cx + cy) / (sy + ay)
    a_minus = mx * mx - 2 * (h - u) * du - 2 * v * dv + du * du - dv * dv
    b_minus = my * my - 2 * (h - v) * dv - 2 * u * du + dv * dv - du * du
    a_plus = 2 + u2 * u2 - v2 * v2 + 2 * h * u2
    b_plus = 2 - u2 * u2 + v2 * v2 + 2 * h * v2
    x = 2 * h * u2 / (torch.sqrt(a_plus) + _sqrt0(a_minus))
    y = 2 * h * v2 / (torch.sqrt(b_plus) + _sqrt0(b_minus))
    out = torch.stack([torch.copysign(x, q[..., 0]), torch.copysign(y, q[..., 1])], -1)
    return torch.where(inside, out, p)


def _through_disk(fn: Callable[[Tensor, Tensor], Tensor], p: Tensor, theta: Tensor) -> Tensor:
    """``E⁻¹ ∘ fn ∘ E`` inside the open square ([`square_to_disk`][]), the identity on and outside
    its border."""
    p, theta = _promote(p, theta)
    inside = (p.abs() < 1).all(-1, keepdim=True)
    out = disk_to_square(fn(square_to_disk(torch.where(inside, p, torch.zeros_like(p))), theta))
    return torch.where(inside, out, p)


# ----------------------------------------------------------------------------------------
# Generic numerical inverse
# ----------------------------------------------------------------------------------------
def newton_inverse(
    phi: Callable[[Tensor, Tensor], Tensor],
    q: Tensor,
    theta: Tensor,
    *,
    max_iter: int = 100,
    tol: float = 1e-13,
) -> Tensor:
    """Invert a bijection ``φ(·, θ)`` of S at points ``q`` by damped Newton iteration.

    Solved in float64 from the start point ``p = q`` with a backtracking line search on the
    residual ``‖φ(p) − q‖`` and iterates kept inside S, which converges for the bi-Lipschitz
    maps layouts are required to be. The converged point is returned with one Newton step
    re-attached to the autograd graph, so gradients w.r.t. ``q`` and ``θ`` follow the
    implicit-function theorem (``dp = J⁻¹ (dq − ∂φ/∂θ dθ)``).

    Raises:
        RuntimeError: if some point does not converge within ``max_iter`` iterations.
    """

    def jac(p: Tensor, th: Tensor) -> Tensor:
        with torch.enable_grad():
            pp = p.detach().requires_grad_(True)
            out = phi(pp, th)
            rows = [torch.autograd.grad(out[..., i].sum(), pp, retain_graph=i == 0)[0] for i in range(2)]
        return torch.stack(rows, -2)

    th64 = theta.detach().double()
    q64 = q.detach().double()
    p = q64.clone()
    with torch.no_grad():
        res = phi(p, th64) - q64
        err = res.norm(dim=-1)
        for _ in range(max_iter):
            if bool((err <= tol).all()):
                break
            j = jac(p, th64)
            step = torch.linalg.solve(j, res.unsqueeze(-1)).squeeze(-1)
            lam = torch.ones_like(err)
            for _ in range(30):  # backtracking: accept the first step that reduces ‖res‖
                cand = (p - lam[..., None] * step).clamp(-1, 1)
                cres = phi(cand, th64) - q64
                cerr = cres.norm(dim=-1)
                better = (cerr < err) | (err <= tol)
                if bool(better.all()):
                    break
                lam = torch.where(better, lam, lam / 2)
            accept = (cerr < err)[..., None]
            p = torch.where(accept, cand, p)
            res = torch.where(accept, cres, res)
            err = res.norm(dim=-1)
        if not bool((err <= max(tol, 1e-9)).all()):
            bad = int((err > max(tol, 1e-9)).sum())
            raise RuntimeError(
                f"newton_inverse: {bad} point(s) did not converge in {max_iter} iterations "
                f"(largest residual {float(err.max()):.3g}); is φ a bijection of S?"
            )
    p = p.to(q.dtype)
    if not (q.requires_grad or theta.requires_grad):
        return p
    # Re-attach: p* − J⁻¹(φ(p*, θ) − q) equals p* in value and has the implicit gradient.
    j = jac(p, theta.detach()).to(q.dtype)
    r = phi(p, theta) - q
    return p - torch.linalg.solve(j, r.unsqueeze(-1)).squeeze(-1)


def make_layout(family: str | Layout, theta: Sequence[float] | Tensor | None = None, **kwargs: Any) -> Layout:
    """Build a layout of a registered family (see [`FAMILIES`][]) or pass a layout through.

    Args:
        family: a family name (``"uniform"``, ``"rect"``, ``"curv"``, ...) or a [`Layout`][].
        theta: initial θ (``None``: zeros; the uniform layout takes ``None``, ``()`` or zeros).
        **kwargs: ``bound``, ``learn`` (default ``False``), ``dtype``.

    Examples:
        >>> make_layout("rect", (0.3, -0.2)).theta
        tensor([ 0.3000, -0.2000])
        >>> make_layout("uniform", ()).family
        'uniform'
    """
    if isinstance(family, Layout):
        return family
    cls = FAMILIES.get(str(family).lower())
    if cls is None:
        raise ValueError(f"family must be one of {', '.join(map(repr, FAMILIES))}; got {family!r}")
    return cls(theta, **kwargs)


# The other built-in families (splines, control grids) register themselves in their own modules,
# which build on this one: loaded with it, so that FAMILIES is complete wherever it is read.
for _module in ("splines", "grids"):
    importlib.import_module(f"{__package__}.{_module}")
