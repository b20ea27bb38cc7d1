"""Grid layouts: any layout given as a control grid, bilinear inside each control cell.

A [`GridLayout`][] maps the uniform ``(g_h + 1) × (g_w + 1)`` control grid of S onto given
control points and interpolates bilinearly inside each control cell. Restricted to a line
parallel to an axis, a bilinear map is affine, so the image of a uniform pixel edge is a
polyline with a vertex where it crosses a control line: the pixel mesh is exact, with no
tolerance. Border points stay on the border and the four corners are fixed.

A bilinear cell is one-to-one exactly when its corner quadrilateral is strictly convex and
positively oriented: ``det J`` is affine in the cell's local coordinates, so it is positive
everywhere once it is positive at the four corners, where it is the cross product of the two
edges meeting there. With the border fixed, that makes the whole grid a bijection of S.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..checks import ArgumentError, check_choice, check_number, check_size
from ..coords import cell_index, pixels_to_sensor, uniform_corners
from .base import FoldoverReport, Layout, register_family
from .values import tensor_dtype

__all__ = ["GridLayout", "cell_corner_dets", "inverse_bilinear"]


def _cross(a: Tensor, b: Tensor) -> Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def cell_corner_dets(control: Tensor) -> Tensor:
    """``det J`` of the bilinear map at the four corners of every control cell, ``(g_h, g_w, 4)``
    (control points ``(..., g_h + 1, g_w + 1, 2)`` give ``(..., g_h, g_w, 4)``).

    In units of the uniform cell (1 for the uniform grid); the order is top-left, top-right,
    bottom-right, bottom-left. All positive exactly when no cell folds.
    """
    gh, gw = control.shape[-3] - 1, control.shape[-2] - 1
    a, b = control[..., :-1, :-1, :], control[..., :-1, 1:, :]
    c, d = control[..., 1:, 1:, :], control[..., 1:, :-1, :]
    dets = torch.stack(
        [_cross(b - a, d - a), _cross(c - b, a - b), _cross(d - c, b - c), _cross(a - d, c - d)], -1
    )
    return dets * (gh * gw / 4)


def inverse_bilinear(a: Tensor, b: Tensor, c: Tensor, d: Tensor, q: Tensor) -> Tensor:
    """Local coordinates ``(u, v)`` with ``q = bilerp(u, v)`` in the quadrilaterals ``a, b, c, d``.

    ``a, b, c, d`` (``(..., 2)``) are the corners at ``(u, v) = (0, 0), (1, 0), (1, 1), (0, 1)``.
    Eliminating ``u`` from ``q − a = u (e + v g) + v f`` (``e = b − a``, ``f = d − a``,
    ``g = a − b + c − d``) leaves ``(f × g) v² + (f × e − h × g) v − h × e = 0`` with
    ``h = q − a``; the root nearest ``[0, 1]`` is taken (cancellation-free form) and ``u`` follows
    by least squares. Points outside the quadrilateral get coordinates outside ``[0, 1]²``.
    """
    e, f, g, h = b - a, d - a, a - b + c - d, q - a
    k2 = _cross(f, g)
    k1 = _cross(f, e) - _cross(h, g)
    k0 = -_cross(h, e)
    disc = (k1 * k1 - 4 * k2 * k0).clamp_min(0)
    sq = torch.sqrt(disc)
    qq = -0.5 * (k1 + torch.where(k1 >= 0, sq, -sq))
    scale = k1.abs() + (e * e).sum(-1) + (f * f).sum(-1)
    linear = k2.abs() <= 1e-14 * scale
    one = torch.ones_like(k1)
    v_lin = -k0 / torch.where(k1 != 0, k1, one)
    r1 = qq / torch.where(k2 != 0, k2, one)
    r2 = k0 / torch.where(qq != 0, qq, one)
    dist1 = (r1 - r1.clamp(0, 1)).abs() + torch.where(k2 != 0, 0.0, math.inf)
    dist2 = (r2 - r2.clamp(0, 1)).abs() + torch.where(qq != 0, 0.0, math.inf)
    v = torch.where(linear, v_lin, torch.where(dist1 <= dist2, r1, r2))
    w = e + v[..., None] * g
    u = ((h - v[..., None] * f) * w).sum(-1) / (w * w).sum(-1).clamp_min(1e-300)
    return torch.stack([u, v], -1)


@register_family
class GridLayout(Layout):
    """A layout given by control points, bilinear in each control cell (see `layoutwarp.layouts.grid`).

    θ holds the free control coordinates: ``(x, y)`` of interior points and the coordinate
    along the border of border points (corners have none), in row-major order. Every pixel edge
    is straight between control lines, so the exact integrator is exact at any tolerance.

    A learnable grid could fold under a large optimiser step; [`guard_`][] (called by
    [`SensorLayer`][layoutwarp.sensor.SensorLayer] before every forward pass) undoes the part of a step that
    would bring any cell's corner determinant below ``min_det``, by halving the step from the
    last valid control points.

    Args:
        control: ``(g_h + 1, g_w + 1, 2)`` control points in sensor coordinates (``None``: the
            uniform grid of ``grid``). Border points must lie on the border (within 1e-9) and
            are snapped onto it; the corners must be the sensor's corners.
        grid: ``(g_h, g_w)`` control cells when ``control`` is ``None`` (default 4 x 4); with
            ``control``, its own (a different ``grid`` is refused).
        min_det: the smallest corner determinant (in units of the uniform cell) a learning step
            may produce; a grid given below it is kept but not made worse.
        bound: unused (accepted for [`make_layout`][layoutwarp.layouts.make_layout]).
        learn: as [`Layout`][].
        dtype: as [`Layout`][] (default: a tensor ``control``'s own floating dtype).

    Raises:
        ValueError: a malformed grid, or a folded one (naming the first bad cell).

    Examples:
        >>> ctrl = uniform_corners((2, 2)).clone()
        >>> ctrl[1, 1] = torch.tensor([0.3, -0.2], dtype=torch.float64)
        >>> layout = GridLayout(ctrl, dtype=torch.float64)
        >>> layout(torch.tensor([[0.0, 0.0]], dtype=torch.float64))
        tensor([[ 0.3000, -0.2000]], dtype=torch.float64)
    """

    family = "grid"
    num_params: int | None = None
    unbounded = True
    straight_edges = True

    def __init__(
        self,
        control: Tensor | Sequence | None = None,
        *,
        grid: Sequence[int] | None = None,
        min_det: float = 0.05,
        bound: float = 1.0,
        learn: bool = False,
        dtype: torch.dtype | None = None,
    ) -> None:
        if control is None:
            gh, gw = check_size((4, 4) if grid is None else grid, "grid")
            ctrl = uniform_corners((gh, gw))
        else:
            ctrl = torch.as_tensor(control, dtype=torch.float64).detach().cpu().clone()
            if ctrl.ndim != 3 or ctrl.shape[-1] != 2 or ctrl.shape[0] < 2 or ctrl.shape[1] < 2:
                raise ValueError(
                    f"control must have shape (gh + 1, gw + 1, 2) with gh, gw >= 1, got {tuple(ctrl.shape)}"
                )
            gh, gw = ctrl.shape[0] - 1, ctrl.shape[1] - 1
            if grid is not None and tuple(grid) != (gh, gw):
                raise ArgumentError(
                    "grid", f"grid {tuple(grid)} disagrees with the control points' grid {(gh, gw)}; give one"
                )
            ctrl = _snap_border(ctrl)
        self.grid = (gh, gw)
        self.min_det = check_number(min_det, "min_det", 0, 1, lo_open=True, hi_open=True)
        mask = torch.ones(gh + 1, gw + 1, 2, dtype=torch.bool)
        mask[:, [0, -1], 0] = False  # left and right columns keep x
        mask[[0, -1], :, 1] = False  # top and bottom rows keep y
        self.num_params = int(mask.sum())
        _raise_if_folded(ctrl)
        super().__init__(ctrl[mask], bound=bound, learn=learn, dtype=dtype or tensor_dtype(control))
        self.register_buffer("free", mask, persistent=False)
        # saved with ρ: a checkpoint taken after a step that folds the grid guards, once loaded,
        # as the layer that wrote it would
        self.register_buffer("last_valid", self.rho.detach().clone())

    # -- constructors ----------------------------------------------------------------
    @classmethod
    def from_layout(cls, layout: Layout, grid: Sequence[int], **kwargs: Any) -> GridLayout:
        """Sample any layout at the ``(g_h + 1) × (g_w + 1)`` uniform control points.

        Exact (the same φ) for separable layouts that are affine between control lines, e.g. a
        piecewise-linear [`SplineLayout`][layoutwarp.layouts.spline.SplineLayout] whose knots lie
        on the grid; for
        others the pixel corners on control points agree and the edges between are chords.
        """
        gh, gw = check_size(grid, "grid")
        with torch.no_grad():
            ctrl = layout.phi(uniform_corners((gh, gw)), layout.theta_as(torch.float64).detach())
        return cls(ctrl, **kwargs)

    @classmethod
    def from_maps(
        cls,
        map_x: Tensor | np.ndarray,
        map_y: Tensor | np.ndarray,
        src_size: Sequence[int],
        *,
        points: str = "centers",
        **kwargs: Any,
    ) -> GridLayout:
        """A grid layout from OpenCV ``remap`` maps (source pixel centres at integers).

        Args:
            map_x: ``(m, n)`` x map into a source image of ``src_size = (H, W)``.
            map_y: the y map, of the same shape.
            points: ``"corners"``: the maps hold the ``(g_h + 1) × (g_w + 1)`` pixel corners,
                used as control points (border points must lie on the source border
                ``−0.5`` / ``W − 0.5`` within 1e-3 px); ``"centers"``: they hold the ``g_h × g_w``
                pixel centres (e.g. [`forward_maps`][layoutwarp.maps.forward_maps]); each interior corner is
                the mean of its four neighbouring centres and each border corner the mean of its
                two, moved onto the border (an approximation of the layout the centres came
                from, exact for affine cells).
            **kwargs: passed to the constructor (``learn``, ``dtype``, ``min_det``).
        """
        check_choice(points, ("centers", "corners"), "points")
        hs, ws = check_size(src_size, "src_size")
        mx = torch.as_tensor(np.asarray(map_x), dtype=torch.float64)
        my = torch.as_tensor(np.asarray(map_y), dtype=torch.float64)
        if mx.ndim != 2 or mx.shape != my.shape:
            raise ValueError(
                f"map_x and map_y must be 2-D of the same shape, got {tuple(mx.shape)} and {tuple(my.shape)}"
            )
        pts = pixels_to_sensor(torch.stack([mx, my], -1), (hs, ws), centered=True)
        if points == "corners":
            tol = 2e-3 / min(hs, ws)
            return cls(_snap_border(pts, tol=tol), **kwargs)
        pad = torch.nn.functional.pad(pts.permute(2, 0, 1)[None], (1, 1, 1, 1), mode="replicate")[0]
        corners = (pad[:, :-1, :-1] + pad[:, :-1, 1:] + pad[:, 1:, :-1] + pad[:, 1:, 1:]).permute(1, 2, 0) / 4
        corners[:, 0, 0], corners[:, -1, 0] = -1.0, 1.0
        corners[0, :, 1], corners[-1, :, 1] = -1.0, 1.0
        return cls(corners, **kwargs)

    # -- parameters ------------------------------------------------------------------
    def control_points(self, theta: Tensor | None = None) -> Tensor:
        """The control points ``(g_h + 1, g_w + 1, 2)`` for θ (default: the layout's own)."""
        th = self.resolve_theta(theta)
        gh, gw = self.grid
        base = uniform_corners((gh, gw), dtype=th.dtype, device=th.device)
        return base.masked_scatter(self.free.to(th.device), th)

    def check_foldover(self, n: int = 0) -> FoldoverReport:
        """Exact fold check: ``det J`` at every control cell's corners (``n`` is ignored).

        ``worst_point`` is the uniform position of the worst corner and ``cell`` the first
        folded cell ``(row, col)`` in row-major order (``None`` when none folds).
        """
        with torch.no_grad():
            ctrl = self.control_points(self.theta_as(torch.float64)).detach().cpu()
        return _foldover_report(ctrl)

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        """As [`Layout`][layoutwarp.layouts.base.Layout]'s; a state written before grids saved
        their last valid control points keeps this layout's."""
        state_dict.setdefault(prefix + "last_valid", self.last_valid.detach().clone())
        theta = state_dict.get(prefix + "fixed_theta")
        if self._keeps_theta and isinstance(theta, Tensor) and theta.shape == self.fixed_theta.shape:
            _raise_if_folded(self.control_points(theta.to(torch.float64)))  # as the constructor does
        super()._load_from_state_dict(state_dict, prefix, *args)

    @torch.no_grad()
    def guard_(self) -> Tensor:
        """Undo the part of the last step that folds the grid (see [`Layout.guard_`][]).

        The current control points are kept if every corner determinant is at least
        ``min(min_det, the last valid grid's)``; otherwise the step from the last valid points is
        halved until it is (at most 39 times; then the last valid points are restored). All 40
        trials are weighed at once, in torch operations: no value is read on the host.
        """
        cur, last = self.rho.detach(), self.last_valid
        halves = 0.5 ** torch.arange(40, dtype=cur.dtype, device=cur.device)  # the step itself first
        trials = torch.cat([last + (cur - last) * halves[:, None], last[None]])  # the last: restore
        dets = cell_corner_dets(self._batch_control_points(trials).double()).flatten(1).amin(1)
        level = torch.clamp(dets[-1], max=self.min_det)  # min(min_det, the last valid grid's)
        ok = dets >= level
        ok[-1] = True
        first = torch.argmax(ok.to(torch.int8)).reshape(1)  # the first trial that does not fold
        chosen = trials.index_select(0, first)[0]
        self.rho.copy_(chosen)
        self.last_valid.copy_(chosen)
        return first[0] != 0

    def _batch_control_points(self, thetas: Tensor) -> Tensor:
        """[`control_points`][] of each θ of ``thetas`` ``(K, P)``: ``(K, g_h + 1, g_w + 1, 2)``."""
        gh, gw = self.grid
        base = uniform_corners((gh, gw), dtype=thetas.dtype, device=thetas.device)
        k = thetas.shape[0]
        mask = self.free.to(thetas.device).expand(k, *self.free.shape)
        return base.expand(k, *base.shape).masked_scatter(mask, thetas)

    # -- the map ---------------------------------------------------------------------
    def _corners(self, p: Tensor, theta: Tensor) -> tuple[Tensor, ...]:
        dtype = torch.promote_types(p.dtype, theta.dtype)
        ctrl = self.control_points(theta.to(device=p.device, dtype=dtype))
        gh, gw = self.grid
        p = p.to(dtype)
        j, u = cell_index(p[..., 0], gw)
        i, v = cell_index(p[..., 1], gh)
        return p, u[..., None], v[..., None], *self._cell_quads(ctrl.reshape(-1, 2), i, j)

    def phi(self, p: Tensor, theta: Tensor) -> Tensor:
        p, u, v, a, b, c, d = self._corners(p, theta)
        out = (1 - v) * ((1 - u) * a + u * b) + v * ((1 - u) * d + u * c)
        inside = (p.abs() <= 1).all(-1, keepdim=True)
        return torch.where(inside, out, p)

    def phi_jacobian(self, p: Tensor, theta: Tensor) -> Tensor:
        p, u, v, a, b, c, d = self._corners(p, theta)
        gh, gw = self.grid
        dx = ((1 - v) * (b - a) + v * (c - d)) * (gw / 2)
        dy = ((1 - u) * (d - a) + u * (c - b)) * (gh / 2)
        jac = torch.stack([dx, dy], -1)
        inside = (p.abs() <= 1).all(-1)[..., None, None]
        eye = torch.eye(2, dtype=jac.dtype, device=jac.device).expand_as(jac)
        return torch.where(inside, jac, eye)

    def phi_dtheta(self, p: Tensor, theta: Tensor) -> Tensor:
        """``∂φ_i/∂θ_j``, ``(..., 2, P)``: the bilinear weight of θ_j's control point, on its axis."""
        dtype = torch.promote_types(p.dtype, theta.dtype)
        if theta.numel() == 0:  # a 1x1 grid: only corners, nothing to move
            return p.to(dtype).new_zeros(*p.shape, 0)
        gh, gw = self.grid
        index = torch.full((gh + 1, gw + 1, 2), -1, dtype=torch.long, device=p.device)
        free = self.free.to(p.device)
        index[free] = torch.arange(int(free.sum()), device=p.device)
        pp = p.to(dtype)
        j, u = cell_index(pp[..., 0], gw)
        i, v = cell_index(pp[..., 1], gh)
        inside = (pp.abs() <= 1).all(-1)
        out = pp.new_zeros(*pp.shape[:-1], 2, theta.numel())
        for di, dj, wt in (
            (0, 0, (1 - u) * (1 - v)),
            (0, 1, u * (1 - v)),
            (1, 0, (1 - u) * v),
            (1, 1, u * v),
        ):
            idx = index[i + di, j + dj]  # (..., 2)
            val = torch.where((idx >= 0) & inside[..., None], wt[..., None], 0.0)
            out.scatter_add_(-1, idx.clamp_min(0)[..., None], val[..., None])
        return out

    def phi_inverse(self, q: Tensor, theta: Tensor) -> Tensor:
        """Exact inverse: walk to the control cell that contains ``q`` (the sides of the current
        cell's quadrilateral say which way to step), search the cells around the points the
        walk leaves unresolved, invert the cell's bilinear map and polish with one Newton step."""
        gh, gw = self.grid
        with torch.no_grad():
            ctrl = self.control_points(theta.detach().to(device=q.device, dtype=torch.float64))
            q64 = q.detach().double().reshape(-1, 2)
            inside = (q64.abs() <= 1).all(-1)
            qc = q64.clamp(-1, 1)
            j, _ = cell_index(qc[:, 0], gw)
            i, _ = cell_index(qc[:, 1], gh)
            flat = ctrl.reshape(-1, 2)
            eps = 1e-12
            walking = torch.arange(qc.shape[0], device=q.device)  # points whose cell still changes
            before = torch.full_like(i, -1)  # the cell each point came from (row-major index)
            for _ in range(gh + gw + 2):
                iw, jw = i[walking], j[walking]
                top, right, bottom, left = self._sides(flat, iw, jw, qc[walking])
                dj = (right < -eps).long() - (left < -eps).long()
                di = (bottom < -eps).long() - (top < -eps).long()
                nj, ni = (jw + dj).clamp(0, gw - 1), (iw + di).clamp(0, gh - 1)
                back = ni * gw + nj == before[walking]  # stepping back and forth: left to the search
                moved = ((nj != jw) | (ni != iw)) & ~back
                before[walking] = iw * gw + jw
                i[walking], j[walking] = torch.where(back, iw, ni), torch.where(back, jw, nj)
                walking = walking[moved]
                if walking.numel() == 0:
                    break
            uv = self._local(flat, i, j, qc)
            lost = ((uv < -1e-9) | (uv > 1 + 1e-9)).any(-1)
            if bool(lost.any()):
                i[lost], j[lost] = self._search(flat, qc[lost])
                uv = self._local(flat, i, j, qc)
            uv = uv.clamp(0, 1)
            p = torch.stack([(j + uv[:, 0]) * (2 / gw) - 1, (i + uv[:, 1]) * (2 / gh) - 1], -1)
            th64 = theta.detach().double().to(q.device)
            jac = self.phi_jacobian(p, th64)
            p = p - torch.linalg.solve(jac, (self.phi(p, th64) - qc)[..., None])[..., 0]
            p = torch.where(inside[:, None], p.clamp(-1, 1), q64).reshape(q.shape)
        p = p.to(q.dtype)
        if not (q.requires_grad or theta.requires_grad):
            return p
        jac = self.phi_jacobian(p.detach(), theta.detach()).to(q.dtype)
        r = self.phi(p, theta) - q
        return p - torch.linalg.solve(jac, r[..., None])[..., 0]

    def _sides(self, flat: Tensor, i: Tensor, j: Tensor, q: Tensor) -> tuple[Tensor, ...]:
        """Signed distances of ``q`` from the lines through the top, right, bottom and left
        sides of cells ``(i, j)``, positive on the cell's side. A cell's image is the convex
        quadrilateral of its control points (no cell folds), so ``q`` is in it when all four
        are ``>= 0`` and the negative ones say which neighbour to step to."""
        corners = self._cell_quads(flat, i, j)
        out = []
        for s in range(4):
            a, b = corners[s], corners[(s + 1) % 4]
            e = b - a
            out.append(_cross(e, q - a) / torch.sqrt(e[:, 0] ** 2 + e[:, 1] ** 2).clamp_min(1e-300))
        return tuple(out)

    def _cell_quads(self, flat: Tensor, i: Tensor, j: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Control points of cells ``(i, j)``: top-left, top-right, bottom-right, bottom-left."""
        gw1 = self.grid[1] + 1
        k = i * gw1 + j
        return flat[k], flat[k + 1], flat[k + gw1 + 1], flat[k + gw1]

    def _local(self, flat: Tensor, i: Tensor, j: Tensor, q: Tensor) -> Tensor:
        return inverse_bilinear(*self._cell_quads(flat, i, j), q)

    def _search(self, flat: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
        """The cell whose quadrilateral contains each point, or comes closest to it in local
        coordinates (the first such cell in row-major order). A cell's image is the
        quadrilateral of its four control points, so only cells whose bounding box holds the
        point are tried; a point outside every box (only by rounding) tries them all."""
        gh, gw = self.grid
        cells = torch.arange(gh * gw, device=q.device)
        quad = torch.stack(self._cell_quads(flat, cells // gw, cells % gw), 1)  # (cells, 4, 2)
        lo, hi = quad.amin(1) - 1e-9, quad.amax(1) + 1e-9  # (cells, 2)
        best = torch.zeros(q.shape[0], dtype=torch.long, device=q.device)
        for start in range(0, q.shape[0], 8192):
            qq = q[start : start + 8192]
            boxed = ((qq >= lo[:, None]) & (qq <= hi[:, None])).all(-1)  # (cells, points)
            boxed[:, ~boxed.any(0)] = True
            cell, point = torch.nonzero(boxed, as_tuple=True)  # cell-major: row-major cells first
            uv = inverse_bilinear(*quad[cell].unbind(1), qq[point])
            out = (uv - uv.clamp(0, 1)).abs().amax(-1)  # 0 inside the cell
            order = torch.argsort(out, stable=True)
            order = order[torch.argsort(point[order], stable=True)]  # by point, then out, then cell
            _, counts = torch.unique_consecutive(point[order], return_counts=True)
            best[start : start + qq.shape[0]] = cell[order[torch.cumsum(counts, 0) - counts]]
        return best // gw, best % gw

    def edge_breakpoints(self, a: Tensor, b: Tensor, theta: Tensor | None = None) -> Tensor:
        """Where the segment crosses a control line (a kink of the piecewise-bilinear φ; the
        control lines do not move with θ)."""
        gh, gw = self.grid
        d = b - a
        cols = [((2 * k - gw) / gw - a[:, 0]) / d[:, 0] for k in range(1, gw)]
        rows = [((2 * k - gh) / gh - a[:, 1]) / d[:, 1] for k in range(1, gh)]
        if not cols and not rows:
            return a.new_zeros(a.shape[0], 0)
        t = torch.stack(cols + rows, -1)
        return torch.where(torch.isfinite(t) & (t > 0) & (t < 1), t, torch.full_like(t, float("nan")))

    # -- files -----------------------------------------------------------------------
    def theta_keys(self) -> tuple[str, ...]:
        return ("control",)

    def to_config(self) -> dict[str, Any]:
        ctrl = self.control_points(self.theta_as(torch.float64)).detach().cpu()
        return {"grid": list(self.grid), "control": ctrl.tolist(), "min_det": self.min_det}

    @classmethod
    def from_config(
        cls, config: dict[str, Any], *, learn: bool = False, dtype: torch.dtype | None = None
    ) -> Layout:
        control = config.get("control")
        if control is None:
            raise ValueError("'control' is missing: the layout's description must give it")
        try:
            ctrl = torch.tensor(control, dtype=torch.float64)
        except (TypeError, ValueError):
            raise ValueError("'control' must be a nested list of shape (gh + 1, gw + 1, 2)") from None
        return cls(ctrl, min_det=float(config.get("min_det", 0.05)), learn=learn, dtype=dtype)

    def extra_repr(self) -> str:
        return f"grid={self.grid}, learn={self.learnable}"


def _snap_border(ctrl: Tensor, tol: float = 1e-9) -> Tensor:
    """Move border control points exactly onto the border; refuse ones farther than ``tol``."""
    ctrl = ctrl.clone()
    if not bool(torch.isfinite(ctrl).all()):
        raise ValueError("control points must be finite")
    for name, sl, axis, value in (
        ("left column", (slice(None), 0), 0, -1.0),
        ("right column", (slice(None), -1), 0, 1.0),
        ("top row", (0, slice(None)), 1, -1.0),
        ("bottom row", (-1, slice(None)), 1, 1.0),
    ):
        off = (ctrl[sl][:, axis] - value).abs()
        if bool((off > tol).any()):
            k = int(off.argmax())
            raise ValueError(
                f"control points of the {name} must have {'xy'[axis]} = {value:+g} (the sensor border); "
                f"point {k} is {float(off[k]):.3g} away"
            )
        ctrl[(*sl, axis)] = value
    return ctrl


def _min_det(ctrl: Tensor) -> float:
    return float(cell_corner_dets(ctrl.double()).min())


def _foldover_report(ctrl: Tensor) -> FoldoverReport:
    dets = cell_corner_dets(ctrl)
    gh, gw = dets.shape[:2]
    k = int(torch.argmin(dets))
    ci, rest = divmod(k, gw * 4)
    cj, corner = divmod(rest, 4)
    ui, uj = ci + (corner in (2, 3)), cj + (corner in (1, 2))
    bad = (dets <= 0).any(-1)
    first = torch.nonzero(bad)
    return FoldoverReport(
        min_det=float(dets.min()),
        num_nonpositive=int(bad.sum()),
        worst_point=((2 * uj - gw) / gw, (2 * ui - gh) / gh),
        grid=0,
        cell=(int(first[0, 0]), int(first[0, 1])) if first.numel() else None,
    )


def _raise_if_folded(ctrl: Tensor) -> None:
    report = _foldover_report(ctrl)
    if not report.ok:
        i, j = report.cell or (0, 0)
        raise ValueError(
            f"control grid folds: cell (row {i}, col {j}) is not a convex, positively oriented "
            f"quadrilateral ({report.num_nonpositive} such cells; smallest corner det J {report.min_det:.3g})"
        )
