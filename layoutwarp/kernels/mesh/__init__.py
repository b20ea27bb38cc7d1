"""Compiled pixel meshes of the built-in curved families, with every vertex's θ-derivative.

[`pixel_mesh`][layoutwarp.mesh.pixel_mesh] builds a learnable layout's mesh in some thousand torch
operations (cut every edge at φ's kinks, bound each piece's sagitta, count its segments, place
the vertices, then autograd back through all of it): on a CPU it costs more than the integral,
on a GPU each operation is a kernel launch. For the curvilinear families (``curv`` and
``fovea``, about any centre, and ``elliptic``) this module does the same in one compiled pass:
φ, its Jacobian and ``∂φ/∂θ`` in closed form as numba functions without a branch on the point
(so a chunk's sample points and new vertices are mapped in one loop that runs in SIMD lanes,
[`phi_run`][layoutwarp.kernels.mesh.phi.phi_run]), the kinks of every edge (with their
θ-derivatives where they move with a learned centre), the count stage and the vertex
placement, each step in the order and arithmetic of [`pixel_mesh`][layoutwarp.mesh.pixel_mesh],
so the two agree to rounding (the same
segment counts, vertices within a few ulp). Instead of an
autograd graph it returns ``∂v/∂θ`` of every vertex ``v``: for a vertex at parameter
``t = lo + (hi − lo) k/m`` of a smooth piece of the uniform edge ``a + t (b − a)``,
``dv/dθ = ∂φ/∂θ + J (b − a) (∂lo/∂θ (1 − k/m) + ∂hi/∂θ k/m)``, the second term where the piece's
ends (kinks) move with θ. For a training step on the CPU, [`mesh_integrals`][] places the
vertices and integrates over them chunk by chunk, carrying ``∂v/∂θ`` to the θ-Jacobian of every
edge integral, so θ's gradient is one contraction with the edge gradient.
On a CUDA device [`build_mesh_device`][] builds the same mesh there, one GPU thread per
corner, edge or vertex running the same scalar functions.

[`mesh_spec`][] says whether a layout has a compiled form: its class declares one
([`Layout.kernel_map`][layoutwarp.layouts.base.Layout.kernel_map]; a subclass may change φ, so it keeps
the torch path). The kernels import no layout class.

One module a step: [`spec`][layoutwarp.kernels.mesh.spec] (what the mesh knows of a layout),
[`phi`][layoutwarp.kernels.mesh.phi] (the maps and the kinks), [`build`][layoutwarp.kernels.mesh.build]
(the mesh on the CPU), [`integrals`][layoutwarp.kernels.mesh.integrals] (a step's integrals and
gradient), [`cuda`][layoutwarp.kernels.mesh.cuda] (the CUDA kernels) and
[`device`][layoutwarp.kernels.mesh.device] (a device mesh's memory and launches).
"""

from __future__ import annotations

from .build import build_mesh
from .cuda import CAPPED, CUDA_KERNELS, PIECES, SEGMENTS
from .device import (
    MESH_ROOMS,
    DeviceMesh,
    MeshRoom,
    build_mesh_device,
    device_means,
    device_status,
    device_theta_gradient,
)
from .integrals import edge_gradient, mesh_integrals, pixel_vertices, theta_gradient
from .spec import CURV, ELLIPTIC, CompiledMesh, MeshSpec, mesh_spec

__all__ = [
    "CAPPED",
    "CUDA_KERNELS",
    "CURV",
    "ELLIPTIC",
    "MESH_ROOMS",
    "PIECES",
    "SEGMENTS",
    "CompiledMesh",
    "DeviceMesh",
    "MeshRoom",
    "MeshSpec",
    "build_mesh",
    "build_mesh_device",
    "device_means",
    "device_status",
    "device_theta_gradient",
    "edge_gradient",
    "mesh_integrals",
    "mesh_spec",
    "pixel_vertices",
    "theta_gradient",
]
