"""The base of the paper's two families: a centred map deformed about a movable centre."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor

from .arith import promote
from .base import Layout
from .values import config_numbers, tensor_dtype

__all__ = ["CenteredLayout", "side_scale"]


def side_scale(p: Tensor, center: Tensor) -> Tensor:
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
        theta: ``(θ_x, θ_y)``; with ``learn_center`` also ``(θ_x, θ_y, c_x, c_y)``, the layout's
            whole θ (as [`theta`][layoutwarp.layouts.base.Layout.theta] and `set_theta` hold it),
            with no ``center`` then.
        center: the centre ``(c_x, c_y)`` in sensor coordinates (default: the sensor's).
        learn_center: make the centre part of θ, which becomes ``(θ_x, θ_y, c_x, c_y)`` (each
            centre entry bounded by 1), so that it is learned with θ (``learn=True``).
        bound: as [`Layout`][].
        learn: as [`Layout`][].
        dtype: as [`Layout`][].
    """

    num_params: int | None = 2
    exact_buffers: ClassVar[tuple[str, ...]] = ("rho", "fixed_theta", "fixed_center")

    def __init__(
        self,
        theta: Sequence[float] | Tensor | None = None,
        *,
        center: Sequence[float] | Tensor | None = None,
        learn_center: bool = False,
        bound: float = 1.0,
        learn: bool = False,
        dtype: torch.dtype | None = None,
    ) -> None:
        dtype = dtype or tensor_dtype(theta, center)
        t = None  # θ_x, θ_y of a learned centre, float64 (numpy keeps Python floats in float64)
        if theta is not None and learn_center:
            t = torch.as_tensor(np.asarray(theta)).double().flatten()
        if t is not None and t.numel() == 4:  # the whole θ of a learned centre
            if center is not None:
                raise ValueError(
                    f"theta holds the centre (4 values: θ_x, θ_y, c_x, c_y), so center must not be given "
                    f"too; got theta={theta!r}, center={center!r}"
                )
            t, center = t[:2], t[2:].tolist()
        center = (0.0, 0.0) if center is None else center
        c = torch.as_tensor(center, dtype=torch.float64).detach().flatten().cpu()
        if c.numel() != 2 or not bool(torch.isfinite(c).all()) or bool((c.abs() >= 1).any()):
            raise ValueError(f"center must be (c_x, c_y) with |c| < 1 each, got {center!r}")
        self.learn_center = bool(learn_center)
        self.num_params = 4 if learn_center else 2
        self._centred = not learn_center and bool((c == 0).all())
        if learn_center:
            t = torch.zeros(2, dtype=torch.float64) if t is None else t
            if t.numel() != 2:
                raise ValueError(
                    f"theta must have 2 values (θ_x, θ_y), or 4 (θ_x, θ_y, c_x, c_y) with a learned centre, "
                    f"got {t.numel()}: {theta!r}"
                )
            theta = torch.cat([t.cpu(), c])
        super().__init__(theta, bound=bound, learn=learn, dtype=dtype)
        self.register_buffer("fixed_center", c)  # float64, as ρ (Layout.exact_buffers)

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        """As [`Layout`][layoutwarp.layouts.base.Layout]'s; a loaded fixed centre may move φ off the
        centred map (or onto it)."""
        super()._load_from_state_dict(state_dict, prefix, *args)
        self._centred = not self.learn_center and bool((self.fixed_center == 0).all())

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
        p, c = promote(p, c)
        s = side_scale(p, c)
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

    def theta_keys(self) -> tuple[str, ...]:
        return ("theta", "center") if self.learn_center else ("theta",)

    def to_config(self) -> dict[str, Any]:
        th = self.theta_as(torch.float64).detach().cpu()
        c = th[2:] if self.learn_center else self.fixed_center.cpu()  # float64, never rounded
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
        theta = config_numbers(config, "theta", required=True)
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
        if torch.compiler.is_compiling():  # e.g. vmap names its function: no values read in a graph
            return super().extra_repr()
        th = ", ".join(f"{v:.4g}" for v in self.theta.detach()[:2].tolist())
        c = ", ".join(f"{v:.4g}" for v in self.center.detach().tolist())
        return f"theta=({th}), center=({c}), bound={self.bound:g}, learn={self.learnable}"
