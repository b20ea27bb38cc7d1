"""The base of every layout family: [`Layout`][] and the family registry (what the families
share of their numbers is in [`layoutwarp.layouts.values`][]).

A layout is a bijection φ(·, θ) of the sensor square S = [-1, 1]² onto itself; sensor pixel ``k``
is the image ``A_k = φ(U_k, θ)`` of the uniform cell ``U_k`` (Sommerhoff et al., "Differentiable
Sensor Layouts for End-to-End Learning of Task-Specific Camera Parameters", §3.2).
"""

from __future__ import annotations

import functools
import json
import math
import threading
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch
from torch import Tensor, nn

from ..checks import ArgumentError, check_bool, check_float_dtype, check_number, check_points, values_readable
from .inverse import forward_jacobian, newton_inverse
from .values import config_numbers, tensor_dtype

__all__ = [
    "FAMILIES",
    "FoldoverReport",
    "Layout",
    "check_layout",
    "layout_by_handle",
    "make_layout",
    "newton_inverse",
    "register_family",
]


@dataclass(frozen=True)
class FoldoverReport:
    """Result of [`Layout.check_foldover`][] on an ``n × n`` grid of S.

    Attributes:
        min_det: smallest Jacobian determinant found.
        num_nonpositive: number of grid points with ``det J <= 0`` (fold-overs).
        worst_point: ``(x, y)`` where ``det J`` is smallest.
        grid: the grid side ``n`` (0 for an exact check, e.g.
            [`GridLayout`][layoutwarp.layouts.grid.GridLayout]'s).
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
        bound: the open bound on ``|θ|``, in ``(0, 1]`` (the paper uses 1).
        learn: make ``ρ`` a trainable parameter (default ``False``: a buffer, fixed layout).
        dtype: the layout's [`dtype`][]: that of θ and of what is computed from it (default: a
            tensor ``theta``'s own floating dtype, else torch's default).

    A fixed layout keeps θ as it was given (``fixed_theta``), ``ρ`` and its other constants (e.g.
    a centre) in float64 whatever its dtype: they are a few numbers, and a float64 computation
    then gets the θ that was written, not its float32 rounding, also after ``.float()`` or
    ``.double()``; those change the layout's [`dtype`][] and move the constants without rounding
    them. [`theta_as`][] gives θ in any
    dtype; the methods that take points ([`forward`][], [`inverse`][], ...) compute at the
    points' precision when it is the finer one. A learnable layout's ``ρ`` is a parameter of its
    dtype, as every torch module's.
    """

    family: ClassVar[str] = "custom"
    num_params: int | None = 2
    separable: ClassVar[bool] = False
    straight_edges: ClassVar[bool] = False
    unbounded: ClassVar[bool] = False
    #: The compiled map of the kernels this class's φ is (``"curv"``: φ_curv about
    #: ``fixed_center``, ``"elliptic"``), or ``None``. Read on the class that declares it only:
    #: a subclass may change φ, so it keeps the torch path unless it declares one itself.
    kernel_map: ClassVar[str | None] = None
    #: Buffers of a fixed layout's constants, held in float64 whatever the layout's dtype.
    exact_buffers: ClassVar[tuple[str, ...]] = ("rho", "fixed_theta")

    def __init_subclass__(cls, **kwargs: Any) -> None:
        # each family's constructor, once the outermost one returns, makes the layout's token
        # (layoutwarp.operators.base.layout_token: how it enters layoutwarp's operators)
        super().__init_subclass__(**kwargs)
        cls.__init__ = _then_token(cls.__init__)  # type: ignore[method-assign]

    def __init__(
        self,
        theta: Sequence[float] | Tensor | None = None,
        *,
        bound: float = 1.0,
        learn: bool = False,
        dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        self._token: str | None = None
        # |θ| < 1 keeps every built-in family a bijection (θ = ±1 folds the sensor onto a point)
        self.bound = check_number(bound, "bound", 0, None if self.unbounded else 1, lo_open=True)
        self._dtype = check_float_dtype(dtype) if dtype is not None else tensor_dtype(theta)
        learn = check_bool(learn, "learn")
        # _bounds() where ρ lives, float64 (a buffer made here: nothing a compiled graph guards on
        # fills in at its first call)
        self.register_buffer("theta_bounds", self._bounds(), persistent=False)
        exact = self._validate_theta(theta, torch.float64)
        rho = self._to_rho(exact)
        self._keeps_theta = not (learn and self.num_params)
        if self._keeps_theta:  # θ as it was set (atanh and tanh do not round-trip every float), and ρ
            self.register_buffer("rho", rho)
            self.register_buffer("fixed_theta", exact.clone())  # never the caller's tensor
        else:
            self.rho = nn.Parameter(rho.to(self._dtype))
            self._check_learned_theta()

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of [`theta`][] and of what is computed from it (``dtype`` at construction;
        ``.to(dtype)``, ``.float()``, ``.double()`` change it)."""
        return self._dtype

    def _apply(self, fn: Callable[[Tensor], Tensor], recurse: bool = True) -> Layout:
        """As `nn.Module`'s, except that a fixed layout's `exact_buffers` are moved, never rounded."""
        dtype = fn(torch.empty(0, dtype=self._dtype)).dtype  # what the conversion does to a float
        exact = {n: self._buffers[n] for n in (*self.exact_buffers, "theta_bounds") if n in self._buffers}
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
        return self._bounds_at(rho.device, rho.dtype) * torch.tanh(rho)

    def _bounds_at(self, device: torch.device, dtype: torch.dtype) -> Tensor:
        """[`_bounds`][] on ``device`` in ``dtype``: the layout's ``theta_bounds`` buffer (moved
        with the layout, float64 whatever its dtype), cast where ``dtype`` asks."""
        return self.theta_bounds.to(device=device, dtype=dtype)

    def theta_source(self) -> tuple[Tensor, Tensor]:
        """What θ is made of, for an operator that makes θ itself (so a learnable step's
        ``ρ → θ``, and its gradient back, cost no launches of their own): ``(ρ, bounds)`` of a
        learnable layout with ``θ = bounds · tanh(ρ)`` (``bounds`` ``(P,)`` float64, kept on
        ρ's device), else ``(θ, empty)``: a fixed layout's θ as it was set (float64), an
        unbounded family's ρ, or θ of a family that makes it its own way. [`theta_of`][] makes
        θ of either, in float64, as [`theta_as`][] with ``torch.float64`` does."""
        empty = self.rho.new_empty(0, dtype=torch.float64)
        if not self.learnable or type(self)._to_theta is not Layout._to_theta:
            return self.theta_as(torch.float64), empty
        if self.unbounded:
            return self.rho, empty
        return self.rho, self._bounds_at(self.rho.device, torch.float64)

    def _to_rho(self, theta: Tensor) -> Tensor:
        """Inverse of `_to_theta`."""
        return theta.clone() if self.unbounded else torch.atanh(theta / self._bounds().to(theta))

    def _outside(self, theta: Tensor) -> tuple[int, float, float] | None:
        """The first entry of a (float64, CPU) θ that is not finite or not inside its bound, as
        ``(index, value, bound)``; ``None`` where every entry is allowed."""
        for i, (v, b) in enumerate(zip(theta.tolist(), self._bounds().tolist(), strict=True)):
            if not math.isfinite(v) or abs(v) >= b:
                return i, v, b
        return None

    def _check_learned_theta(self) -> None:
        """Refuse a θ that ``ρ`` in the layout's dtype cannot hold inside the bound (θ so near it
        that ``bound · tanh(ρ)`` rounds onto it: a layout that folds)."""
        bad = None if self.unbounded else self._outside(self._to_theta(self.rho.detach()).double())
        if bad is not None:
            i, _, b = bad
            raise ArgumentError(
                "theta",
                f"theta[{i}] is within {str(self._dtype).removeprefix('torch.')} rounding of the "
                f"bound {b:g}: a learnable layout of this dtype holds |θ| up to about "
                f"{b * (1 - 2 * torch.finfo(self._dtype).eps):.9g}",
            )

    def check_theta_now(self) -> None:
        """Raise, in one line, where θ as it is now is no layout: an entry that is not finite, or one
        on or past its bound. A learnable layout's ``ρ`` is unconstrained, so a training step (a
        learning rate too large, a loss gone NaN) can make it NaN or ±inf, or so large that
        ``bound · tanh(ρ)`` rounds onto the bound, where the layout folds (NaN values, or a crash
        in torch's ``grid_sample`` backward). θ is taken at the precision the integrators compute
        it in (float32 at least). Reads ρ's values where that costs no wait: a CPU ``ρ`` whose
        values can be read ([`values_readable`][layoutwarp.checks.values_readable]); on a CUDA
        device, or in a compiled graph, a transform or a fake-tensor mode, nothing is read.
        [`simulate`][layoutwarp.sensor.simulate] and every entry that takes a layout
        (``check_layout``) call it for learnable layouts; ``load_state_dict`` checks the θ it
        is given before it takes it."""
        rho = self.rho
        if rho.device.type != "cpu" or not values_readable():
            return
        values = rho.detach().tolist()
        calm = _CALM_RHO.get(self._dtype, 0.0)  # |ρ| below it: θ well inside its bound
        if all(math.isfinite(v) and (self.unbounded or abs(v) < calm) for v in values):
            return  # what nearly every call meets: no θ computed
        with torch.no_grad():
            theta = self.theta_as(torch.promote_types(self._dtype, torch.float32))
        self._refuse_folded(theta, rho)

    def _refuse_folded(self, theta: Tensor, rho: Tensor | None) -> None:
        """Raise, in one line, where ``theta`` (θ as a computation takes it, from ``rho`` where
        given) has an entry that is not finite or not inside its bound."""
        bad = self._outside(theta.detach().double().cpu())
        if bad is not None:
            i, v, b = bad
            held = "" if rho is None else f" (rho[{i}] = {float(rho.detach()[i])!r})"
            raise ArgumentError(
                "theta",
                f"theta[{i}] = {v!r}{held} is no layout: each θ must be finite with |θ| < bound = {b:g}; "
                "a training step (its learning rate) or a state dict made it so",
            )

    def _check_theta(self, theta: Tensor) -> None:
        """Raise ``ValueError`` naming the first entry of a (float64, CPU) θ that is not allowed."""
        bad = self._outside(theta)
        if bad is not None:
            i, v, b = bad
            raise ArgumentError(
                "theta", f"theta[{i}] = {v!r} is out of range: each θ must be finite with |θ| < bound = {b}"
            )

    def _validate_theta(self, theta: Sequence[float] | Tensor | None, dtype: torch.dtype) -> Tensor:
        n = self.num_params or 0
        if theta is None:
            return torch.zeros(n, dtype=dtype)
        what = f"{n} numbers (θ_x, θ_y)" if n == 2 else f"{n} numbers" if n else "empty or zeros"
        try:  # numpy keeps Python floats in float64 (torch.as_tensor would round them to float32)
            raw = theta.detach().cpu() if isinstance(theta, Tensor) else torch.as_tensor(np.asarray(theta))
            if raw.is_complex() or raw.dtype == torch.bool or raw.ndim > 1:
                raise TypeError
            t = raw.to(torch.float64).flatten()
        except (TypeError, ValueError, RuntimeError):
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
        """θ in ``dtype``: a fixed layout's as it was set (held in float64, so
        ``theta_as(torch.float64)`` is exactly the θ given, a layout file's or ``set_theta``'s);
        a learnable layout's from ``ρ``, differentiable, computed at the finer of ρ's precision
        and ``dtype``'s."""
        if self._keeps_theta and not self.rho.requires_grad:
            return self.fixed_theta.to(dtype)
        return self._to_theta(self.rho.to(torch.promote_types(self.rho.dtype, dtype))).to(dtype)

    @torch.no_grad()
    def set_theta(self, theta: Sequence[float] | Tensor) -> None:
        """Set ``θ`` in place (validated like the constructor). A fixed layout's θ is set this
        way (or by loading a state dict), not by writing to ``rho``."""
        t = self._validate_theta(theta, torch.float64)
        self.rho.copy_(self._to_rho(t).to(self.rho))
        if self._keeps_theta:
            self.fixed_theta.copy_(t)

    def _save_to_state_dict(self, destination: dict[str, Any], prefix: str, keep_vars: bool) -> None:
        """As `nn.Module`'s, with the layout's ``kind`` (its family and bound, as bytes); a fixed
        layout whose ``rho`` was made to require grad (and trained) saves the θ of its ``rho``."""
        super()._save_to_state_dict(destination, prefix, keep_vars)
        destination[prefix + "kind"] = torch.tensor(list(self._kind().encode()), dtype=torch.uint8)
        if self._keeps_theta and self.rho.requires_grad:
            destination[prefix + "fixed_theta"] = self._to_theta(self.rho.detach()).to(torch.float64)

    def _kind(self) -> str:
        """What a state dict says of the layout besides its tensors: ``family;bound`` (the bound
        makes ρ θ), so that loading it into a layout of another family (or, for ρ alone,
        another bound) is refused."""
        return f"{self.family};{self.bound!r}"

    def _check_kind(self, saved: Tensor, loading_theta: bool) -> None:
        """Refuse, in one line, a state dict of another family (or a ρ of another bound)."""
        family, _, bound = bytes(saved.to(torch.uint8).tolist()).decode(errors="replace").partition(";")
        if family != self.family:
            raise ValueError(
                f"the state dict holds a {family} layout, not a {self.family} one: load it into a "
                f"{family} layout (make_layout({family!r}, learn=...))"
            )
        if bound and float(bound) != self.bound and not loading_theta:
            raise ValueError(
                f"the state dict holds ρ of a layout with bound={bound}, this one has bound={self.bound}: "
                f"θ = bound · tanh(ρ) would differ; make the layout with bound={bound}"
            )

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        """As `nn.Module`'s, and a state dict with ``rho`` alone (a learnable layout's, or one
        written before fixed layouts kept θ) sets a fixed layout's θ from it, as the layout that
        wrote it computed θ (in ``ρ``'s dtype); a fixed layout's ``fixed_theta`` is left out where
        ``ρ`` is learned. One of another family is refused (its ``kind``, the family and bound as
        bytes: a state dict stays tensors only); one written before layouts said their family is
        taken as this layout's."""
        kind = state_dict.pop(prefix + "kind", None)  # a state written before layouts said it: none
        if kind is not None:  # θ itself in the state (a fixed layout's): ρ's bound does not matter
            self._check_kind(kind, self._keeps_theta and prefix + "fixed_theta" in state_dict)
        rho, kept = state_dict.get(prefix + "rho"), prefix + "fixed_theta"
        if self._keeps_theta and kept not in state_dict and rho is not None and rho.shape == self.rho.shape:
            state_dict[kept] = self._to_theta(rho.detach().cpu()).to(torch.float64)
        elif not self._keeps_theta:
            state_dict.pop(kept, None)
        self._refuse_folded_state(state_dict.get(kept) if self._keeps_theta else rho)
        super()._load_from_state_dict(state_dict, prefix, *args)
        self._token = self.make_token(keep_theta=True)  # its settings may have changed, not θ's part

    def _refuse_folded_state(self, held: Tensor | None) -> None:
        """Refuse, before anything is loaded, a state dict whose θ (a fixed layout's ``held`` θ, a
        learnable one's ``held`` ρ) is no layout: the layout keeps the θ it had."""
        if not isinstance(held, Tensor) or held.shape != self.rho.shape or not held.numel():
            return  # a missing or misshapen entry: nn.Module's own report
        if held.device.type == "meta" or not values_readable():
            return
        if self._keeps_theta:
            self._refuse_folded(held, None)
        else:
            self._refuse_folded(
                self._to_theta(held.detach().to(torch.promote_types(self._dtype, torch.float32))), held
            )

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
        [`GridLayout`][layoutwarp.layouts.grid.GridLayout]) undo the part of a step that would
        fold the layout ([`guard_`][]).

        Returns:
            whether the parameters were changed.
        """
        changed = self.guard_()
        return changed is not None and bool(changed)

    def guard_(self) -> Tensor | None:
        """[`project_`][] in torch operations only, reading no value on the host (what a compiled
        graph runs; [`SensorLayer`][layoutwarp.sensor.SensorLayer] calls it before each forward
        pass, so any training loop gets the guarded step): whether the parameters changed as a
        0-d tensor, or ``None`` for a family with nothing to pull back (the default)."""
        return None

    # -- files -----------------------------------------------------------------------
    def to_config(self) -> dict[str, Any]:
        """The JSON-able constructor arguments that rebuild this layout (see [`from_config`][])."""
        return {"theta": [float(v) for v in self.theta_as(torch.float64).detach().cpu()], "bound": self.bound}

    def theta_keys(self) -> tuple[str, ...]:
        """The keys of [`to_config`][] that hold θ (those a new θ changes; the rest are settings)."""
        return ("theta",)

    def make_token(self, keep_theta: bool = False) -> str:
        """The layout's token ([`layoutwarp.operators.base.layout_token`][]): its description as JSON text
        (a registered family) or a handle of the object in this process. With ``keep_theta``, θ's
        part is the previous token's: a new θ (a loaded state dict) leaves the token as it was,
        so a compiled graph that reads it is not compiled again."""
        if FAMILIES.get(self.family) is not type(self):
            token = f"object:{id(self)}"
            _OBJECTS[token] = self
            return token
        spec = {"family": self.family, **self.to_config()}
        old = getattr(self, "_token", None)
        if keep_theta and old is not None and not old.startswith("object:"):
            before = json.loads(old)
            spec.update({k: before[k] for k in self.theta_keys() if k in before and k in spec})
        return json.dumps(spec, sort_keys=True)

    @classmethod
    def from_config(
        cls, config: dict[str, Any], *, learn: bool = False, dtype: torch.dtype | None = None
    ) -> Layout:
        """Rebuild a layout from [`to_config`][]'s dict (raises ``ValueError`` on bad or missing
        values)."""
        theta = config_numbers(config, "theta", required=bool(cls.num_params))
        return cls(theta, bound=config.get("bound", 1.0), learn=learn, dtype=dtype)

    # -- the map ---------------------------------------------------------------------
    def phi(self, p: Tensor, theta: Tensor) -> Tensor:
        """``φ(p, θ)`` for points ``(..., 2)``. Subclasses must implement this."""
        raise NotImplementedError(f"{type(self).__name__} must implement phi(p, theta)")

    def phi_inverse(self, q: Tensor, theta: Tensor) -> Tensor:
        """``φ⁻¹(q, θ)``; generic fallback: [`newton_inverse`][]."""
        return newton_inverse(self.phi, q, theta)

    def phi_jacobian(self, p: Tensor, theta: Tensor) -> Tensor:
        """``∂φ_i/∂p_j``, shape ``(..., 2, 2)``; generic fallback by forward-mode autodiff (one
        Jacobian-vector product per axis, differentiable in θ; it runs inside operators and
        compiled graphs, where reverse-mode calls cannot)."""
        return forward_jacobian(lambda q: self.phi(q, theta), p, 2)

    def phi_jacobian_det(self, p: Tensor, theta: Tensor) -> Tensor:
        """``det ∂φ/∂p``, shape ``(...)``: the local area scale (Monte Carlo weights); generic
        fallback from [`phi_jacobian`][] in closed 2x2 form."""
        j = self.phi_jacobian(p, theta)
        return j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0]

    def phi_dtheta(self, p: Tensor, theta: Tensor) -> Tensor:
        """``∂φ_i/∂θ_j``, shape ``(..., 2, P)``; generic fallback by forward-mode autodiff (one
        Jacobian-vector product per entry of θ)."""
        if theta.numel() == 0:
            return p.new_zeros(*p.shape, 0)
        return forward_jacobian(lambda th: self.phi(p, th), theta, theta.numel())

    def edge_breakpoints(self, a: Tensor, b: Tensor, theta: Tensor | None = None) -> Tensor:
        """Parameters ``t ∈ (0, 1)`` where φ is not smooth along the segments ``a + t (b − a)``.

        Where the kinks move with θ (e.g. a learned fovea centre), the parameters are
        differentiable in ``theta``, so that mesh vertices follow the kinks and θ-gradients see
        them move.

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
        if torch.compiler.is_compiling():  # e.g. vmap names its function: no values read in a graph
            return f"bound={self.bound:g}, learn={self.learnable}"
        th = ", ".join(f"{v:.4g}" for v in self.theta.detach().tolist())
        return f"theta=({th}), bound={self.bound:g}, learn={self.learnable}"


FAMILIES: dict[str, type[Layout]] = {}
"""Every registered layout family by name: ``uniform``, ``rect``, ``curv``, ``fovea`` and
``elliptic`` (this module), ``spline`` and ``grid`` (their modules, loaded with this one), and any
a user adds with [`register_family`][]. Each family registers itself when its module loads, so
the dict is filled on import (the source reads ``{}``)."""


_BUILDING = threading.local()
#: Layouts of families that are not registered, by their tokens' handles (``object:<id>``).
_OBJECTS: weakref.WeakValueDictionary[str, Layout] = weakref.WeakValueDictionary()


#: Per dtype, a |ρ| below which ``bound · tanh(ρ)`` stays well inside the bound (64 of the dtype's
#: steps from it): [`Layout.check_theta_now`][] computes no θ there.
_CALM_RHO = {
    dt: math.atanh(1 - 64 * torch.finfo(torch.promote_types(dt, torch.float32)).eps)
    for dt in (torch.float16, torch.bfloat16, torch.float32, torch.float64)
}


def check_layout(layout: Any, name: str = "layout") -> Layout:
    """``layout`` if it is a layoutwarp [`Layout`][] (a family name or anything else is refused,
    naming what to pass), a learnable one's θ checked as it is now ([`Layout.check_theta_now`][])."""
    if isinstance(layout, Layout):
        if layout.learnable_param:  # a step may have made its θ no layout: said here, not as NaN
            layout.check_theta_now()
        return layout
    hint = (
        f" (make one with make_layout({layout!r}, theta))"
        if isinstance(layout, str) and layout in FAMILIES
        else ""
    )
    raise ArgumentError(
        name.split("[")[0], f"{name} must be a layoutwarp Layout{hint}, got {type(layout).__name__}"
    )


def layout_by_handle(token: str) -> Layout | None:
    """The layout whose token is the handle ``token`` (``object:<id>``: a family that is not
    registered), while it lives in this process; else ``None``."""
    return _OBJECTS.get(token)


def _then_token(init: Callable[..., None]) -> Callable[..., None]:
    """``init`` followed, where it is the outermost constructor running, by the layout's token."""

    @functools.wraps(init)
    def wrapped(self: Layout, *args: Any, **kwargs: Any) -> None:
        depth = getattr(_BUILDING, "depth", 0)
        _BUILDING.depth = depth + 1
        try:
            init(self, *args, **kwargs)
        finally:
            _BUILDING.depth = depth
        if depth == 0:
            self._token = self.make_token()

    return wrapped


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
