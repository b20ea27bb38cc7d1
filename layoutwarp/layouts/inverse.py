"""The generic fallbacks of a layout's map: its derivatives by forward-mode autodiff, and its
inverse by damped Newton iteration in float64 with the implicit gradient re-attached."""

from __future__ import annotations

import threading
from collections.abc import Callable

import torch
from torch import Tensor

__all__ = ["forward_jacobian", "newton_inverse"]


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


def forward_jacobian(f: Callable[[Tensor], Tensor], x: Tensor, n: int) -> Tensor:
    """The derivatives of ``f`` along each of the ``n`` entries of ``x``'s last axis, stacked last:
    ``(..., n)`` for outputs ``(...)``, by ``torch.func.jvp``: one thread's at a time, since
    torch's forward-mode levels are one stack per process (two threads' at once break each
    other's); a compiled graph's tracing takes no lock."""
    if torch.compiler.is_compiling():
        return _jvp_columns(f, x, n)
    with _FORWARD_AD:
        return _jvp_columns(f, x, n)


_FORWARD_AD = threading.RLock()  # a map whose φ takes a forward Jacobian of its own nests


def _jvp_columns(f: Callable[[Tensor], Tensor], x: Tensor, n: int) -> Tensor:
    eye = torch.eye(n, dtype=x.dtype, device=x.device)
    cols = [torch.func.jvp(f, (x,), (eye[k].expand_as(x),))[1] for k in range(n)]
    return torch.stack(cols, -1)
