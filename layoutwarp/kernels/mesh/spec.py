"""What the compiled mesh knows of a layout besides θ ([`MeshSpec`][], [`mesh_spec`][]: the
map its class declares), and the mesh it returns ([`CompiledMesh`][])."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...caches import ObjectMemo, version_of
from ...mesh import PixelMesh
from ..base import available

if TYPE_CHECKING:
    from ...layouts import Layout

#: Family codes of the compiled maps.
CURV, ELLIPTIC = 0, 1


@dataclass(frozen=True)
class MeshSpec:
    """What the compiled mesh needs to know of a layout besides θ.

    Attributes:
        kind: [`CURV`][] (φ_curv about ``center``) or [`ELLIPTIC`][].
        center: the fixed centre ``(c_x, c_y)``; a learned one is θ's last two entries.
        centred: φ is the centred map itself (fixed centre at the origin): no affine step.
        nparams: θ's length ``P`` (2, or 4 with a learned centre).
    """

    kind: int
    center: tuple[float, float]
    centred: bool
    nparams: int


#: Each fixed centre tensor's values as last read ([`layoutwarp.caches`][]).
CENTRES = ObjectMemo("fixed centres")


def _centre_values(centre: torch.Tensor) -> tuple[float, float]:
    """A fixed centre's two values, read from its device once per tensor and version (a training
    step on a GPU then waits for no copy of it; writing to the tensor in place bumps its
    version)."""
    return CENTRES.get(centre, (version_of(centre),), lambda: tuple(centre.detach().double().cpu().tolist()))


def mesh_spec(layout: Layout) -> MeshSpec | None:
    """The compiled form of ``layout`` (its class's
    [`kernel_map`][layoutwarp.layouts.base.Layout.kernel_map] with its centre), or ``None`` where
    it has none (or numba is missing)."""
    if not available():
        return None
    kind = vars(type(layout)).get("kernel_map")  # declared by the layout's own class
    if kind == "curv":
        c = _centre_values(layout.fixed_center)
        return MeshSpec(CURV, c, layout.centred, int(layout.num_params or 0))
    if kind == "elliptic":
        return MeshSpec(ELLIPTIC, (0.0, 0.0), True, 2)
    return None


@dataclass
class CompiledMesh:
    """A pixel mesh as [`build_mesh`][] returns it: the arrays of a
    [`PixelMesh`][] (float64 / int64, CPU) plus ``dverts`` ``(V, 2, P)``, each
    vertex's derivative in θ, and ``counts``, the segments of every smooth piece (what
    ``pixel_mesh(..., subdivisions=counts)`` takes to rebuild the same mesh)."""

    size: tuple[int, int]
    vertices: np.ndarray
    dverts: np.ndarray
    seg_start: np.ndarray
    seg_end: np.ndarray
    seg_edge: np.ndarray
    edge_offsets: np.ndarray
    counts: np.ndarray

    def pixel_mesh(self, device: torch.device | str = "cpu") -> PixelMesh:
        """The [`PixelMesh`][] of these arrays (vertices without gradient)."""

        def t(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(a).to(device)

        arrays = (self.vertices, self.seg_start, self.seg_end, self.seg_edge, self.edge_offsets)
        return PixelMesh(self.size, *(t(a) for a in arrays))
