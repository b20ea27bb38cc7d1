"""A device mesh's memory and its launches: the rooms kept per layout kind and size
([`MeshRoom`][]), [`build_mesh_device`][], the means and θ-gradient from it, and
[`device_status`][] (what a device step found, read at once)."""

from __future__ import annotations

import functools
import math
import threading
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from ...mesh import MAX_SUBDIV, PixelMesh, warn_if_capped
from ..device import CHECKS, Stamps, cuda_launch, device_checks, host_mapped, stream_of
from ..prefix import BLOCK
from .build import mesh_topology
from .cuda import (
    CAPPED,
    CUDA_KERNELS,
    OVERFLOW,
    PIECES,
    SEGMENTS,
    cuda_edge_gradient,
    cuda_pixel_means,
    cuda_theta_gradient,
)
from .spec import MeshSpec

if TYPE_CHECKING:
    pass

#: How much more room than it needed a device mesh's kind gets (see [`MeshRoom`][]).
HEADROOM = 1.25


@dataclass
class MeshRoom:
    """The room the device meshes of one learnable layout, sensor size and tolerance are built
    in ([`build_mesh_device`][]): their pieces and segments, sized by the first mesh (the one
    time the host reads how many it needs) with [`HEADROOM`][], and grown when a later mesh came
    within ``1 / HEADROOM`` of them. The kernels write what a mesh needed straight into
    ``status``, page-locked host memory mapped into the device's address space
    ([`host_mapped`][layoutwarp.kernels.device.host_mapped]: no copy launched, nothing waited
    for; a CUDA graph's replays write it too), which the host reads whenever it builds the next
    mesh. So a step allocates without waiting for the device, and a captured step keeps its
    buffers. A mesh that outgrows its room is built with straight chords instead (valid, but
    coarser than the tolerance) and stamps the status: [`device_status`][] reads it at once.
    Its overflows are [`Stamps`][layoutwarp.kernels.device.Stamps]: a captured graph's replays
    all write the stamp of the capture, which [`device_status`][] tells of each time and
    [`look`][layoutwarp.kernels.mesh.MeshRoom.look] the first time."""

    status: np.ndarray  # the slots PIECES, SEGMENTS, OVERFLOW, CAPPED, int64, written by the kernels
    pieces: int = 0
    segments: int = 0
    overflows: Stamps = field(init=False)  # the stamps in slot OVERFLOW

    def __post_init__(self) -> None:
        self.overflows = Stamps(self.status, OVERFLOW)

    def ahead(self, need: int, least: int) -> int:
        """Room for ``need`` items with headroom, at least ``least``."""
        return max(least, math.ceil(need * HEADROOM) + 64)

    def look(self, tell: bool = True) -> dict[str, int | bool]:
        """Take in what the kernels wrote so far, without waiting for them: grow the room a mesh
        came close to and, with ``tell``, warn where one outgrew it or had a piece at the cap of
        its segments ([`warn_if_capped`][layoutwarp.mesh.warn_if_capped]). Returns the status'
        values, whether an overflow is news and whether a piece reached the cap since the host
        looked."""
        pieces, segments = int(self.status[PIECES]), int(self.status[SEGMENTS])
        news = self.overflows.news()
        capped = int(self.status[CAPPED])
        if capped:  # a mesh since the host looked had a piece at the cap (warned once a process)
            self.status[CAPPED] = 0
            if tell:
                warn_if_capped(capped, capped)
        if news and tell:
            need = f"{pieces} pieces" if pieces > self.pieces else f"{segments} segments"
            warnings.warn(
                f"a learnable step's pixel mesh outgrew its room ({need} for {self.pieces} and "
                f"{self.segments} segments): that step integrated straight chords, coarser than its "
                "tolerance; the room has grown (layoutwarp.device_status() tells at once)",
                RuntimeWarning,
                stacklevel=5,
            )
        if pieces > self.pieces:  # the pieces outgrew their room: the segments went uncounted,
            self.segments = 0  # so the next mesh reads its total (once)
        if pieces * HEADROOM > self.pieces:
            self.pieces = self.ahead(pieces, self.pieces)
        if self.segments and segments * HEADROOM > self.segments:
            self.segments = self.ahead(segments, self.segments)
        if self.segments:
            self.segments = max(self.segments, self.pieces)  # room for a chord a piece
        return {"pieces": pieces, "segments": segments, "overflowed": news, "capped": bool(capped)}


#: Every [`MeshRoom`][], by layout kind and centre, sensor size, tolerance, θ's length and device
#: (the source's size changes no count). Never let go of: a captured CUDA graph writes its
#: room's status for as long as it lives (a few bytes a room).
MESH_ROOMS: dict[tuple, MeshRoom] = {}
_ROOMS_LOCK = threading.Lock()


@dataclass
class DeviceMesh:
    """A compiled mesh built where its θ lives ([`build_mesh_device`][]), as torch tensors
    there: the [`PixelMesh`][] (its segment arrays as long as its room, the room left over holding
    segments of no length), its vertices in pixel units of the source (clamped to it) and every
    vertex's θ-derivative ``(V, 2, P)`` (the rows past the mesh's vertices are not written),
    every smooth piece's segment count (as [`CompiledMesh`][] has them, in the first
    ``status[PIECES]`` rows; not written where the pieces outgrew their room, and not the mesh's
    where its segments did), the room it was built in and its stamp there, the source
    image's prefix table and block offsets
    ([`prefix_tables`][layoutwarp.kernels.prefix.prefix_tables], built in the same launches), and
    θ's derivative in the parameter it was built from (``(P,)``, float64; see
    [`build_mesh_device`][])."""

    mesh: PixelMesh
    pixel_vertices: torch.Tensor
    dverts: torch.Tensor
    counts: torch.Tensor
    room: MeshRoom
    stamp: int
    incl: torch.Tensor
    offsets: torch.Tensor
    slope: torch.Tensor


@functools.lru_cache(maxsize=16)
def _device_centre(center: tuple[float, float], device: str) -> torch.Tensor:
    """A centre as a float64 tensor on ``device`` (cached: no copy to the device every step; do
    not modify)."""
    return torch.tensor(center, dtype=torch.float64, device=device)


@functools.lru_cache(maxsize=16)
def _device_topology(size: tuple[int, int], device: str) -> tuple[torch.Tensor, ...]:
    """[`mesh_topology`][] on ``device`` (cached per size and device; do not modify)."""
    return tuple(torch.from_numpy(np.ascontiguousarray(a)).to(device) for a in mesh_topology(size))


def build_mesh_device(
    spec: MeshSpec,
    size: tuple[int, int],
    theta: torch.Tensor,
    tol: float,
    src_size: tuple[int, int],
    *,
    bounds: torch.Tensor | None = None,
    image: torch.Tensor | None = None,
    max_subdiv: int = MAX_SUBDIV,
) -> DeviceMesh:
    """[`build_mesh`][] (``with_grad``) and [`pixel_vertices`][] on the CUDA device that
    holds ``theta`` ``(P,)``: θ itself, or with ``bounds`` (``(P,)``, float64, on that device;
    ``None`` or empty: none) the parameter ρ of ``θ = bounds · tanh(ρ)`` (a learnable layout's,
    in its dtype), which the first kernel makes θ of in float64, so neither takes a launch of its
    own. In four kernels (corners and smooth pieces, the pieces' bounds and swept areas, counts from
    the pixels' areas, vertices with their pixel units: one thread per corner and edge, each thread
    the CPU's steps for its item) and two cumulative sums, so no mesh crosses the bus: at 2048x1024
    → 257x129 a fovea mesh is about 50 MB. The first two kernels also build the prefix table of the
    source ``image`` ``(N, H, W)`` (contiguous, on the same device; ``None``: none). The buffers are
    its [`MeshRoom`][]'s: the host reads the mesh's totals only for the first mesh of its kind (and
    its segments' after a mesh whose pieces outgrew their room, which counted none), and never waits
    for the device otherwise. A ``theta`` on the CPU runs the same kernels in numba's CUDA simulator
    (``NUMBA_ENABLE_CUDASIM=1``), which is how they are tested without a GPU."""
    dev = theta.device
    stream = stream_of(theta)
    (h, w), (hs, ws) = size, src_size
    ends, ea, eb, uniform = _device_topology(size, str(dev))
    param = theta.detach().contiguous()
    c = _device_centre(spec.center, str(dev))
    p, ne, nc = param.numel(), ends.shape[0], uniform.shape[0]
    f64, i64 = {"dtype": torch.float64, "device": dev}, {"dtype": torch.int64, "device": dev}
    th, slope = torch.empty(p, **f64), torch.empty(p, **f64)
    bounds = th[:0] if bounds is None else bounds
    key = (spec, size, float(tol), p, str(dev), max_subdiv)
    with _ROOMS_LOCK:  # threads building one kind of mesh at once share its one room
        room = MESH_ROOMS.get(key)
        if room is None:
            room = MESH_ROOMS[key] = MeshRoom(host_mapped(4, dev))
    room.look()
    stamp = room.overflows.take()

    def launch(name: str, count: int, *args: object) -> None:
        cuda_launch(CUDA_KERNELS[name][0], count, stream, *args)

    q, dq, piece_offsets = torch.empty(nc, 2, **f64), torch.empty(nc, 2, p, **f64), torch.empty(ne + 1, **i64)
    if image is None:
        image = torch.empty(0, hs, ws, **f64)
    n = image.shape[0]
    incl = image.new_empty(hs, ws, n)
    offsets = image.new_empty(hs, -(-ws // BLOCK), n, dtype=torch.float64)
    launch(
        "corners", max(ne, hs * offsets.shape[1] * n), spec.kind, spec.centred, uniform, ends, param,
        bounds, c, th, slope, q, dq, piece_offsets, image, BLOCK, incl,
    )  # fmt: skip
    piece_offsets.cumsum_(0)
    if not room.pieces:  # the first mesh of its kind: its totals read, once
        room.pieces = room.ahead(int(piece_offsets[-1]), ne)
    lims, dlims = torch.empty(room.pieces, 2, **f64), torch.empty(room.pieces, 2, p, **f64)  # pieces' ends
    sag, length, swept = (torch.empty(k, **f64) for k in (room.pieces, room.pieces, ne))
    launch(
        "pieces", max(ne, hs * n), spec.kind, spec.centred, ends, th, c, piece_offsets, lims, dlims, sag,
        length, swept, BLOCK, incl, offsets,
    )  # fmt: skip
    counts, edge_counts = torch.empty(room.pieces, **i64), torch.empty(ne + 1, **i64)
    launch(
        "counts", ne, h, w, q, swept, piece_offsets, sag, length, float(tol), int(max_subdiv), counts,
        edge_counts, room.status, stamp,
    )  # fmt: skip
    edge_offsets = torch.cumsum(edge_counts, 0)
    if not room.segments:  # the first mesh, or one after the pieces outgrew theirs: read, once
        room.segments = room.ahead(int(edge_offsets[-1]), room.pieces)
    nv = nc + room.segments - ne
    verts, dverts = torch.empty(nv, 2, **f64), torch.empty(nv, 2, p, **f64)
    seg_start, seg_end, seg_edge = (torch.empty(room.segments, **i64) for _ in range(3))
    pv, seg_offsets = torch.empty_like(verts), torch.empty(ne + 1, **i64)
    launch(
        "place", ne, spec.kind, spec.centred, ends, ea, eb, th, c, piece_offsets, lims, dlims, counts,
        edge_offsets, q, dq, float(ws), float(hs), verts, dverts, seg_start, seg_end, seg_edge, pv,
        seg_offsets, room.status, stamp,
    )  # fmt: skip
    mesh = PixelMesh(size, verts, seg_start, seg_end, seg_edge, seg_offsets)
    return DeviceMesh(mesh, pv, dverts, counts, room, stamp, incl, offsets, slope)


def device_means(
    dm: DeviceMesh, per_seg: torch.Tensor, unit: float, check: bool, dtype: torch.dtype, zero: torch.Tensor
) -> tuple[torch.Tensor, ...]:
    """The pixels' means ``(N, h, w)`` (in ``dtype``, rounded once), areas ``(h, w)`` and areas
    in sensor units (float64) of the device mesh ``dm`` from its segments' integrals ``per_seg``
    ``(S, N + 1)`` (the exact forward's,
    [`exact_forward`][layoutwarp.kernels.exact.exact_forward]'s per-segment values), in one
    launch (``unit``: a source pixel's area in sensor units; ``check``: a NaN or ±inf mean
    raises when the host next looks, [`DeviceChecks`][layoutwarp.kernels.device.DeviceChecks];
    an earlier call's raises now), which also zeroes the one-element ``zero``."""
    (h, w), n = dm.mesh.size, per_seg.shape[1] - 1
    means, area, area_units = (
        per_seg.new_empty(n, h, w, dtype=dtype),
        per_seg.new_empty(h, w),
        per_seg.new_empty(h, w),
    )
    checks = device_checks(per_seg.device)
    if check:
        checks.look()
    args = (per_seg, dm.mesh.edge_offsets, float(unit), means, area, area_units, checks.status)
    cuda_launch(cuda_pixel_means, h * w, stream_of(per_seg), *args, checks.take() if check else 0, zero)
    return means, area, area_units


def device_status() -> dict[str, object]:
    """What the GPU reported since the last call, read now: every device is synchronised first
    (so call it where the loop waits anyway, e.g. beside ``loss.item()``; a captured CUDA graph's
    replays report too). Returns ``{"overflowed": bool, "capped": bool, "nonfinite": bool,
    "meshes": [...]}``,
    a dict per kind of learnable mesh with the pieces and segments the newest needed and its
    room. ``overflowed``: some mesh outgrew its room and integrated straight chords, coarser than
    its tolerance: run that step again outside the graph (the room has grown; a graph captured
    before keeps its buffers, so capture it again). ``capped``: a smooth piece of some mesh
    reached ``max_subdiv`` segments, so its polyline may err by more than the tolerance.
    ``nonfinite``: a checked call's input held NaN or Inf. Nothing is raised or warned."""
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        for index in range(torch.cuda.device_count()):
            torch.cuda.synchronize(index)
    meshes = []
    for room in list(MESH_ROOMS.values()):
        before = (room.pieces, room.segments)
        values = room.look(tell=False)  # the room grown by what it reports
        meshes.append({**values, "overflowed": room.overflows.clear(), "room": before})
    nonfinite = [checks.clear() for checks in CHECKS.values()]
    overflowed, capped = any(m["overflowed"] for m in meshes), any(m["capped"] for m in meshes)
    return {"overflowed": overflowed, "capped": capped, "nonfinite": any(nonfinite), "meshes": meshes}


def device_theta_gradient(
    dm: DeviceMesh,
    means: torch.Tensor,
    area: torch.Tensor,
    grad: torch.Tensor,
    grad_area: torch.Tensor | None,
    unit: float,
    src_size: tuple[int, int],
    dtype: torch.dtype,
) -> torch.Tensor:
    """The gradient ``(P,)`` of the parameter ``dm`` was built from (θ, or ρ; see
    [`build_mesh_device`][]), in ``dtype``, from the gradients of [`device_means`][]' means
    ``grad`` (the means' dtype) and areas in sensor units ``grad_area`` (``None``: none), over
    the image whose prefix table ``dm`` holds: two launches (the edge integrals' gradient, then
    every segment's Reynolds weights carried to θ, summed in float64 and carried to the
    parameter)."""
    stream, mesh = stream_of(means), dm.mesh
    g_area = area.new_empty(0, 0) if grad_area is None else grad_area.detach().double().contiguous()
    g_edge = area.new_empty(means.shape[0] + 1, mesh.edge_offsets.numel() - 1)
    sums, done = area.new_empty(dm.dverts.shape[2]), mesh.edge_offsets.new_empty(1)
    args = (grad.detach(), means, area, g_area, float(unit), g_edge, sums, done)  # grad as it is: no copy
    cuda_launch(cuda_edge_gradient, g_edge.shape[1], stream, *args)
    hs, ws = src_size
    g_param = area.new_empty(sums.shape[0], dtype=dtype)
    args = (dm.pixel_vertices, mesh.seg_start, mesh.seg_end, mesh.seg_edge, dm.incl, BLOCK, g_edge, dm.dverts)
    cuda_launch(
        cuda_theta_gradient, mesh.num_segments, stream, *args, ws / 2, hs / 2, sums, done, dm.slope, g_param
    )
    return g_param
