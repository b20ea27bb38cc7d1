"""Test images of the benchmark: a real photo, blurred noise, and a scene with known pixel means."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from ..integrators import integrate_exact
from ..layouts import Layout
from ..mesh import MeshTopology, pixel_mesh, smooth_pieces
from .data import samples_dir

__all__ = ["SineScene", "blurred_noise", "load_photo"]


def blurred_noise(h: int, w: int, c: int = 3, sigma: float = 2.0, seed: int = 0) -> Tensor:
    """A ``(1, c, h, w)`` float32 image of Gaussian-blurred uniform noise in [0, 1]."""
    rng = np.random.default_rng(seed)
    img = rng.random((h, w, c), dtype=np.float32)
    img = cv2.GaussianBlur(img, (0, 0), sigma)
    img = (img - img.min()) / (img.max() - img.min())
    return torch.from_numpy(np.ascontiguousarray(img.reshape(h, w, c).transpose(2, 0, 1)))[None]


def load_photo(h: int, w: int, path: str | Path | None = None) -> Tensor | None:
    """A real photo (Kodak ``kodim20``) resized to ``(h, w)`` with INTER_CUBIC, ``(1, 3, h, w)`` in [0, 1].

    ``path`` defaults to the bundled samples' copy; returns ``None`` when that cannot be read.
    """
    for p in [Path(path)] if path else [samples_dir() / "photos" / "kodim20.png"]:
        bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if bgr is not None:
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255
            rgb = np.clip(cv2.resize(rgb, (w, h), interpolation=cv2.INTER_CUBIC), 0, 1)
            return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))[None]
    if path:
        raise FileNotFoundError(f"cannot read image {path}")
    return None


@dataclass(frozen=True)
class SineScene:
    """A synthetic radiance with known pixel integrals, one frequency pair per channel.

    ``f_c(x, y) = 0.5 + 0.4 sin(a_c x + p_c) sin(b_c y + q_c)`` in sensor coordinates
    ``[-1, 1]²``. [`image`][] gives the exact cell averages of ``f`` on a source grid (so a
    box integrator sees the best pixel image of the scene); [`pixel_means`][] gives the
    exact mean of ``f`` over every pixel of a layout, by Green's theorem along the true
    (curved) edges with Gauss–Legendre quadrature between the kinks of φ (and the axes).
    """

    a: tuple[float, ...]
    b: tuple[float, ...]
    p: tuple[float, ...]
    q: tuple[float, ...]

    @classmethod
    def random(cls, channels: int = 3, cycles: tuple[float, float] = (6.0, 30.0), seed: int = 0) -> SineScene:
        """Frequencies of ``cycles`` periods across ``[-1, 1]`` and random phases."""
        rng = np.random.default_rng(seed)
        a, b = (tuple(float(v) for v in np.pi * rng.uniform(*cycles, channels)) for _ in range(2))
        p, q = (tuple(float(v) for v in rng.uniform(0, 2 * np.pi, channels)) for _ in range(2))
        return cls(a, b, p, q)

    def _vec(self, name: str) -> Tensor:
        return torch.tensor(getattr(self, name), dtype=torch.float64)

    def image(self, h: int, w: int) -> Tensor:
        """Cell averages on an ``h × w`` source grid, ``(1, C, h, w)`` float64."""

        def avg(k: Tensor, ph: Tensor, n: int) -> Tensor:  # (C, n) mean of sin(k s + ph) per cell
            edges = torch.linspace(-1, 1, n + 1, dtype=torch.float64)
            c = torch.cos(k[:, None] * edges + ph[:, None])
            return (c[:, :-1] - c[:, 1:]) / (k[:, None] * (2 / n))

        sx, sy = avg(self._vec("a"), self._vec("p"), w), avg(self._vec("b"), self._vec("q"), h)
        return (0.5 + 0.4 * sy[:, :, None] * sx[:, None, :])[None]

    def pixel_means(self, layout: Layout, size: tuple[int, int], nodes: int = 16) -> Tensor:
        """Exact mean of ``f`` over every pixel of ``layout``, ``(C, H, W)`` float64."""
        theta = layout.theta_as(torch.float64).detach().cpu()
        topo = MeshTopology(size)
        a, b = topo.edge_ends()
        d = b - a
        axes = -a / torch.where(d == 0, torch.ones_like(d), d)  # where the edge crosses x = 0 or y = 0:
        axes = torch.where(d == 0, torch.nan, axes)  # layouts built on |x|, |y| bend there
        edge, t0, t1 = smooth_pieces(layout, a, b, extra=axes)
        x, wq = np.polynomial.legendre.leggauss(nodes)
        x, wq = torch.from_numpy((x + 1) / 2), torch.from_numpy(wq / 2)
        chord = (layout.phi(b, theta) - layout.phi(a, theta)).norm(dim=-1).max()
        panels = max(2, math.ceil(float(chord) * max(self.a + self.b)))
        s = (torch.arange(panels, dtype=torch.float64)[:, None] + x) / panels  # (panels, nodes)
        ak, bk, ph = self._vec("a"), self._vec("b"), (self._vec("p"), self._vec("q"))
        out = torch.zeros(len(self.a) + 1, topo.num_edges, dtype=torch.float64)
        for lo in range(0, edge.numel(), 8192):
            sl = slice(lo, lo + 8192)
            e, p0, p1 = edge[sl], t0[sl], t1[sl]  # smooth pieces between kinks
            tt = p0[:, None, None] + (p1 - p0)[:, None, None] * s  # (pieces, panels, nodes)
            dd = d[e][:, None, None, :]
            u = a[e][:, None, None, :] + tt[..., None] * dd
            qv = layout.phi(u, theta)
            dy = (layout.phi_jacobian(u, theta)[..., 1, :] * dd).sum(-1)  # dφ_y/dt
            weight = (p1 - p0)[:, None, None] * wq / panels * dy
            px = [qv[..., 0]] + [
                0.5 * qv[..., 0]
                - 0.4
                / ak[c]
                * torch.cos(ak[c] * qv[..., 0] + ph[0][c])
                * torch.sin(bk[c] * qv[..., 1] + ph[1][c])
                for c in range(len(self.a))
            ]  # P with ∂P/∂x = integrand: x for the area, then one per channel
            out.index_add_(1, e, torch.stack([(pc * weight).flatten(1).sum(1) for pc in px]))
        pix = topo.combine(out)
        return pix[1:] / pix[0]


def _exact64(img64: Tensor, layout: Layout, size, subdivisions: int, theta: Tensor) -> Tensor:
    """Float64 exact forward with θ; curved edges on a fixed-subdivision mesh (smooth in θ, for
    finite differences), straight-edged layouts on their exact mesh."""
    if layout.straight_edges:
        mesh = pixel_mesh(layout, size, theta=theta)
    else:
        mesh = pixel_mesh(layout, size, subdivisions=subdivisions, theta=theta)
    return integrate_exact(img64.flatten(0, 1), layout, size, mesh=mesh)


def fd_theta_gradient(
    img64: Tensor,
    layout: Layout,
    theta: Sequence[float] | Tensor,
    size,
    weights: Tensor,
    h: float = 1e-6,
    subdiv: int = 64,
    directions: Tensor | None = None,
) -> Tensor:
    """Central finite differences of ``Σ weights · exact(θ)`` in float64, shape ``(P,)``; with
    ``directions`` ``(K, P)``, the derivatives along each of them instead, ``(K,)`` (a gradient
    ``g`` checked as ``directions @ g``: two evaluations a direction, not two an entry).

    Curved edges use ``subdiv`` equal parameter steps (no adaptive choice), so the forward
    is smooth in θ and the differences are not polluted by changing subdivisions. The box
    image makes the loss only piecewise smooth in θ (its derivative jumps whenever an edge
    crosses a source row or column), so the step is small: edges move by about
    ``1e-6 · source size`` pixels and few of them cross a boundary inside the window.
    """
    th = torch.as_tensor(theta, dtype=torch.float64)

    def loss(t: Tensor) -> float:
        with torch.no_grad():
            return float((_exact64(img64, layout, size, subdiv, t) * weights).sum())

    steps = torch.eye(th.numel(), dtype=torch.float64) if directions is None else directions.double()
    grads = [(loss(th + h * step) - loss(th - h * step)) / (2 * h) for step in steps]
    return torch.tensor(grads, dtype=torch.float64)
